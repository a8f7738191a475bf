import numpy as np
import pytest
import torch

from neumesh_core.errors import VertexMismatchError
from neumesh_core.field.field import FieldConfig, NeuMeshField
from neumesh_core.field.knn import knn_radius_reference
from neumesh_core.mesh import vertex_normals

from ..conftest import textured_field


def test_local_indicators_match_brute_force(blob_mesh):
    f = NeuMeshField(blob_mesh)
    g = torch.Generator().manual_seed(1)
    v = f.rest_vertices
    # points near the surface: vertices pushed along random directions
    x = v[torch.randint(0, len(v), (1000,), generator=g)] + 0.5 * f.radius * torch.randn(1000, 3, generator=g)
    nb = f.neighbourhood(x)
    ridx, rdist = knn_radius_reference(x, v, 4, f.radius)
    valid = ridx >= 0
    assert torch.equal(nb.valid, valid)
    n = torch.as_tensor(vertex_normals(blob_mesh.vertices, blob_mesh.faces))
    for m in range(0, 1000, 37):
        ids = ridx[m][valid[m]]
        if len(ids) == 0:
            assert nb.w[m].sum() == 0
            continue
        inv = 1.0 / rdist[m][valid[m]]
        w_ref = inv / inv.sum()
        p_ref = ((v[ids] - x[m]) * n[ids]).sum(-1)
        got = {int(i): (float(w), float(p)) for i, w, p, ok in zip(nb.idx[m], nb.w[m], nb.p[m], nb.valid[m]) if ok}
        for i, w, p in zip(ids.tolist(), w_ref.tolist(), p_ref.tolist()):
            assert got[i][0] == pytest.approx(w, abs=1e-5)
            assert got[i][1] == pytest.approx(p, abs=1e-5)


def test_hashgrid_backend_gives_the_same_field(blob_mesh):
    f = textured_field(blob_mesh)
    h = textured_field(blob_mesh, knn="hashgrid")
    assert type(h.scaffold.index).__name__ == "HashGridIndex"
    h.set_vertices(h.rest_vertices * 1.1)  # deforming rebuilds the index with the configured backend
    f.set_vertices(f.rest_vertices * 1.1)
    assert type(h.scaffold.index).__name__ == "HashGridIndex"
    g = torch.Generator().manual_seed(2)
    x = f.scaffold.vertices_[torch.randint(0, f.num_vertices, (2000,), generator=g)]
    x = x + 0.5 * f.radius * torch.randn(2000, 3, generator=g)
    d = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g), dim=-1)
    sf, cf = f.query(x, d)[:2]
    sh, ch = h.query(x, d)[:2]
    assert torch.allclose(sf, sh, atol=1e-4) and torch.allclose(cf, ch, atol=1e-5)
    with pytest.raises(ValueError, match="knn must be one of"):
        FieldConfig(knn="octree")


def test_post_interpolation_is_weighted_mean_of_per_neighbour_decodes(blob_mesh):
    f = textured_field(blob_mesh)
    x = f.rest_vertices[:50] + 0.01
    d = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    nb = f.neighbourhood(x)
    sigma, rgb, mod = f.decode(nb, d)
    from neumesh_core.field.encoding import frequency_encoding, sh_encoding, trunc_exp

    for m in range(0, 50, 7):
        s_ref = 0.0
        c_ref = torch.zeros(3)
        for k in range(4):
            if not nb.valid[m, k]:
                continue
            i = nb.idx[m, k]
            pe = frequency_encoding(nb.p[m, k:k + 1] / f.radius, f.config.pos_freqs)[0]
            w = nb.w[m, k]
            s_k = trunc_exp(f.geo_decoder(torch.cat([f.geo_codes[i], pe, w[None]]))[0])
            c_k = torch.sigmoid(f.rad_decoder(torch.cat([f.tex_codes[i], pe, w[None], sh_encoding(d[m], 4),
                                                         f.rest_normals[i]]))) + f.mod_colours[i]
            s_ref = s_ref + w * s_k
            c_ref = c_ref + w * c_k
        assert float(sigma[m].detach()) == pytest.approx(float(s_ref.detach()), rel=1e-4)
        assert torch.allclose(rgb[m], c_ref, atol=1e-5)


def test_far_points_have_zero_density(blob_mesh):
    f = textured_field(blob_mesh)
    sigma, rgb, _ = f.query(torch.tensor([[10.0, 0, 0], [0, 0, 0.0]]), torch.tensor([[1.0, 0, 0]] * 2))
    assert torch.all(sigma == 0)


@pytest.mark.parametrize("interp", ["post", "early"])
def test_decode_is_differentiable(blob_mesh, interp):
    f = textured_field(blob_mesh, interp)
    x = f.rest_vertices[:64] * 1.001
    sigma, rgb, _ = f.query(x, torch.nn.functional.normalize(torch.randn(64, 3), dim=-1))
    (sigma.mean() + rgb.mean()).backward()
    assert f.geo_codes.grad.abs().sum() > 0 and f.tex_codes.grad.abs().sum() > 0
    assert f.rad_decoder[0].weight.grad.abs().sum() > 0


def test_set_vertices_errors(blob_mesh):
    f = NeuMeshField(blob_mesh)
    with pytest.raises(VertexMismatchError, match="topology changed"):
        f.set_vertices(np.zeros((f.num_vertices + 3, 3)))
    bad = f.vertices.copy()
    bad[5, 1] = np.nan
    with pytest.raises(VertexMismatchError, match="NaN"):
        f.set_vertices(bad)
    with pytest.raises(VertexMismatchError):
        f.set_vertices(np.zeros((f.num_vertices,)))


def test_set_vertices_refreshes_geometry(blob_mesh):
    f = NeuMeshField(blob_mesh)
    v = f.vertices + np.array([5.0, 0, 0], np.float32)
    f.set_vertices(v)
    assert np.allclose(f.vertices, v)
    assert (f.grid.aabb[0, 0] > 3.0)
    idx, _ = f.scaffold.index.query(torch.as_tensor(v[:3]))
    assert idx[:, 0].tolist() == [0, 1, 2]
    f.reset_vertices()
    assert np.allclose(f.vertices, f.rest_vertices.numpy())
    assert f.to_rest is None


def test_auto_radius_scales_with_edges(blob_mesh):
    f = NeuMeshField(blob_mesh, FieldConfig(radius_scale=2.0))
    e = blob_mesh.edges()
    mean_edge = np.linalg.norm(blob_mesh.vertices[e[:, 0]] - blob_mesh.vertices[e[:, 1]], axis=1).mean()
    assert f.radius == pytest.approx(2.0 * mean_edge, rel=1e-5)


def test_same_mesh_and_config_give_the_same_field(blob_mesh):
    """Initialisation does not depend on (or disturb) the global RNG: results are reproducible."""
    torch.manual_seed(1)
    a = NeuMeshField(blob_mesh, FieldConfig())
    state = torch.random.get_rng_state()
    torch.manual_seed(2)
    b = NeuMeshField(blob_mesh, FieldConfig())
    for (name, pa), (_, pb) in zip(a.named_parameters(), b.named_parameters()):
        assert torch.equal(pa, pb), name  # seeded draws on one machine: exact by construction
    torch.manual_seed(1)
    NeuMeshField(blob_mesh, FieldConfig())
    assert torch.equal(torch.random.get_rng_state(), state)


def test_trunc_exp_saturates_without_inf():
    from neumesh_core.field.encoding import trunc_exp

    x = torch.tensor([0.0, 10.0, 200.0], requires_grad=True)
    y = trunc_exp(x)
    # what it protects: a huge input saturates at exp(15) (finite, not inf), and its gradient is finite
    # and positive.  torch's vectorised exp and numpy's libm may differ by an ulp or two between CPUs,
    # so the saturation value is compared with a relative tolerance of a few float32 ulps, not exactly.
    assert torch.isfinite(y).all()
    assert float(y[2].detach()) == pytest.approx(float(np.exp(15.0)), rel=1e-6)
    assert float(y[1].detach()) == pytest.approx(float(np.exp(10.0)), rel=1e-6)
    assert float(y[0].detach()) == pytest.approx(1.0, rel=1e-6)
    y.sum().backward()
    assert torch.isfinite(x.grad).all() and (x.grad > 0).all()  # a saturated sample can still be lowered


def test_tv_loss_over_given_vertices(blob_mesh):
    """``vertices`` restricts TV to those vertices: the value matches the formula, and only they and
    their TV neighbours receive gradient."""
    f = textured_field(blob_mesh)
    with torch.no_grad():
        f.geo_codes.normal_(generator=torch.Generator().manual_seed(2))
    ids = torch.tensor([3, 17, 40, 41])
    j = f.scaffold.tv_neighbours[ids]
    ref = ((f.geo_codes[ids][:, None] - f.geo_codes[j]).pow(2).sum(-1).mean()
           + (f.tex_codes[ids][:, None] - f.tex_codes[j]).pow(2).sum(-1).mean())
    tv = f.tv_loss(vertices=ids)
    assert float(tv.detach()) == pytest.approx(float(ref.detach()), rel=1e-6) and float(tv.detach()) > 0
    tv.backward()
    rows = set(f.geo_codes.grad.abs().sum(1).nonzero().squeeze(1).tolist())
    assert rows and rows <= set(ids.tolist()) | set(j.reshape(-1).tolist())
    assert set(ids.tolist()) <= rows
    assert float(f.tv_loss(vertices=torch.zeros(0, dtype=torch.long)).detach()) == 0.0
    with pytest.raises(IndexError, match="vertex indices"):
        f.tv_loss(vertices=torch.tensor([f.num_vertices]))


def test_a_deep_copy_is_independent_and_renders_the_same(blob_mesh):
    import copy

    f = textured_field(blob_mesh)
    f.set_vertices(f.rest_vertices * 1.1)
    g = copy.deepcopy(f)
    x = f.scaffold.vertices_[:50] * 1.001
    d = torch.nn.functional.normalize(torch.ones(50, 3), dim=-1)
    a, b = f.query(x, d), g.query(x, d)
    # exact on purpose: copied tensors through the same path in one process
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    g.reset_vertices()
    with torch.no_grad():
        g.tex_codes.zero_()
    assert f.to_rest is not None and f.tex_codes.abs().sum() > 0   # the original is untouched


def test_run_decoder_in_row_blocks_matches_one_call():
    from neumesh_core.field import field as fm

    torch.manual_seed(0)
    mlp = fm._mlp(16, 64, 3)
    x = torch.randn(fm._INFERENCE_ROWS * 2 + 123, 16)
    with torch.no_grad():
        blocks = fm.run_decoder(mlp, x)
        whole = mlp(x)
    assert blocks.shape == whole.shape
    assert torch.allclose(blocks, whole, atol=1e-6, rtol=1e-5)
    # with autograd on it is one call, and gradients flow
    y = fm.run_decoder(mlp, x[:50].requires_grad_())
    y.sum().backward()
    assert mlp[0].weight.grad is not None


def test_take_rows_is_advanced_indexing():
    from neumesh_core.field.scaffold import take_rows

    g = torch.Generator().manual_seed(5)
    for table in (torch.randn(50, 7, generator=g), torch.randn(50, generator=g), torch.randn(50, 3, 3, generator=g),
                  torch.randint(0, 9, (50,), generator=g).to(torch.int16)):
        for idx in (torch.randint(0, 50, (13, 4), generator=g), torch.randint(0, 50, (9,), generator=g),
                    torch.zeros(0, 4, dtype=torch.long), torch.randint(0, 50, (6, 4), generator=g).t()):
            got = take_rows(table, idx)
            assert got.shape == table[idx].shape and torch.equal(got, table[idx])
    t = torch.randn(20, 3, requires_grad=True)
    take_rows(t, torch.tensor([[1, 1], [2, 5]])).sum().backward()
    assert t.grad[1].tolist() == [2.0, 2.0, 2.0] and t.grad[0].tolist() == [0.0, 0.0, 0.0]


def _assert_decode_matches_autograd_reference(f, nb, d):
    """The decode without autograd (rendering's fast paths) against the same decode with autograd on
    (the reference paths): sigma, rgb and mod colour."""
    with torch.no_grad():
        fast = f.decode(nb, d)
    with torch.enable_grad():
        ref = [t.detach() for t in f.decode(nb, d)]
    for a, b in zip(fast, ref):
        assert torch.allclose(a, b, atol=1e-5, rtol=1e-5), (a - b).abs().max()


@pytest.mark.parametrize("case", ["rest", "deformed", "tex_frame", "two_decoders"])
def test_early_decode_without_autograd_matches_the_gather_reference(blob_mesh, case):
    """Rendering (autograd off) sums w-weighted per-vertex rows with one embedding bag; with autograd
    on, the same decode gathers the (M,K,C) rows and sums them (the reference)."""
    f = textured_field(blob_mesh, interpolation="early")
    if case == "deformed":
        f.set_vertices(f.rest_vertices * torch.tensor([1.2, 1.0, 0.9]))
    if case == "tex_frame":
        q, _ = torch.linalg.qr(torch.randn(f.num_vertices, 3, 3, generator=torch.Generator().manual_seed(7)))
        f.tex_frame = q
    if case == "two_decoders":
        import copy

        dec = copy.deepcopy(f.rad_decoder)
        with torch.no_grad():
            dec[0].weight.mul_(-1.0)
        i = f.add_decoder(dec)
        f.decoder_id[: f.num_vertices // 2] = i
    g = torch.Generator().manual_seed(6)
    v = f.scaffold.vertices_
    x = v[torch.randint(0, f.num_vertices, (3000,), generator=g)] + 0.6 * f.radius * torch.randn(3000, 3, generator=g)
    d = torch.nn.functional.normalize(torch.randn(3000, 3, generator=g), dim=-1)
    nb = f.neighbourhood(x)
    assert bool((~nb.valid).any()) and bool(nb.valid.all(1).any())   # partial and full neighbourhoods
    _assert_decode_matches_autograd_reference(f, nb, d)


def test_run_decoder_on_column_blocks_matches_the_concatenated_input():
    from neumesh_core.field import field as fm

    torch.manual_seed(1)
    mlp = fm._mlp(12, 32, 3)
    n = fm._INFERENCE_ROWS + 77
    parts = [torch.randn(n, 5), torch.randn(n, 1), torch.randn(n, 4)[:, 1:].contiguous(), torch.randn(n, 4)[:, :3]]
    with torch.no_grad():
        whole = mlp(torch.cat(parts, -1))
        for ps in (parts, [p[:10] for p in parts], [p[:0] for p in parts]):
            got = fm.run_decoder(mlp, ps)
            ref = whole[:len(ps[0])]
            assert got.shape == ref.shape and torch.allclose(got, ref, atol=1e-6, rtol=1e-5)
    # with autograd on: one call on the concatenation, gradients reach every block
    ps = [p[:20].clone().requires_grad_() for p in parts]
    fm.run_decoder(mlp, ps).sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in ps)


@pytest.mark.parametrize("sparse", [False, True])
def test_post_decode_without_autograd_matches_the_per_row_reference(blob_mesh, sparse):
    """Post-interpolation without autograd encodes each sample's direction once (at rest, no texture
    frames); with autograd every neighbour row encodes its own copy (the reference)."""
    f = textured_field(blob_mesh)
    g = torch.Generator().manual_seed(8)
    v = f.rest_vertices
    spread = 0.95 if sparse else 0.2    # far points leave neighbour slots empty: the sparse layout
    x = v[torch.randint(0, f.num_vertices, (2000,), generator=g)] + \
        spread * f.radius * torch.randn(2000, 3, generator=g)
    d = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g), dim=-1)
    nb = f.neighbourhood(x)
    dense = int(nb.valid.sum()) >= 0.85 * nb.valid.numel()
    assert dense != sparse
    _assert_decode_matches_autograd_reference(f, nb, d)
