"""Triangle-mesh mode of the reference tracer (neumesh_core/data/mesh_truth.py)."""
import math

import numpy as np
import pytest

from neumesh_core.data import synthetic as S
from neumesh_core.data.deformations import DEFORMATIONS, bend, crease, stretch, twist
from neumesh_core.data.mesh_truth import raster_mesh, render_mesh_truth, triangle_rotations
from neumesh_core.metrics import psnr


def _K(res, angle=S.CAMERA_ANGLE_X):
    f = 0.5 * res / np.tan(0.5 * angle)
    return np.array([[f, 0, res / 2], [0, f, res / 2], [0, 0, 1]])


VIEWS = [np.array([4.0, 0.0, 1.0]), np.array([-2.0, 3.0, -2.0])]


@pytest.mark.parametrize("subdiv,min_db", [(4, 34.0), (5, 40.0)])
def test_undeformed_mesh_truth_matches_analytic_reference(subdiv, min_db):
    # The mesh is a polygonal approximation of the analytic blob: silhouettes and the hit points
    # differ by the chords' sagitta. Measured at 96 px: subdiv 4 37.84/39.20 dB, subdiv 5 44.92/45.53 dB.
    m = S.default_mesh(subdiv)
    res = 96
    for pos in VIEWS:
        c2w = S.look_at_opencv(pos)
        ref, a_ref = S.render_truth(_K(res), c2w, res, res)
        mesh, a_mesh = render_mesh_truth(_K(res), c2w, res, res, m.vertices, m.faces, rest_vertices=m.vertices)
        assert psnr(mesh, ref) >= min_db
        assert np.abs(a_mesh - a_ref).mean() < 0.01
        # rest_vertices=None is the same image (no rotation)
        same, _ = render_mesh_truth(_K(res), c2w, res, res, m.vertices, m.faces)
        np.testing.assert_allclose(same, mesh, atol=1e-6)


def test_raster_matches_brute_force_ray_triangle():
    m = S.default_mesh(2)
    V, F = m.vertices.astype(np.float64), m.faces
    res = 24
    K, c2w = _K(res), S.look_at_opencv(np.array([3.0, 1.0, 0.5]))
    off = np.full((1, res, res, 2), 0.5)
    face, bary, t = raster_mesh(K, c2w, res, res, V, F, off)
    # brute force: every pixel centre against every triangle
    ys, xs = np.meshgrid(np.arange(res) + 0.5, np.arange(res) + 0.5, indexing="ij")
    d = np.stack([xs, ys, np.ones_like(xs)], -1).reshape(-1, 3) @ np.linalg.inv(K).T @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = c2w[:3, 3]
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    e1, e2 = b - a, c - a
    pv = np.cross(d[:, None], e2[None])
    det = (e1[None] * pv).sum(-1)
    tv = o - a
    u = (tv[None] * pv).sum(-1) / det
    qv = np.cross(tv, e1)
    v = (d[:, None] * qv[None]).sum(-1) / det
    tt = (e2 * qv).sum(-1)[None] / det
    ok = (u >= 0) & (v >= 0) & (u + v <= 1) & (tt > 0)
    tt = np.where(ok, tt, np.inf)
    t_bf = tt.min(1).reshape(res, res)
    f_bf = np.where(np.isfinite(t_bf), tt.argmin(1).reshape(res, res), -1)
    assert (f_bf >= 0).sum() > 100 and (f_bf < 0).sum() > 100
    np.testing.assert_array_equal(face[0], f_bf)
    np.testing.assert_allclose(t[0][np.isfinite(t_bf)], t_bf[np.isfinite(t_bf)], rtol=1e-9)
    hit = face[0] >= 0
    p = (bary[0][hit][:, :, None] * V[F[face[0][hit]]]).sum(1)
    np.testing.assert_allclose(p, o + t[0][hit][:, None] * d.reshape(res, res, 3)[hit], atol=1e-9)


def test_rigid_motion_of_mesh_and_camera_renders_the_same_image():
    m = S.default_mesh(4)
    rest = m.vertices.astype(np.float64)
    Q = S._rotation([0.3, -1.0, 0.5], 1.1)
    shift = np.array([0.2, -0.4, 0.3])
    moved = rest @ Q.T + shift
    res = 64
    c2w = S.look_at_opencv(VIEWS[0])
    c2w_moved = np.eye(4)
    c2w_moved[:3, :3] = Q @ c2w[:3, :3]
    c2w_moved[:3, 3] = Q @ c2w[:3, 3] + shift
    a, _ = render_mesh_truth(_K(res), c2w, res, res, rest, m.faces, rest_vertices=rest)
    b, _ = render_mesh_truth(_K(res), c2w_moved, res, res, moved, m.faces, rest_vertices=rest)
    assert psnr(a, b) > 55.0  # equal up to samples landing exactly on shared edges
    rot = triangle_rotations(rest, moved, m.faces)
    np.testing.assert_allclose(rot, np.broadcast_to(Q, rot.shape), atol=1e-9)


def test_triangle_rotations_are_rotations_that_map_rest_normals():
    m = S.default_mesh(3)
    rest = m.vertices.astype(np.float64)
    for fn in DEFORMATIONS.values():
        rot = triangle_rotations(rest, fn(rest), m.faces)
        np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-9)
        np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-9)
    # a pure stretch along z leaves triangles facing +-z and +-x/y nearly unrotated, those at 45 deg tilt
    rot = triangle_rotations(rest, stretch(rest, 2.0), m.faces)
    n = np.cross(rest[m.faces[:, 1]] - rest[m.faces[:, 0]], rest[m.faces[:, 2]] - rest[m.faces[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n_def = np.cross(*(stretch(rest, 2.0)[m.faces[:, i]] - stretch(rest, 2.0)[m.faces[:, 0]] for i in (1, 2)))
    n_def /= np.linalg.norm(n_def, axis=1, keepdims=True)
    np.testing.assert_allclose(np.einsum("fij,fj->fi", rot, n), n_def, atol=1e-9)  # normals map exactly


def test_deformations_are_the_identity_at_zero_strength_and_continuous():
    v = S.default_mesh(3).vertices.astype(np.float64)
    np.testing.assert_allclose(bend(v, 1e-6), v, atol=1e-6)
    np.testing.assert_allclose(twist(v, 0.0), v)
    np.testing.assert_allclose(stretch(v, 1.0), v)
    np.testing.assert_allclose(crease(v, 0.0), v, atol=1e-12)
    # the crease keeps the lower bone in place and turns the upper one rigidly
    c = crease(v, 60.0)
    low, high = v[:, 2] < -0.4, v[:, 2] > 0.4
    np.testing.assert_allclose(c[low], v[low])
    a = math.radians(60.0)
    rot = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    np.testing.assert_allclose(c[high], v[high] @ rot.T, atol=1e-12)


def test_inverted_fraction_flags_deformations_that_turn_the_surface_inside_out():
    from neumesh_core.data.deformations import inverted_fraction

    m = S.default_mesh(4)
    v = m.vertices.astype(np.float64)
    for name in ("bend35", "bend70", "twist90", "stretch2", "squash0p7", "crease45"):
        assert inverted_fraction(DEFORMATIONS[name], v, m.faces) == 0.0, name
    assert 0.01 < inverted_fraction(DEFORMATIONS["bend140"], v, m.faces) < 0.1
    assert 0.03 < inverted_fraction(DEFORMATIONS["crease60"], v, m.faces) < 0.15
    assert inverted_fraction(lambda x: x * np.array([1.0, 1.0, -1.0]), v, m.faces) == 1.0  # a mirror
