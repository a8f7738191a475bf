"""Painting from one view into the paint atlas (texel paint): the painted pixels reach the paint as
sharp as painted (a one-pixel line stays one pixel), nothing 2 px away changes, another view sees the
paint on the same surface, undo/redo are exact, the bake carries the paint, and per-vertex
painting stays the default for fields without an atlas.  Untrained textured blob, 64 px views."""
import numpy as np
import pytest

import neumesh_core as nm
from neumesh_core.errors import EditError, PaintMissError
from neumesh_core.edit.paint import create_paint_atlas, paint_atlas_from_view, paint_texture
from neumesh_core.metrics import psnr

from ..conftest import textured_field
from .helpers import camera

S = 64
RED = np.array([1.0, 0.05, 0.1], np.float32)


@pytest.fixture(scope="module")
def blob4():
    from neumesh_core.data.synthetic import default_mesh

    return default_mesh(subdiv=4)


def _field(mesh, method="xatlas"):
    f = textured_field(mesh, interpolation="early")
    create_paint_atlas(f, resolution=512, method=method)     # xatlas / grid of the 2,562-vertex blob
    return f


def _far_from(mask, r):
    from scipy.ndimage import binary_dilation

    return ~binary_dilation(mask, iterations=r)


@pytest.mark.parametrize("method", ["xatlas", "grid"])
def test_a_thin_line_and_a_block_paint_as_sharp_as_painted(blob4, method):
    f = _field(blob4, method)
    assert f.paint_atlas.source == method
    K, c2w = camera(10.0, size=S)
    before = nm.render_camera(f, K, c2w, S, S)
    mask = np.zeros((S, S), bool)
    mask[30, 18:46] = True                     # a one-pixel line
    mask[22:26, 26:38] = True                  # a small block
    mask &= before.opacity > 0.95
    layer = np.zeros((S, S, 4), np.float32)
    layer[mask, :3] = RED
    layer[mask, 3] = 1.0
    rec = paint_texture(f, K, c2w, S, S, layer)             # the field has an atlas: texel paint
    assert rec.op == "paint_atlas" and rec.num_changed > 0 and len(rec.vertices) == 0
    after = nm.render_camera(f, K, c2w, S, S)
    p_in = psnr(np.clip(after.rgb[mask], 0, 1), np.broadcast_to(RED, (int(mask.sum()), 3)))
    delta = np.abs(after.rgb - before.rgb).max(-1)
    far = _far_from(mask, 2)
    print(f"stroke {p_in:.1f} dB; changed > 1/255 farther than 2 px: {int((delta[far] > 1 / 255).sum())}")
    assert p_in > 30.0
    assert (delta[far] <= 1 / 255).all()
    # the line is one pixel wide: the rows above and below it keep most of their colour
    row = np.abs(after.rgb[31, 20:44] - before.rgb[31, 20:44]).max(-1)
    assert np.median(row) < 0.1
    # the per-vertex colours did not move
    np.testing.assert_allclose(f.mod_colours.detach().numpy(),
                               textured_field(blob4, interpolation="early").mod_colours.detach().numpy(), atol=0)
    # undo and redo are exact
    rec.undo(f)
    np.testing.assert_allclose(nm.render_camera(f, K, c2w, S, S).rgb, before.rgb, atol=1e-6)
    rec.redo(f)
    np.testing.assert_allclose(nm.render_camera(f, K, c2w, S, S).rgb, after.rgb, atol=1e-6)


def test_another_view_sees_the_paint_on_the_same_surface(blob4):
    f = _field(blob4)
    K, c2w = camera(0.0, size=S)
    before = nm.render_camera(f, K, c2w, S, S)
    mask = np.zeros((S, S), bool)
    mask[24:36, 26:38] = True
    layer = np.zeros((S, S, 4), np.float32)
    layer[mask, :3] = RED
    layer[mask, 3] = 1.0
    paint_atlas_from_view(f, K, c2w, S, S, layer)
    # the painted surface points, projected into a view 25 degrees round
    from neumesh_core.data.cameras import pixel_rays
    import torch

    ys, xs = np.nonzero(mask)
    o, d = pixel_rays(K, c2w, S, S, pixels=torch.as_tensor(np.stack([xs, ys], 1)))
    pts = (o + d * torch.as_tensor(before.depth[ys, xs])[:, None]).numpy()
    K2, c2 = camera(25.0, size=S)
    w2c = np.linalg.inv(c2)
    cam = pts @ w2c[:3, :3].T + w2c[:3, 3]
    q = (cam @ K2.T)[:, :2] / cam[:, 2:3]
    hit = np.zeros((S, S), bool)
    hit[np.clip(q[:, 1].astype(int), 0, S - 1), np.clip(q[:, 0].astype(int), 0, S - 1)] = True
    plain = nm.render_camera(textured_field(blob4, interpolation="early"), K2, c2, S, S)
    other = nm.render_camera(f, K2, c2, S, S)
    red = np.abs(other.rgb - RED).max(-1) < 0.1
    changed = np.abs(other.rgb - plain.rgb).max(-1) > 1 / 255
    assert red.sum() > 0.6 * hit.sum()
    assert (changed & _far_from(hit, 2)).sum() == 0         # nothing changes away from the painted surface


def test_the_bake_carries_the_paint(blob4):
    from neumesh_core.bake import bake_texture

    GREEN = np.array([0.1, 0.95, 0.2], np.float32)     # a colour the textured field has nowhere
    f = _field(blob4)
    K, c2w = camera(0.0, size=S)
    mask = np.zeros((S, S), bool)
    mask[20:40, 22:42] = True
    layer = np.zeros((S, S, 4), np.float32)
    layer[mask, :3] = GREEN
    layer[mask, 3] = 1.0
    paint_atlas_from_view(f, K, c2w, S, S, layer)
    plain = bake_texture(textured_field(blob4, interpolation="early"), resolution=128, fit=False, mesh=None,
                         colours="rays")
    b = bake_texture(f, resolution=128, fit=False, mesh=None, colours="rays")
    red = (np.abs(b.texture - GREEN).max(-1) < 0.15) & b.mask
    was = (np.abs(plain.texture - GREEN).max(-1) < 0.15) & plain.mask
    assert red.sum() > 100 and was.sum() < 0.1 * red.sum()


def test_without_an_atlas_paint_goes_to_the_vertex_colours_and_bad_input_is_refused(blob4):
    f = textured_field(blob4, interpolation="early")
    K, c2w = camera(0.0, size=S)
    layer = np.zeros((S, S, 4), np.float32)
    layer[28:34, 28:34] = (*RED, 1.0)
    rec = paint_texture(f, K, c2w, S, S, layer)
    assert rec.op == "paint_texture" and getattr(f, "paint_atlas", None) is None and rec.num_changed > 0
    with pytest.raises(EditError, match="no paint atlas"):
        paint_atlas_from_view(f, K, c2w, S, S, layer)
    with pytest.raises(EditError):
        paint_texture(f, K, c2w, S, S, layer, target="texels")
    # target="atlas" makes one (given UVs per vertex here)
    v = f.rest_vertices.numpy()
    create_paint_atlas(f, resolution=128, uvs=(v[:, :2] - v[:, :2].min()) / np.ptp(v[:, :2]).max())
    assert f.paint_atlas.source == "given" and f.paint_atlas.size == (128, 128)
    with pytest.raises(EditError, match="already has"):
        create_paint_atlas(f)
    f.paint_atlas = None
    with pytest.raises(EditError, match="UVs must be"):
        create_paint_atlas(f, uvs=np.zeros((5, 2)))
    with pytest.raises(EditError, match="resolution"):
        create_paint_atlas(f, resolution=8)
    create_paint_atlas(f, resolution=64)
    with pytest.raises(EditError, match="nothing is painted"):
        paint_atlas_from_view(f, K, c2w, S, S, np.zeros((S, S, 4), np.float32))
    sky = np.zeros((S, S, 4), np.float32)
    sky[0:3, 0:3] = (*RED, 1.0)
    with pytest.raises(PaintMissError, match="background"):
        paint_atlas_from_view(f, K, c2w, S, S, sky)
    with pytest.raises(EditError, match="RGBA"):
        paint_atlas_from_view(f, K, c2w, S, S, np.zeros((S, S, 3), np.float32))
    assert f.paint_atlas.is_empty


def test_the_render_painted_on_gives_the_same_paint_as_rendering_the_pixels_again(blob4, monkeypatch):
    """``surface=`` (the render the layer was painted on: no render in the apply) against the reference
    that renders the painted pixels' box again: the same texels painted, the same picture, nothing
    farther than 2 px from the paint changed.  (What skipping the render saves in time:
    benchmarks/bench/bench_paint.py --target atlas, with and without --no-surface.)"""
    from neumesh_core.render import renderer
    K, c2w = camera(10.0, size=S)
    f_ref, f_fast = _field(blob4), _field(blob4)
    before = nm.render_camera(f_ref, K, c2w, S, S)
    mask = np.zeros((S, S), bool)
    mask[26:29, 16:48] = True
    mask[18:40, 30] = True
    mask &= before.opacity > 0.95
    layer = np.zeros((S, S, 4), np.float32)
    layer[mask, :3] = RED
    layer[mask, 3] = 1.0
    rays = []   # rays each apply renders
    render_rays = renderer.render_rays

    def counted(fields, origins, *args, **kwargs):
        rays.append(int(origins.shape[0]))
        return render_rays(fields, origins, *args, **kwargs)

    monkeypatch.setattr(renderer, "render_rays", counted)
    ref = paint_atlas_from_view(f_ref, K, c2w, S, S, layer)
    ref_rays, rays[:] = sum(rays), []
    fast = paint_texture(f_fast, K, c2w, S, S, layer, surface=before)
    fast_rays = sum(rays)
    monkeypatch.undo()
    assert fast.info["surface_given"] and not ref.info["surface_given"] and fast_rays == 0 < ref_rays
    a, b = set(ref.texels.tolist()), set(fast.texels.tolist())
    assert len(a & b) > 0.97 * max(len(a), len(b))
    ra, rb = nm.render_camera(f_ref, K, c2w, S, S).rgb, nm.render_camera(f_fast, K, c2w, S, S).rgb
    far = _far_from(mask, 2)
    for r in (ra, rb):
        assert psnr(np.clip(r[mask], 0, 1), np.broadcast_to(RED, (int(mask.sum()), 3))) > 30.0
        assert (np.abs(r - before.rgb).max(-1)[far] <= 1 / 255).all()
    with pytest.raises(EditError, match="render painted on"):
        paint_atlas_from_view(f_fast, K, c2w, S, S, layer, surface=(before.opacity[:10], before.depth))


def test_paint_made_in_the_image_is_recorded_saved_and_undone(blob4, tmp_path):
    """Paint written straight into the atlas image (Blender's Texture Paint) becomes an AtlasRecord:
    exactly the texels that changed, saved with the field as an edit, undone and redone exactly."""
    from neumesh_core.edit import paint_image_record, save_edited

    f = _field(blob4)
    parent = str(tmp_path / "blob.neumesh")
    nm.save_field(f, parent)
    saved = f.paint_atlas.image.numpy().copy()
    px = np.zeros((20, 30, 4), np.float32)
    px[5:15, 5:25] = (*RED, 1.0)
    changed = f.paint_atlas.set_image(px, (100, 120, 200, 230))
    rec = paint_image_record(f, saved)
    assert rec.op == "paint_image" and sorted(rec.texels.tolist()) == sorted(changed.tolist()) and len(changed) == 200
    out = save_edited(f, parent, rec)
    g = nm.load_field(out)
    np.testing.assert_allclose(g.paint_atlas.image.numpy(), f.paint_atlas.image.numpy(), atol=0.5 / 255)
    painted = f.paint_atlas.image.numpy().copy()
    rec.undo(f)
    np.testing.assert_allclose(f.paint_atlas.image.numpy(), saved, atol=0)
    assert f.paint_atlas.is_empty
    rec.redo(f)
    np.testing.assert_allclose(f.paint_atlas.image.numpy(), painted, atol=0)
    with pytest.raises(EditError, match="same image"):
        paint_image_record(f, saved[:10])
