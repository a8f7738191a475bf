"""ARAP deformation (neumesh_core.deform): the energy's fast pieces against plain references, the solver's
guarantees (rigid motions recovered, anchors fixed, energy decreasing), the cage against the full solve,
the one-call field form, and clear errors for bad input."""
import numpy as np
import pytest

from neumesh_core.deform import ArapConfig, ArapSolver, ArapTerms, arap, build_cage, edge_weights
from neumesh_core.deform.arap import covariances_reference, energy_reference, rhs_reference
from neumesh_core.deform.rotations import polar_rotations, polar_rotations_reference
from neumesh_core.errors import DeformError


def rot_y(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def rigid(R, t):
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t
    return M


@pytest.fixture(scope="module")
def blob(blob_mesh):
    v = np.asarray(blob_mesh.vertices, np.float64)
    f = np.asarray(blob_mesh.faces, np.int64)
    z = v[:, 2]
    return v, f, np.nonzero(z < z.min() + 0.2)[0], np.nonzero(z > z.max() - 0.2)[0]


def bend_targets(v, anchors, handles, degrees):
    """Handle targets of a bend of the z axis by ``degrees`` relative to the (fixed) bottom."""
    from neumesh_core.data.deformations import bend

    b = bend(v, degrees)
    src, dst = v[anchors], b[anchors]
    R = polar_rotations(((dst - dst.mean(0)).T @ (src - src.mean(0)))[None])[0]
    t = dst.mean(0) - R @ src.mean(0)
    return (b[handles] - t) @ R        # undo the bottom's motion: anchors stay at rest


def test_terms_match_the_per_edge_references(blob):
    v, f, _, _ = blob
    rng = np.random.default_rng(0)
    e, w = edge_weights(v, f)
    assert (w > 0).all() and len(e) == 3 * len(v) - 6          # a closed genus-0 mesh
    T = ArapTerms(v, e, w)
    x = v + 0.05 * rng.normal(size=v.shape)
    R = polar_rotations(rng.normal(size=(len(v), 3, 3)))
    np.testing.assert_allclose(T.covariances(x), covariances_reference(v, x, e, w), atol=1e-12)
    np.testing.assert_allclose(T.rhs(R), rhs_reference(v, R, e, w), atol=1e-12)
    assert T.energy(x, R) == pytest.approx(energy_reference(v, x, R, e, w), rel=1e-9)
    # L is the weighted graph Laplacian: rows sum to zero, x^T L x = sum_e w |dx|^2
    assert np.abs(np.asarray(T.laplacian.sum(1))).max() < 1e-9
    dx = x[e[:, 0]] - x[e[:, 1]]
    assert float((x * (T.laplacian @ x)).sum()) == pytest.approx(float((w * (dx * dx).sum(1)).sum()), rel=1e-9)


def test_polar_rotations_match_the_svd_reference_including_degenerate_inputs():
    rng = np.random.default_rng(1)
    full = rng.normal(size=(3000, 3, 3))
    planar = rng.normal(size=(500, 3, 2)) @ rng.normal(size=(500, 2, 3))     # flat 1-rings: rank 2
    rank1 = rng.normal(size=(2000, 3, 1)) @ rng.normal(size=(2000, 1, 3))   # double roots: the fallback
    S = np.concatenate([full, planar, rank1, np.zeros((2, 3, 3)), np.full((1, 3, 3), np.nan)])
    got, ref = polar_rotations(S), polar_rotations_reference(S[:-1])   # the SVD fails on NaN
    assert np.abs(got @ got.transpose(0, 2, 1) - np.eye(3)).max() < 1e-9
    assert np.abs(np.linalg.det(got) - 1).max() < 1e-9
    ok = slice(0, 3500)                      # unique maximiser: the same rotation
    np.testing.assert_allclose(got[ok], ref[ok], atol=1e-7)
    # rank 1: not unique, but as good a maximiser of tr(R^T S)
    tr = lambda R, M: np.einsum("nab,nab->n", R, M)   # noqa: E731
    assert (tr(got[3500:5500], rank1) >= tr(ref[3500:5500], rank1) - 1e-9).all()
    assert np.array_equal(got[-3:], np.tile(np.eye(3), (3, 1, 1)))            # zero and NaN: identity


def test_rigid_motion_of_the_handles_without_anchors_is_recovered(blob):
    v, f, _, handles = blob
    M = rigid(rot_y(50) @ rot_y(0), [0.3, -0.2, 0.5])
    s = ArapSolver(v, f, [], handles, ArapConfig(iterations=5, energies=True))
    res = s.solve(s.targets_from_transforms(M), warm_start=False)
    want = v @ M[:3, :3].T + M[:3, 3]
    np.testing.assert_allclose(res.vertices, want, atol=1e-9)
    np.testing.assert_allclose(res.rotations, np.broadcast_to(M[:3, :3], res.rotations.shape), atol=1e-9)
    # warm-started from a translated pose, the local-global iterations alone head for the rotated one
    # (linearly, and slowly for a global rotation: the energy falls by 100x, the error by 4x)
    start = s.solve(v[handles] + [0.1, 0.0, 0.0], warm_start=False).vertices
    M2 = rigid(rot_y(25), [0.1, 0.0, 0.0])
    res2 = s.solve(s.targets_from_transforms(M2), iterations=150)
    want2 = v @ M2[:3, :3].T + M2[:3, 3]
    assert np.abs(res2.vertices - want2).max() < 0.25 * np.abs(start - want2).max()
    assert res2.energies[-1] < 1e-2 * res2.energies[0]


def test_anchors_stay_and_handles_reach_their_targets(blob):
    v, f, anchors, handles = blob
    q = bend_targets(v, anchors, handles, 70)
    for cage in (0, 400):
        s = ArapSolver(v, f, anchors, handles, ArapConfig(iterations=10, cage_vertices=cage, coarse_start=0))
        res = s.solve(q)
        np.testing.assert_allclose(res.vertices[anchors], v[anchors], atol=1e-12)
        np.testing.assert_allclose(res.vertices[handles], q, atol=1e-12)
        free = np.setdiff1d(np.arange(len(v)), np.concatenate([anchors, handles]))
        assert np.abs(res.vertices[free] - v[free]).max() > 0.1          # the rest did follow


def test_energy_decreases_over_the_iterations(blob):
    v, f, anchors, handles = blob
    q = bend_targets(v, anchors, handles, 90)
    for weights in ("cotangent", "uniform"):
        s = ArapSolver(v, f, anchors, handles,
                       ArapConfig(weights=weights, iterations=40, tolerance=0.0, coarse_start=0, energies=True))
        E = np.array(s.solve(q).energies)
        assert len(E) == 40
        assert (np.diff(E) <= 1e-9 * E[0]).all(), weights
        assert E[-1] < 0.7 * E[0]
        # the energy reported is the energy of the returned pose
        e, w = edge_weights(v, f, weights)
        res = s.solve(q, iterations=1)
        assert res.energies[-1] == pytest.approx(energy_reference(v, res.vertices, res.rotations, e, w), rel=1e-7)


def test_a_cage_solve_is_close_to_the_full_solve_on_a_smooth_bend(blob):
    v, f, anchors, handles = blob
    q = bend_targets(v, anchors, handles, 35)
    full = ArapSolver(v, f, anchors, handles, ArapConfig(iterations=150, coarse_start=400)).solve(q)
    cage_solver = ArapSolver(v, f, anchors, handles, ArapConfig(iterations=150, cage_vertices=500))
    cage = cage_solver.solve(q)
    assert 400 <= len(cage_solver.cage.samples) <= 650
    size = np.ptp(v, 0).max()
    moved = np.linalg.norm(full.vertices - v, axis=1)
    d = np.linalg.norm(cage.vertices - full.vertices, axis=1)
    assert moved.mean() > 0.05 * size
    # a coarser discretisation of the same energy: close on average, a few per cent at worst
    assert d.mean() < 0.01 * size and d.max() < 0.08 * size
    # per-vertex rotations close too (the carried blend of the cage's)
    ang = np.degrees(np.arccos(np.clip((np.einsum("nab,nab->n", cage.rotations, full.rotations) - 1) / 2, -1, 1)))
    assert np.median(ang) < 8.0


def test_the_cage_carry_reproduces_the_rest_pose_and_keeps_every_group(blob):
    v, f, anchors, handles = blob
    lone = np.array([int(np.argmax(v[:, 0]))])                 # a one-vertex group must get a cage vertex
    cage = build_cage(v, f, 300, keep=[anchors, handles, lone])
    for g in (anchors, handles, lone):
        assert np.isin(g, cage.samples).any()
    W = cage.W
    np.testing.assert_allclose(np.asarray(W.sum(1)).ravel(), 1.0, atol=1e-12)
    y = v[cage.samples]
    R = np.tile(np.eye(3), (len(y), 1, 1))
    size = np.ptp(v, 0).max()
    for carry, tol in ((cage.carry_reference, 1e-12), (cage.carry, 1e-6)):   # float32: 1e-6 of the size
        x, _ = carry(y, R, v)
        np.testing.assert_allclose(x, v, atol=tol * size)
        # a rigid motion of the cage carries to the same rigid motion of every vertex
        Rm = rot_y(40)
        x, A = carry(y @ Rm.T + 1.0, np.tile(Rm, (len(y), 1, 1)), v)
        np.testing.assert_allclose(x, v @ Rm.T + 1.0, atol=max(1e-9, tol) * size)


def test_the_float32_carry_matches_its_float64_reference(blob):
    v, f, anchors, handles = blob
    rng = np.random.default_rng(3)
    cage = build_cage(v, f, 300, keep=[anchors, handles])
    y = v[cage.samples] + 0.05 * rng.normal(size=(len(cage.samples), 3))
    R = polar_rotations(np.eye(3) + 0.3 * rng.normal(size=(len(y), 3, 3)))
    x, A = cage.carry(y, R, v)
    xr, Ar = cage.carry_reference(y, R, v)
    assert np.abs(xr - v).max() > 0.01                        # it moved: the comparison means something
    np.testing.assert_allclose(x, xr, atol=2e-6 * np.abs(v).max())
    np.testing.assert_allclose(A, Ar, atol=1e-6)


def test_warm_start_follows_a_drag(blob):
    v, f, anchors, handles = blob
    s = ArapSolver(v, f, anchors, handles, ArapConfig(iterations=4, coarse_start=0))
    cold = ArapSolver(v, f, anchors, handles, ArapConfig(iterations=200, tolerance=1e-6, coarse_start=300))
    for deg in (10, 20, 30, 40):              # a drag: small steps, a few iterations each
        res = s.solve(bend_targets(v, anchors, handles, deg))
    q = bend_targets(v, anchors, handles, 40)
    ref = cold.solve(q)
    from_rest = s.solve(q, warm_start=False)   # the same 4 iterations, from rest
    size = np.ptp(v, 0).max()
    err = np.linalg.norm(res.vertices - ref.vertices, axis=1).mean()
    assert err < 0.02 * size
    assert err < 0.8 * np.linalg.norm(from_rest.vertices - ref.vertices, axis=1).mean()


def test_arap_sets_the_field_vertices(blob_mesh):
    import neumesh_core as nm

    field = nm.create_field(blob_mesh)
    v = field.rest_vertices.numpy().astype(np.float64)
    z = v[:, 2]
    anchors, handles = np.nonzero(z < z.min() + 0.2)[0], np.nonzero(z > z.max() - 0.2)[0]
    M = rigid(rot_y(30), [0.4, 0.0, -0.1])
    res = nm.deform.arap(field, anchors, handles, M)
    np.testing.assert_allclose(field.vertices, res.vertices, atol=1e-5)
    np.testing.assert_allclose(field.vertices[anchors], v[anchors], atol=1e-6)
    np.testing.assert_allclose(field.vertices[handles], v[handles] @ M[:3, :3].T + M[:3, 3], atol=1e-5)
    assert field.scaffold.to_rest is not None                    # frames derived by set_vertices
    # two handle groups, one transform each
    top, side = handles, np.nonzero(v[:, 0] > v[:, 0].max() - 0.1)[0]
    side = np.setdiff1d(side, np.concatenate([top, anchors]))
    res = arap(field, anchors, [top, side], [M, np.eye(4)], ArapConfig(iterations=5))
    np.testing.assert_allclose(res.vertices[side], v[side], atol=1e-9)


def test_bad_input_gets_clear_errors(blob):
    v, f, anchors, handles = blob
    n = len(v)
    with pytest.raises(DeformError, match="both anchors and handles"):
        ArapSolver(v, f, anchors, np.concatenate([handles, anchors[:3]]))
    with pytest.raises(DeformError, match="handle set is empty"):
        ArapSolver(v, f, anchors, [])
    with pytest.raises(DeformError, match="handle group 1 is empty"):
        ArapSolver(v, f, anchors, [handles, np.zeros(0, int)])
    with pytest.raises(DeformError, match="handle groups overlap"):
        ArapSolver(v, f, anchors, [handles, handles[:2]])
    with pytest.raises(DeformError, match="out of range"):
        ArapSolver(v, f, [n + 5], handles)
    with pytest.raises(DeformError, match="out of range"):
        ArapSolver(v, f, anchors, [-1])
    with pytest.raises(DeformError, match="boolean mask"):
        ArapSolver(v, f, np.zeros(n - 1, bool), handles)
    with pytest.raises(DeformError, match="no faces"):
        ArapSolver(v, np.zeros((0, 3), int), anchors, handles)
    with pytest.raises(DeformError, match="weights"):
        ArapConfig(weights="mean")
    s = ArapSolver(v, f, anchors, handles)
    with pytest.raises(DeformError, match=r"shape \(%d, 3\)" % len(handles)):
        s.solve(np.zeros((len(handles) - 1, 3)))
    with pytest.raises(DeformError, match="NaN"):
        s.solve(np.full((len(handles), 3), np.nan))
    with pytest.raises(DeformError, match="one 4x4 transform or one per handle group"):
        s.targets_from_transforms(np.zeros((2, 4, 4)))
    # boolean masks work as index sets
    mask = np.zeros(n, bool)
    mask[handles] = True
    assert np.array_equal(ArapSolver(v, f, anchors, mask).handles, np.sort(handles))


def test_a_piece_without_anchors_or_handles_is_held_at_rest(blob):
    v, f, anchors, handles = blob
    v2 = np.concatenate([v, v + [5.0, 0, 0]])
    f2 = np.concatenate([f, f + len(v)])
    q = bend_targets(v, anchors, handles, 45)
    for cage in (0, 600):
        s = ArapSolver(v2, f2, anchors, handles, ArapConfig(iterations=5, cage_vertices=cage, coarse_start=0))
        res = s.solve(q)
        assert len(s.held) > 0 and (s.held >= len(v)).all()
        tol = 1e-9 if cage == 0 else 1e-6 * np.abs(v2).max()   # the cage's carry runs in float32
        np.testing.assert_allclose(res.vertices[len(v):], v2[len(v):], rtol=0, atol=tol)


def test_the_symmetric_factorisation_solves_like_the_reference(blob):
    from scipy.sparse.linalg import spsolve

    from neumesh_core.deform.arap import factorise_reference, factorise_spd

    v, f, anchors, handles = blob
    e, w = edge_weights(v, f)
    L = ArapTerms(v, e, w).laplacian
    free = np.setdiff1d(np.arange(len(v)), np.concatenate([anchors, handles]))
    A = L[free][:, free].tocsc()
    b = np.random.default_rng(4).normal(size=(len(free), 3))
    fast, ref = factorise_spd(A), factorise_reference(A)
    assert fast.L.nnz < ref.L.nnz + ref.U.nnz                # a Cholesky-like factor: less fill
    x = fast.solve(b)
    np.testing.assert_allclose(x, ref.solve(b), rtol=1e-9, atol=1e-9 * np.abs(x).max())
    np.testing.assert_allclose(x, spsolve(A, b), rtol=1e-9, atol=1e-9 * np.abs(x).max())


@pytest.mark.parametrize("cage", [0, 400])
def test_the_solver_matches_the_plain_local_global_loop_through_a_drag(blob, cage):
    """The fast loop (free rows only, rotations of the active vertices per iteration, the others once per
    solve and cached between moves) against every vertex recomputed each iteration with spsolve."""
    v, f, anchors, handles = blob
    s = ArapSolver(v, f, anchors, handles, ArapConfig(iterations=3, tolerance=0.0, coarse_start=0,
                                                      cage_vertices=cage))
    core = s.core
    assert len(core.inactive) > 0 and len(core.active) < len(core.terms.rest)   # the restriction is used
    pts = core.terms.rest
    x0, R0 = pts, np.broadcast_to(np.eye(3), (len(pts), 3, 3))
    for deg in (20, 40):                       # the second move re-uses the cached inactive rotations
        q = bend_targets(v, anchors, handles, deg)
        if cage:
            targets = np.concatenate([pts[s._c_anchor], q[s._c_handle_src]])
        else:
            targets = np.concatenate([v[anchors], q])
        x, R, _, it = core.solve(targets, x0, R0, 3, 0.0, energies=False)
        xr, Rr = core.solve_reference(targets, x0, R0, 3)
        assert it == 3 and np.abs(x - pts).max() > 0.05
        np.testing.assert_allclose(x, xr, atol=1e-8)
        np.testing.assert_allclose(R, Rr, atol=1e-6)
        x0, R0 = x, R
