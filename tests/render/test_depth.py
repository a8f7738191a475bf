"""Depth conventions (ray distance -> camera-axis Z, the Z of Blender's Depth pass), the z-buffer of
occluder meshes (raster.depth_buffer) and renders cut by a per-pixel far distance (holdouts)."""
import numpy as np

import neumesh_core as nm
from neumesh_core.data.cameras import axis_to_ray_depth, intrinsics_from_fov, ray_to_axis_depth
from neumesh_core.render.raster import depth_buffer

from ..conftest import textured_field


def _cam(w=20, h=16, shift=(0.0, 0.0)):
    K = intrinsics_from_fov(0.8, w, h).astype(np.float64)
    K[0, 2] += shift[0]
    K[1, 2] += shift[1]
    c2w = np.eye(4)
    c2w[:3, :3] = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float).T @ np.eye(3)   # any rotation
    c2w[:3, 3] = (0.3, -0.2, 0.5)
    return K, c2w


def test_axis_depth_of_a_plane_facing_the_camera_is_constant():
    """Rays hitting the plane z_cam = 4 (at pixel centres, off-centre principal point): their lengths
    differ, their Z is 4 everywhere; inf stays inf; the inverse gives the lengths back."""
    w, h = 20, 16
    K, _ = _cam(w, h, shift=(3.0, -2.0))
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    d = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1)
    t = 4.0 * np.linalg.norm(d, axis=-1)
    assert t.max() - t.min() > 0.3
    t[0, 0] = np.inf
    z = ray_to_axis_depth(t, K)
    assert np.isinf(z[0, 0])
    np.testing.assert_allclose(np.delete(z.ravel(), 0), 4.0, rtol=1e-6)
    np.testing.assert_allclose(axis_to_ray_depth(z, K)[1:], t[1:], rtol=1e-6)


def test_depth_buffer_of_a_quad_matches_the_ray_cast_plane():
    w, h = 24, 18
    K, c2w = _cam(w, h)
    # a quad in the camera frame at z = 3 .. 5 (tilted), world coordinates through c2w
    quad_cam = np.array([[-2, -2, 3.0], [2, -2, 3.0], [2, 2, 5.0], [-2, 2, 5.0]])
    V = quad_cam @ c2w[:3, :3].T + c2w[:3, 3]
    F = np.array([[0, 1, 2], [0, 2, 3]])
    z = depth_buffer(V, F, K, c2w, w, h)
    # exact plane: z = 4 + y_cam / 2, and along the pixel's ray y_cam = z * (v - cy) / fy
    ys = (np.arange(h) + 0.5 - K[1, 2]) / K[1, 1]
    expect = 4.0 / (1.0 - 0.5 * ys)
    hit = np.isfinite(z)
    assert hit.mean() > 0.9
    np.testing.assert_allclose(z, np.broadcast_to(expect[:, None], z.shape), rtol=1e-5)
    # a triangle behind the camera is skipped, not projected through
    assert np.isinf(depth_buffer(V * [1, 1, 1] - 10 * c2w[:3, 2], F, K, c2w, w, h)).all()


def test_far_cuts_the_field_behind_an_occluder(blob_mesh):
    f = textured_field(blob_mesh)
    f.grid.refresh(lambda x: f.query(x, with_rgb=False)[0], f.radius * 0.25)
    K = intrinsics_from_fov(0.8, 20, 16)
    c2w = np.eye(4, dtype=np.float32)
    c2w[2, 3] = -3.5
    full = nm.render_camera(f, K, c2w, 20, 16, background=None)
    assert full.opacity.max() > 0.9
    # no limit (inf everywhere) is the same render
    same = nm.render_camera(f, K, c2w, 20, 16, background=None, far=np.full((16, 20), np.inf))
    np.testing.assert_array_equal(same.rgb, full.rgb)
    # an occluder right in front of the field on the left half: nothing there; right half unchanged
    far = np.full((16, 20), np.inf, np.float32)
    far[:, :10] = 1.0
    cut = nm.render_camera(f, K, c2w, 20, 16, background=None, far=far)
    assert cut.opacity[:, :10].max() == 0.0 and np.isinf(cut.depth[:, :10]).all()
    np.testing.assert_allclose(cut.rgb[:, 10:], full.rgb[:, 10:], atol=1e-6)
    # a far limit inside the field keeps only what lies in front of it
    mid = np.where(np.isfinite(full.depth), full.depth, np.inf).astype(np.float32)
    half = nm.render_camera(f, K, c2w, 20, 16, background=None, far=mid)
    hit = full.opacity > 0.5
    assert (half.opacity[hit] < full.opacity[hit]).all()
    some = hit & (half.opacity > 1e-6)
    assert some.sum() > 0.5 * hit.sum() and (half.depth[some] <= full.depth[some] + 1e-5).all()
