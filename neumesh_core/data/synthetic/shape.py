"""The built-in scene's shape: a star-shaped "bumpy blob" around the origin (analytic surface, implicit
function and normals) and the icosphere mesh whose vertices lie on it.

For a unit direction ``u`` the surface point is ``r(u) * u`` with ``r(u) = 1 + AMPLITUDE * bumps(u)``
and ``bumps`` a sum of smooth von Mises-Fisher lobes ``c_k * exp(kappa_k * (u . d_k - 1))`` (positive
lobes are hills, negative ones dents, so the surface has concavities).
"""
from __future__ import annotations

import contextlib
import math
import threading

import numpy as np
import torch

from ...mesh import Mesh

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


@contextlib.contextmanager
def _torch_single_thread():
    """Run torch ops single-threaded for the duration (restored afterwards).

    The tracer issues thousands of small ops; with intra-op threads each op synchronises the
    OpenMP team, which costs milliseconds per op when other processes keep the cores busy. Callers
    render images in
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
