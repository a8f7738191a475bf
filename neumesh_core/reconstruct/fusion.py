"""The scaffold of photos without masks: one surface where the photos see one.

``build_fused_scaffold`` works in the object box's own frame (``data.frame.ObjectBox``):

1. a density grid over the box is fitted by volume rendering the training photos **with a background
   model behind it** (``field/background.py``, the same composite as training a field: what the
   rays see outside the box is the room's, so nothing of the room is painted onto the box);
2. every training view's median depth and opacity are rendered from that grid (``density.grid_depths``);
3. those depths are fused into a truncated signed distance (TSDF, KinectFusion's running average):
   in front of a view's surface +, behind it (up to the truncation) -, free space + where the view's
   ray crosses the box without meeting anything; a voxel counts once ``min_views`` views say so;
4. the zero level of the TSDF, where enough views observed it, is the scaffold: an open surface of one
   layer (no inside to fill, no back wall), resampled to the target vertex count, moved to world space.

The background model fitted in step 1 is kept (:class:`FusedScaffold`) so that training the field can
start from it.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import torch

from ..data.cameras import Cameras
from ..data.scene import ImageSet
from ..mesh import Mesh


@dataclass
class FusionConfig:
    """resolution: TSDF cells on the box's longest side (fewer where a photo's pixel at the box spans
    more than two such cells: a cell is never finer than half a pixel). truncation: in cells. min_views: views that
    must observe a cell (surface, or free space through it) before it counts. surface_opacity /
    free_opacity: a pixel's grid opacity at least the first gives a surface depth, below the second
    says its ray crossed the box empty (between them the pixel says nothing). max_slope: a pixel's depth
    counts where the depths of its 3x3 neighbours differ by less than this many pixel footprints per
    pixel (about 76 degrees from facing the camera; beyond: an outline or a grazing view)."""

    resolution: int = 256
    truncation: float = 3.0
    min_views: int = 3
    surface_opacity: float = 0.5
    free_opacity: float = 0.05
    max_slope: float = 4.0


@dataclass
class TSDF:
    values: np.ndarray    # (nx,ny,nz) float32 truncated signed distance in [-1, 1] (+ in front)
    weights: np.ndarray   # (nx,ny,nz) float32 views that observed each node
    lo: np.ndarray        # (3,) first node, box frame
    voxel: float
    stats: dict = field(default_factory=dict)


def local_cameras(cameras: Cameras, box) -> Cameras:
    """``cameras`` seen in ``box``'s frame (origin at its centre, axes its rotation's columns)."""
    T = np.eye(4)
    T[:3, :3] = box.rotation.T
    T[:3, 3] = -box.rotation.T @ box.centre
    c2w = np.einsum("ij,njk->nik", T, np.asarray(cameras.c2w, np.float64)).astype(np.float32)
    return Cameras(cameras.K, c2w, cameras.width, cameras.height)


def fuse_depths(depths: np.ndarray, opacities: np.ndarray, cameras: Cameras, lo, hi, config: FusionConfig,
                check: Optional[Callable[[float], None]] = None) -> TSDF:
    """TSDF of per-view median depths (ray distances; inf where the view saw no surface) over the box
    ``lo``..``hi`` (the cameras' frame), ``config.resolution`` cells on its longest side."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    # no cell finer than half the photos' pixels at the box (their footprint): many cells under one
    # pixel would each take its depth from a different place than its centre, and fall on the wrong side
    footprint = float(np.median(np.linalg.norm(np.asarray(cameras.c2w)[:, :3, 3] - 0.5 * (lo + hi), axis=1)
                                / np.asarray(cameras.K)[:, 0, 0])) if len(cameras) else 0.0
    voxel = max(float((hi - lo).max() / config.resolution), 0.5 * footprint)
    dims = tuple(int(max(2, math.ceil((hi[a] - lo[a]) / voxel) + 1)) for a in range(3))
    axes = [torch.arange(n, dtype=torch.float32) * voxel + float(lo[a]) for a, n in enumerate(dims)]
    X = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    total = torch.zeros(X.shape[0])
    weight = torch.zeros(X.shape[0])
    N, H, W = len(cameras), cameras.height, cameras.width
    K = torch.as_tensor(cameras.K, dtype=torch.float32)
    c2w = torch.as_tensor(cameras.c2w, dtype=torch.float32)
    trunc = config.truncation * voxel
    dep = torch.as_tensor(depths, dtype=torch.float32).reshape(N, -1)
    opa = torch.as_tensor(opacities, dtype=torch.float32).reshape(N, -1)
    # a pixel says "empty" only when its neighbours do too: a cell near the object's outline can
    # project into a pixel whose centre ray just misses the object, and must not be carved from inside
    opa_near = torch.nn.functional.max_pool2d(opa.reshape(N, 1, H, W), 3, stride=1, padding=1).reshape(N, -1)
    # and its depth counts only where it is smooth: across an outline or at a grazing angle one pixel
    # spans depths far apart, and the cells behind its centre ray would get the wrong side
    finite = torch.where(torch.isfinite(dep), dep, torch.full_like(dep, 1e30)).reshape(N, 1, H, W)
    spread = (torch.nn.functional.max_pool2d(finite, 3, stride=1, padding=1)
              + torch.nn.functional.max_pool2d(-finite, 3, stride=1, padding=1)).reshape(N, -1)
    for v in range(N):
        R, t = c2w[v, :3, :3], c2w[v, :3, 3]
        xc = (X - t) @ R                                   # camera frame (OpenCV: +z forward)
        z = xc[:, 2]
        u = K[v, 0, 0] * xc[:, 0] / z.clamp_min(1e-9) + K[v, 0, 1] * xc[:, 1] / z.clamp_min(1e-9) + K[v, 0, 2]
        w_ = K[v, 1, 1] * xc[:, 1] / z.clamp_min(1e-9) + K[v, 1, 2]
        seen = (z > 1e-6) & (u >= 0) & (u < W) & (w_ >= 0) & (w_ < H)
        pix = (w_.clamp(0, H - 1).long() * W + u.clamp(0, W - 1).long())
        d_pix, o_pix, o_near = dep[v, pix], opa[v, pix], opa_near[v, pix]
        smooth = spread[v, pix] < torch.clamp(2.0 * config.max_slope * d_pix / K[v, 0, 0], min=trunc)
        r = (X - t).norm(dim=-1)
        sdf = d_pix - r
        surface = seen & smooth & (o_pix >= config.surface_opacity) & torch.isfinite(d_pix) & (sdf >= -trunc)
        free = seen & (o_near < config.free_opacity)
        total += torch.where(surface, (sdf / trunc).clamp(-1, 1), torch.zeros_like(sdf))
        total += free.float()
        weight += (surface | free).float()
        if check is not None:
            check((v + 1) / N)
    values = torch.where(weight > 0, total / weight.clamp_min(1), torch.ones_like(total))
    return TSDF(values.reshape(dims).numpy().astype(np.float32), weight.reshape(dims).numpy().astype(np.float32),
                lo.astype(np.float32), voxel)


def extract_surface(tsdf: TSDF, min_views: int, target_vertices: int, min_component_fraction: float,
                    max_grid_nodes: int, check=None):
    """The TSDF's zero level where at least ``min_views`` views observed it: an open mesh (faces
    towards the cameras), resampled towards ``target_vertices``. Returns (Mesh in the TSDF's frame,
    info)."""
    from .meshing import extract_with_target

    observed = tsdf.weights >= min_views
    # inside = behind the surface (negative distance); unobserved cells make no faces
    return extract_with_target(-tsdf.values, 0.0, tsdf.lo, tsdf.voxel, target_vertices, min_component_fraction,
                               max_grid_nodes=max_grid_nodes, check=check, mask=observed)


@dataclass
class FusedScaffold:
    mesh: Mesh                       # world space
    background: Optional[object]     # the BackgroundModel fitted with the grid, in world space
    report: dict


def build_fused_scaffold(images: ImageSet, box, cfg, fusion: Optional[FusionConfig] = None,
                         check: Optional[Callable[[str, float], None]] = None,
                         log: Optional[Callable[[str], None]] = None) -> FusedScaffold:
    """Steps 1-4 of the module on ``images`` (already reduced for the density grid) inside ``box``
    (an ObjectBox); ``cfg`` the ScaffoldConfig (density stages, target vertices...)."""
    from ..data.frame import ObjectBox
    from ..field.background import FIT_BACKGROUND, BackgroundModel
    from .density import fit_density, grid_depths

    fusion = fusion or FusionConfig()
    say = log or (lambda m: None)
    chk = check or (lambda stage, f: None)
    t0 = time.perf_counter()
    local = ImageSet(local_cameras(images.cameras, box), images.images, None, images.names)
    half = box.half_extents.astype(np.float64)
    lo, hi = -half, half
    # 1. density + background model in the box's frame (the same model, moved, is the world one)
    local_box = ObjectBox(np.zeros(3), half)
    bg = BackgroundModel(np.zeros(3), 2.0 * float(half.max()), local_box, **FIT_BACKGROUND)
    res = int(cfg.density_resolutions[-1])
    g_vox = float((hi - lo).max() / res)
    dims = [max(2, int(math.ceil((hi[a] - lo[a]) / g_vox)) + 1) for a in range(3)]
    g_vox = float(((hi - lo) / (np.asarray(dims) - 1)).max())
    allowed = np.ones(dims, bool)
    if box.on_support:   # the support's slab (two cells) is the room's: the grid may not paint it
        allowed[:, :, :2] = False
    dres = fit_density(local, allowed, np.zeros(dims, bool), lo.astype(np.float32), g_vox,
                       resolutions=tuple(cfg.density_resolutions), iters=tuple(cfg.density_iters),
                       batch_rays=cfg.density_batch_rays, use_masks=False, lr=cfg.density_lr, seed=cfg.seed,
                       check=lambda f: chk("density", f), log=say, background_model=bg, empty_init=-5.0)
    t1 = time.perf_counter()
    # 2. per-view depths of the grid
    depth, opac = grid_depths(dres, local.cameras, check=lambda f: chk("depths", f))
    seen = np.isfinite(depth)
    say(f"depths: {seen.mean():.1%} of the training pixels meet the object (opacity >= 0.5)")
    t2 = time.perf_counter()
    # 3. fusion
    tsdf = fuse_depths(depth, opac, local.cameras, lo, hi, fusion, check=lambda f: chk("fusion", f))
    t3 = time.perf_counter()
    # 4. surface
    mesh, info = extract_surface(tsdf, fusion.min_views, cfg.target_vertices, cfg.min_component_fraction,
                                 int(cfg.max_mesh_grid) ** 3, check=lambda f: chk("mesh", f))
    world = (mesh.vertices.astype(np.float64) @ box.rotation.T + box.centre).astype(np.float32)
    mesh = Mesh(world, mesh.faces)
    bg_world = BackgroundModel(box.centre, bg.radius, box, **FIT_BACKGROUND)
    bg_world.load_state_dict(bg.state_dict())
    report = {"density": {"iterations": dres.iterations, "final_loss": dres.final_loss,
                          "final_psnr": dres.final_psnr, "rays_per_sec": dres.rays_per_sec,
                          "grid": list(dres.sigma.shape), "background_model": "K-Planes, trained with the grid",
                          "image_size": [images.cameras.width, images.cameras.height]},
              "fusion": {"grid": list(tsdf.values.shape), "voxel": tsdf.voxel,
                         "truncation_cells": fusion.truncation, "min_views": fusion.min_views,
                         "pixels_meeting_the_object": float(seen.mean()),
                         "observed_fraction": float((tsdf.weights >= fusion.min_views).mean())},
              "meshing": info,
              "timings": {"density": t1 - t0, "depths": t2 - t1, "fusion": t3 - t2,
                          "mesh": time.perf_counter() - t3}}
    return FusedScaffold(mesh, bg_world, report)
