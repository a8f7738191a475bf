import numpy as np
import pytest
import torch

from neumesh_core.field.knn import VertexIndex, knn_radius_reference, vertex_neighbours


@pytest.mark.parametrize("radius", [0.05, 0.15, float("inf")])
def test_kdtree_matches_brute_force(radius):
    g = torch.Generator().manual_seed(0)
    verts = torch.rand(3000, 3, generator=g)
    pts = torch.rand(2000, 3, generator=g) * 1.2 - 0.1
    idx, dist = VertexIndex(verts, k=4, radius=radius).query(pts)
    ridx, rdist = knn_radius_reference(pts, verts, 4, radius)
    assert torch.equal(idx >= 0, ridx >= 0)
    valid = ridx >= 0
    assert torch.allclose(dist[valid], rdist[valid], atol=1e-5)
    # indices agree except for exact distance ties
    same = (idx == ridx) | ~valid
    assert same.float().mean() > 0.999
    assert (dist[valid] <= radius).all()
    assert torch.isinf(dist[~valid]).all()


def test_fewer_vertices_than_k():
    verts = torch.tensor([[0.0, 0, 0], [1.0, 0, 0]])
    idx, dist = VertexIndex(verts, k=4).query(torch.tensor([[0.1, 0, 0]]))
    assert idx.tolist() == [[0, 1, -1, -1]]
    assert torch.isinf(dist[0, 2:]).all()


def test_vertex_neighbours_excludes_self():
    v = np.random.default_rng(0).random((500, 3)).astype(np.float32)
    nb = vertex_neighbours(v, 6)
    assert nb.shape == (500, 6)
    assert not (nb == np.arange(500)[:, None]).any()
