"""The built-in scene's ground-truth ray tracer: Lipschitz-safe marching + bisection on the analytic
surface, analytic normals, Lambert + Blinn-Phong shading, jittered samples per pixel."""
from __future__ import annotations

import math

import numpy as np
import torch

from .shape import _consts, _torch_single_thread, implicit, shape_bounds, surface_normal, surface_radius  # noqa: F401
from .texture import default_texture

LIGHT_DIR = np.array([0.45, 0.35, 0.82]) / np.linalg.norm([0.45, 0.35, 0.82])
AMBIENT, DIFFUSE, SPECULAR, SHININESS = 0.30, 0.70, 0.30, 32.0


def trace_rays(origins: torch.Tensor, dirs: torch.Tensor, min_step: float = 2e-3, bisect_iters: int = 22,
               max_iters: int = 4000):
    """First intersection of rays with the analytic surface.

    Lipschitz-safe marching inside the bounding sphere (steps ``max(f/L, min_step)``; a root cannot be
    skipped by the f/L steps, only features thinner than ``min_step``), then bisection on the first
    sign change. Returns (hit (N,) bool, t (N,) float64; inf where missed). Marches in float32
    (root accurate to ~1e-6).
    """
    b = shape_bounds()
    o = origins.to(torch.float64)
    d = dirs.to(torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    n = o.shape[0]
    t_hit = torch.full((n,), float("inf"), dtype=torch.float64)
    # bounding sphere
    R = b["r_max"]
    bb = (o * d).sum(-1)
    cc = (o * o).sum(-1) - R * R
    disc = bb * bb - cc
    cand = disc > 0
    sq = disc.clamp_min(0).sqrt()
    t0 = (-bb - sq).clamp_min(0.0)
    t1 = -bb + sq
    cand &= t1 > 0
    idx = torch.nonzero(cand).squeeze(1)
    if len(idx) == 0:
        return t_hit < float("inf"), t_hit
    oo, dd = o[idx].float(), d[idx].float()
    t = t0[idx].float()
    tend = t1[idx].float()
    f = implicit(oo + t[:, None] * dd)
    inv_l = 1.0 / b["lipschitz"]
    found_idx, found_lo, found_hi = [], [], []
    # rays starting inside (camera inside the blob) hit at t0
    inside = f <= 0
    if inside.any():
        t_hit[idx[inside]] = t[inside].double()
        keep = ~inside
        idx, oo, dd, t, tend, f = idx[keep], oo[keep], dd[keep], t[keep], tend[keep], f[keep]
    it = 0
    while len(idx) and it < max_iters:
        it += 1
        step = torch.clamp(f * inv_l, min=min_step)
        t_new = t + step
        past = t_new > tend
        t_new = torch.minimum(t_new, tend)
        f_new = implicit(oo + t_new[:, None] * dd)
        crossed = f_new <= 0
        if crossed.any():
            found_idx.append(idx[crossed])
            found_lo.append(t[crossed])
            found_hi.append(t_new[crossed])
        alive = ~crossed & ~past
        idx, oo, dd, t, f, tend = idx[alive], oo[alive], dd[alive], t_new[alive], f_new[alive], tend[alive]
    if found_idx:
        gi = torch.cat(found_idx)
        lo = torch.cat(found_lo)
        hi = torch.cat(found_hi)
        og, dg = o[gi].float(), d[gi].float()
        for _ in range(bisect_iters):
            mid = 0.5 * (lo + hi)
            fm = implicit(og + mid[:, None] * dg)
            neg = fm <= 0
            hi = torch.where(neg, mid, hi)
            lo = torch.where(neg, lo, mid)
        t_hit[gi] = (0.5 * (lo + hi)).double()
    return torch.isfinite(t_hit), t_hit


def shade(points: torch.Tensor, view_dirs: torch.Tensor) -> torch.Tensor:
    """Colour (N,3) of surface points seen along ``view_dirs`` (ray directions, camera -> point)."""
    n = surface_normal(points.to(torch.float64))
    alb = default_texture(points.to(torch.float32), n.to(torch.float32)).to(torch.float64)
    light = torch.as_tensor(LIGHT_DIR, dtype=torch.float64)
    v = -view_dirs.to(torch.float64)
    v = v / v.norm(dim=-1, keepdim=True)
    ndl = (n @ light).clamp_min(0.0)
    h = light[None, :] + v
    h = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    spec = (n * h).sum(-1).clamp_min(0.0) ** SHININESS * (ndl > 0)
    col = alb * (AMBIENT + DIFFUSE * ndl[:, None]) + SPECULAR * spec[:, None]
    return col.clamp(0.0, 1.0)


def _sample_offsets(width: int, height: int, spp: int, seed: int) -> np.ndarray:
    """(spp,H,W,2) sub-pixel offsets in [0,1): stratified (jittered grid) per pixel, seeded."""
    rng = np.random.default_rng(seed)
    g = int(math.ceil(math.sqrt(spp)))
    cells = np.stack(np.meshgrid(np.arange(g), np.arange(g), indexing="xy"), -1).reshape(-1, 2)[:spp]
    jit = rng.random((spp, height, width, 2))
    return ((cells[:, None, None, :] + jit) / g).astype(np.float64)


def _render_unpremultiplied(K, c2w, width: int, height: int, spp: int = 4, seed: int = 0):
    """(colour of the hit samples averaged, i.e. un-premultiplied (H,W,3); alpha (H,W)), float64."""
    K = np.asarray(K, dtype=np.float64)
    c2w = np.asarray(c2w, dtype=np.float64)
    off = _sample_offsets(width, height, spp, seed)
    ys, xs = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    px = xs[None] + off[..., 0]
    py = ys[None] + off[..., 1]
    y = (py - K[1, 2]) / K[1, 1]
    x = (px - K[0, 2] - K[0, 1] * y) / K[0, 0]
    d_cam = np.stack([x, y, np.ones_like(x)], -1).reshape(-1, 3)
    d = torch.as_tensor(d_cam @ c2w[:3, :3].T)
    d = d / d.norm(dim=-1, keepdim=True)
    o = torch.as_tensor(c2w[:3, 3]).expand_as(d)
    hit, t = trace_rays(o, d)
    col = torch.zeros(d.shape[0], 3, dtype=torch.float64)
    if hit.any():
        p = o[hit] + t[hit, None] * d[hit]
        col[hit] = shade(p, d[hit])
    col = col.reshape(spp, height, width, 3)
    hits = hit.reshape(spp, height, width).to(torch.float64)
    nh = hits.sum(0)
    alpha = nh / spp
    rgb = col.sum(0) / nh.clamp_min(1.0)[..., None]
    return rgb.numpy(), alpha.numpy()


def render_truth(K, c2w, width: int, height: int, background=(1.0, 1.0, 1.0), spp: int = 4, seed: int = 0):
    """Ray-traced image of the analytic blob for one OpenCV camera (K 3x3, c2w 4x4).

    Returns ``(rgb (H,W,3) float32 composited on background, alpha (H,W) float32)``; alpha is the
    fraction of the ``spp`` jittered samples that hit the surface (soft, anti-aliased edges).
    ``background=None`` returns the un-premultiplied colour (as stored in RGBA PNGs).
    """
    with _torch_single_thread():
        rgb, alpha = _render_unpremultiplied(K, c2w, int(width), int(height), spp=spp, seed=seed)
    if background is not None:
        bg = np.asarray(background, dtype=np.float64).reshape(1, 1, 3)
        rgb = rgb * alpha[..., None] + bg * (1.0 - alpha[..., None])
    return rgb.astype(np.float32), alpha.astype(np.float32)


# --------------------------------------------------------------------------------------------
# dataset writer
# --------------------------------------------------------------------------------------------
