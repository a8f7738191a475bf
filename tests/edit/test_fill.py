"""Texture fill through UV maps: tiling, wrap-around, seams, and the exactness of an identity fill."""
import copy

import numpy as np
import pytest
import torch

import neumesh_core as nm
from neumesh_core.edit import CornerUVs, fill_texture

from ..conftest import textured_field
from .helpers import masked_psnr, render, touched_pixels


def _grid(n=16):
    """A flat (n+1)x(n+1) grid in the xy plane whose UVs are its xy coordinates in [0,1]."""
    ii, jj = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    uv = np.stack([ii.ravel() / n, jj.ravel() / n], 1)
    v = np.concatenate([uv * 2 - 1, np.zeros((len(uv), 1))], 1)
    idx = ii * (n + 1) + jj
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return nm.Mesh(v, faces), uv


def _spherical_corner_uvs(f):
    """Per face-corner spherical UVs of the blob: faces across the u=0/1 line are unwrapped so their
    corners agree, and each corner at a pole takes its face's u, so poles and the seam carry several
    UVs per vertex, as a Blender UV map does."""
    v = f.rest_vertices.numpy().astype(np.float64)
    faces = f.faces.numpy()
    r = np.linalg.norm(v, axis=1)
    u = np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi) % 1.0
    w = np.arccos(np.clip(v[:, 2] / r, -1, 1)) / np.pi
    fu = u[faces]
    wrap = fu.max(1, keepdims=True) - fu > 0.5
    fu = np.where(wrap, fu + 1.0, fu)
    return CornerUVs.from_faces(faces, np.stack([fu, w[faces]], -1))


@pytest.mark.parametrize("interp", ["post", "early"])
def test_fill_at_scale_1_from_coinciding_uvs_renders_the_original(blob_mesh, interp):
    f = textured_field(blob_mesh, interp)
    img = render(f)
    region = np.nonzero(f.rest_vertices[:, 2].numpy() > -0.2)[0]
    uvs = _spherical_corner_uvs(f)
    counts = np.bincount(uvs.restricted(region, "t").vertex)
    assert counts.max() > 1   # several UVs on some vertices (the seam, the pole)
    before = f.tex_codes.detach().clone()
    rec = fill_texture(f, region, uvs, copy.deepcopy(f), region, uvs, scale=1.0)
    assert len(rec.vertices) == len(region) and f.num_decoders == 1
    # only rows whose values changed count (vertices with several UVs take a mean; the rest copy
    # themselves exactly)
    differ = (f.tex_codes != before).any(1).numpy()
    assert rec.num_changed == int(differ.sum()) < len(region)
    p = masked_psnr(render(f).rgb, img.rgb, np.ones(img.rgb.shape[:2], bool))
    assert p >= 40.0, p


def test_scale_2_repeats_the_template_twice_across():
    mesh, uv = _grid(16)
    target = textured_field(mesh, seed=1)
    template = textured_field(mesh, seed=2)
    all_v = np.arange(mesh.num_vertices)
    n = 16
    ij = np.round(uv * n).astype(int)
    # the template tile: its u = 1 and v = 1 borders are the u = 0 and v = 0 ones of the next tile
    tile = np.nonzero((ij < n).all(1))[0]
    fill_texture(target, all_v, uv, template, tile, uv[tile], scale=2.0)
    for v in range(mesh.num_vertices):
        i, j = ij[v]
        src = ((2 * i) % n) * (n + 1) + (2 * j) % n      # the template vertex at frac(2 u)
        assert torch.allclose(target.tex_codes[v], template.tex_codes[src], atol=1e-6), (i, j)
        assert torch.allclose(target.mod_colours[v], template.mod_colours[src], atol=1e-6)
    # so the pattern repeats: vertex (i, j) equals vertex (i + n/2, j)
    a = target.tex_codes.view(n + 1, n + 1, -1)
    assert torch.allclose(a[: n // 2 + 1], a[n // 2:], atol=1e-6)


def test_lookups_wrap_across_tile_borders():
    mesh, uv = _grid(4)
    target = textured_field(mesh, seed=1)
    template = textured_field(mesh, seed=2)
    # template samples at u = 0.02 (vertex 0) and u = 0.5 (vertex 1); the target vertex at u = 0.99 is
    # 0.03 from the first across the border and 0.49 from the second
    tmpl = CornerUVs(np.array([0, 1]), np.array([[0.02, 0.5], [0.5, 0.5]]))
    fill_texture(target, [7], np.array([[0.99, 0.5]]), template, [0, 1], tmpl, scale=1.0,
                 config=nm.edit.FillConfig(k=2))
    w0, w1 = 1 / 0.03, 1 / 0.49
    want = (w0 * template.tex_codes[0] + w1 * template.tex_codes[1]) / (w0 + w1)
    assert torch.allclose(target.tex_codes[7], want, atol=1e-5)


def test_a_vertex_on_a_uv_seam_takes_the_mean_of_its_uvs():
    """A target vertex with two UVs looks each one up and averages the results (equal weight); a
    template vertex with two UVs is a sample at each of them."""
    mesh, uv = _grid(4)
    target = textured_field(mesh, seed=1)
    template = textured_field(mesh, seed=2)
    tmpl = CornerUVs(np.array([3, 3, 9]), np.array([[0.1, 0.1], [0.6, 0.6], [0.35, 0.85]]))
    tgt = CornerUVs(np.array([5, 5, 6]), np.array([[0.1, 0.1], [0.35, 0.85], [0.6, 0.6]]))
    fill_texture(target, [5, 6], tgt, template, [3, 9], tmpl, scale=1.0)
    assert torch.allclose(target.tex_codes[5], 0.5 * (template.tex_codes[3] + template.tex_codes[9]), atol=1e-6)
    assert torch.allclose(target.tex_codes[6], template.tex_codes[3], atol=1e-6)   # its seam twin


def test_fill_changes_only_the_target_region(blob_mesh):
    f = textured_field(blob_mesh)
    before = {n: getattr(f, n).detach().clone() for n in ("tex_codes", "mod_colours", "geo_codes")}
    img = render(f)
    region = np.nonzero(f.rest_vertices[:, 0].numpy() > 0.3)[0]
    uvs = _spherical_corner_uvs(f)
    template = textured_field(blob_mesh, seed=4)
    with torch.no_grad():
        for p in template.rad_decoder.parameters():
            p.mul_(-1.0)
    tmpl_region = np.nonzero(template.rest_vertices[:, 2].numpy() > 0.0)[0]
    rec = fill_texture(f, region, uvs, template, tmpl_region, uvs, scale=3.0)
    assert f.num_decoders == 2 and set(f.decoder_id[region].tolist()) == {1}
    out = np.setdiff1d(np.arange(f.num_vertices), region)
    assert torch.equal(f.tex_codes[out], before["tex_codes"][out]) and torch.equal(f.geo_codes, before["geo_codes"])
    untouched = ~touched_pixels(f, region)
    after = render(f)
    assert np.abs(after.rgb[untouched] - img.rgb[untouched]).max() < 1 / 255
    assert np.abs(after.rgb - img.rgb).max() > 0.1
    rec.undo(f)
    assert f.num_decoders == 1 and torch.equal(f.tex_codes, before["tex_codes"])


def test_bad_uvs_are_refused_and_change_nothing(blob_mesh):
    f = textured_field(blob_mesh)
    before = f.tex_codes.detach().clone()
    region = np.arange(0, 100)
    uvs = CornerUVs(np.arange(0, 50), np.zeros((50, 2)))
    with pytest.raises(ValueError, match="have no UV"):
        fill_texture(f, region, uvs, f, np.arange(50), uvs)
    with pytest.raises(ValueError, match="one per region vertex"):
        fill_texture(f, region, np.zeros((99, 2)), f, np.arange(50), uvs)
    with pytest.raises(ValueError, match="positive"):
        fill_texture(f, np.arange(50), uvs, f, np.arange(50), uvs, scale=0.0)
    with pytest.raises(ValueError, match="NaN"):
        CornerUVs(np.arange(2), np.array([[0.0, np.nan], [0, 0]]))
    with pytest.raises(ValueError, match="tex_dim"):
        fill_texture(f, np.arange(50), uvs, textured_field(blob_mesh, tex_dim=4), np.arange(50), uvs)
    assert torch.equal(f.tex_codes, before) and f.num_decoders == 1


def test_planar_uvs_unwrap_a_flat_region_to_the_unit_square():
    from neumesh_core.edit import planar_uvs

    mesh, uv = _grid(8)
    R = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    got = planar_uvs(mesh.vertices @ R.T + 5.0)     # a tilted, moved copy of the grid
    assert got.min() >= 0 and np.isclose(got.max(), 1.0)
    d_got = np.linalg.norm(got[:, None] - got[None], axis=-1)
    d_uv = np.linalg.norm(uv[:, None] - uv[None], axis=-1)
    # distances kept up to one scale (a square's principal axes may lie along its diagonals)
    assert np.allclose(d_got / d_got.max(), d_uv / d_uv.max(), atol=1e-9)
