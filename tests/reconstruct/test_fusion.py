"""Fused depths (neumesh_core/reconstruct/fusion.py): the TSDF of exact per-view depths of a ball in a
box gives one surface on the ball, nothing on the box's walls, and the parts no view saw stay open."""
import numpy as np
import pytest
import torch

from neumesh_core.data.cameras import Cameras, pixel_rays
from neumesh_core.data.frame import ObjectBox
from neumesh_core.data.synthetic.scene import look_at_opencv
from neumesh_core.reconstruct.fusion import FusionConfig, extract_surface, fuse_depths, local_cameras

RADIUS = 0.6


def _ball_views(n=40, size=48, upper_only=False):
    """Cameras around a ball of RADIUS at the origin, the ray distance to it (inf: a miss) and opacity."""
    elev = np.linspace(1.0, 1.3, n) if upper_only else np.linspace(-1.0, 1.0, n)
    eyes = [3.0 * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])
            for a, e in zip(np.linspace(0, 2 * np.pi, n, endpoint=False) * 3, elev)]
    c2w = np.stack([look_at_opencv(e) for e in eyes]).astype(np.float32)
    f = 40.0 * size / 48   # the same field of view at any size
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], np.float32)
    cams = Cameras(np.repeat(K[None], n, 0), c2w, size, size)
    depths, opac = [], []
    for i in range(n):
        o, d = pixel_rays(cams.K[i], cams.c2w[i], size, size)
        b = (o * d).sum(-1)
        disc = b * b - ((o * o).sum(-1) - RADIUS ** 2)
        t = -b - torch.sqrt(disc.clamp_min(0))
        hit = disc > 0
        depths.append(torch.where(hit, t, torch.full_like(t, float("inf"))).numpy())
        opac.append(hit.float().numpy())
    return cams, np.stack(depths), np.stack(opac)


def test_exact_depths_of_a_ball_fuse_into_one_surface_on_it():
    cams, depths, opac = _ball_views()
    box = ObjectBox([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    local = local_cameras(cams, box)
    cfg = FusionConfig(resolution=48)
    seen = []
    tsdf = fuse_depths(depths, opac, local, -box.half_extents, box.half_extents, cfg, check=seen.append)
    assert seen[-1] == 1.0 and seen == sorted(seen)
    mesh, _ = extract_surface(tsdf, cfg.min_views, 0, 0.01, 64 ** 3)
    V = np.asarray(mesh.vertices, np.float64)
    r = np.linalg.norm(V, axis=1)
    assert len(V) > 500
    assert np.abs(r - RADIUS).max() < 1.5 * tsdf.voxel   # on the ball, no floaters
    assert np.all(np.abs(V).max(1) < 0.95)                 # nothing on the box's walls
    # one layer: rays at the ball from all around cross it twice (in and out), never more
    F = np.asarray(mesh.faces)
    a, b, c = (torch.as_tensor(V[F[:, k]]) for k in range(3))
    e1, e2 = b - a, c - a
    dirs = np.random.default_rng(0).normal(size=(200, 3))
    crossings = []
    for dd in dirs / np.linalg.norm(dirs, axis=1, keepdims=True):
        o, d = torch.as_tensor(3.0 * dd)[None], torch.as_tensor(-dd)[None]
        p = torch.cross(d.expand_as(e2), e2, dim=-1)
        det = (e1 * p).sum(-1)
        s = o - a
        u = (s * p).sum(-1) / det
        q = torch.cross(s, e1, dim=-1)
        v = (d * q).sum(-1) / det
        t = (e2 * q).sum(-1) / det
        crossings.append(int(((u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)).sum()))
    crossings = np.array(crossings)
    assert crossings.max() <= 2 and (crossings == 2).mean() > 0.9


def test_the_side_no_view_saw_stays_open():
    cams, depths, opac = _ball_views(upper_only=True)
    box = ObjectBox([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    cfg = FusionConfig(resolution=40)
    tsdf = fuse_depths(depths, opac, local_cameras(cams, box), -box.half_extents, box.half_extents, cfg)
    mesh, _ = extract_surface(tsdf, cfg.min_views, 0, 0.01, 64 ** 3)
    V = np.asarray(mesh.vertices)
    assert V[:, 2].max() > 0.5 * RADIUS          # the top the cameras look down on
    assert V[:, 2].min() > -0.5 * RADIUS         # no made-up bottom: no view saw below -21 degrees


def test_a_mask_leaves_open_every_cube_with_a_node_outside_it():
    from neumesh_core.reconstruct.meshing import marching_cubes

    x = np.linspace(-1, 1, 21)
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    values = 0.5 - np.sqrt(X ** 2 + Y ** 2 + Z ** 2)
    for axis in range(3):
        for keep_low in (True, False):
            mask = np.zeros(values.shape, bool)
            sl = [slice(None)] * 3
            sl[axis] = slice(0, 10) if keep_low else slice(10, None)
            mask[tuple(sl)] = True
            V = np.asarray(marching_cubes(values, 0.0, np.zeros(3), 1.0, mask=mask).vertices)
            assert len(V) > 50
            assert (V[:, axis].max() <= 9 + 1e-6) if keep_low else (V[:, axis].min() >= 10 - 1e-6)


def test_cells_are_no_finer_than_half_a_pixel_at_the_box():
    """Small photos (a pixel at the ball spans many requested cells) still fuse into the ball."""
    cams, depths, opac = _ball_views(size=24)
    box = ObjectBox([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    cfg = FusionConfig(resolution=256)
    tsdf = fuse_depths(depths, opac, local_cameras(cams, box), -box.half_extents, box.half_extents, cfg)
    footprint = 3.0 / cams.K[0, 0, 0]
    assert tsdf.voxel == pytest.approx(0.5 * footprint, rel=1e-3)
    mesh, _ = extract_surface(tsdf, cfg.min_views, 0, 0.01, 256 ** 3)
    V = np.asarray(mesh.vertices, np.float64)
    assert len(V) > 300 and np.abs(np.linalg.norm(V, axis=1) - RADIUS).max() < 2 * tsdf.voxel
    dirs = np.random.default_rng(1).normal(size=(500, 3))
    near = np.min(np.linalg.norm(V[None] - (RADIUS * dirs / np.linalg.norm(dirs, axis=1, keepdims=True))[:, None],
                                 axis=2), axis=1)
    assert (near < 2 * tsdf.voxel).mean() > 0.85   # the ball all round, not scattered bits
