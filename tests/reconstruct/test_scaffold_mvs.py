"""Multi-view stereo refinement of the hull: a textured sphere captured from one side only (as DTU).

From one side the visual hull cannot tell depth: it reaches from the sphere towards the cameras
until the silhouette cones meet.  The plane sweep must put the front surface back on the sphere.
"""
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from neumesh_core.data.cameras import Cameras, pixel_rays
from neumesh_core.data.scene import ImageSet, Scene
from neumesh_core.reconstruct import ScaffoldConfig, build_scaffold
from neumesh_core.reconstruct.mvs import MVSConfig, _box_sum_stack, select_sources

R_SPHERE = 0.8
SIZE = 80


def _look_at(eye):
    eye = np.asarray(eye, float)
    z = -eye / np.linalg.norm(eye)
    up = np.array([0.0, 0.0, 1.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, np.cross(z, x), z, eye
    return m


def _texture(p: torch.Tensor) -> torch.Tensor:
    """Lambertian-free albedo with detail at several scales (no lighting: photo-consistent)."""
    a = torch.sin(11.0 * p[:, 0] + 3.0 * torch.sin(7.0 * p[:, 2])) * torch.sin(13.0 * p[:, 1] + 5.0 * p[:, 2])
    b = torch.sin(23.0 * p[:, 1] + 17.0 * p[:, 2]) * torch.cos(19.0 * p[:, 0])
    g = 0.5 + 0.3 * a + 0.15 * b
    return torch.stack([g, 0.8 * g + 0.1, 0.6 * g + 0.2], -1).clamp(0, 1)


def _render(K, c2w, w, h, ss=2):
    """Ray-sphere renders with ss x ss supersampling; returns rgb (h,w,3), mask (h,w)."""
    Ks = K.copy()
    Ks[:2] *= ss
    o, d = pixel_rays(Ks, c2w, w * ss, h * ss)
    b = (o * d).sum(-1)
    c = (o * o).sum(-1) - R_SPHERE ** 2
    disc = b * b - c
    hit = disc > 0
    t = -b - torch.sqrt(disc.clamp_min(0))
    p = o + t[:, None] * d
    col = torch.where(hit[:, None], _texture(p), torch.zeros(1, 3))
    col = col.view(1, h * ss, w * ss, 3).permute(0, 3, 1, 2)
    m = hit.float().view(1, 1, h * ss, w * ss)
    col = F.avg_pool2d(col, ss)[0].permute(1, 2, 0)
    m = F.avg_pool2d(m, ss)[0, 0]
    col = col / m.clamp_min(1e-6)[..., None]  # un-premultiply (straight colour, as DTU images)
    return col.numpy(), m.numpy()


@pytest.fixture(scope="module")
def frontal_scene():
    eyes = []
    for el in (10.0, 25.0):  # two rings of views within 30 degrees of the x axis
        for az in np.linspace(-25, 25, 6):
            a, e = np.radians(az), np.radians(el - 17.5)
            eyes.append(3.2 * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)]))
    K = np.array([[90.0, 0, SIZE / 2], [0, 90.0, SIZE / 2], [0, 0, 1]], np.float32)
    c2w = np.stack([_look_at(e) for e in eyes]).astype(np.float32)
    imgs, masks = zip(*[_render(K, c, SIZE, SIZE) for c in c2w])
    cams = Cameras(np.repeat(K[None], len(eyes), 0), c2w, SIZE, SIZE)
    train = ImageSet(cams, np.stack(imgs).astype(np.float32), (np.stack(masks) > 0.5).astype(np.float32))
    return Scene(splits={"train": train}, background=None,
                 bbox=np.array([[-1.5] * 3, [1.5] * 3], np.float32), kind="dtu")


def _front_error(mesh):
    """Mean |distance to the sphere| of the vertices the cameras face (x > 0.3 R)."""
    v = mesh.vertices
    front = v[:, 0] > 0.3 * R_SPHERE
    return float(np.abs(np.linalg.norm(v[front], axis=1) - R_SPHERE).mean())


def test_box_filter_matches_avg_pool():
    x = torch.rand(3, 37, 53)
    for r in (1, 3):
        ref = F.avg_pool2d(x[:, None], 2 * r + 1, stride=1, padding=r, count_include_pad=False)[:, 0]
        assert torch.allclose(_box_sum_stack(x, r), ref, atol=2e-6)


def test_select_sources_prefers_near_views():
    eyes = [np.array([np.cos(a), np.sin(a), 0.0]) * 3 for a in np.radians([0, 5, 10, 60, 120])]
    cams = Cameras(np.repeat(np.eye(3, dtype=np.float32)[None], 5, 0),
                   np.stack([_look_at(e) for e in eyes]).astype(np.float32), 8, 8)
    src = select_sources(cams, np.zeros(3), 2, 40.0)
    assert src[0] == [1, 2] and src[3] == [] and src[4] == []


def test_mvs_carves_the_frontal_hull(frontal_scene):
    base = dict(target_vertices=6000, hull_resolution=96, compute_iou=True)
    hull_mesh, _ = build_scaffold(frontal_scene, ScaffoldConfig(method="hull", **base))
    mvs_mesh, rep = build_scaffold(frontal_scene, ScaffoldConfig(method="hull+mvs", mvs=MVSConfig(planes=64),
                                                                 **base))
    err_hull, err_mvs = _front_error(hull_mesh), _front_error(mvs_mesh)
    voxel = rep.hull["voxel"]
    # measured (96 planes): the hull bulges to x = 1.22 (sphere: 0.8), mean front error 0.086;
    # hull+mvs reaches x = 0.795 with a mean front error of 0.015 (voxel 0.031)
    assert hull_mesh.vertices[:, 0].max() > R_SPHERE + 0.3
    assert mvs_mesh.vertices[:, 0].max() < R_SPHERE + voxel
    assert err_mvs < 0.6 * voxel and err_mvs < 0.25 * err_hull, (err_mvs, err_hull, voxel)
    assert rep.mvs["depth_fraction_kept"] > 0.5, rep.mvs
    assert rep.mvs["carved_fraction_of_hull"] > 0.03, rep.mvs
    assert "mvs" in rep.timings
    assert rep.silhouette_iou["mean"] > 0.95, rep.silhouette_iou


def test_erode_matches_scipy_and_keeps_the_frame_border():
    from scipy.ndimage import binary_erosion

    from neumesh_core.reconstruct.mvs import _erode

    rng = np.random.default_rng(0)
    m = F.max_pool2d(torch.from_numpy(rng.random((1, 1, 40, 50)) > 0.97).float(), 7, 1, 3)[0, 0] > 0
    m[:, :6] = True  # touches the left frame border
    for r in (1, 3):
        ref = binary_erosion(m.numpy(), np.ones((2 * r + 1, 2 * r + 1)), border_value=1)
        assert np.array_equal(_erode(m, r).numpy(), ref)
    assert bool(_erode(m, 3)[:, :3].all())  # the frame is not a silhouette


def _sphere_views(eyes, size=64):
    K = np.array([[60.0, 0, size / 2], [0, 60.0, size / 2], [0, 0, 1]], np.float32)
    c2w = np.stack([_look_at(e) for e in eyes]).astype(np.float32)
    cams = Cameras(np.repeat(K[None], len(eyes), 0), c2w, size, size)
    masks = np.stack([_render(K, c, size, size, ss=1)[1] for c in c2w])
    return cams, masks


@pytest.mark.parametrize("side_views", [True, False])
def test_keep_silhouettes_gives_back_only_what_the_masks_need(side_views):
    from neumesh_core.data.views import ViewStack
    from neumesh_core.reconstruct.hull import grid_points
    from neumesh_core.reconstruct.mvs import keep_silhouettes

    n, lo = 49, np.full(3, -1.2, np.float32)
    voxel = 2.4 / (n - 1)
    p = grid_points(lo, voxel, (n, n, n)).numpy().reshape(n, n, n, 3)
    r = np.linalg.norm(p, axis=-1)
    hull = ((R_SPHERE - r) / voxel).astype(np.float32)
    cap = (p[..., 0] > 0.5) & (hull > 0)      # a wrong carve of the rim seen by side views
    cavity = (r < 0.3)                          # a true carve no silhouette shows
    carved = np.where(cap | cavity, -1.0, hull).astype(np.float32)
    eyes = [(3.0, 0.0, 0.0)]  # looking at the cap: the rest of the sphere still fills its disc
    if side_views:
        eyes += [(0.0, 3.0, 0.0), (0.0, -2.1, 2.1)]
    cams, masks = _sphere_views(eyes)
    out, stats = keep_silhouettes(carved, hull, lo, voxel, ViewStack.from_cameras(cams), masks)
    assert (out[cavity] <= 0).all()                         # hidden carving stays
    assert stats["carved_nodes"] == int((cap | cavity).sum())
    if side_views:
        # the side views' masks reach x = R: the cap's outer nodes must come back.  Measured: 118
        # uncovered mask pixels -> 0, 810 of the cap's 1330 nodes restored, the cavity's 916 kept carved
        assert stats["restored_nodes"] > 0 and stats["uncovered_px"][-1] < stats["uncovered_px"][0]
        assert p[out > 0][:, 0].max() > R_SPHERE - 2 * voxel
        assert stats["uncovered_px"][-1] <= 0.002 * masks.sum()
    else:
        assert stats["restored_nodes"] == 0 and np.array_equal(out, carved)
