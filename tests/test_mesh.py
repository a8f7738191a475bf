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
