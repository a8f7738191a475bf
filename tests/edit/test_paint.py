"""Texture painting from one view: the painted pixels reach the paint, nothing else in the view
changes, novel views see the paint where the painted surface is, undo is exact, bad input changes
nothing.  The field is the built-in blob with a visible texture (10,242 vertices), 64 px views."""
import numpy as np
import pytest
import torch

import neumesh_core as nm
from neumesh_core.edit import PaintConfig, paint_layer, paint_texture
from neumesh_core.metrics import psnr

from ..conftest import textured_field
from .helpers import camera

S = 64


@pytest.fixture(scope="module")
def blob5():
    from neumesh_core.data.synthetic import default_mesh

    return default_mesh(subdiv=5)


def _stroke(colour, rows=(26, 33), cols=(20, 44)):
    layer = np.zeros((S, S, 4), np.float32)
    layer[rows[0]:rows[1], cols[0]:cols[1], :3] = colour
    layer[rows[0]:rows[1], cols[0]:cols[1], 3] = 1.0
    return layer


def _dilate(mask, r):
    from scipy.ndimage import binary_dilation

    return binary_dilation(mask, iterations=r)


def _view(f, az):
    K, c2w = camera(az, size=S)
    return K, c2w, nm.render_camera(f, K, c2w, S, S)


@pytest.mark.parametrize("interp", ["post", "early"])
@pytest.mark.parametrize("colour", [(0.9, 0.1, 0.1), (0.0, 0.0, 0.0)])
def test_a_painted_stroke_reaches_its_colour_and_nothing_else_changes(blob5, interp, colour):
    """In the painted view: >= 30 dB against the paint inside the stroke, and every
    pixel more than 2 px from the stroke changes by < 1/255.  Black is far below what the decoder
    produces on this texture and is reached too (the modification colour is unbounded)."""
    f = textured_field(blob5, interp)
    K, c2w, before = _view(f, 0.0)
    layer = _stroke(colour)
    mask = layer[..., 3] > 0
    assert before.opacity[mask].min() > 0.9             # the stroke lies on the object
    rec = paint_texture(f, K, c2w, S, S, layer)
    after = nm.render_camera(f, K, c2w, S, S)
    p = psnr(np.clip(after.rgb[mask], 0, 1), layer[mask][:, :3])
    print(f"{interp} {colour}: {p:.1f} dB in the stroke, {rec.info['affected_vertices']} vertices, "
          f"{rec.info['ring_pixels']} ring pixels, {rec.info['seconds']:.2f} s")
    assert p >= 30.0
    far = ~_dilate(mask, 2)
    assert np.abs(after.rgb - before.rgb)[far].max() < 1 / 255
    assert (np.abs(after.rgb - before.rgb).max(-1) > 0.1).sum() >= 0.9 * mask.sum()


@pytest.mark.parametrize("interp", ["post", "early"])
def test_novel_views_see_the_paint_where_the_painted_surface_is(blob5, interp):
    """The painted surface points are projected into views 25 and 50 degrees away (kept where the
    view's own depth shows them: not occluded).  The pixels that change match that projection
    (IoU against it dilated by 1 px: at least 0.6), and nothing changes more than
    1/255 farther than 3 px from it."""
    f = textured_field(blob5, interp)
    K, c2w, before0 = _view(f, 0.0)
    layer = _stroke((0.1, 0.2, 0.9))
    mask = layer[..., 3] > 0
    ys, xs = np.nonzero(mask)
    o, d = nm.pixel_rays(K, c2w, S, S, pixels=torch.as_tensor(np.stack([xs, ys], 1)))
    pts = (o + d * torch.as_tensor(before0.depth[ys, xs])[:, None]).numpy()
    views = {az: _view(f, az) for az in (25.0, 50.0)}
    paint_texture(f, K, c2w, S, S, layer)
    for az, (Kn, c2wn, before) in views.items():
        after = nm.render_camera(f, Kn, c2wn, S, S)
        changed = np.abs(after.rgb - before.rgb).max(-1) > 1 / 255
        w2c = np.linalg.inv(c2wn)
        cam = pts @ w2c[:3, :3].T + w2c[:3, 3]
        uv = cam @ Kn.T
        px = np.round(uv[:, :2] / uv[:, 2:3] - 0.5).astype(int)
        ok = (px[:, 0] >= 0) & (px[:, 0] < S) & (px[:, 1] >= 0) & (px[:, 1] < S)
        px, z = px[ok], np.linalg.norm(pts[ok] - c2wn[:3, 3], axis=1)
        visible = np.abs(before.depth[px[:, 1], px[:, 0]] - z) < 0.05
        proj = np.zeros((S, S), bool)
        proj[px[visible, 1], px[visible, 0]] = True
        near = _dilate(proj, 1)
        iou = (changed & near).sum() / max((changed | near).sum(), 1)
        print(f"{interp} view {az:.0f}: changed {changed.sum()} px, projection {near.sum()} px, IoU {iou:.2f}")
        assert proj.sum() > 50 and iou >= 0.6
        assert np.abs(after.rgb - before.rgb)[~_dilate(proj, 3)].max() < 1 / 255


def test_undo_restores_the_modification_colours_exactly(blob5):
    f = textured_field(blob5)
    old = f.mod_colours.detach().clone()
    K, c2w, _ = _view(f, 0.0)
    rec = paint_texture(f, K, c2w, S, S, _stroke((0.0, 1.0, 0.0)))
    changed = np.nonzero((f.mod_colours != old).any(1).numpy())[0]
    assert np.array_equal(changed, rec.vertices) or set(changed) <= set(rec.vertices)
    rec.undo(f)
    assert torch.equal(f.mod_colours, old)   # exact: the old rows are written back


def test_paint_layer_from_a_painted_image():
    render = np.random.default_rng(0).random((8, 8, 3)).astype(np.float32)
    painted = np.round(render * 255) / 255          # an 8-bit round trip is not paint
    painted[2:4, 3:6] = [1.0, 0.0, 0.0]
    layer = paint_layer(painted, render)
    assert layer.shape == (8, 8, 4) and layer[..., 3].sum() == 6 and (layer[2:4, 3:6, 3] == 1).all()
    with pytest.raises(nm.EditError, match="8x8"):
        paint_layer(painted[:4], render)


def test_bad_input_changes_nothing(blob5):
    f = textured_field(blob5)
    old = f.mod_colours.detach().clone()
    K, c2w, _ = _view(f, 0.0)
    with pytest.raises(nm.EditError, match="nothing is painted"):
        paint_texture(f, K, c2w, S, S, np.zeros((S, S, 4), np.float32))
    with pytest.raises(nm.PaintMissError, match="only background"):
        paint_texture(f, K, c2w, S, S, _stroke((1, 0, 0), rows=(0, 3), cols=(0, 4)))
    with pytest.raises(nm.EditError, match="size changed|camera or the image size"):
        paint_texture(f, K, c2w, S, S, np.zeros((S // 2, S, 4), np.float32))
    with pytest.raises(nm.Cancelled):
        paint_texture(f, K, c2w, S, S, _stroke((1, 0, 0)), progress=lambda x: x < 0.5)
    assert torch.equal(f.mod_colours, old)
    with pytest.raises(nm.EditError, match="damping"):
        PaintConfig(damping=0)
