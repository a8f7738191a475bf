"""Rigid motion of scaffold + camera renders the same image; a bend carries the texture along."""
import numpy as np
import pytest
import torch

from neumesh_core.data.cameras import intrinsics_from_fov
from neumesh_core.render.renderer import render_camera

from .conftest import textured_field

RES = 40


def _rot(axis, angle):
    axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return (np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K).astype(np.float32)


def _cam():
    K = intrinsics_from_fov(0.8, RES, RES)
    c2w = np.eye(4, dtype=np.float32)
    c2w[:3, :3] = _rot([0, 1, 0], 0.4)
    c2w[:3, 3] = c2w[:3, :3] @ np.array([0, 0, -3.6], np.float32)
    return K, c2w


@pytest.mark.parametrize("interp", ["post", "early"])
def test_rigid_motion_of_scaffold_and_camera_renders_the_same_image(blob_mesh, interp):
    f = textured_field(blob_mesh, interp)
    # empty the top of the shell and prune exactly the cells that only top vertices can reach, so the
    # rest grid is refined and the deformation must carry that pruning along
    top = f.rest_vertices[:, 2] > 0.3
    with torch.no_grad():
        f.geo_codes[top, 0] = -60.0
    from neumesh_core.sampling.occupancy import OccupancyGrid

    g = f.grid
    g.occ = g.mesh_mask & OccupancyGrid.mask_from_vertices(f.rest_vertices[~top], g.aabb, g.resolution, f.radius)
    g.density.fill_(0.0)
    assert g.refined
    K, c2w = _cam()
    before = render_camera(f, K, c2w, RES, RES)
    R = _rot([0.3, 1.0, -0.5], 1.1)
    t = np.array([0.7, -1.2, 2.5], np.float32)
    f.set_vertices(f.rest_vertices.numpy() @ R.T + t)
    M = np.eye(4, dtype=np.float32)
    M[:3, :3], M[:3, 3] = R, t
    after = render_camera(f, K, M @ c2w, RES, RES)
    assert f.grid.occupied_fraction < 0.9 * f.grid.mesh_mask.float().mean()  # pruning survived the move
    assert before.opacity.mean() > 0.2
    # tolerance: float32 round-off in positions/normals (stated: max 2e-3, mean 1e-4 per channel)
    assert np.abs(before.rgb - after.rgb).max() < 2e-3
    assert np.abs(before.rgb - after.rgb).mean() < 1e-4
    assert np.abs(before.opacity - after.opacity).max() < 2e-3


def test_view_dependence_is_expressed_in_the_rest_frame(blob_mesh):
    f = textured_field(blob_mesh)
    x = f.rest_vertices[:20] * 1.001
    d = torch.nn.functional.normalize(torch.randn(20, 3), dim=-1)
    with torch.no_grad():
        s0, c0, _ = f.query(x, d)
        R = torch.as_tensor(_rot([1, 2, 3], 0.7))
        f.set_vertices(f.rest_vertices @ R.T)
        s1, c1, _ = f.query(x @ R.T, d @ R.T)
    assert torch.allclose(s0, s1, rtol=1e-4, atol=1e-3)
    assert torch.allclose(c0, c1, atol=1e-5)


def test_bend_moves_texture_with_surface(blob_mesh):
    """Rotate the x>0.3 part of the blob about the z axis (a bend); the red texture of those vertices
    must follow them: point queries at the moved vertices give the rest colours, and the red region
    of the image moves to where the moved vertices project."""
    f = textured_field(blob_mesh)
    v = f.rest_vertices.numpy()
    moving = v[:, 0] > 0.3
    R = _rot([0, 0, 1], 0.6)
    pivot = np.array([0.3, 0, 0], np.float32)
    v_new = v.copy()
    v_new[moving] = (v[moving] - pivot) @ R.T + pivot
    # smooth transition band so the surface stays connected
    band = (v[:, 0] > 0.1) & ~moving
    a = ((v[band, 0] - 0.1) / 0.2)[:, None]
    Rb = np.stack([_rot([0, 0, 1], 0.6 * float(s)) for s in a[:, 0]])
    v_new[band] = np.einsum("nij,nj->ni", Rb, v[band] - pivot) + pivot

    probe = np.nonzero(moving & (v[:, 0] > 0.6))[0][:30]
    d = torch.nn.functional.normalize(torch.randn(len(probe), 3), dim=-1)
    with torch.no_grad():
        s0, c0, _ = f.query(f.rest_vertices[probe], d)
        K, c2w = _cam()
        img0 = render_camera(f, K, c2w, RES, RES)
        f.set_vertices(v_new)
        s1, c1, _ = f.query(torch.as_tensor(v_new[probe]), d @ torch.as_tensor(R).T)
        img1 = render_camera(f, K, c2w, RES, RES)
    assert torch.allclose(s0, s1, rtol=1e-3, atol=1e-2)
    assert torch.allclose(c0, c1, atol=1e-4)

    from neumesh_core.data.cameras import pixel_rays
    from pykdtree.kdtree import KDTree

    def red_points(img):
        """3D points (from the rendered depth) of pixels that render red."""
        red = (img.rgb[..., 0] > 0.6) & (img.rgb[..., 2] < 0.4) & (img.opacity > 0.9)
        o, d = pixel_rays(K, c2w, RES, RES)
        pts = (o + d * torch.as_tensor(img.depth).reshape(-1, 1)).numpy()
        return red, pts[red.reshape(-1)]

    red_v = v[:, 0] > 0  # vertices whose modification colour is red (see textured_field)
    mask0, pts0 = red_points(img0)
    mask1, pts1 = red_points(img1)
    assert mask0.sum() > 30 and mask1.sum() > 30
    # the bend visibly changes which pixels are red
    iou = (mask0 & mask1).sum() / (mask0 | mask1).sum()
    assert iou < 0.8
    # every red pixel shows a point of the surface near a red vertex, at its *current* position
    d_new, _ = KDTree(v_new[red_v]).query(pts1.astype(np.float32), k=1)
    d_old, _ = KDTree(v[red_v]).query(pts0.astype(np.float32), k=1)
    assert np.mean(d_new < 1.5 * f.radius) > 0.97
    assert np.mean(d_old < 1.5 * f.radius) > 0.97
