import numpy as np
import pytest
import torch

from neumesh_core.field.knn import (HashGridIndex, KDTreeIndex, knn_radius_reference, make_index,
                                   vertex_neighbours)


def _assert_matches_reference(idx, dist, ridx, rdist, radius):
    assert torch.equal(idx >= 0, ridx >= 0)
    valid = ridx >= 0
    assert torch.allclose(dist[valid], rdist[valid], atol=1e-5)
    same = (idx == ridx) | ~valid  # indices agree except for exact distance ties
    assert same.float().mean() > 0.999
    assert (dist[valid] <= radius).all()
    assert torch.isinf(dist[~valid]).all() and (idx[~valid] == -1).all()


@pytest.mark.parametrize("radius", [0.05, 0.15, float("inf")])
def test_kdtree_matches_brute_force(radius):
    g = torch.Generator().manual_seed(0)
    verts = torch.rand(3000, 3, generator=g)
    pts = torch.rand(2000, 3, generator=g) * 1.2 - 0.1
    idx, dist = KDTreeIndex(verts, k=4, radius=radius).query(pts)
    ridx, rdist = knn_radius_reference(pts, verts, 4, radius)
    _assert_matches_reference(idx, dist, ridx, rdist, radius)


@pytest.mark.parametrize("radius", [0.03, 0.05, 0.15])
def test_hashgrid_matches_brute_force(radius):
    g = torch.Generator().manual_seed(0)
    verts = torch.rand(3000, 3, generator=g)
    # points inside, around and far outside the vertices' box (the far ones find nothing)
    pts = torch.cat([torch.rand(2000, 3, generator=g) * 1.2 - 0.1,
                     torch.tensor([[50.0, 0.5, 0.5], [-1e6, -1e6, 1e6]])])
    # a small chunk so that the chunked path runs too
    idx, dist = HashGridIndex(verts, k=4, radius=radius, chunk=700).query(pts)
    ridx, rdist = knn_radius_reference(pts, verts, 4, radius)
    _assert_matches_reference(idx, dist, ridx, rdist, radius)
    assert (ridx >= 0).any() and (ridx < 0).any()  # both cases are exercised


def test_hashgrid_matches_kdtree_on_a_surface(blob_mesh):
    # the field's use: a 2D scaffold, samples near it, radius a few edges
    v = torch.as_tensor(blob_mesh.vertices, dtype=torch.float32)
    edge = float((v[blob_mesh.faces[:, 0]] - v[blob_mesh.faces[:, 1]]).norm(dim=1).mean())
    g = torch.Generator().manual_seed(3)
    x = v[torch.randint(0, len(v), (5000,), generator=g)] + edge * torch.randn(5000, 3, generator=g)
    idx, dist = HashGridIndex(v, 4, 2.5 * edge).query(x)
    kidx, kdist = KDTreeIndex(v, 4, 2.5 * edge).query(x)
    _assert_matches_reference(idx, dist, kidx, kdist, 2.5 * edge)


def test_hashgrid_edge_cases():
    verts = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0.05, 0, 0]])
    idx, dist = HashGridIndex(verts, k=4, radius=0.5).query(torch.tensor([[0.1, 0, 0]]))
    assert idx.tolist() == [[2, 0, -1, -1]]
    assert dist[0, :2].tolist() == pytest.approx([0.05, 0.1])
    empty_idx, empty_dist = HashGridIndex(torch.empty(0, 3), k=2, radius=1.0).query(torch.zeros(3, 3))
    assert (empty_idx == -1).all() and torch.isinf(empty_dist).all()
    none_idx, _ = HashGridIndex(verts, k=2, radius=1.0).query(torch.empty(0, 3))
    assert none_idx.shape == (0, 2)
    with pytest.raises(ValueError, match="finite positive radius"):
        HashGridIndex(verts, k=2, radius=float("inf"))


def test_make_index_names_backends():
    v = torch.rand(50, 3)
    assert isinstance(make_index(v, 4, 0.3, "auto"), KDTreeIndex)       # on the CPU: the KD-tree
    assert isinstance(make_index(v, 4, 0.3, "kdtree"), KDTreeIndex)     # the name older files saved for auto
    assert isinstance(make_index(v, 4, 0.3, "hashgrid"), HashGridIndex)
    with pytest.raises(ValueError, match="auto, hashgrid"):
        make_index(v, 4, 0.3, "octree")


def test_field_config_reads_kdtree_as_auto():
    """Field files saved with knn="kdtree" (what "auto" was called) load with the same neighbour search."""
    from neumesh_core.field.params import FieldConfig

    assert FieldConfig(knn="kdtree").knn == "auto" and FieldConfig().knn == "auto"


def test_fewer_vertices_than_k():
    verts = torch.tensor([[0.0, 0, 0], [1.0, 0, 0]])
    idx, dist = KDTreeIndex(verts, k=4).query(torch.tensor([[0.1, 0, 0]]))
    assert idx.tolist() == [[0, 1, -1, -1]]
    assert torch.isinf(dist[0, 2:]).all()


def test_vertex_neighbours_excludes_self():
    v = np.random.default_rng(0).random((500, 3)).astype(np.float32)
    nb = vertex_neighbours(v, 6)
    assert nb.shape == (500, 6)
    assert not (nb == np.arange(500)[:, None]).any()


def test_a_triton_index_asked_for_where_triton_cannot_run_is_the_devices_default(monkeypatch):
    """FieldConfig(knn="triton") saved with a field trained on a GPU: on a CPU without Triton's
    interpreter the field still loads and searches with the KD-tree."""
    from neumesh_core.kernels import knn as knn_triton

    monkeypatch.setattr(knn_triton, "triton_runs_on", lambda device: False)
    v = torch.rand(50, 3)
    assert isinstance(make_index(v, 4, 0.3, "triton"), KDTreeIndex)
