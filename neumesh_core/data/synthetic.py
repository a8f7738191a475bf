"""The built-in default scene: a textured, non-convex "bumpy blob" and its reference ray tracer.

Analytic surface (star-shaped around the origin): for a unit direction ``u`` the surface point is
``r(u) * u`` with ``r(u) = 1 + AMPLITUDE * bumps(u)`` and ``bumps`` a sum of smooth von Mises-Fisher
lobes ``c_k * exp(kappa_k * (u . d_k - 1))`` (positive lobes are hills, negative ones dents, so the
surface has concavities). Everything here (shape, texture, light, cameras) is fixed and deterministic.

* :func:`default_mesh` - icosphere whose vertices lie exactly on the analytic surface.
* :func:`default_texture` - a high-frequency solid texture (stripes/checker + stroke lettering).
* :func:`render_reference` - ray tracer of the analytic surface (Lipschitz-safe marching + bisection,
  analytic normals, Lambert + Blinn-Phong, 4 jittered samples per pixel).
* :func:`make_default_scene` / :func:`default_scene_dir` - write / cache it in NeRF-synthetic format.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
import threading
import time

import numpy as np
import torch

from ..mesh import Mesh, save_mesh

SCENE_VERSION = 1
AMPLITUDE = 0.25

# Fixed lobes (direction, coefficient, concentration). Hard-coded: no RNG, identical everywhere.
_LOBES = np.array(
    [
        # dx,    dy,    dz,     c,    kappa
        [0.00, 0.00, 1.00, 0.80, 3.0],
        [0.90, 0.30, 0.10, 1.00, 9.0],
        [-0.50, 0.80, -0.20, 0.90, 7.0],
        [-0.40, -0.70, 0.45, -1.00, 8.0],
        [0.30, -0.60, -0.75, 1.00, 6.0],
        [-0.85, -0.10, -0.50, -0.90, 9.0],
        [0.45, 0.60, 0.65, -0.90, 10.0],
        [0.10, 0.20, -1.00, -0.70, 5.0],
        [-0.60, 0.10, 0.80, 0.90, 12.0],
        [0.70, -0.65, 0.30, -0.80, 11.0],
        [0.05, 0.95, 0.30, 0.70, 14.0],
        [-0.20, -0.90, -0.35, 0.80, 12.0],
        [0.80, 0.10, -0.60, -0.70, 13.0],
    ],
    dtype=np.float64,
)
_DIRS = _LOBES[:, :3] / np.linalg.norm(_LOBES[:, :3], axis=1, keepdims=True)
_COEF = _LOBES[:, 3].copy()
_KAPPA = _LOBES[:, 4].copy()

LIGHT_DIR = np.array([0.45, 0.35, 0.82]) / np.linalg.norm([0.45, 0.35, 0.82])
AMBIENT, DIFFUSE, SPECULAR, SHININESS = 0.30, 0.70, 0.30, 32.0

# Defaults of the scene and of the small variant used by tests.
CAMERA_RADIUS = 4.0
CAMERA_ANGLE_X = 0.9  # radians (~52 deg): the blob fills ~70% of the frame
SMALL_SCENE_KWARGS = dict(resolution=64, n_train=30, n_val=4, n_test=4, mesh_subdiv=4)


@contextlib.contextmanager
def _torch_single_thread():
    """Run torch ops single-threaded for the duration (restored afterwards).

    The tracer issues thousands of small ops; with intra-op threads each op synchronises the
    OpenMP team, which costs milliseconds per op when other processes keep the cores busy (measured
    5.5 s vs 0.07 s for a 64px image on a loaded 2-core machine). Callers render images in
    parallel threads instead. Note: torch's thread count is process-wide.
    """
    with _THREAD_LOCK:
        _THREAD_STATE["depth"] += 1
        if _THREAD_STATE["depth"] == 1:
            _THREAD_STATE["saved"] = torch.get_num_threads()
            torch.set_num_threads(1)
    try:
        yield
    finally:
        with _THREAD_LOCK:
            _THREAD_STATE["depth"] -= 1
            if _THREAD_STATE["depth"] == 0:
                torch.set_num_threads(_THREAD_STATE["saved"])


_THREAD_LOCK = threading.Lock()
_THREAD_STATE = {"depth": 0, "saved": 1}


# --------------------------------------------------------------------------------------------
# analytic shape
# --------------------------------------------------------------------------------------------
_CONST_CACHE: dict = {}


def _consts(dtype: torch.dtype, device) -> tuple:
    key = (dtype, str(device))
    if key not in _CONST_CACHE:
        d = torch.as_tensor(_DIRS, dtype=dtype, device=device)
        k = torch.as_tensor(_KAPPA, dtype=dtype, device=device)
        c = torch.as_tensor(_COEF * AMPLITUDE, dtype=dtype, device=device)
        _CONST_CACHE[key] = ((d * k[:, None]).T.contiguous(), k, c, d)
    return _CONST_CACHE[key]


def _radius_and_grad(u: torch.Tensor, need_grad: bool = True):
    """r(u) and its Euclidean gradient dr/du (u treated as a free 3-vector) for unit u (N,3)."""
    kdT, k, c, d = _consts(u.dtype, u.device)
    e = torch.exp(torch.addmm(-k, u, kdT)) * c  # c_k exp(kappa_k (u.d_k - 1)), (N,L)
    r = 1.0 + e.sum(-1)
    if not need_grad:
        return r, None
    g = (e * k) @ d  # (N,3)
    return r, g


def surface_radius(u) -> np.ndarray | torch.Tensor:
    """r(u) for directions u (N,3) (normalised internally). Numpy in -> numpy out."""
    is_np = not isinstance(u, torch.Tensor)
    ut = torch.as_tensor(np.asarray(u, dtype=np.float64) if is_np else u)
    ut = ut / ut.norm(dim=-1, keepdim=True)
    r, _ = _radius_and_grad(ut)
    return r.numpy() if is_np else r


def implicit(x: torch.Tensor) -> torch.Tensor:
    """f(x) = |x| - r(x/|x|): negative inside the blob, 0 on its surface."""
    rho = x.norm(dim=-1).clamp_min(1e-12)
    r, _ = _radius_and_grad(x / rho[:, None], need_grad=False)
    return rho - r


def surface_normal(x) -> np.ndarray | torch.Tensor:
    """Analytic outward unit normal (normalised gradient of f) at points x (N,3)."""
    is_np = not isinstance(x, torch.Tensor)
    xt = torch.as_tensor(np.asarray(x, dtype=np.float64) if is_np else x)
    rho = xt.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    u = xt / rho
    _, g = _radius_and_grad(u)
    g_t = g - (g * u).sum(-1, keepdim=True) * u
    n = u - g_t / rho
    n = n / n.norm(dim=-1, keepdim=True)
    return n.numpy() if is_np else n


def _fibonacci_sphere(n: int, offset: float = 0.5, rotation: np.ndarray | None = None) -> np.ndarray:
    i = np.arange(n, dtype=np.float64) + offset
    z = 1.0 - 2.0 * i / n
    rad = np.sqrt(np.clip(1.0 - z * z, 0.0, 1.0))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    p = np.stack([rad * np.cos(phi), rad * np.sin(phi), z], -1)
    return p if rotation is None else p @ rotation.T


_BOUNDS_CACHE: dict = {}


def shape_bounds() -> dict:
    """Numerically bounded facts about the shape: r_min, r_max (with margins) and the Lipschitz
    constant of f outside the surface (used for safe ray marching)."""
    if not _BOUNDS_CACHE:
        u = torch.as_tensor(_fibonacci_sphere(200_000))
        r, g = _radius_and_grad(u)
        g_t = g - (g * u).sum(-1, keepdim=True) * u
        gt_norm = g_t.norm(dim=-1)
        spacing = math.sqrt(4 * math.pi / 200_000) * 2.0  # >= distance to the nearest sample
        gmax = float(gt_norm.max())
        margin = spacing * (gmax + 0.5)
        r_min, r_max = float(r.min()) - margin, float(r.max()) + margin
        # outside the surface |grad f|^2 = 1 + |g_t|^2/rho^2 <= 1 + |g_t|^2/r^2
        lip = math.sqrt(1.0 + ((gmax + margin * 10) / r_min) ** 2) * 1.05
        _BOUNDS_CACHE.update(r_min=r_min, r_max=r_max, lipschitz=lip)
    return dict(_BOUNDS_CACHE)


# --------------------------------------------------------------------------------------------
# mesh
# --------------------------------------------------------------------------------------------
def icosphere(subdiv: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: (10*4^subdiv + 2) vertices (float64, unit length), CCW-outward faces."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    v = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
        dtype=np.float64,
    )
    f = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]],
        dtype=np.int64,
    )
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(int(subdiv)):
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        e_sorted = np.sort(e, axis=1)
        uniq, inv = np.unique(e_sorted, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        mid = v[uniq[:, 0]] + v[uniq[:, 1]]
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1).T + len(v)  # midpoint index of edges (01, 12, 20) per face
        a, b, c = f[:, 0], f[:, 1], f[:, 2]
        ab, bc, ca = m[:, 0], m[:, 1], m[:, 2]
        f = np.concatenate([
            np.stack([a, ab, ca], 1), np.stack([b, bc, ab], 1),
            np.stack([c, ca, bc], 1), np.stack([ab, bc, ca], 1),
        ])
        v = np.concatenate([v, mid])
    return v, f


def default_mesh(subdiv: int = 5) -> Mesh:
    """The blob as a triangle mesh: an icosphere (subdiv 5: 10,242 vertices; 6: 40,962) with every
    vertex moved radially onto the analytic surface (``|v| = r(v/|v|)``)."""
    if subdiv < 0 or subdiv > 8:
        raise ValueError(f"subdiv must be in 0..8 (vertices = 10*4^subdiv+2), got {subdiv}")
    u, f = icosphere(subdiv)
    r = surface_radius(u)
    return Mesh((u * r[:, None]).astype(np.float32), f)


# --------------------------------------------------------------------------------------------
# texture
# --------------------------------------------------------------------------------------------
_FONT = {  # 5x7 bitmap glyphs
    "N": ["X...X", "XX..X", "X.X.X", "X..XX", "X...X", "X...X", "X...X"],
    "E": ["XXXXX", "X....", "X....", "XXXX.", "X....", "X....", "XXXXX"],
    "U": ["X...X", "X...X", "X...X", "X...X", "X...X", "X...X", ".XXX."],
    "M": ["X...X", "XX.XX", "X.X.X", "X.X.X", "X...X", "X...X", "X...X"],
    "S": [".XXXX", "X....", "X....", ".XXX.", "....X", "....X", "XXXX."],
    "H": ["X...X", "X...X", "X...X", "XXXXX", "X...X", "X...X", "X...X"],
    "R": ["XXXX.", "X...X", "X...X", "XXXX.", "X.X..", "X..X.", "X...X"],
    "F": ["XXXXX", "X....", "X....", "XXXX.", "X....", "X....", "X...."],
    "7": ["XXXXX", "....X", "...X.", "..X..", ".X...", ".X...", ".X..."],
    "Z": ["XXXXX", "....X", "...X.", "..X..", ".X...", "X....", "XXXXX"],
    " ": ["....."] * 7,
}
_TEXT_ROWS = ["NEUMESH NERF 7 ", "SHUZ MESH FUNE "]  # two lines of "lettering" around the equator
_GLYPHS_AROUND = 22
_PALETTE = np.array(
    [[0.85, 0.12, 0.10], [0.98, 0.80, 0.10], [0.10, 0.35, 0.85], [0.10, 0.65, 0.25],
     [0.95, 0.50, 0.05], [0.55, 0.15, 0.65]],
    dtype=np.float32,
)
_PAPER = np.array([0.95, 0.93, 0.85], dtype=np.float32)
_INK = np.array([0.05, 0.05, 0.12], dtype=np.float32)


def _font_bits(text: str) -> np.ndarray:
    return np.array([[[ch == "X" for ch in row] for row in _FONT[c]] for c in text], dtype=bool)


def _bit_lookup(bits: torch.Tensor, glyph: torch.Tensor, bx: torch.Tensor, by: torch.Tensor) -> torch.Tensor:
    inside = (bx >= 0) & (bx < 5) & (by >= 0) & (by < 7)
    val = bits[glyph, by.clamp(0, 6), bx.clamp(0, 4)]
    return val & inside


def default_texture(points, normals=None):
    """Albedo (N,3) in [0,1] of the solid texture at 3D surface points (N,3).

    Latitude stripes in six saturated colours times a longitude checker; two rows of stroke lettering
    (dark ink on paper) in a band around the equator; near the poles a fine triplanar checker whose
    projection axis follows ``normals`` (the analytic normal is used when ``normals`` is None).
    Numpy in -> numpy float32 out; torch in -> torch out.
    """
    is_np = not isinstance(points, torch.Tensor)
    p = torch.as_tensor(np.asarray(points, dtype=np.float32) if is_np else points).to(torch.float32)
    if normals is None:
        n = surface_normal(p.double()).float()
    else:
        n = torch.as_tensor(np.asarray(normals, dtype=np.float32) if is_np else normals).to(torch.float32)
    u = p / p.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    theta = torch.acos(u[:, 2].clamp(-1, 1))  # 0 at +z pole
    phi = torch.atan2(u[:, 1], u[:, 0]) + math.pi  # [0, 2pi]
    pal = torch.as_tensor(_PALETTE)
    # stripes x checker
    band = torch.floor(theta / (math.pi / 14)).long()
    sector = torch.floor(phi / (2 * math.pi / 20)).long()
    col = pal[band % len(_PALETTE)]
    dark = ((band + sector) % 2 == 1).float()[:, None]
    col = col * (1.0 - 0.45 * dark) + 0.08 * dark
    # lettering band: theta in [pi/2 - 0.36, pi/2 + 0.36] holds two text rows
    cell_w = 2 * math.pi / _GLYPHS_AROUND
    cell_h = cell_w * 1.25
    row_f = (theta - (math.pi / 2 - cell_h)) / cell_h
    row = torch.floor(row_f).long()
    in_band = (row >= 0) & (row < 2)
    gx = phi / cell_w
    gcol = torch.floor(gx).long() % _GLYPHS_AROUND
    lx = (gx - torch.floor(gx)) * 6.0 - 0.5  # 5 bit columns + spacing
    ly = (row_f - torch.floor(row_f)) * 8.5 - 0.75  # 7 bit rows + spacing
    bx = torch.floor(lx).long()
    by = torch.floor(ly).long()
    fx, fy = lx - bx, ly - by
    ink = torch.zeros_like(theta, dtype=torch.bool)
    half = 0.24  # stroke half width in bit units (thin strokes)
    for r_i, text in enumerate(_TEXT_ROWS):
        bits = torch.as_tensor(_font_bits(text))
        glyph = (gcol + 3 * r_i) % len(text)
        sel = in_band & (row == r_i)
        node = _bit_lookup(bits, glyph, bx, by)
        right = _bit_lookup(bits, glyph, bx + 1, by)
        left = _bit_lookup(bits, glyph, bx - 1, by)
        down = _bit_lookup(bits, glyph, bx, by + 1)
        up = _bit_lookup(bits, glyph, bx, by - 1)
        cx_ok = (fx - 0.5).abs() < half
        cy_ok = (fy - 0.5).abs() < half
        stroke = node & cx_ok & cy_ok
        stroke |= node & cy_ok & ((right & (fx >= 0.5)) | (left & (fx <= 0.5)))
        stroke |= node & cx_ok & ((down & (fy >= 0.5)) | (up & (fy <= 0.5)))
        ink |= sel & stroke
    paper = torch.as_tensor(_PAPER).expand_as(col)
    col = torch.where(in_band[:, None], paper, col)
    col = torch.where(ink[:, None], torch.as_tensor(_INK).expand_as(col), col)
    # poles: triplanar fine checker (projection axis = dominant normal axis)
    polar = u[:, 2].abs() > 0.93
    axis = n.abs().argmax(-1)
    q = torch.floor(p * 12.0).long()
    c0 = torch.where(axis == 0, q[:, 1] + q[:, 2], torch.where(axis == 1, q[:, 0] + q[:, 2], q[:, 0] + q[:, 1]))
    pole_col = torch.where((c0 % 2 == 0)[:, None], pal[2].expand_as(col), pal[1].expand_as(col))
    col = torch.where(polar[:, None], pole_col, col)
    col = col.clamp(0.0, 1.0)
    return col.numpy().astype(np.float32) if is_np else col


# --------------------------------------------------------------------------------------------
# reference ray tracer
# --------------------------------------------------------------------------------------------
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


def render_reference(K, c2w, width: int, height: int, background=(1.0, 1.0, 1.0), spp: int = 4, seed: int = 0):
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
def look_at_opencv(position: np.ndarray, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """4x4 OpenCV camera-to-world (x right, y down, z forward) at ``position`` looking at ``target``."""
    pos = np.asarray(position, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - pos
    fwd /= np.linalg.norm(fwd)
    up = np.asarray(up, dtype=np.float64)
    if abs(float(fwd @ up)) > 0.999:
        up = np.array([0.0, 1.0, 0.0])
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, fwd, pos
    return c2w


def _rotation(axis, angle) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a /= np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def camera_positions(n_train: int, n_val: int, n_test: int, radius: float = CAMERA_RADIUS, seed: int = 0) -> dict:
    """Camera centres: train on a Fibonacci sphere; val/test on differently rotated Fibonacci spheres
    (both hemispheres, not coinciding with training views)."""
    rng = np.random.default_rng(seed)
    out = {"train": _fibonacci_sphere(n_train) * radius}
    for name, n in (("val", n_val), ("test", n_test)):
        rot = _rotation(rng.normal(size=3), rng.uniform(0.3, 2.8))
        out[name] = _fibonacci_sphere(n, offset=0.5, rotation=rot) * radius if n else np.zeros((0, 3))
    return out


def _render_split(pool, cams, K, res, folder, split, seed_base):
    from ..imageio import save_image

    def job(i):
        rgb, alpha = _render_unpremultiplied(K, cams[i], res, res, spp=4, seed=seed_base + i)
        rgba = np.concatenate([rgb, alpha[..., None]], -1)
        save_image(os.path.join(folder, split, f"r_{i}.png"), rgba)

    list(pool.map(job, range(len(cams))))


def _write_splits(out_dir, pos, K, resolution, camera_angle_x, seed, workers):
    from concurrent.futures import ThreadPoolExecutor

    split_seeds = {"train": seed * 100_003 + 0, "val": seed * 100_003 + 10_000, "test": seed * 100_003 + 20_000}
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for split, centres in pos.items():
            cams = [look_at_opencv(c) for c in centres]
            # exact float64 OpenGL matrices (opencv_to_opengl rounds to float32)
            gl_flip = np.diag([1.0, -1.0, -1.0, 1.0])
            frames = [
                {"file_path": f"./{split}/r_{i}", "transform_matrix": (c @ gl_flip).tolist()}
                for i, c in enumerate(cams)
            ]
            os.makedirs(os.path.join(out_dir, split), exist_ok=True)
            _render_split(pool, cams, K, resolution, out_dir, split, split_seeds[split])
            meta = {"camera_angle_x": float(camera_angle_x), "frames": frames}
            tmp = os.path.join(out_dir, f".transforms_{split}.json.tmp")
            with open(tmp, "w", encoding="utf-8") as fh:
                json.dump(meta, fh, indent=1)
            os.replace(tmp, os.path.join(out_dir, f"transforms_{split}.json"))


def make_default_scene(out_dir: str, resolution: int = 128, n_train: int = 60, n_val: int = 8, n_test: int = 8,
                       seed: int = 0, mesh_subdiv: int = 5, camera_radius: float = CAMERA_RADIUS,
                       camera_angle_x: float = CAMERA_ANGLE_X, num_workers: int | None = None) -> str:
    """Write the default scene in NeRF-synthetic format and return ``out_dir``.

    Files: transforms_{train,val,test}.json (camera_angle_x, OpenGL transform_matrix), RGBA PNGs in
    train/ val/ test/, mesh.ply (the blob mesh, vertices exactly on the analytic surface) and
    scene.json (description; written last, so its presence marks a complete scene). Deterministic
    for given arguments. ``SMALL_SCENE_KWARGS`` gives a quick variant for tests.
    """
    if resolution < 8:
        raise ValueError(f"resolution must be >= 8, got {resolution}")
    if n_train < 1:
        raise ValueError("n_train must be >= 1")
    t_start = time.perf_counter()
    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    marker = os.path.join(out_dir, "scene.json")
    if os.path.exists(marker):
        os.remove(marker)
    pos = camera_positions(n_train, n_val, n_test, camera_radius, seed)
    f = 0.5 * resolution / math.tan(0.5 * camera_angle_x)
    K = np.array([[f, 0, resolution / 2], [0, f, resolution / 2], [0, 0, 1]], dtype=np.float64)
    workers = num_workers or max(1, min(8, os.cpu_count() or 1))
    # one torch thread per worker: images are rendered in parallel threads (ops release the GIL)
    with _torch_single_thread():
        _write_splits(out_dir, pos, K, resolution, camera_angle_x, seed, workers)
    mesh = default_mesh(mesh_subdiv)
    save_mesh(mesh, os.path.join(out_dir, "mesh.ply"))
    b = shape_bounds()
    desc = {
        "name": "neumesh default scene (bumpy blob)",
        "version": SCENE_VERSION,
        "description": (
            "Star-shaped non-convex blob r(u) = 1 + amplitude * sum_k c_k exp(kappa_k (u.d_k - 1)) with a "
            "solid texture (colour stripes x checker, two rows of stroke lettering around the equator, "
            "triplanar checker at the poles), shaded with ambient + Lambert + white Blinn-Phong "
            "(directional light), ray-traced analytically with 4 jittered samples per pixel. "
            "mesh.ply is an icosphere with its vertices on the analytic surface. Cameras use the "
            "NeRF-synthetic convention (OpenGL c2w), RGBA images (alpha = coverage)."
        ),
        "generator": "neumesh_core.data.synthetic.make_default_scene",
        "params": {
            "resolution": resolution, "n_train": n_train, "n_val": n_val, "n_test": n_test, "seed": seed,
            "mesh_subdiv": mesh_subdiv, "camera_radius": camera_radius, "camera_angle_x": camera_angle_x,
        },
        "shape": {
            "amplitude": AMPLITUDE, "lobes": _LOBES.tolist(), "r_min": round(b["r_min"], 4),
            "r_max": round(b["r_max"], 4),
        },
        "shading": {"light_dir": LIGHT_DIR.tolist(), "ambient": AMBIENT, "diffuse": DIFFUSE,
                    "specular": SPECULAR, "shininess": SHININESS, "samples_per_pixel": 4},
        "mesh": {"file": "mesh.ply", "vertices": int(mesh.num_vertices), "faces": int(len(mesh.faces))},
        "bbox": [[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]],
    }
    tmp = marker + ".tmp"
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(desc, fh, indent=1)
    os.replace(tmp, marker)
    _LAST_TIMING["seconds"] = time.perf_counter() - t_start
    return out_dir


_LAST_TIMING: dict = {}


def _cache_base(cache_root=None) -> str:
    if cache_root is not None:
        return os.fspath(cache_root)
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = xdg if xdg else os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "neumesh")


def _is_complete(path: str, params: dict) -> bool:
    try:
        with open(os.path.join(path, "scene.json"), "r", encoding="utf-8") as fh:
            desc = json.load(fh)
    except (OSError, ValueError):
        return False
    if desc.get("version") != SCENE_VERSION:
        return False
    stored = desc.get("params", {})
    return all(stored.get(k) == v for k, v in params.items()) and os.path.isfile(os.path.join(path, "mesh.ply"))


def default_scene_dir(cache_root: str | None = None, small: bool = False) -> str:
    """Path of the cached default scene, generating it on first use.

    Location: ``<cache_root>/default_scene_v1`` (``default_scene_v1_small`` for the quick test
    variant); ``cache_root`` defaults to ``$XDG_CACHE_HOME/neumesh`` or ``~/.cache/neumesh``. A scene
    is reused when its scene.json matches; otherwise it is generated in a temporary sibling folder
    and moved into place (safe against concurrent callers and interrupted runs).
    """
    base = _cache_base(cache_root)
    name = f"default_scene_v{SCENE_VERSION}" + ("_small" if small else "")
    path = os.path.join(base, name)
    kwargs = dict(SMALL_SCENE_KWARGS) if small else {}
    params = dict(resolution=128, n_train=60, n_val=8, n_test=8, seed=0, mesh_subdiv=5)
    params.update(kwargs)
    if _is_complete(path, params):
        return path
    os.makedirs(base, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=f".{name}.", dir=base)
    try:
        make_default_scene(tmp, **params)
        if os.path.isdir(path):
            if _is_complete(path, params):  # another process finished first
                return path
            stale = tempfile.mkdtemp(prefix=f".{name}.stale.", dir=base)
            os.replace(path, os.path.join(stale, "old"))
            shutil.rmtree(stale, ignore_errors=True)
        try:
            os.replace(tmp, path)
        except OSError:
            if not _is_complete(path, params):
                raise
    finally:
        if os.path.isdir(tmp):
            shutil.rmtree(tmp, ignore_errors=True)
    return path
