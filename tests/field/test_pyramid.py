"""Coarse-to-fine code levels (training-time reparameterisation of the per-vertex codes)."""
import numpy as np
import pytest
import torch

from neumesh_core.field.field import FieldConfig, NeuMeshField
from neumesh_core.field.pyramid import CodePyramid, parent_weights, subsample_vertices

from ..conftest import textured_field


def _queries(f, n, seed):
    """``n`` points within a third of the radius of the first ``n`` vertices, and random unit directions."""
    x = f.rest_vertices[:n] + 0.3 * f.radius * torch.randn(n, 3, generator=torch.Generator().manual_seed(seed))
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=torch.Generator().manual_seed(seed + 1)), dim=-1)
    return x, d


def test_subsample_keeps_one_vertex_per_cell():
    g = np.random.default_rng(0)
    v = g.uniform(0, 1, (5000, 3))
    keep = subsample_vertices(v, 0.25)
    cells = np.floor((v[keep] - v.min(0)) / 0.25).astype(int)
    assert len(np.unique(cells, axis=0)) == len(keep)                        # no cell twice
    assert len(keep) == len(np.unique(np.floor((v - v.min(0)) / 0.25), axis=0))  # every cell once
    assert np.array_equal(keep, np.sort(keep)) and np.array_equal(keep, subsample_vertices(v, 0.25))
    with pytest.raises(ValueError, match="spacing"):
        subsample_vertices(v, 0.0)


def test_parent_weights_are_normalised_and_never_cross_to_a_surface_facing_away():
    # two parallel sheets 0.05 apart facing away from each other (a thin wall), coarse vertices on both
    xs, ys = np.meshgrid(np.linspace(0, 1, 21), np.linspace(0, 1, 21))
    top = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.05)], 1)
    bottom = top.copy()
    bottom[:, 2] = 0.0
    v = np.concatenate([top, bottom])
    n = np.concatenate([np.tile([0, 0, 1.0], (len(top), 1)), np.tile([0, 0, -1.0], (len(top), 1))])
    coarse = np.arange(0, len(v), 7)
    idx, w = parent_weights(v, n, coarse, spacing=0.2, j=6)
    assert idx.shape == w.shape == (len(v), 6)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-5)
    side = v[coarse][idx][..., 2] > 0.01                       # which sheet each parent is on
    assert np.all(w[: len(top)][~side[: len(top)]] == 0)
    assert np.all(w[len(top):][side[len(top):]] == 0)


def test_an_attached_pyramid_renders_the_same_until_trained_and_bakes_exactly(blob_mesh):
    f = textured_field(blob_mesh, interpolation="early")
    x, d = _queries(f, 400, seed=0)
    sigma0, rgb0, _ = f.query(x, d)
    p = CodePyramid(f, levels=2, factor=3.0)
    assert p.levels == 2 and p.sizes[0] > p.sizes[1] > 1 and p.sizes[0] < f.num_vertices
    f.set_code_prior(p)
    assert "code_prior" not in dict(f.named_modules()) and not any("geo" == n for n, _ in f.named_parameters())
    sigma1, rgb1, _ = f.query(x, d)
    # exact on purpose: codes + 0.0 are the same floats and the decode path is the same, in one process
    assert torch.equal(sigma0, sigma1) and torch.equal(rgb0, rgb1)      # zero coarse codes: no change
    with torch.no_grad():
        p.geo.normal_(0, 0.3)
        p.tex.normal_(0, 0.3)
    sigma2, rgb2, _ = f.query(x, d)
    assert not torch.allclose(rgb2, rgb1)
    # a vertex's coarse contribution is the weighted sum of its parents' codes
    i = torch.tensor([0, 17, 123])
    (tex,) = p.lookup(("tex",), i)
    ref = (p.weights[i][..., None] * p.tex[p.parents[i]]).sum(1)
    assert torch.allclose(tex, ref, atol=1e-6)
    codes_before = f.tex_codes.detach().clone()
    with p.baked_into(f):                       # a plain field inside: what a checkpoint stores
        assert f.code_prior is None
        sigma3, rgb3, _ = f.query(x, d)
    assert f.code_prior is p and torch.equal(f.tex_codes, codes_before)
    assert torch.allclose(sigma3, sigma2, rtol=1e-5) and torch.allclose(rgb3, rgb2, atol=1e-6)
    p.bake(f)
    assert f.code_prior is None                  # baking detaches the levels from the field
    sigma4, rgb4, _ = f.query(x, d)
    assert torch.allclose(sigma4, sigma2, rtol=1e-5) and torch.allclose(rgb4, rgb2, atol=1e-6)
    assert float(p.tex.detach().abs().sum()) == 0.0


def test_gradients_reach_the_coarse_codes_of_the_looked_up_vertices(blob_mesh):
    f = NeuMeshField(blob_mesh, FieldConfig(interpolation="early"))
    p = CodePyramid(f, levels=1, factor=3.0)
    i = torch.tensor([5, 6, 5])
    (geo,) = p.lookup(("geo",), i)
    geo.sum().backward()
    touched = torch.unique(p.parents[torch.tensor([5, 6])][p.weights[torch.tensor([5, 6])] > 0])
    got = (p.geo.grad.abs().sum(1) > 0).nonzero().squeeze(1)
    assert torch.equal(got, touched)


def test_pyramid_arguments_are_checked(blob_mesh):
    f = NeuMeshField(blob_mesh)
    with pytest.raises(ValueError, match="levels"):
        CodePyramid(f, levels=0)
    with pytest.raises(ValueError, match="factor"):
        CodePyramid(f, levels=1, factor=1.0)


def test_a_texture_only_pyramid_leaves_the_geometry_codes_alone(blob_mesh):
    f = textured_field(blob_mesh, interpolation="early")
    p = CodePyramid(f, levels=1, factor=3.0, kinds=("tex",))
    assert not hasattr(p, "geo")
    f.set_code_prior(p)
    with torch.no_grad():
        p.tex.normal_(0, 0.3)
    geo0 = f.geo_codes.detach().clone()
    i = torch.arange(50)
    g, t = f.codes(("geo", "tex"), i)
    assert torch.equal(g, geo0[i]) and not torch.allclose(t, f.tex_codes[i])
    p.bake(f)
    assert torch.equal(f.geo_codes, geo0)
    with pytest.raises(ValueError, match="kinds"):
        CodePyramid(f, levels=1, kinds=("sem",))


def test_saving_a_field_with_coarse_levels_writes_a_plain_field(blob_mesh, tmp_path):
    # snapshots taken from a training callback call save_field on the live field: the file must render
    # what the field renders, without the (training-only) levels, and the live split must survive
    from neumesh_core.field.io import load_field, save_field

    f = textured_field(blob_mesh, interpolation="early")
    p = CodePyramid(f, levels=2, factor=3.0)
    f.set_code_prior(p)
    with torch.no_grad():
        p.geo.normal_(0, 0.3)
        p.tex.normal_(0, 0.3)
    x, d = _queries(f, 300, seed=2)
    sigma, rgb, _ = f.query(x, d)
    geo_before, coarse_before = f.geo_codes.detach().clone(), p.geo.detach().clone()
    save_field(f, str(tmp_path / "snap.neumesh"))
    assert f.code_prior is p and torch.equal(f.geo_codes, geo_before) and torch.equal(p.geo, coarse_before)
    g = load_field(str(tmp_path / "snap.neumesh"))
    assert g.code_prior is None
    sigma2, rgb2, _ = g.query(x, d)
    assert torch.allclose(sigma2, sigma, rtol=1e-5, atol=1e-6) and torch.allclose(rgb2, rgb, atol=1e-6)
