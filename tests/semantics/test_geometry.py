"""Geometric selection features: creases, the crease-aware heat embedding, the cache, and selection of
parts that share one colour (a field whose semantic features are the same on every vertex)."""
import numpy as np
import pytest
import torch

import neumesh_core as nm
from neumesh_core.data import multipart as mp
from neumesh_core.semantics import SelectConfig, SelectionContext, select_at_point
from neumesh_core.semantics import geometry as geo

from ..conftest import one_thread


@pytest.fixture(scope="module")
def mp_mesh():
    return mp.multipart_mesh(grid=48)


def _part_means(emb, labels):
    m = np.stack([emb[labels == p].mean(0) for p in range(4)])
    return m / np.linalg.norm(m, axis=1, keepdims=True)


@pytest.mark.parametrize("max_vertices", [100_000, 2_000])   # the plain path (no decimation) and clustered
def test_heat_embedding_separates_the_parts(mp_mesh, max_vertices):
    mesh, labels = mp_mesh
    cfg = geo.GeometryConfig(max_vertices=max_vertices, sdf_rays=0)
    with one_thread():
        f = geo.compute_geometric_features(mesh.vertices, mesh.faces, cfg)
    assert (len(f.embedding) == mesh.num_vertices) == (max_vertices >= mesh.num_vertices)
    assert f.cluster.shape == (mesh.num_vertices,) and f.cluster.max() < len(f.embedding)
    emb = f.vertex_embedding()
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-4)
    means = _part_means(emb, labels)
    cross = means @ means.T - np.eye(4)
    assert np.abs(cross).max() < 0.2, np.round(means @ means.T, 2)   # parts ~orthogonal
    for p in range(4):
        assert (emb[labels == p] @ means[p] >= 0.75).mean() > 0.95   # ~constant inside a part
    assert f.log_sdf is None and f.timings["parts"] == 4


def test_signed_bend_and_concavity_of_a_fold():
    # a V-shaped valley (concave seen from +z, where the normals point) and a ridge (convex)
    x = np.array([-1.0, 0.0, 1.0])
    for sign, concave in ((1.0, True), (-1.0, False)):
        v = np.array([[xi, y, sign * abs(xi)] for y in (0.0, 1.0) for xi in x], np.float32)
        f = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]])
        n = geo.smoothed_normals(v, f, 0)
        if n[:, 2].mean() < 0:
            f = f[:, ::-1].copy()
            n = geo.smoothed_normals(v, f, 0)
        b = geo.signed_bend(v, n, np.array([0]), np.array([2]))
        assert (b[0] < -0.5) if concave else (b[0] > 0.5)
        c = geo.vertex_concavity(v, n, f)
        assert (c.max() > 0.5) == concave and (c >= 0).all()


def test_attach_copies_the_best_agreeing_reachable_neighbour():
    # path 0-1-2-3, 4 isolated; 0 and 3 are ok; 1 agrees with 0, 2 with 3
    import scipy.sparse as sp

    e = np.array([[0, 1], [1, 2], [2, 3]])
    a = sp.coo_matrix((np.ones(3), (e[:, 0], e[:, 1])), shape=(5, 5)).tocsr()
    a = a + a.T
    n = np.array([[1, 0, 0], [1, 0.1, 0], [0, 1, 0.1], [0, 1, 0], [0, 0, 1]], np.float32)
    ok = np.array([True, False, False, True, False])
    assert geo.attach(ok, a, n).tolist() == [0, 0, 3, 3, -1]


def test_clustering_is_the_identity_below_the_target_and_a_partition_above(mp_mesh):
    mesh, _ = mp_mesh
    c, p, f = geo.cluster_vertices(mesh.vertices, mesh.faces, 10 ** 6)
    assert np.array_equal(c, np.arange(mesh.num_vertices)) and np.array_equal(f, mesh.faces)
    c, p, f = geo.cluster_vertices(mesh.vertices, mesh.faces, 1000)
    assert len(p) <= 1000 and f.max() < len(p) and (f[:, 0] != f[:, 1]).all()
    # a cluster's position is the mean of its vertices
    np.testing.assert_allclose(p[c[0]], mesh.vertices[c == c[0]].mean(0), atol=1e-5)


def test_cache_file_round_trip_and_key(tmp_path, mp_mesh, monkeypatch):
    mesh, _ = mp_mesh
    field = nm.create_field(mesh, nm.FieldConfig())
    cfg = geo.GeometryConfig(max_vertices=1500, sdf_rays=4)
    geo._MEMO.clear()
    with one_thread():
        a = geo.geometric_features(field, cfg, cache_dir=str(tmp_path))
    files = list(tmp_path.glob("neumesh-geometry-*.npz"))
    assert len(files) == 1 and a.log_sdf is not None
    geo._MEMO.clear()
    monkeypatch.setattr(geo, "compute_geometric_features", lambda *a, **k: pytest.fail("recomputed"))
    b = geo.geometric_features(field, cfg, cache_dir=str(tmp_path))   # read from the file
    for name in ("normals", "concavity", "embedding", "cluster", "log_sdf"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert b.key == a.key and b.config == cfg
    assert geo.load_geometric_features(files[0], key="another") is None
    assert geo.load_geometric_features(tmp_path / "missing.npz") is None
    # another rest pose is another scaffold
    moved = field.rest_vertices.numpy().copy()
    moved[0] += 0.01
    assert geo.scaffold_key(moved, field.faces.numpy(), cfg) != a.key


def _uniform_semantics_field(mesh):
    """A field whose semantic feature is the same on every vertex: colour says nothing about parts."""
    field = nm.create_field(mesh, nm.FieldConfig())
    field.enable_semantics(8, 16)
    with torch.no_grad():
        field.sem_codes.copy_(field.sem_codes[:1].expand_as(field.sem_codes))
    return field


def test_parts_of_one_colour_come_apart_by_shape(mp_mesh):
    mesh, labels = mp_mesh
    field = _uniform_semantics_field(mesh)
    geo._MEMO.clear()
    ctx = SelectionContext(field).prepare()
    assert ctx.geometry is not None and ctx.cut_graph.nnz < ctx.graph.nnz   # crease edges cut
    V = field.vertices
    ious = {}
    with one_thread():
        for p in range(4):
            inside = np.nonzero(labels == p)[0]
            # a vertex of the part far from the others: deepest by distance to other parts' vertices
            from pykdtree.kdtree import KDTree

            d, _ = KDTree(V[labels != p]).query(V[inside], k=1)
            sel = select_at_point(field, V[inside[np.argmax(d)]], context=ctx)
            gt = inside
            ious[mp.PART_NAMES[p]] = len(np.intersect1d(sel.vertices, gt)) / len(np.union1d(sel.vertices, gt))
            # Similarity still grows / shrinks the region
            loose = select_at_point(field, V[inside[np.argmax(d)]], SelectConfig(threshold=0.55), context=ctx)
            assert set(sel.vertices) <= set(loose.vertices)
        everything = select_at_point(field, V[labels == 0][0], SelectConfig(geometry=0.0, creases=False), context=ctx)
    assert all(v >= 0.85 for v in ious.values()), ious
    assert len(everything.vertices) > 0.95 * field.num_vertices   # colour alone cannot tell the parts


def test_combined_growth_equals_the_step_by_step_fixed_point(mp_mesh):
    from .test_select import _grow_step_by_step

    mesh, _ = mp_mesh
    field = _uniform_semantics_field(mesh)
    with torch.no_grad():   # some variation in the semantic features too
        field.sem_codes.add_(0.3 * torch.randn_like(field.sem_codes))
    ctx = SelectionContext(field)
    rng = np.random.default_rng(1)
    for t in (0.6, 0.8):
        i = int(rng.integers(field.num_vertices))
        mean = ctx.features[i]
        seeds = rng.integers(0, field.num_vertices, 20)
        got = ctx.grow(mean, seeds, t, i, 0.5, creases=True)
        ok = ctx.similarity(mean, i, 0.5) >= t
        assert np.array_equal(got, _grow_step_by_step(ctx.cut_graph, ok, seeds))
        direct = 0.5 * ctx.features @ (mean / np.linalg.norm(mean)) + 0.5 * ctx.geo_embedding @ ctx.geo_embedding[i]
        np.testing.assert_allclose(ctx.similarity(mean, i, 0.5), direct, atol=1e-5)


def test_shape_diameter_tells_thick_from_thin(mp_mesh):
    mesh, labels = mp_mesh
    with one_thread():
        f = geo.compute_geometric_features(mesh.vertices, mesh.faces, geo.GeometryConfig(sdf_rays=16))
    ls = f.log_sdf[f.cluster]
    med = [np.median(ls[labels == p]) for p in range(4)]
    assert med[0] > med[1] + 0.2 and med[0] > med[2] + 0.2 and med[0] > med[3] + 0.2   # the body is thickest
    field = _uniform_semantics_field(mesh)
    ctx = SelectionContext(field, SelectConfig(geometry_config=geo.GeometryConfig(sdf_rays=16)))
    body = int(np.nonzero(labels == 0)[0][np.argmax(ls[labels == 0])])
    with_sdf = ctx.similarity(ctx.features[0], body, 1.0)
    plain = ctx.geo_embedding @ ctx.geo_embedding[body]
    thin = labels == 2
    assert (with_sdf <= plain + 1e-6).all() and with_sdf[thin].mean() < plain[thin].mean()


def test_config_errors():
    with pytest.raises(ValueError, match="geometry is a weight"):
        SelectConfig(geometry=1.5)
    with pytest.raises(ValueError, match="crease_angle"):
        geo.GeometryConfig(crease_angle=200)
    with pytest.raises(geo.GeometryUnavailable, match="no faces"):
        geo.compute_geometric_features(np.zeros((3, 3), np.float32), np.zeros((0, 3), np.int64))


def test_semantic_tolerance_treats_close_features_as_alike(mp_mesh):
    """On an object of one colour the distilled (centred) features are small noise whose directions mean
    nothing: within the tolerance (extractor units) they count as alike; far apart, the cosine decides."""
    mesh, labels = mp_mesh
    field = _uniform_semantics_field(mesh)
    ctx = SelectionContext(field)
    rng = np.random.default_rng(0)
    n = field.num_vertices
    raw = rng.normal(size=(n, 16)).astype(np.float32) * 0.1      # noise, random directions
    raw[labels == 2] += 3.0                                       # the arm: another colour, far away
    ctx.raw_features = raw
    ctx.features = raw / np.linalg.norm(raw, axis=1, keepdims=True)
    body = np.nonzero(labels == 0)[0]
    mean_raw = raw[body].mean(0)
    mean = mean_raw / np.linalg.norm(mean_raw)
    cos_only = ctx.similarity(mean, raw_mean=mean_raw, tolerance=0.0)
    tol = ctx.similarity(mean, raw_mean=mean_raw, tolerance=1.0)
    assert (cos_only[body] >= 0.75).mean() < 0.5          # noise directions: the cosine scatters
    assert (tol[body] >= 0.75).mean() > 0.99 and (tol[labels == 2] < 0.5).all()
    assert (tol >= cos_only - 1e-6).all()
    d2 = ((raw - mean_raw) ** 2).sum(1)
    np.testing.assert_allclose(tol, np.maximum(cos_only, np.exp(-d2 / 2.0)), atol=1e-5)


def test_without_robust_laplacian_selection_falls_back_to_semantics(mp_mesh, monkeypatch):
    import sys

    mesh, labels = mp_mesh
    field = _uniform_semantics_field(mesh)
    geo._MEMO.clear()
    monkeypatch.setitem(sys.modules, "robust_laplacian", None)   # import fails
    ctx = SelectionContext(field)
    sel = select_at_point(field, field.vertices[0], context=ctx)
    assert ctx.geometry is None and "pip install robust-laplacian" in ctx.geometry_error
    assert "robust-laplacian" in sel.info["geometry"] and len(sel.vertices) > 0
