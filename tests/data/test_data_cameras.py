"""pixel_rays and OpenGL/OpenCV conversions (neumesh_core/data/cameras.py)."""
import numpy as np
import torch

from neumesh_core.data.cameras import (
    Cameras,
    intrinsics_from_fov,
    opencv_to_opengl,
    opengl_to_opencv,
    pixel_rays,
)


def _random_pose(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    c2w = np.eye(4)
    c2w[:3, :3] = q
    c2w[:3, 3] = rng.normal(size=3) * 3
    return c2w.astype(np.float32)


def test_centre_pixel_ray_is_optical_axis():
    rng = np.random.default_rng(0)
    c2w = _random_pose(rng)
    W, H = 65, 49  # odd sizes: pixel (32, 24) has its centre on the principal point
    K = intrinsics_from_fov(0.8, W, H)
    o, d = pixel_rays(K, c2w, W, H)
    assert o.shape == (H * W, 3) and d.shape == (H * W, 3)
    centre = d.reshape(H, W, 3)[H // 2, W // 2].numpy()
    np.testing.assert_allclose(centre, c2w[:3, 2], atol=1e-6)  # OpenCV: +z looks forward
    np.testing.assert_allclose(o[0].numpy(), c2w[:3, 3], atol=1e-6)
    np.testing.assert_allclose(d.norm(dim=-1).numpy(), 1.0, atol=1e-6)
    # pixel (x, y) -> +x right / +y down in the camera frame
    cam_d = d.reshape(H, W, 3) @ torch.as_tensor(c2w[:3, :3])
    assert cam_d[H // 2, -1, 0] > 0 and cam_d[-1, W // 2, 1] > 0


def test_pixels_argument_matches_full_grid():
    rng = np.random.default_rng(1)
    c2w = _random_pose(rng)
    K = intrinsics_from_fov(1.0, 20, 10)
    _, d_all = pixel_rays(K, c2w, 20, 10)
    pix = torch.tensor([[0, 0], [19, 9], [7, 3]])
    _, d_sel = pixel_rays(K, c2w, 20, 10, pixels=pix)
    for k, (x, y) in enumerate(pix.tolist()):
        np.testing.assert_allclose(d_sel[k].numpy(), d_all[y * 20 + x].numpy(), atol=1e-6)


def test_opengl_opencv_round_trip_and_axes():
    rng = np.random.default_rng(2)
    poses = np.stack([_random_pose(rng) for _ in range(5)])
    cv = opengl_to_opencv(poses)
    np.testing.assert_allclose(opencv_to_opengl(cv), poses, atol=1e-6)
    # OpenGL looks down -z with y up; OpenCV looks down +z with y down; same centre
    np.testing.assert_allclose(cv[:, :3, 2], -poses[:, :3, 2], atol=1e-6)
    np.testing.assert_allclose(cv[:, :3, 1], -poses[:, :3, 1], atol=1e-6)
    np.testing.assert_allclose(cv[:, :3, 3], poses[:, :3, 3], atol=1e-6)


def test_cameras_scaled_keeps_rays():
    rng = np.random.default_rng(3)
    c2w = _random_pose(rng)
    cams = Cameras(intrinsics_from_fov(0.7, 64, 48), c2w[None], 64, 48)
    half = cams.scaled(0.5)
    assert (half.width, half.height) == (32, 24)
    # the centre of half-res pixel (x, y) is the shared corner of full-res pixels 2x..2x+1
    _, d_half = pixel_rays(half.K[0], c2w, 32, 24)
    _, d_full = pixel_rays(cams.K[0], c2w, 64, 48)
    full = d_full.reshape(48, 64, 3)
    avg = (full[0::2, 0::2] + full[1::2, 1::2]) / 2
    avg = avg / avg.norm(dim=-1, keepdim=True)
    np.testing.assert_allclose(d_half.reshape(24, 32, 3).numpy(), avg.numpy(), atol=1e-4)


def test_sub_pixel_offsets_match_a_finer_grid():
    """Rays at offset ((i+0.5)/S, (j+0.5)/S) of each pixel are the centre rays of the S-times finer
    image (K scaled by S): the rays a supersampled render averages."""
    rng = np.random.default_rng(3)
    c2w = _random_pose(rng)
    K = intrinsics_from_fov(0.9, 8, 6)
    K2 = K.copy()
    K2[:2] *= 2
    _, fine = pixel_rays(K2, c2w, 16, 12)
    fine = fine.view(6, 2, 8, 2, 3)
    for j in range(2):
        for i in range(2):
            _, d = pixel_rays(K, c2w, 8, 6, offset=((i + 0.5) / 2, (j + 0.5) / 2))
            assert torch.allclose(d.view(6, 8, 3), fine[:, j, :, i], atol=1e-6)
