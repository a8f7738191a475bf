"""Multi-view stereo refinement of the visual hull (pure torch): plane-sweep NCC depth maps, a
geometric consistency filter, and truncated-signed-distance fusion on the hull grid.

A visual hull cannot carve what no silhouette shows: concavities, and for captures from one side
(DTU) most of the depth.  For every training view the sweep tests depth planes that lie inside the
hull, warps the source views' grey images onto each plane and scores it by windowed normalised
cross-correlation (the mean of the best ``top_k`` source views, which tolerates occlusion).  The
best plane per pixel, refined to sub-plane precision, gives a depth map; depths that fewer than
``min_consistent`` neighbouring depth maps confirm are dropped.  Fusion writes, for each hull-grid
node, the truncated signed distance to the observed surface along each view (+ behind the surface,
- in front), averaged over views.  The caller intersects it with the hull (min), so observed free
space carves the hull and unobserved regions keep it.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import torch
import torch.nn.functional as F

from ..data.cameras import Cameras
from ..data.views import ViewStack
from .hull import HullGrid, _node_positions, keep_silhouettes  # noqa: F401 (re-exported; build.py imports it from here)


@dataclass
class MVSConfig:
    """Settings of the plane sweep and fusion.

    planes: depth hypotheses per view (spread over the depth range of the hull in that view).
    sources / top_k: neighbour views warped per reference view, and how many of the best scores
        are averaged (1, 2, or >= sources for all).
    window: NCC window side in pixels (odd).
    min_ncc: pixels whose best score is lower get no depth.
    min_std: reference windows flatter than this (grey levels 0..1) get no depth (textureless).
    min_consistent: neighbour depth maps that must agree (reprojection < 1 px, depth < 1%).
    truncation: fusion truncation in hull voxels.
    min_observations: fused nodes need this many views before they override the hull.
    """

    planes: int = 128
    sources: int = 4
    top_k: int = 2
    window: int = 7
    min_ncc: float = 0.5
    min_std: float = 0.01
    min_consistent: int = 2
    max_angle_deg: float = 40.0
    truncation: float = 4.0
    min_observations: int = 2

    def __post_init__(self) -> None:
        if self.top_k < 1 or (self.top_k > 2 and self.top_k < self.sources):
            raise ValueError(f"MVSConfig.top_k must be 1, 2 or >= sources ({self.sources}), got {self.top_k}")
        if self.window < 3 or self.window % 2 == 0:
            raise ValueError(f"MVSConfig.window must be an odd number >= 3, got {self.window}")
        if self.planes < 3 or self.sources < 1:
            raise ValueError("MVSConfig.planes must be >= 3 and sources >= 1")


@dataclass
class MVSResult:
    values: np.ndarray       # (nx,ny,nz) fused truncated distance in voxels (+ inside), nan = unobserved
    depths: np.ndarray       # (N,H,W) filtered depth maps (0 = no depth)
    stats: dict = field(default_factory=dict)


def _grey(images: np.ndarray) -> torch.Tensor:
    im = torch.from_numpy(np.ascontiguousarray(images[..., :3], dtype=np.float32))
    return (im @ torch.tensor([0.299, 0.587, 0.114]))[:, None]  # (N,1,H,W)


def select_sources(cams: Cameras, centre: np.ndarray, n: int, max_angle_deg: float) -> list[list[int]]:
    """For every view, up to ``n`` other views with the smallest angle between their directions to
    ``centre`` (above 1 degree: a baseline is needed; below ``max_angle_deg``)."""
    d = cams.centres.astype(np.float64) - centre[None]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(d @ d.T, -1.0, 1.0)))
    out = []
    for i in range(len(cams)):
        order = [j for j in np.argsort(ang[i]) if j != i and 1.0 < ang[i, j] <= max_angle_deg]
        out.append([int(j) for j in order[:n]])
    return out


class _Hull:
    """Trilinear lookups of hull values (voxels, + inside) at world points."""

    def __init__(self, hull_vox: np.ndarray, lo: np.ndarray, voxel: float):
        self.t = torch.from_numpy(np.ascontiguousarray(hull_vox, dtype=np.float32))[None, None]
        self.lo = torch.as_tensor(np.asarray(lo, np.float32))
        self.scale = torch.tensor([2.0 / ((n - 1) * voxel) for n in hull_vox.shape], dtype=torch.float32)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        g = (x - self.lo) * self.scale - 1.0  # (...,3) in [-1,1] for (x,y,z) = (D,H,W) of the volume
        shp = g.shape[:-1]
        g = g.reshape(1, 1, 1, -1, 3).flip(-1)
        v = F.grid_sample(self.t, g, mode="bilinear", padding_mode="border", align_corners=True)
        return v.reshape(shp)


def _camera(cams: Cameras, i: int):
    c2w = torch.as_tensor(cams.c2w[i], dtype=torch.float32)
    K = torch.as_tensor(cams.K[i], dtype=torch.float32)
    return K, c2w[:3, :3], c2w[:3, 3]


def _cam_dirs(K: torch.Tensor, W: int, H: int) -> torch.Tensor:
    """(H,W,3) camera-space directions with z=1 through pixel centres."""
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float32) + 0.5,
                            torch.arange(W, dtype=torch.float32) + 0.5, indexing="ij")
    y = (ys - K[1, 2]) / K[1, 1]
    x = (xs - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return torch.stack([x, y, torch.ones_like(x)], -1)


def _box_sum_stack(x: torch.Tensor, r: int) -> torch.Tensor:
    """(2r+1)^2 window means over the last two dims of x (B,H,W) with running sums (separable: rows,
    then columns, which keeps float32 sums small); windows are clipped at the border and divided by
    the number of pixels they cover."""
    B, H, W = x.shape
    k = 2 * r + 1
    c = F.pad(x, (r + 1, r)).cumsum(2)
    x = c[:, :, k:] - c[:, :, :W]
    c = F.pad(x, (0, 0, r + 1, r)).cumsum(1)
    x = c[:, k:] - c[:, :H]
    ny = (torch.arange(H) + r + 1).clamp_max(H) - (torch.arange(H) - r).clamp_min(0)
    nx = (torch.arange(W) + r + 1).clamp_max(W) - (torch.arange(W) - r).clamp_min(0)
    return x * (1.0 / (ny[:, None] * nx[None]).float())


def _erode(mask: torch.Tensor, r: int) -> torch.Tensor:
    """Binary erosion of an (H,W) bool mask by a (2r+1)^2 square; pixels outside the image count as
    inside (a mask cut by the frame border is not a silhouette)."""
    if r <= 0:
        return mask
    outside = (~mask).float()[None, None]
    grown = F.max_pool2d(F.pad(outside, (r, r, r, r), value=0.0), 2 * r + 1, stride=1)
    return grown[0, 0] < 0.5


def sweep_depth(ref: int, sources: list[int], grey: torch.Tensor, masks: Optional[np.ndarray], cams: Cameras,
                hull: _Hull, z_range: tuple[float, float], cfg: MVSConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth (H,W) (0 = none) and best score (H,W) of view ``ref`` by a plane sweep.

    Only the bounding box of the reference mask (plus the NCC window) is swept."""
    H, W = cams.height, cams.width
    r = cfg.window // 2
    depth_full = torch.zeros(H, W)
    best_full = torch.full((H, W), -1.0)
    y0, y1, x0, x1 = 0, H, 0, W
    if masks is not None:
        m = masks[ref] > 0.5
        if not m.any():
            return depth_full, best_full
        rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
        y0, y1 = max(0, rows[0] - r), min(H, rows[-1] + r + 1)
        x0, x1 = max(0, cols[0] - r), min(W, cols[-1] + r + 1)
    h, w = y1 - y0, x1 - x0
    K, Rc, C = _camera(cams, ref)
    I = grey[ref, 0, y0:y1, x0:x1][None]
    mu_i = _box_sum_stack(I, r)
    var_i = (_box_sum_stack(I * I, r) - mu_i * mu_i).clamp_min(0.0)
    dirs_w = _cam_dirs(K, W, H)[y0:y1, x0:x1] @ Rc.T  # world direction per unit camera depth
    z0, z1 = z_range
    D = cfg.planes
    zs = torch.linspace(z0, z1, D)
    src = []
    for s in sources:
        Ks, Rs, Cs = _camera(cams, s)
        Rw2c = Rs.T
        a = Rw2c @ C - Rw2c @ Cs            # source-camera coordinates of the reference centre
        b = (dirs_w @ Rw2c.T).permute(2, 0, 1)  # (3,h,w) per unit depth
        # fold the intrinsics in: u*z = fx x + s y + cx z, v*z = fy y + cy z
        A = torch.stack([Ks[0, 0] * a[0] + Ks[0, 1] * a[1] + Ks[0, 2] * a[2], Ks[1, 1] * a[1] + Ks[1, 2] * a[2], a[2]])
        B = torch.stack([Ks[0, 0] * b[0] + Ks[0, 1] * b[1] + Ks[0, 2] * b[2], Ks[1, 1] * b[1] + Ks[1, 2] * b[2], b[2]])
        src.append((A, B, grey[s:s + 1]))
    scores = torch.full((D, h, w), -1.0)
    chunk = max(1, 2_000_000 // (h * w))
    for j0 in range(0, D, chunk):
        zc = zs[j0:j0 + chunk]
        c = len(zc)
        zb = zc[:, None, None]
        X = C + zc[:, None, None, None] * dirs_w[None]  # (c,h,w,3)
        inside = hull(X) > -1.0
        top1 = torch.full((c, h, w), -1.0)
        top2 = torch.full((c, h, w), -1.0)
        total = torch.zeros((c, h, w))
        for A, B, Js in src:
            uz = A[0] + zb * B[0]
            vz = A[1] + zb * B[1]
            z = A[2] + zb * B[2]
            zsafe = z.clamp_min(1e-6)
            gx = uz / zsafe * (2.0 / W) - 1.0
            gy = vz / zsafe * (2.0 / H) - 1.0
            ok = (z > 1e-6) & (gx.abs() <= 1.0) & (gy.abs() <= 1.0)
            J = F.grid_sample(Js.expand(c, 1, H, W), torch.stack([gx, gy], -1), mode="bilinear",
                              padding_mode="border", align_corners=False)[:, 0]
            st = _box_sum_stack(torch.cat([J, J * J, I * J]), r)
            mu_j, ej2, eij = st[:c], st[c:2 * c], st[2 * c:]
            var_j = (ej2 - mu_j * mu_j).clamp_min_(0.0)
            ncc = (eij - mu_i * mu_j) / torch.sqrt(var_i * var_j + 1e-8)
            ncc = torch.where(ok, ncc, torch.full_like(ncc, -1.0))
            if cfg.top_k >= len(src):
                total += ncc
            else:  # running best two scores
                top2 = torch.maximum(top2, torch.minimum(top1, ncc))
                top1 = torch.maximum(top1, ncc)
        if cfg.top_k >= len(src):
            sc = total / len(src)
        elif cfg.top_k == 1:
            sc = top1
        else:
            sc = 0.5 * (top1 + top2)
        sc = torch.where(inside, sc, torch.full_like(sc, -1.0))
        scores[j0:j0 + c] = sc
    best, j = scores.max(0)
    # sub-plane refinement: parabola through the neighbouring scores
    jm, jp = (j - 1).clamp_min(0), (j + 1).clamp_max(D - 1)
    sm, sp = scores.gather(0, jm[None])[0], scores.gather(0, jp[None])[0]
    den = sm - 2 * best + sp
    off = torch.where((den < -1e-6) & (j > 0) & (j < D - 1), 0.5 * (sm - sp) / den, torch.zeros_like(den))
    step = (z1 - z0) / max(D - 1, 1)
    depth = zs[j] + off.clamp(-0.5, 0.5) * step
    ok = (best >= cfg.min_ncc) & (var_i[0].sqrt() >= cfg.min_std)
    if masks is not None:  # no depth within the window radius of the silhouette: there the window
        # straddles the background, which matches at wrong depths and would carve the object's rim
        ok &= _erode(torch.from_numpy(masks[ref] > 0.5), r)[y0:y1, x0:x1]
    depth_full[y0:y1, x0:x1] = torch.where(ok, depth, torch.zeros_like(depth))
    best_full[y0:y1, x0:x1] = best
    return depth_full, best_full


def consistency_filter(depths: torch.Tensor, cams: Cameras, sources: list[list[int]],
                       min_consistent: int) -> torch.Tensor:
    """Keep depths confirmed by ``min_consistent`` neighbour depth maps (forward-backward reprojection
    error < 1 px and relative depth difference < 1%)."""
    N, H, W = depths.shape
    out = torch.zeros_like(depths)
    views = ViewStack.from_cameras(cams)
    for i in range(N):
        K, Rc, C = _camera(cams, i)
        d = depths[i]
        valid = d > 0
        if not valid.any():
            continue
        dirs = _cam_dirs(K, W, H) @ Rc.T
        X = C + d[..., None] * dirs
        ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float32) + 0.5,
                                torch.arange(W, dtype=torch.float32) + 0.5, indexing="ij")
        count = torch.zeros(H, W, dtype=torch.int32)
        for s in sources[i]:
            Ks, Rs, Cs = _camera(cams, s)
            u, v, z = views.project_view(s, X)
            ui, vi = u.floor().long(), v.floor().long()
            inb = valid & (z > 0) & (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
            ds = depths[s][vi.clamp(0, H - 1), ui.clamp(0, W - 1)]
            inb &= ds > 0
            # back-project the source depth at that pixel (its centre) and bring it into the reference view
            dirs_s = _cam_dirs(Ks, W, H)[vi.clamp(0, H - 1), ui.clamp(0, W - 1)]
            Xs = Cs + (dirs_s * ds[..., None]) @ Rs.T
            u2, v2, z2 = views.project_view(i, Xs)
            err = torch.sqrt((u2 - xs) ** 2 + (v2 - ys) ** 2)
            ok = inb & (err < 1.0) & ((z2 - d).abs() < 0.01 * d)
            count += ok.int()
        out[i] = torch.where(valid & (count >= min_consistent), d, torch.zeros_like(d))
    return out


def fuse_tsdf(depths: torch.Tensor, cams: Cameras, shape, lo: np.ndarray, voxel: float,
              active: np.ndarray, truncation: float, min_observations: int) -> np.ndarray:
    """Truncated signed distance (voxels, + behind the observed surface) averaged over the views,
    at the ``active`` nodes of the grid; nan where fewer than ``min_observations`` views saw a node."""
    N, H, W = depths.shape
    idx = np.flatnonzero(active.reshape(-1))
    out = np.full(int(np.prod(shape)), np.nan, np.float32)
    tau = truncation * voxel
    views = ViewStack.from_cameras(cams)
    for s in range(0, len(idx), 1 << 20):
        X = _node_positions(idx[s:s + (1 << 20)], shape, lo, voxel)
        acc = torch.zeros(len(X))
        cnt = torch.zeros(len(X))
        for i in range(N):
            u, v, z = views.project_view(i, X)
            ui, vi = u.floor().long(), v.floor().long()
            ok = (z > 0) & (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
            d = depths[i][vi.clamp(0, H - 1), ui.clamp(0, W - 1)]
            ok &= d > 0
            sd = z - d  # + behind the surface (inside), - in front (free space)
            ok &= sd < tau
            acc += torch.where(ok, sd.clamp(-tau, tau) / voxel, torch.zeros_like(sd))
            cnt += ok.float()
        val = torch.where(cnt >= min_observations, acc / cnt.clamp_min(1.0), torch.full_like(acc, float("nan")))
        out[idx[s:s + len(X)]] = val.numpy()
    return out.reshape(shape)


def refine_hull(images, hull: HullGrid, hull_vox: np.ndarray, cfg: MVSConfig | None = None,
                check: Optional[Callable[[float], None]] = None, log: Optional[Callable[[str], None]] = None
                ) -> MVSResult:
    """Plane-sweep depth maps of every view of ``images`` (an ImageSet) inside the hull, filtered and
    fused on the hull grid.  ``hull_vox``: hull values in voxels (+ inside).  ``check(fraction)`` is
    called after each view (it raises to cancel)."""
    cfg = cfg or MVSConfig()
    t0 = time.perf_counter()
    cams = images.cameras
    N = len(cams)
    grey = _grey(images.float_images())
    masks = images.float_masks()
    hl = _Hull(hull_vox, hull.lo, hull.voxel)
    inside = hull_vox > 0
    ijk = np.argwhere(inside)
    pts = torch.from_numpy((ijk * hull.voxel + hull.lo).astype(np.float32))
    centre = pts.mean(0).numpy().astype(np.float64)
    sources = select_sources(cams, centre, cfg.sources, cfg.max_angle_deg)
    if len(pts) > 200_000:
        pts = pts[torch.randperm(len(pts), generator=torch.Generator().manual_seed(0))[:200_000]]
    depths = torch.zeros(N, cams.height, cams.width)
    n_src_used = 0
    for i in range(N):
        if len(sources[i]) < max(1, cfg.top_k):
            continue
        K, Rc, C = _camera(cams, i)
        z = (pts - C) @ Rc[:, 2]
        z0, z1 = float(z.min()), float(z.max())
        pad = 0.02 * (z1 - z0)
        d, _ = sweep_depth(i, sources[i], grey, masks, cams, hl, (max(z0 - pad, 1e-4), z1 + pad), cfg)
        depths[i] = d
        n_src_used += 1
        if check is not None:
            check(0.85 * (i + 1) / N)
        if log is not None:
            log(f"mvs: view {i + 1}/{N}: {float((d > 0).float().mean()):.1%} of pixels with depth")
    t_sweep = time.perf_counter() - t0
    raw_px = int((depths > 0).sum())
    filt = consistency_filter(depths, cams, sources, cfg.min_consistent)
    kept_px = int((filt > 0).sum())
    if check is not None:
        check(0.9)
    active = hull_vox > -2.0
    fused = fuse_tsdf(filt, cams, hull_vox.shape, hull.lo, hull.voxel, active, cfg.truncation,
                      cfg.min_observations)
    if check is not None:
        check(1.0)
    mask_px = int((masks > 0.5).sum()) if masks is not None else N * cams.height * cams.width
    stats = {"views": n_src_used, "sweep_s": t_sweep, "total_s": time.perf_counter() - t0,
             "depth_fraction_raw": raw_px / max(mask_px, 1), "depth_fraction_kept": kept_px / max(mask_px, 1),
             "fused_nodes": int(np.isfinite(fused).sum()),
             "config": {k: getattr(cfg, k) for k in cfg.__dataclass_fields__}}
    return MVSResult(fused, filt.numpy(), stats)
