"""Camera geometry helpers and a soft visual hull (coarse-to-fine, pure torch + scipy).

The hull value of a point is, in pixels, the ``(tolerance+1)``-th smallest signed distance to the
mask boundary over the views that see the point in frame (positive inside the mask).  Its zero level
set is the visual hull with ``tolerance`` views allowed to disagree; being a continuous field,
marching cubes places the surface with sub-voxel accuracy, which keeps thin parts alive.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ..data.cameras import Cameras
from ..data.views import ViewStack

OUTSIDE = -1.0e4  # hull value of points that are not seen by enough views / out of the domain


def mask_sdf(masks: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """(N,H,W) masks -> (N,H,W) float32 signed distance in pixels to the mask boundary (+ inside)."""
    from scipy.ndimage import distance_transform_edt

    out = np.empty(masks.shape, np.float32)
    for i, m in enumerate(masks):
        inside = m > threshold
        if inside.all():
            out[i] = 1.0e3
            continue
        if not inside.any():
            out[i] = -1.0e3
            continue
        d_in = distance_transform_edt(inside)  # inside pixels: distance to nearest outside pixel
        d_out = distance_transform_edt(~inside)
        out[i] = np.where(inside, d_in - 0.5, -(d_out - 0.5))
    return out


def axes_meeting_point(cams: Cameras) -> tuple[np.ndarray, float]:
    """Least-squares point nearest to all optical axes and the largest camera distance to it."""
    c = cams.centres.astype(np.float64)
    d = cams.c2w[:, :3, 2].astype(np.float64)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for ci, di in zip(c, d):
        P = np.eye(3) - np.outer(di, di)
        A += P
        b += P @ ci
    try:
        p = np.linalg.solve(A + 1e-9 * np.eye(3), b)
    except np.linalg.LinAlgError:
        p = c.mean(0) + d.mean(0)
    radius = float(np.linalg.norm(c - p, axis=1).max())
    return p, max(radius, 1e-3)


def grid_points(lo: np.ndarray, voxel: float, dims) -> torch.Tensor:
    """Node positions (nx*ny*nz, 3) of a grid (x slowest, z fastest = numpy C order)."""
    axes = [torch.arange(n, dtype=torch.float32) * voxel + float(lo[i]) for i, n in enumerate(dims)]
    g = torch.meshgrid(*axes, indexing="ij")
    return torch.stack([a.reshape(-1) for a in g], -1)


def common_view_volume(views: ViewStack, lo, hi, min_views: int, res: int = 48):
    """Nodes of a res^3 grid over [lo,hi] seen in frame by >= min_views cameras.

    Returns (bbox (2,3) of those nodes expanded by one cell, or None when there are none;
    fraction of the domain that is commonly seen).
    """
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    voxel = float((hi - lo).max() / (res - 1))
    dims = [max(2, int(math.ceil((hi[i] - lo[i]) / voxel)) + 1) for i in range(3)]
    pts = grid_points(lo, voxel, dims)
    count = torch.zeros(len(pts), dtype=torch.int32)
    for s in range(0, len(pts), 65536):
        u, v, z = views.project(pts[s:s + 65536])
        count[s:s + 65536] = views.in_frame(u, v, z).sum(0).int()
    ok = count >= min_views
    if not bool(ok.any()):
        return None, 0.0
    p = pts[ok]
    box = np.stack([p.min(0).values.numpy() - voxel, p.max(0).values.numpy() + voxel]).astype(np.float32)
    return box, float(ok.float().mean())


def hull_values(views: ViewStack, pts: torch.Tensor, tolerance: int, min_views: int,
                chunk: int = 1 << 17) -> torch.Tensor:
    """Soft visual-hull value (pixels, + inside) of points (P,3); see the module docstring."""
    assert views.sdf is not None
    n = len(views)
    k = min(tolerance + 1, n)
    out = torch.empty(len(pts), dtype=torch.float32)
    W, H = views.width, views.height
    per = max(1024, chunk // max(1, n // 16))
    for s in range(0, len(pts), per):
        p = pts[s:s + per]
        u, v, z = views.project(p)
        inf = views.in_frame(u, v, z)
        grid = torch.stack([2.0 * u / W - 1.0, 2.0 * v / H - 1.0], -1)[:, :, None, :]  # (N,P,1,2)
        val = F.grid_sample(views.sdf, grid, mode="bilinear", padding_mode="border", align_corners=False)
        val = val[:, 0, :, 0]  # (N,P)
        val = torch.where(inf, val, torch.full_like(val, float("inf")))
        kth = torch.kthvalue(val, k, dim=0).values if k > 1 else val.min(0).values
        seen = inf.sum(0)
        kth = torch.where((seen >= min_views) & torch.isfinite(kth), kth, torch.full_like(kth, OUTSIDE))
        out[s:s + per] = kth
    return out


def _upsample(vals: np.ndarray, dims_new) -> np.ndarray:
    t = torch.from_numpy(np.ascontiguousarray(vals, dtype=np.float32))[None, None]
    r = F.interpolate(t, size=tuple(int(d) for d in dims_new), mode="trilinear", align_corners=True)
    return r[0, 0].numpy()


@dataclass
class HullGrid:
    values: np.ndarray  # (nx,ny,nz) float32 hull values at grid nodes (pixels, + inside)
    lo: np.ndarray      # (3,) position of node (0,0,0)
    voxel: float
    evaluated: int      # number of exact evaluations done (for the report)

    @property
    def dims(self):
        return self.values.shape


def carve_hull(views: ViewStack, lo, hi, resolution: int, tolerance: int, min_views: int,
               dilate_px: float = 0.5, start_res: int = 48, check=None) -> HullGrid:
    """Coarse-to-fine soft visual hull over the box [lo,hi] with ``resolution`` cells on the longest side.

    Level 0 evaluates every node; finer levels re-evaluate only nodes in a band around the zero level
    (the rest keep trilinearly upsampled values).  ``check(fraction)`` is called between levels.
    """
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    ext = float((hi - lo).max())
    resolutions = [resolution]
    while resolutions[-1] // 2 >= start_res:
        resolutions.append(resolutions[-1] // 2)
    resolutions = resolutions[::-1]
    focal = views.mean_focal()
    centre = torch.as_tensor(0.5 * (lo + hi), dtype=torch.float32)[None]
    depth = float(torch.cat([views.project(centre)[2]]).abs().mean().clamp_min(1e-6))
    vals = None
    evaluated = 0
    for li, r in enumerate(resolutions):
        voxel = ext / r
        dims = [max(2, int(math.ceil((hi[i] - lo[i]) / voxel)) + 1) for i in range(3)]
        if vals is None:
            pts = grid_points(lo, voxel, dims)
            new = hull_values(views, pts, tolerance, min_views).reshape(dims).numpy()
            evaluated += len(pts)
        else:
            new = _upsample(vals, dims)
            px = voxel * 2.0 * focal / depth  # coarse voxel size in pixels (at the object)
            band = np.abs(new) < 3.0 * px + 2.0
            idx = np.nonzero(band.reshape(-1))[0]
            if len(idx):
                ijk = np.stack(np.unravel_index(idx, dims), -1).astype(np.float32)
                pts = torch.from_numpy(ijk * voxel + lo.astype(np.float32))
                flat = new.reshape(-1)
                flat[idx] = hull_values(views, pts, tolerance, min_views).numpy()
                new = flat.reshape(dims)
                evaluated += len(idx)
        px_here = voxel * focal / depth
        vals = np.clip(new, -(8.0 * px_here + 8.0), None)
        if check is not None:
            check((li + 1) / len(resolutions))
    vals = vals + np.float32(dilate_px)
    vals[vals < OUTSIDE / 2] = OUTSIDE
    return HullGrid(vals.astype(np.float32), lo.astype(np.float32), ext / resolutions[-1], evaluated)


def _node_positions(flat_idx: np.ndarray, shape, lo, voxel: float) -> torch.Tensor:
    """World positions (P,3) of grid nodes given by flat (C-order) indices into a grid of ``shape``."""
    li = torch.from_numpy(np.asarray(flat_idx))
    ny, nz = int(shape[1]), int(shape[2])
    ijk = torch.stack([li // (ny * nz), (li // nz) % ny, li % nz], -1)
    return torch.as_tensor(np.asarray(lo, np.float32)) + ijk.float() * voxel


def keep_silhouettes(values: np.ndarray, hull_values: np.ndarray, lo: np.ndarray, voxel: float,
                     views: ViewStack, masks: np.ndarray, threshold: float = 0.5, rounds: int = 2,
                     chunk: int = 1 << 18) -> tuple[np.ndarray, dict]:
    """Give back carved hull nodes where carving uncovered mask pixels.

    ``values``: the hull after stereo carving (+ inside); ``hull_values``: the hull before it;
    ``views``: the cameras of the ``masks`` (N,H,W).  Stereo is
    least reliable at silhouettes (the window straddles the background) and a wrong depth there
    carves the object's rim, which the field then cannot render (it has no density far from the
    scaffold).  Every mask pixel must stay covered: the inside nodes are splatted into every view,
    and carved nodes that project onto a mask pixel no inside node covers are restored to their hull
    value.  Returns the new values and counts for the report.
    """
    N = len(views)
    H, W = views.height, views.width
    m = torch.from_numpy(np.asarray(masks) > threshold)
    out = values.copy()
    carved = np.flatnonzero(((hull_values > 0) & (values <= 0)).reshape(-1))
    flat_hull = hull_values.reshape(-1)
    flat_out = out.reshape(-1)

    def pixels(idx):
        u, v, z = views.project(_node_positions(idx, values.shape, lo, voxel))
        ok = views.in_frame(u, v, z)
        ui = u.floor().long().clamp(0, W - 1)
        vi = v.floor().long().clamp(0, H - 1)
        return ok, vi * W + ui

    stats = {"carved_nodes": int(len(carved)), "restored_nodes": 0, "uncovered_px": []}
    for _ in range(rounds):
        cover = torch.zeros(N, H * W, dtype=torch.bool)
        inside = np.flatnonzero(flat_out > 0)
        for s in range(0, len(inside), chunk):
            ok, pix = pixels(inside[s:s + chunk])
            for n in range(N):
                cover[n, pix[n][ok[n]]] = True
        # a node covers the pixels its voxel spans: close the one-pixel gaps between node centres
        cover = F.max_pool2d(cover.view(N, 1, H, W).float(), 3, stride=1, padding=1)[:, 0] > 0
        cover = F.max_pool2d(1.0 - cover[:, None].float(), 3, stride=1, padding=1)[:, 0] < 0.5
        missed = (m & ~cover).view(N, H * W)
        stats["uncovered_px"].append(int(missed.sum()))
        if not bool(missed.any()) or len(carved) == 0:
            break
        restore = np.zeros(len(carved), bool)
        for s in range(0, len(carved), chunk):
            ok, pix = pixels(carved[s:s + chunk])
            hit = torch.zeros(pix.shape[1], dtype=torch.bool)
            for n in range(N):
                hit |= ok[n] & missed[n][pix[n]]
            restore[s:s + chunk] = hit.numpy()
        if not restore.any():
            break
        idx = carved[restore]
        flat_out[idx] = flat_hull[idx]
        carved = carved[~restore]
        stats["restored_nodes"] += int(len(idx))
    return out, stats
