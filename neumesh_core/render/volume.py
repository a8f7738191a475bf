"""Packed volume rendering (compositing) and its plain per-ray reference."""
from __future__ import annotations

from typing import Dict

import torch


def render_weights(ray_indices: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                   sigmas: torch.Tensor, n_rays: int) -> torch.Tensor:
    """Weights w_i = T_i (1 - exp(-sigma_i dt_i)), T_i = exp(-sum_{j<i in the same ray} sigma_j dt_j).

    Samples must be sorted by ray (then t).  Differentiable w.r.t. ``sigmas``.
    """
    if sigmas.numel() == 0:
        return sigmas
    tau = sigmas * (t_ends - t_starts)
    cs = torch.cumsum(tau.double(), 0)
    excl = cs - tau.double()
    # exclusive cumsum restarted at the first sample of every ray
    first = torch.ones_like(ray_indices, dtype=torch.bool)
    first[1:] = ray_indices[1:] != ray_indices[:-1]
    seg = torch.cumsum(first.long(), 0) - 1
    base = excl[first][seg]
    trans = torch.exp(-(excl - base)).to(sigmas.dtype)
    return trans * (1.0 - torch.exp(-tau))


def accumulate(weights: torch.Tensor, ray_indices: torch.Tensor, values: torch.Tensor, n_rays: int):
    """Sum of weights * values per ray: (S,) or (S,C) -> (R,) or (R,C)."""
    if values.ndim == 1:
        return torch.zeros(n_rays, device=weights.device, dtype=values.dtype).index_add(
            0, ray_indices, weights * values)
    out = torch.zeros(n_rays, values.shape[1], device=weights.device, dtype=values.dtype)
    return out.index_add(0, ray_indices, weights[:, None] * values)


def composite(ray_indices, t_starts, t_ends, sigmas, values: Dict[str, torch.Tensor], n_rays: int):
    """Composite packed samples.  Returns dict with 'opacity' (R,), 'depth' (R,) (expected t,
    un-normalised), 'weights' (S,) and every entry of ``values`` accumulated."""
    w = render_weights(ray_indices, t_starts, t_ends, sigmas, n_rays)
    out = {"weights": w,
           "opacity": accumulate(w, ray_indices, torch.ones_like(w), n_rays),
           "depth": accumulate(w, ray_indices, 0.5 * (t_starts + t_ends), n_rays)}
    for k, v in values.items():
        out[k] = accumulate(w, ray_indices, v, n_rays)
    return out


def composite_reference(ray_indices, t_starts, t_ends, sigmas, values: Dict[str, torch.Tensor], n_rays: int):
    """Per-ray loop reference of :func:`composite` (slow; for tests)."""
    opacity = torch.zeros(n_rays)
    depth = torch.zeros(n_rays)
    acc = {k: torch.zeros(n_rays, *v.shape[1:]) for k, v in values.items()}
    for r in range(n_rays):
        m = (ray_indices == r).nonzero().squeeze(1)
        T = 1.0
        for i in m.tolist():
            a = 1.0 - float(torch.exp(-sigmas[i] * (t_ends[i] - t_starts[i])))
            w = T * a
            opacity[r] += w
            depth[r] += w * 0.5 * float(t_starts[i] + t_ends[i])
            for k, v in values.items():
                acc[k][r] += w * v[i]
            T *= 1.0 - a
    return {"opacity": opacity, "depth": depth, **acc}
