"""neumesh_core.mesh: unique_edges (the 1-D key path) against the plain row-unique reference."""
import numpy as np

from neumesh_core.mesh import unique_edges


def test_unique_edges_matches_the_row_unique_reference():
    rng = np.random.default_rng(0)
    faces = rng.integers(0, 500, (3000, 3))
    faces[:5] = [0, 0, 1]                       # degenerate triangles and repeated faces
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    ref = np.unique(e, axis=0)
    got = unique_edges(faces)
    assert got.dtype == np.int64 and np.array_equal(got, ref)   # integer data: exact
    assert (got[:, 0] <= got[:, 1]).all()
    assert unique_edges(np.zeros((0, 3), np.int64)).shape == (0, 2)
    assert np.array_equal(unique_edges([[2, 1, 0]]), [[0, 1], [0, 2], [1, 2]])


def test_vertex_normals_through_the_incidence_matrix_match_the_index_add_reference():
    import torch

    from neumesh_core.mesh import face_incidence, vertex_normals

    rng = np.random.default_rng(1)
    v = rng.normal(size=(400, 3)).astype(np.float32)
    faces = rng.integers(0, 380, (900, 3))          # vertices 380.. belong to no face: the (0,0,1) fallback
    faces[:4] = [7, 7, 8]                           # degenerate faces add nothing
    inc = face_incidence(faces, len(v))
    assert inc.shape == (400, 900) and inc.layout == torch.sparse_csr
    dense = torch.zeros(400, 900)
    for j in range(3):
        dense[torch.as_tensor(faces[:, j]), torch.arange(900)] += 1.0
    assert torch.equal(inc.to_dense(), dense)      # small integers: exact
    ref = vertex_normals(torch.as_tensor(v), torch.as_tensor(faces))
    got = vertex_normals(torch.as_tensor(v), torch.as_tensor(faces), inc)
    # the same face vectors summed in another order: float32 round-off only
    assert torch.allclose(got, ref, atol=1e-5)
    assert torch.equal(got[380:], torch.tensor([[0.0, 0.0, 1.0]]).expand(20, 3))
    assert np.allclose(vertex_normals(v, faces, inc), ref.numpy(), atol=1e-5)   # numpy in, numpy out
