"""Diagnostic geometry of neumesh_core/evaluate.py: surface_points and view_coverage."""
import numpy as np
import pytest

from neumesh_core.data.cameras import Cameras, intrinsics_from_fov, pixel_rays
from neumesh_core.evaluate import surface_points, view_coverage

W, H = 40, 30


def _plane_depth(K, c2w):
    """Distance along each pixel ray to the plane z = 0 (inf where the ray misses it)."""
    o, d = pixel_rays(K, c2w, W, H)
    t = -o[:, 2] / d[:, 2]
    t = np.where(t.numpy() > 0, t.numpy(), np.inf)
    return t.reshape(H, W).astype(np.float32)


def _camera(x):
    c2w = np.eye(4, dtype=np.float32)
    c2w[:3, 3] = (x, 0.0, -3.0)  # OpenCV: looking along +z, at the plane z = 0
    return c2w


def test_surface_points_lie_on_the_rendered_surface():
    K = intrinsics_from_fov(0.7, W, H)
    c2w = _camera(0.2)
    pix = np.array([[0, 0], [W - 1, H - 1], [17, 11]])
    pts = surface_points(K, c2w, _plane_depth(K, c2w), pix)
    assert np.allclose(pts[:, 2], 0.0, atol=1e-5)
    # the centre pixel's point is straight ahead of the camera
    centre = surface_points(K, c2w, _plane_depth(K, c2w), np.array([[W // 2, H // 2]]))[0]
    assert abs(centre[0] - 0.2) < 0.1 and abs(centre[1]) < 0.1


def test_view_coverage_counts_unoccluded_in_frame_views():
    K = intrinsics_from_fov(0.7, W, H)
    c2ws = np.stack([_camera(0.0), _camera(0.3), _camera(-0.3)])
    cams = Cameras(np.stack([K] * 3), c2ws, W, H)
    depths = np.stack([_plane_depth(K, c) for c in c2ws])
    depths[2] = 2.0  # camera 2 sees an occluder 2 units away, in front of the plane
    pts = np.array([[0.0, 0.0, 0.0],      # on the plane, in frame of all three: seen by 0 and 1
                    [50.0, 0.0, 0.0],     # on the plane, out of every frame
                    [0.0, 0.0, -5.0],     # behind every camera
                    [0.0, 0.0, 0.5]], np.float32)  # in frame, but hidden behind the plane
    assert view_coverage(pts, cams, depths).tolist() == [2, 0, 0, 0]
    # a loose tolerance accepts the hidden point's 0.5-unit depth gap (0.5 / 3.5 ~ 14%)
    assert view_coverage(pts, cams, depths, rel_tol=0.2).tolist() == [2, 0, 0, 2]
    with pytest.raises(ValueError, match="depths must be"):
        view_coverage(pts, cams, depths[:2])


def test_uint8_photos_evaluate_as_their_float32_reference(small_scene_dir):
    """evaluate reads uint8 photos and masks through ImageSet.float_view/float_mask: the same figures
    as the float32 storage of the same pixels (the old path)."""
    import neumesh_core as nm
    from neumesh_core.data.scene import ImageSet

    scene = nm.load_scene(small_scene_dir)
    va = scene.split("val").subset([0, 1])
    img8, m8 = np.rint(va.images * 255).astype(np.uint8), np.rint(va.masks * 255).astype(np.uint8)
    field = nm.create_field(nm.load_mesh(scene.mesh_path))
    got = {}
    for key, iset in {"uint8": ImageSet(va.cameras, img8, m8, va.names),
                      "float32": ImageSet(va.cameras, img8 / np.float32(255), m8 / np.float32(255), va.names)}.items():
        got[key] = nm.evaluate(field, iset, background=scene.background, masked=True)["mean"]
    for k in ("psnr", "ssim", "psnr_fg", "ssim_fg"):
        assert abs(got["uint8"][k] - got["float32"][k]) < 1e-4, k
    assert 0 < got["uint8"]["psnr"] < 60
