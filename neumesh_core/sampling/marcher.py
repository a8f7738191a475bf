"""Ray marching through the occupancy grid with early termination (pure torch).

nerfacc-style: the marcher knows nothing about the field; it calls ``sigma_fn(points) -> (sigma, aux)``
where ``aux`` is any per-sample object with ``select(mask)`` and ``Neighbourhood.cat``-like ``cat``
(or None).  Rays advance in windows of ``window`` steps; only occupied steps are evaluated; a ray stops
when its transmittance falls below ``early_stop_eps``.  Samples whose compositing weight is below
``weight_threshold`` are dropped from the output (they cannot change the image noticeably).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional

import torch

from .occupancy import OccupancyGrid


@dataclass
class RaySamples:
    """Packed samples sorted by (ray, t).  ``aux``: per-sample data from sigma_fn (e.g. neighbourhoods)."""

    ray_indices: torch.Tensor  # (S,) long
    t_starts: torch.Tensor     # (S,)
    t_ends: torch.Tensor       # (S,)
    sigmas: torch.Tensor       # (S,) densities seen while marching (no grad)
    aux: Any
    n_rays: int

    def __len__(self) -> int:
        return self.ray_indices.shape[0]

    def positions(self, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        t = 0.5 * (self.t_starts + self.t_ends)
        return origins[self.ray_indices] + dirs[self.ray_indices] * t[:, None]


def _cat_aux(items):
    items = [a for a in items if a is not None]
    if not items:
        return None
    return type(items[0]).cat(items)


@torch.no_grad()
def march_rays(origins: torch.Tensor, dirs: torch.Tensor, grid: OccupancyGrid,
               sigma_fn: Callable[[torch.Tensor], tuple], step_size: float,
               near=0.0, far=float("inf"), window: int = 32,
               early_stop_eps: float = 1e-4, weight_threshold: float = 1e-4,
               jitter: Optional[torch.Tensor] = None, max_eval: int = 8) -> RaySamples:
    """March rays (R,3)/(R,3 unit) through ``grid``; returns packed samples sorted by (ray, t).

    Each round looks ``window`` steps ahead but evaluates at most ``max_eval`` occupied steps per ray,
    so a ray that turns opaque stops within a few samples.  ``jitter`` (R,) in [0,1) offsets each
    ray's sample positions (training); None = step centres.  ``near`` / ``far``: one distance each, or
    (R,) tensors of per-ray distances (e.g. an occluder in front of the field, or the interval where a
    ray can meet an occupied cell) outside which nothing is sampled; sample positions stay anchored at
    multiples of the step from the origin, so a tighter interval samples the same points.
    """
    device = origins.device
    n_rays = origins.shape[0]
    t_near, t_far = grid.ray_aabb(origins, dirs)
    t_near = torch.maximum(t_near, near) if torch.is_tensor(near) else t_near.clamp_min(near)
    t_far = torch.minimum(t_far, far) if torch.is_tensor(far) else t_far.clamp_max(far)
    alive = (t_far > t_near).nonzero().squeeze(1)
    # sample positions are anchored at multiples of the step from the ray origin, so that moving the
    # scene and the camera together (or changing the grid box) samples exactly the same points
    t_cur = torch.floor(t_near / step_size) * step_size
    log_T = torch.zeros(n_rays, device=device)
    log_eps = float(torch.log(torch.tensor(early_stop_eps)))
    offs = (torch.arange(window, device=device, dtype=torch.float32) + 0.5) * step_size
    out_r, out_t, out_s, out_aux = [], [], [], []
    # rays in the grid's cell coordinates: a step's cell is floor(g_o + g_d t), no (R,W,3) world points
    g_o, g_d = grid.cell_coordinates(origins, dirs)
    while alive.numel():
        t0 = t_cur[alive]
        ts = t0[:, None] + offs[None]
        if jitter is not None:
            ts = ts + (jitter[alive, None] - 0.5) * step_size
        in_range = (ts < t_far[alive, None]) & (ts >= t_near[alive, None])
        occ = grid.lookup_steps(g_o[alive], g_d[alive], ts) & in_range
        n_occ = torch.cumsum(occ, 1)
        within = n_occ <= max_eval
        occ = occ & within
        # a capped ray resumes right after its last evaluated step, the others after the window
        last = torch.where(n_occ[:, -1] > max_eval, within.sum(1), torch.full_like(n_occ[:, -1], window))
        sel = occ.nonzero()
        if sel.numel():
            rl, si = sel[:, 0], sel[:, 1]
            flat = rl * occ.shape[1] + si
            t_s = ts.reshape(-1).index_select(0, flat)
            ray = alive.index_select(0, rl)
            sigma, aux = sigma_fn(origins.index_select(0, ray) + dirs.index_select(0, ray) * t_s[:, None])
            sigma = sigma.float()
            # transmittance along the window, only for the rays that have samples in it (rl is sorted)
            rows, row_of = torch.unique_consecutive(rl, return_inverse=True)
            row_rays = alive.index_select(0, rows)
            dense = torch.zeros(len(rows), occ.shape[1], device=device)
            tau = sigma * step_size
            dense[row_of, si] = tau
            excl = torch.cumsum(dense, 1) - dense
            log_t_sample = log_T.index_select(0, row_rays).index_select(0, row_of) - \
                excl.reshape(-1).index_select(0, row_of * occ.shape[1] + si)
            weights = torch.exp(log_t_sample) * (1.0 - torch.exp(-tau))
            keep = (weights > weight_threshold) & (log_t_sample > log_eps)
            if keep.any():
                k_idx = keep.nonzero().squeeze(1)
                out_r.append(ray.index_select(0, k_idx))
                out_t.append(t_s.index_select(0, k_idx))
                out_s.append(sigma.index_select(0, k_idx))
                out_aux.append(aux.select(k_idx) if aux is not None else None)
            log_T[row_rays] = log_T[row_rays] - dense.sum(1)
        t_cur[alive] = t0 + last.float() * step_size
        still = (t_cur[alive] < t_far[alive]) & (log_T[alive] > log_eps)
        alive = alive[still]
    if out_r:
        ray_idx = torch.cat(out_r)
        t_mid = torch.cat(out_t)
        sig = torch.cat(out_s)
        aux = _cat_aux(out_aux)
        # sort by (ray, t): t inside a ray is already increasing across windows; a stable sort by ray
        # index keeps that order
        order = torch.sort(ray_idx, stable=True).indices
        ray_idx, t_mid, sig = (x.index_select(0, order) for x in (ray_idx, t_mid, sig))
        if aux is not None:
            aux = aux.select(order)
    else:
        ray_idx = torch.zeros(0, dtype=torch.long, device=device)
        t_mid = torch.zeros(0, device=device)
        sig = torch.zeros(0, device=device)
        aux = None
    half = 0.5 * step_size
    return RaySamples(ray_idx, t_mid - half, t_mid + half, sig, aux, n_rays)


@torch.no_grad()
def march_rays_reference(origins: torch.Tensor, dirs: torch.Tensor, t_near: torch.Tensor,
                         t_far: torch.Tensor, step_size: float) -> RaySamples:
    """Plain reference: every step between t_near and t_far, no grid, no early stop, no pruning."""
    r_list, t_list = [], []
    for r in range(origins.shape[0]):
        if t_far[r] <= t_near[r]:
            continue
        n = int(torch.ceil((t_far[r] - t_near[r]) / step_size))
        t = t_near[r] + (torch.arange(n, dtype=torch.float32) + 0.5) * step_size
        t = t[t < t_far[r]]
        r_list.append(torch.full((len(t),), r, dtype=torch.long))
        t_list.append(t)
    ray_idx = torch.cat(r_list) if r_list else torch.zeros(0, dtype=torch.long)
    t_mid = torch.cat(t_list) if t_list else torch.zeros(0)
    half = 0.5 * step_size
    return RaySamples(ray_idx, t_mid - half, t_mid + half, torch.zeros_like(t_mid), None, origins.shape[0])
