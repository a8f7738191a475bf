"""Texture swap: alignment, code transfer, the decoder travelling with its codes, texture frames."""
import copy

import numpy as np
import pytest
import torch

import neumesh_core as nm
from neumesh_core.edit import SwapConfig, swap_texture

from ..conftest import textured_field
from .helpers import masked_psnr, only_touching, render, touched_pixels

TABLES = ("tex_codes", "mod_colours", "decoder_id", "geo_codes")


def _region(f, axis=0, above=0.2):
    return np.nonzero(f.rest_vertices[:, axis].numpy() > above)[0]


def _other_texture(f, seed=5):
    """A copy of ``f``'s geometry with another texture: other codes, other modification colours and a
    radiance decoder with other weights (as if trained on differently coloured images)."""
    g = copy.deepcopy(f)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        g.tex_codes.normal_(0, 0.8, generator=gen)
        g.mod_colours.copy_(torch.tensor([-0.4, 0.5, -0.4]).expand_as(g.mod_colours))
        for p in g.rad_decoder.parameters():
            p.normal_(0, 0.6, generator=gen)
    return g


def _snapshot(f):
    return {n: getattr(f, n).detach().clone() for n in TABLES}


@pytest.mark.parametrize("interp", ["post", "early"])
def test_swapping_a_region_onto_itself_renders_the_original(blob_mesh, interp):
    f = textured_field(blob_mesh, interp)
    before, img = _snapshot(f), render(f)
    region = _region(f)
    rec = swap_texture(f, region, f, region)
    assert rec.info["residual"] < 1e-6 and abs(rec.info["scale"] - 1) < 1e-9
    assert f.num_decoders == 1 and f.tex_frame is None   # nothing new to bind, no frame needed
    out = render(f)
    assert masked_psnr(out.rgb, img.rgb, np.ones(out.rgb.shape[:2], bool)) >= 40.0
    for n, t in before.items():
        assert torch.allclose(getattr(f, n).float(), t.float(), atol=1e-6), n


@pytest.mark.parametrize("interp", ["post", "early"])
def test_swap_from_an_identical_copy_with_given_pairs(blob_mesh, interp):
    f = textured_field(blob_mesh, interp)
    copy_ = copy.deepcopy(f)
    img = render(f)
    region = _region(f)
    pairs = np.stack([region[[0, 40, 80, 160]], region[[0, 40, 80, 160]]], 1)   # (source, target) ids
    rec = swap_texture(f, region, copy_, region, pairs=pairs)
    assert rec.info["pairs"] == 4 and np.allclose(rec.info["transform"], np.eye(4), atol=1e-9)
    assert f.num_decoders == 1            # a bit-identical decoder is the field's own: not added again
    out = render(f)
    p = masked_psnr(out.rgb, img.rgb, np.ones(out.rgb.shape[:2], bool))
    assert p >= 40.0, p


@pytest.mark.parametrize("interp", ["post", "early"])
def test_the_source_decoder_travels_with_its_codes(blob_mesh, interp):
    """A region takes the texture of the same region of a field with another decoder.  Pixels that see
    only the region then render like the source field; pixels that see none of it are unchanged; and
    without the source decoder (codes decoded by the target's own decoder) the region is wrong."""
    f = textured_field(blob_mesh, interp)
    src = _other_texture(f)
    region = _region(f)
    before = render(f)
    inside = only_touching(f, region)
    outside = ~touched_pixels(f, region)
    assert inside.sum() > 100 and outside.sum() > 100
    swap_texture(f, region, src, region)
    assert f.num_decoders == 2 and set(f.decoder_id[region].tolist()) == {1}
    assert int(f.decoder_id[np.setdiff1d(np.arange(f.num_vertices), region)].abs().sum()) == 0
    out = render(f)
    want = render(src)
    p_in = masked_psnr(out.rgb, want.rgb, inside)
    assert p_in >= 40.0, p_in
    assert np.abs(out.rgb[outside] - before.rgb[outside]).max() < 1 / 255
    assert masked_psnr(before.rgb, want.rgb, inside) < 25   # the test means something: they differ
    # a second swap from the same source field adds no second copy of its decoder
    swap_texture(f, _region(f, 1, 0.3), src, _region(f, 1, 0.3))
    assert f.num_decoders == 2
    # the decoder must travel: the same codes decoded by the target's own decoder are far off
    with torch.no_grad():
        f.decoder_id.zero_()
    p_wrong = masked_psnr(render(f).rgb, want.rgb, inside)
    print(f"{interp}: region vs source {p_in:.1f} dB with the decoder, {p_wrong:.1f} dB without")
    assert p_wrong < p_in - 15


def _rotation(deg_z=70.0, deg_x=25.0):
    a, b = np.radians(deg_z), np.radians(deg_x)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return Rz @ Rx


def _rotated_copy(f, R, t):
    """The field ``f`` moved rigidly to x -> R x + t in its rest pose: a new scaffold, the same codes and
    decoders, and texture frames R^T so that its decoders see what they saw before the move."""
    mesh = nm.Mesh(f.rest_vertices.numpy() @ R.T + t, f.faces.numpy())
    g = nm.NeuMeshField(mesh, f.config, num_decoders=f.num_decoders)
    g.load_state_dict({k: v for k, v in f.state_dict().items() if not k.startswith("scaffold.")}, strict=False)
    g.tex_frame = torch.as_tensor(R.T, dtype=torch.float32).expand(g.num_vertices, 3, 3).clone()
    g.eval()
    return g


@pytest.mark.parametrize("interp", ["post", "early"])
def test_a_swap_from_a_rotated_source_keeps_its_look(blob_mesh, interp):
    """The source is the other-texture field moved by a rotation and a shift; the swap finds the
    alignment by itself (no pairs).  The texture frames let the source decoder see normals and view
    directions as it was trained with, so the region renders like the unmoved source; without them
    (``match_orientation=False``) the region's shading is off."""
    f = textured_field(blob_mesh, interp)
    src = _other_texture(f)
    R, t = _rotation(), np.array([3.0, -1.0, 0.5])
    moved = _rotated_copy(src, R, t)
    region = _region(f)
    inside = only_touching(f, region)
    want = render(src)
    g = copy.deepcopy(f)
    rec = swap_texture(f, region, moved, region)
    M = rec.info["transform"]
    assert np.allclose(M[:3, :3], R.T, atol=1e-4) and rec.info["residual"] < 1e-3
    p_frames = masked_psnr(render(f).rgb, want.rgb, inside)
    swap_texture(g, region, moved, region, config=SwapConfig(match_orientation=False))
    p_plain = masked_psnr(render(g).rgb, want.rgb, inside)
    print(f"{interp}: rotated source: {p_frames:.1f} dB with texture frames, {p_plain:.1f} dB without")
    assert p_frames >= 40.0 and p_plain < p_frames - 10


@pytest.mark.parametrize("interp", ["post", "early"])
def test_undo_restores_the_field_exactly(blob_mesh, interp):
    f = textured_field(blob_mesh, interp)
    before, img = _snapshot(f), render(f)
    moved = _rotated_copy(_other_texture(f), _rotation(), np.zeros(3))
    rec = swap_texture(f, _region(f), moved, _region(f, 1, 0.0))
    assert f.tex_frame is not None and f.num_decoders == 2
    rec.undo(f)
    assert f.num_decoders == 1 and f.tex_frame is None
    for n, t in before.items():   # exact: undo writes back copies of the old rows
        assert torch.equal(getattr(f, n), t), n
    assert np.array_equal(render(f).rgb, img.rgb)   # same tensors, same path, same process


def test_geometry_and_rows_outside_the_region_never_change(blob_mesh):
    f = textured_field(blob_mesh)
    src = _other_texture(f)
    region = _region(f)
    before = _snapshot(f)
    verts = f.rest_vertices.clone()
    swap_texture(f, region, src, _region(src, 1, 0.1))
    out = np.setdiff1d(np.arange(f.num_vertices), region)
    for n in ("tex_codes", "mod_colours", "decoder_id"):
        assert torch.equal(getattr(f, n)[out], before[n][out]), n
    assert torch.equal(f.geo_codes, before["geo_codes"]) and torch.equal(f.rest_vertices, verts)


def test_bad_input_is_refused_and_changes_nothing(blob_mesh):
    f = textured_field(blob_mesh)
    before = _snapshot(f)
    region = _region(f)
    with pytest.raises(ValueError, match="empty"):
        swap_texture(f, [], f, region)
    with pytest.raises(ValueError, match="source_vertices"):
        swap_texture(f, region, f, None)
    with pytest.raises(ValueError, match="at least 3"):
        swap_texture(f, region, f, region, pairs=np.array([[1, 1], [2, 2]]))
    with pytest.raises(ValueError, match=r"\[0, "):
        swap_texture(f, region, f, region, pairs=np.array([[1, 1], [2, 2], [3, 10 ** 7]]))
    other = textured_field(blob_mesh, tex_dim=8)
    with pytest.raises(ValueError, match="tex_dim"):
        swap_texture(f, region, other, region)
    with pytest.raises(ValueError, match="at least 4 vertices"):
        swap_texture(f, region, f, region[:2])
    cancelled = []
    with pytest.raises(nm.Cancelled):
        swap_texture(f, region, _other_texture(f), region, progress=lambda x: cancelled.append(x) or x < 0.5)
    for n, t in before.items():
        assert torch.equal(getattr(f, n), t), n
    assert f.num_decoders == 1 and f.tex_frame is None
