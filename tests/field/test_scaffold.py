"""neumesh_core.field.scaffold: tangent frames and what set_vertices refreshes."""
import numpy as np
import pytest
import torch

from neumesh_core.field import scaffold as S
from neumesh_core.field.field import NeuMeshField
from neumesh_core.field.knn import knn_radius_reference


def _frames_reference(v, n, towards):
    """The plain per-row formula in float64: t = edge to the tangent neighbour projected on the tangent
    plane, normalised; where that edge is missing or within 1e-4 rad of the normal, a fixed axis
    projected instead."""
    v, n = v.double(), n.double()
    out = torch.zeros(len(v), 3, 3, dtype=torch.float64)
    for i in range(len(v)):
        e = v[towards[i]] - v[i]
        t = e - (e @ n[i]) * n[i]
        if t.norm() <= 1e-4 * e.norm():
            axis = torch.tensor([1.0, 0, 0]) if abs(n[i, 0]) < 0.9 else torch.tensor([0, 1.0, 0])
            t = axis.double() - (axis.double() @ n[i]) * n[i]
        t = t / t.norm()
        out[i] = torch.stack([t, torch.linalg.cross(n[i], t), n[i]], -1)
    return out.float()


def test_tangent_frames_match_the_per_row_formula():
    g = torch.Generator().manual_seed(0)
    v = torch.randn(60, 3, generator=g)
    n = torch.nn.functional.normalize(torch.randn(60, 3, generator=g), dim=-1)
    towards = torch.randint(0, 60, (60,), generator=g)
    towards[:5] = torch.arange(5)                       # isolated vertices: no edge, fixed-axis fallback
    v[towards[10]] = v[10] + 0.5 * n[10]                # an edge along the normal: fallback too
    v[towards[30]] = v[30] + 0.5 * n[30] + 1e-3 * torch.linalg.cross(n[30], torch.tensor([0.0, 0, 1]))
    n[:3] = torch.tensor([1.0, 0.0, 0.0])           # normal on the first fallback axis: the second axis
    got = S.tangent_frames(v, n, towards)
    # atol: row 30's 1e-3 edge carries float32 round-off of the positions (~1e-7) magnified 1e3 times
    assert torch.allclose(got, _frames_reference(v, n, towards), atol=1e-4)
    eye = torch.eye(3).expand(60, 3, 3)
    assert torch.allclose(got.transpose(1, 2) @ got, eye, atol=1e-5)   # orthonormal, right-handed
    assert torch.allclose(torch.linalg.det(got), torch.ones(60), atol=1e-5)


def test_set_vertices_refreshes_index_normals_and_rotations(blob_mesh):
    f = NeuMeshField(blob_mesh)
    sc = f.scaffold
    g = torch.Generator().manual_seed(3)
    v = sc.rest_vertices * torch.tensor([1.3, 0.8, 1.0]) + 0.01 * torch.randn(sc.num_vertices, 3, generator=g)
    f.set_vertices(v)
    # the index built beside the main thread answers for the new positions
    x = v[::50] + 0.3 * sc.radius * torch.randn(len(v[::50]), 3, generator=g)
    idx, dist = sc.index.query(x)
    ridx, rdist = knn_radius_reference(x, v, sc.k, sc.radius)
    assert torch.allclose(dist, rdist, atol=1e-5, equal_nan=True)
    assert (idx == ridx).float().mean() > 0.99          # equal distances may swap
    from neumesh_core.mesh import vertex_normals

    assert torch.allclose(sc.normals, vertex_normals(v, sc.faces), atol=1e-5)
    frames = S.tangent_frames(v, sc.normals, sc.tangent_neighbour)
    assert torch.allclose(sc.to_rest @ frames, sc.rest_frames, atol=1e-5)   # current -> rest frames


def test_a_failed_index_build_leaves_the_field_as_it_was(blob_mesh, monkeypatch):
    f = NeuMeshField(blob_mesh)
    before = f.scaffold.index
    rest = f.vertices.copy()

    def broken(*a, **k):
        raise MemoryError("no room for the index")

    monkeypatch.setattr(S, "make_index", broken)
    with pytest.raises(MemoryError, match="no room"):
        f.set_vertices(rest + np.float32(0.1))
    assert f.scaffold.index is before and f.to_rest is None
    assert np.array_equal(f.vertices, rest)
    assert torch.equal(f.scaffold.normals, f.scaffold.rest_normals)
