"""Alignment for texture swap: Umeyama, the automatic similarity guess, ARAP non-rigid ICP."""
import numpy as np
import pytest

from neumesh_core.edit.align import Similarity, arap_icp, initial_alignment, region_edges, rigid_icp, umeyama


def _rotation(seed):
    q = np.random.default_rng(seed).normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _cap(blob_mesh):
    """A curved, bumpy region of the built-in scene's mesh with its edges and mean edge length."""
    v = blob_mesh.vertices.astype(np.float64)
    region = np.nonzero(v[:, 0] > 0.1)[0]
    pts = v[region]
    e = region_edges(blob_mesh.faces, region)
    unit = np.linalg.norm(pts[e[:, 0]] - pts[e[:, 1]], axis=1).mean()
    return pts, e, unit


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_umeyama_recovers_a_known_similarity(seed):
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(30, 3))
    T = Similarity(float(rng.uniform(0.3, 3.0)), _rotation(seed), rng.normal(size=3))
    S = umeyama(p, T.apply(p))
    assert S.scale == pytest.approx(T.scale, rel=1e-9)
    assert np.allclose(S.R, T.R, atol=1e-9) and np.allclose(S.t, T.t, atol=1e-9)
    assert np.isclose(np.linalg.det(S.R), 1.0)
    # three pairs are enough; noise gives the least-squares answer close to the truth
    S3 = umeyama(p[:3], T.apply(p[:3]))
    assert np.allclose(S3.apply(p), T.apply(p), atol=1e-8)
    noisy = T.apply(p) + rng.normal(scale=1e-3, size=p.shape)
    assert np.abs(umeyama(p, noisy).apply(p) - T.apply(p)).max() < 1e-2


def test_umeyama_refuses_too_few_or_degenerate_pairs():
    p = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    with pytest.raises(ValueError, match="at least 3"):
        umeyama(p[:2], p[:2])
    with pytest.raises(ValueError, match="collinear"):
        umeyama(p, p)
    with pytest.raises(ValueError, match="pairs"):
        umeyama(p, np.zeros((4, 3)))


def test_automatic_alignment_finds_a_rotated_scaled_copy_of_a_region(blob_mesh):
    """No correspondences: principal axes + extents + the axis-sign choice by nearest-neighbour fit
    recover the similarity of a copy (the bumpy region has no symmetry that could fool it)."""
    pts, _, unit = _cap(blob_mesh)
    for seed in (3, 4, 5):
        T = Similarity(1.6, _rotation(seed), np.array([0.5, -2.0, 1.0]))
        A = initial_alignment(pts, T.apply(pts))
        err = np.linalg.norm(A.apply(pts) - T.apply(pts), axis=1).mean() / (1.6 * unit)
        assert err < 0.05, (seed, err)
        assert A.scale == pytest.approx(1.6, rel=0.02)


def test_rigid_icp_refines_a_perturbed_guess(blob_mesh):
    """Point-to-plane ICP (target normals given) reaches the exact pose of a copy from a guess 6 degrees
    and a quarter edge off; point-to-point ICP stalls at the vertex sampling's scale on a smooth
    surface and is only checked to improve on it."""
    from neumesh_core.mesh import vertex_normals

    pts, _, unit = _cap(blob_mesh)
    region = np.nonzero(blob_mesh.vertices[:, 0] > 0.1)[0]
    normals = vertex_normals(blob_mesh.vertices, blob_mesh.faces).astype(np.float64)[region]
    T = Similarity(1.0, _rotation(7), np.array([0.1, 0.2, 0.3]))
    target = T.apply(pts)
    guess = Similarity(1.0, T.R @ _small_rotation(0.1), T.t + 0.02)
    guess_err = np.linalg.norm(guess.apply(pts) - target, axis=1).mean()
    plane, err = rigid_icp(pts, target, guess, dst_normals=normals @ T.R.T)
    assert err < 1e-6 * unit and np.linalg.norm(plane.apply(pts) - target, axis=1).max() < 1e-6 * unit
    point, _ = rigid_icp(pts, target, guess, iterations=50)
    assert np.linalg.norm(point.apply(pts) - target, axis=1).mean() < guess_err


def _small_rotation(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _bend(x, degrees):
    """Bend points about the z axis: the region's y extent becomes an arc of ``degrees``."""
    ext = np.ptp(x[:, 1])
    k = np.radians(degrees) / ext
    c = x[:, 1].mean()
    y = x[:, 1] - c
    out = x.copy()
    out[:, 1] = c + np.sin(y * k) / k
    out[:, 0] = x[:, 0] + (1 - np.cos(y * k)) / k
    return out


@pytest.mark.parametrize("degrees, mean_edges", [(15, 0.05), (30, 0.2)])
def test_nonrigid_step_recovers_a_known_smooth_bend(blob_mesh, degrees, mean_edges):
    """The source is a copy of a region, the target the same region bent; vertex i of one is vertex i of
    the other, so the error is measured against the true correspondence (not only to the surface)."""
    pts, e, unit = _cap(blob_mesh)
    target = _bend(pts, degrees)
    rigid, _ = rigid_icp(pts, target, Similarity.identity())
    x0 = rigid.apply(pts)
    rigid_err = np.linalg.norm(x0 - target, axis=1).mean() / unit
    nr = arap_icp(x0, e, target, max_distance=5 * unit)
    err = np.linalg.norm(nr.points - target, axis=1).mean() / unit
    print(f"bend {degrees} deg: rigid {rigid_err:.3f}, non-rigid {err:.3f} edge lengths "
          f"(residual {nr.residual / unit:.3f})")
    assert err < mean_edges and err < rigid_err / 2
    assert nr.residual / unit < 0.1
    assert nr.residuals[-1] < nr.residuals[0]


def test_nonrigid_step_leaves_an_exact_fit_in_place(blob_mesh):
    pts, e, unit = _cap(blob_mesh)
    nr = arap_icp(pts, e, pts)
    assert np.abs(nr.points - pts).max() < 1e-6 * unit and nr.residual < 1e-6 * unit


def test_region_edges_are_reindexed_into_the_region(blob_mesh):
    region = np.array([0, 5, 9, 11, 12, 40])
    faces = np.array([[0, 5, 9], [9, 11, 100], [11, 12, 40]])
    e = region_edges(faces, region)
    # 9-11 lies on a face with a vertex outside the region, but both its ends are inside: kept
    assert sorted(map(tuple, e.tolist())) == [(0, 1), (0, 2), (1, 2), (2, 3), (3, 4), (3, 5), (4, 5)]


def test_polar_rotations_are_the_rotation_factor():
    """The rotation of R times a symmetric positive stretch is R; reflections and singular matrices
    still give proper rotations."""
    from neumesh_core.edit.align import polar_rotations

    rng = np.random.default_rng(0)
    R = np.stack([_rotation(s) for s in range(50)])
    P = rng.normal(size=(50, 3, 3)) * 0.3
    S = np.concatenate([R @ (P @ P.transpose(0, 2, 1) + np.eye(3)), np.zeros((1, 3, 3)), -np.eye(3)[None]])
    got = polar_rotations(S)
    assert np.allclose(got[:50], R, atol=1e-9)
    assert np.allclose(np.linalg.det(got), 1.0) and np.allclose(got @ got.transpose(0, 2, 1), np.eye(3), atol=1e-9)


def _open_box(n=24):
    """Points on five faces of a unit box (no lid): a bucket-like target of another shape."""
    g = (np.stack(np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n)), -1).reshape(-1, 2))
    z0 = np.zeros(len(g))
    faces = [np.c_[g, z0], np.c_[g[:, 0], z0, g[:, 1]], np.c_[g[:, 0], z0 + 1, g[:, 1]],
             np.c_[z0, g], np.c_[z0 + 1, g]]
    return np.unique(np.concatenate(faces).round(9), axis=0) * np.array([1.6, 1.0, 0.7])


def test_automatic_alignment_between_different_shapes_keeps_the_extent_scale(blob_mesh):
    """A dome onto an open box: no similarity fits both, and a free ICP scale could shrink the dome onto
    a patch of the box (lego's bucket <- a cap of another object went to scale 4e-19).  The scale
    stays the ratio of the extents and the aligned source spans the target."""
    from neumesh_core.edit.align import principal_frame

    pts, _, _ = _cap(blob_mesh)
    box = _open_box()
    A = initial_alignment(pts, box)
    ratio = principal_frame(box)[2] / principal_frame(pts)[2]
    assert A.scale == pytest.approx(ratio, rel=1e-9)
    x = A.apply(pts)
    assert np.ptp(x, axis=0).max() > 0.5 * np.ptp(box, axis=0).max()


def test_polar_rotations_fast_path_matches_the_svd_reference():
    """Horn's quaternion method against the batched-SVD reference: the same rotation where it is unique
    (full rank, and rank 2: a vertex whose edges lie in a plane), the same objective tr(R^T S) and a
    proper rotation where it is not (rank 1), the identity for a zero matrix."""
    from neumesh_core.edit.align import polar_rotations, polar_rotations_reference

    rng = np.random.default_rng(1)
    full = rng.normal(size=(200, 3, 3))
    a, b = rng.normal(size=(100, 3, 1)), rng.normal(size=(100, 3, 1))
    c, d = rng.normal(size=(100, 3, 1)), rng.normal(size=(100, 3, 1))
    rank2 = a @ b.transpose(0, 2, 1) + c @ d.transpose(0, 2, 1)
    rank1 = a[:20] @ b[:20].transpose(0, 2, 1)
    for S, unique in ((full, True), (rank2, True), (rank1, False)):
        got, ref = polar_rotations(S), polar_rotations_reference(S)
        assert np.allclose(got @ got.transpose(0, 2, 1), np.eye(3), atol=1e-9)
        assert np.allclose(np.linalg.det(got), 1.0, atol=1e-9)
        obj = lambda R: np.einsum("nij,nij->n", R, S)  # noqa: E731  tr(R^T S)
        assert np.allclose(obj(got), obj(ref), atol=1e-9 * np.abs(S).max())
        if unique:
            assert np.allclose(got, ref, atol=1e-7)
    assert np.array_equal(polar_rotations(np.zeros((2, 3, 3))), np.tile(np.eye(3), (2, 1, 1)))   # set exactly
