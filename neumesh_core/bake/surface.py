"""Where the field's surface is, seen from a mesh, and moving the mesh onto it.

A scaffold (or a decimated copy of it) sits up to a field radius off the surface the field actually
renders: the density the decoders learnt is where the photos put it, not where the scaffold vertices
are.  A texture baked onto such a mesh shows the right colours at the wrong places (part edges a few
pixels off, a silhouette too wide or too narrow).  This module

* measures, for points on a mesh with their normals, the signed distance along the normal to the
  field's surface: a short ray starts ``search`` radii out along the normal and looks back along it;
  the surface is where its opacity first reaches ``level`` (0.5: the depth at which the ray is half
  covered), found on densely sampled density (:func:`surface_offsets`);
* moves a mesh's vertices along their normals so that the whole mesh (its vertices and points inside
  its faces) lies on that surface: a sparse least-squares fit with a smoothness term over the edges,
  iterated with fresh normals (:func:`fit_to_field`);
* summarises how far a mesh lies from the field's surface (:func:`offset_stats`).

The search rays are independent of the occupancy grid and of the renderer's step (they sample the
density every ``step`` radii), so the surface found is the field's density level, not one renderer's
sample positions.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from ..errors import NeuMeshError


@dataclass
class SurfaceFitConfig:
    """How :func:`fit_to_field` moves a mesh onto the field's surface."""

    search: float = 1.5          # field radii searched on each side of the mesh along its normal
    # opacity at which a ray coming from outside along the normal has reached the surface; None: the
    # one of ``levels`` whose fitted mesh best matches the field's own renders (depth and silhouette)
    # from ``views`` virtual cameras of ``view_size`` pixels around the mesh (:func:`calibrate_level`)
    level: Optional[float] = None
    levels: tuple = (0.02, 0.05, 0.1, 0.2, 0.35, 0.5)
    views: int = 6
    view_size: int = 128
    step: float = 0.1            # density sampled every this many field radii along the search rays
    face_samples: int = 3        # points inside each face fitted besides the vertices (0, 1, 3 or 6)
    smoothness: float = 0.3      # weight of (d_i - d_j)^2 over the edges (displacements in radii)
    damping: float = 1e-3        # weight of d_i^2 (keeps vertices that see no surface where they are)
    iterations: int = 2          # fits, each with the normals of the previous one
    max_samples: int = 262144    # vertices + face points per fit; beyond, a fixed random subset of the faces
    chunk: int = 8192            # search rays per batch

    def __post_init__(self) -> None:
        if self.search <= 0 or self.step <= 0:
            raise ValueError("search and step must be positive (in field radii)")
        for lv in ([self.level] if self.level is not None else list(self.levels)):
            if not 0.0 < float(lv) < 1.0:
                raise ValueError(f"a level is an opacity in (0, 1), got {lv}")
        if self.level is None and (len(self.levels) < 1 or self.views < 1 or self.view_size < 16):
            raise ValueError("level None calibrates over levels (at least one), views >= 1 of view_size >= 16")
        if self.face_samples not in (0, 1, 3, 6):
            raise ValueError(f"face_samples must be 0, 1, 3 or 6, got {self.face_samples}")
        if self.smoothness < 0 or self.damping <= 0 or self.iterations < 1:
            raise ValueError("smoothness must be >= 0, damping > 0 and iterations >= 1")


def _cancel(progress, fraction):
    if progress is not None and progress(float(fraction)) is False:
        from ..render.renderer import Cancelled

        raise Cancelled("cancelled; nothing was changed")


@torch.no_grad()
def surface_offsets(field, points, normals, search: float = 1.5, level=0.5, step: float = 0.1,
                    chunk: int = 8192, progress: Optional[Callable[[float], bool]] = None,
                    span: tuple = (0.0, 1.0)) -> np.ndarray:
    """(n,) signed distance along each unit normal from the point to the field's surface: positive
    when the surface lies outside the point (along +normal), NaN where none was found.  ``level`` a
    sequence of L opacities: (n, L), one column per level, from the same density samples.

    A ray starts ``search`` field radii out along the normal and looks back along it for 2 x search
    radii; the density is sampled every ``step`` radii (midpoints) and the surface is where the ray's
    opacity first reaches ``level`` (linear in optical depth inside the crossing sample).  All
    lengths are world units in the result."""
    p = torch.as_tensor(np.asarray(points, np.float32)).reshape(-1, 3)
    n = torch.nn.functional.normalize(torch.as_tensor(np.asarray(normals, np.float32)).reshape(-1, 3), dim=1)
    if len(p) != len(n):
        raise ValueError(f"{len(p)} points but {len(n)} normals")
    dev = field.geo_codes.device
    r = float(field.radius)
    h = float(step) * r
    length = 2.0 * float(search) * r
    m = max(2, int(math.ceil(length / h)))
    h = length / m
    t = (torch.arange(m, dtype=torch.float32) + 0.5) * h                 # (m,) distances along the ray
    single = np.ndim(level) == 0
    levels = [float(level)] if single else [float(x) for x in level]
    out = np.full((len(p), len(levels)), np.nan, np.float32)
    per = max(1, int(chunk))
    for s in range(0, len(p), per):
        pc, nc = p[s:s + per], n[s:s + per]
        o = pc + nc * (float(search) * r)
        x = (o[:, None, :] - nc[:, None, :] * t[None, :, None]).reshape(-1, 3).to(dev)
        sigma, _ = field.sigma_fn(x)
        tau = (sigma.float().cpu().reshape(len(pc), m) * h).clamp_min(0)
        depth = torch.cumsum(tau, 1)                                      # optical depth after each sample
        for li, lv in enumerate(levels):
            target = -math.log(1.0 - lv)                                  # optical depth at the level
            reached = depth >= target
            hit = reached.any(1)
            k = torch.argmax(reached.to(torch.uint8), 1)                  # first sample at the level
            before = torch.where(k > 0, depth.gather(1, (k - 1).clamp_min(0)[:, None]).squeeze(1),
                                 torch.zeros(len(pc)))
            tk = tau.gather(1, k[:, None]).squeeze(1)
            frac = ((target - before) / tk.clamp_min(1e-12)).clamp(0, 1)
            t_cross = k.float() * h + frac * h
            off = float(search) * r - t_cross
            out[s:s + per, li] = torch.where(hit, off, torch.full_like(off, float("nan"))).numpy()
        _cancel(progress, span[0] + (span[1] - span[0]) * min(1.0, (s + per) / max(1, len(p))))
    return out[:, 0] if single else out


def _face_barycentrics(count: int) -> np.ndarray:
    """Barycentric sample points inside a triangle (the vertices are fitted separately)."""
    if count == 0:
        return np.zeros((0, 3))
    if count == 1:
        return np.array([[1 / 3, 1 / 3, 1 / 3]])
    if count == 3:
        return np.array([[4, 1, 1], [1, 4, 1], [1, 1, 4]], float) / 6.0
    return np.array([[4, 1, 1], [1, 4, 1], [1, 1, 4], [0, 1, 1], [1, 0, 1], [1, 1, 0]], float) / \
        np.array([6, 6, 6, 2, 2, 2], float)[:, None]


def offset_stats(offsets: np.ndarray, radius: float) -> dict:
    """Summary of signed offsets to the field's surface (world units, NaN = no surface found): the
    share found and |offset| mean / median / 90th / 99th percentile, in world units and field radii."""
    off = np.asarray(offsets, np.float64)
    ok = np.isfinite(off)
    a = np.abs(off[ok])
    out = {"points": int(len(off)), "found": float(ok.mean()) if len(off) else 0.0}
    if a.size == 0:
        return out
    for key, val in (("mean", a.mean()), ("median", np.median(a)), ("p90", np.percentile(a, 90)),
                     ("p99", np.percentile(a, 99))):
        out[f"{key}"] = float(val)
        out[f"{key}_radii"] = float(val / radius)
    out["signed_mean_radii"] = float(off[ok].mean() / radius)
    return out


def _sample_points(V, F, N, bary):
    """Vertices, then ``bary`` points in every face of ``F`` (the faces sampled): positions, normals,
    and the sparse map B from vertex values to sample values."""
    import scipy.sparse as sp

    nv, nf, nb = len(V), len(F), len(bary)
    rows = [np.arange(nv)]
    cols = [np.arange(nv)]
    vals = [np.ones(nv)]
    for j, b in enumerate(bary):
        r = nv + j * nf + np.arange(nf)
        for c in range(3):
            rows.append(r)
            cols.append(F[:, c])
            vals.append(np.full(nf, b[c]))
    B = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(nv + nb * nf, nv))
    P = B @ V
    Nn = B @ N
    Nn /= np.maximum(np.linalg.norm(Nn, axis=1, keepdims=True), 1e-12)
    return P, Nn, B


def view_cameras(vertices, count: int, size: int) -> list:
    """``count`` pinhole cameras (K (3,3), c2w (4,4) OpenCV, size x size pixels) spread evenly over a
    sphere around the mesh (a Fibonacci spiral), each looking at its bounding box's centre with the
    whole box in view."""
    v = np.asarray(vertices, np.float64)
    lo, hi = v.min(0), v.max(0)
    centre = 0.5 * (lo + hi)
    rad = max(float(np.linalg.norm(hi - lo)) * 0.5, 1e-6)
    dist = 3.0 * rad
    half = math.asin(min(0.99, rad / dist)) * 1.05                     # half field of view
    f = 0.5 * size / math.tan(half)
    K = np.array([[f, 0, 0.5 * size], [0, f, 0.5 * size], [0, 0, 1]], np.float32)
    cams = []
    golden = math.pi * (3.0 - math.sqrt(5.0))
    for i in range(int(count)):
        z = 1.0 - 2.0 * (i + 0.5) / count
        rr = math.sqrt(max(0.0, 1.0 - z * z))
        eye_dir = np.array([rr * math.cos(golden * i), rr * math.sin(golden * i), z])
        eye = centre + dist * eye_dir
        fwd = -eye_dir
        up = np.array([0.0, 0.0, 1.0]) if abs(fwd[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
        right = np.cross(fwd, -up)
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, fwd, eye
        cams.append((K, c2w.astype(np.float32)))
    return cams


def render_disagreement(field_depths: list, vertices, faces, cams: list, size: int, clip: float) -> float:
    """The share of the pixels of ``cams`` where the mesh shows another surface than the field: one
    of the two is empty (a silhouette off), or their depths (ray distances, inf where empty) differ
    by more than ``clip`` (an occlusion edge off: another part in front)."""
    from ..data.cameras import axis_to_ray_depth
    from ..render.raster import depth_buffer

    total = 0.0
    for (K, c2w), ref in zip(cams, field_depths):
        z = axis_to_ray_depth(depth_buffer(vertices, faces, K, c2w, size, size), K)
        a, b = np.isfinite(z), np.isfinite(ref)
        far = a & b & (np.abs(np.where(a, z, 0) - np.where(b, ref, 0)) > clip)
        total += float(((a ^ b) | far).mean())
    return total / max(1, len(cams))


def _regulariser(F: np.ndarray, nv: int, smoothness: float, damping: float):
    """smoothness * L + damping * I, L = D^T D the graph Laplacian of the mesh's edges (D the
    edge-difference operator)."""
    import scipy.sparse as sp

    from ..mesh import unique_edges

    E = unique_edges(F)
    D = sp.csr_matrix((np.concatenate([np.ones(len(E)), -np.ones(len(E))]),
                       (np.concatenate([np.arange(len(E))] * 2), np.concatenate([E[:, 0], E[:, 1]]))),
                      shape=(len(E), nv))
    return smoothness * (D.T @ D) + damping * sp.identity(nv)


def _best_level(field, V, F, P, Ns, cfg: SurfaceFitConfig, solve, progress, span, after: float, info: dict):
    """The first fit solved for every level of ``cfg.levels``; the level whose mesh's depth maps best
    match the field's own renders wins.  Returns (level, its offsets, its fit (V, d, found)); the
    scores go into ``info``."""
    from ..render.renderer import render_camera

    r = float(field.radius)
    levels = [float(x) for x in cfg.levels]
    offs = surface_offsets(field, P, Ns, cfg.search, levels, cfg.step, cfg.chunk, progress, span)
    cams = view_cameras(V, cfg.views, cfg.view_size)
    refs = []
    for K, c2w in cams:
        out = render_camera(field, K, c2w, cfg.view_size, cfg.view_size, background=None)
        refs.append(np.where(out.opacity >= 0.5, out.depth, np.inf))
    _cancel(progress, after)
    fits = [solve(offs[:, li]) for li in range(len(levels))]
    scores = [render_disagreement(refs, Vl.astype(np.float32), F, cams, cfg.view_size, r) for Vl, _, _ in fits]
    best = int(np.argmin(scores))
    info["level_scores"] = {f"{lv:g}": sc for lv, sc in zip(levels, scores)}
    info["before_render_disagreement"] = render_disagreement(refs, V.astype(np.float32), F, cams, cfg.view_size, r)
    return levels[best], offs[:, best], fits[best]


def fit_to_field(field, vertices, faces, config: Optional[SurfaceFitConfig] = None,
                 progress: Optional[Callable[[float], bool]] = None) -> tuple:
    """Move a mesh's vertices along their normals onto the field's surface.

    Each vertex i moves by d_i (world units) along its area-weighted normal N_i.  Sample points (the
    vertices and ``face_samples`` points inside every face) each measure their offset delta_s to the
    field's surface along their normal n_s (:func:`surface_offsets`); the displacements solve the
    sparse least squares

        sum_s (sum_j b_sj (N_j . n_s) d_j - delta_s)^2 + smoothness * sum_edges (d_i - d_j)^2
        + damping * sum_i d_i^2        (displacements measured in field radii)

    over the samples that found a surface (one factorisation per solve), ``iterations`` times with
    fresh normals.  Vertices with no surface near them follow their neighbours or stay.

    Which opacity level is "the surface" depends on how sharp the field's density is: a camera ray
    that grazes a soft surface collects far more density than one along the normal, so the field's
    silhouette lies outside its level-0.5 surface.  ``config.level`` None (default) picks the level:
    the first fit is solved for every one of ``config.levels`` (offsets from the same density samples),
    and the level whose mesh's depth maps best match the field's own renders from ``config.views``
    virtual cameras wins (:func:`render_disagreement`: the share of pixels showing another surface).

    Returns (vertices (V,3) float32, info): the offsets' statistics before and after (``before``,
    ``after``: :func:`offset_stats` over the sample points), the level used (and each candidate's
    score), and the seconds taken.
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    from ..mesh import vertex_normals

    cfg = config or SurfaceFitConfig()
    t0 = time.perf_counter()
    V = np.asarray(vertices, np.float64).reshape(-1, 3).copy()
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(V) < 3 or len(F) < 1:
        raise NeuMeshError("the mesh to fit has no triangles")
    r = float(field.radius)
    bary = _face_barycentrics(cfg.face_samples)
    nv = len(V)
    reg = _regulariser(F, nv, cfg.smoothness, cfg.damping)
    Fs = F       # the faces that carry sample points: all, or a fixed random subset of a big mesh
    room = max(0, int(cfg.max_samples) - nv) // max(1, len(bary))
    if len(bary) and len(F) > room:
        Fs = F[np.sort(np.random.default_rng(0).permutation(len(F))[:room])]

    def solve(V, N, Ns, B, off):
        ok = np.isfinite(off)
        Bc = B.tocoo()
        dots = (N[Bc.col] * Ns[Bc.row]).sum(1)      # b_sj (N_j . n_s): vertex moves -> sample offsets
        A = sp.csr_matrix((Bc.data * dots, (Bc.row, Bc.col)), shape=B.shape)[ok]
        d = splu((A.T @ A + reg).tocsc()).solve(A.T @ (off[ok].astype(np.float64) / r))
        d = np.clip(d, -cfg.search, cfg.search)
        return V + (d * r)[:, None] * N, d, float(ok.mean())

    info = {"iterations": []}
    n_iter = int(cfg.iterations)
    level = cfg.level
    calibrate = level is None
    for it in range(n_iter):
        N = np.asarray(vertex_normals(V.astype(np.float32), F), np.float64)
        P, Ns, B = _sample_points(V, Fs, N, bary)
        lo, hi = it / (n_iter + 2), (it + 1) / (n_iter + 2)
        if it == 0 and calibrate:
            level, off, (V, d, found) = _best_level(field, V, F, P, Ns, cfg, lambda o: solve(V, N, Ns, B, o),
                                                    progress, (lo, hi), (it + 1.5) / (n_iter + 2), info)
        else:
            off = surface_offsets(field, P, Ns, cfg.search, level, cfg.step, cfg.chunk, progress, (lo, hi))
            V, d, found = solve(V, N, Ns, B, off)
        if it == 0:
            info["before"] = offset_stats(off, r)
        info["iterations"].append({"found": found, "mean_abs_move_radii": float(np.abs(d).mean()),
                                   "max_abs_move_radii": float(np.abs(d).max())})
    N = np.asarray(vertex_normals(V.astype(np.float32), F), np.float64)
    P, Ns, _ = _sample_points(V, Fs, N, bary)
    off = surface_offsets(field, P, Ns, cfg.search, level, cfg.step, cfg.chunk, progress,
                          ((n_iter + 1) / (n_iter + 2), 1.0))
    info["level"] = float(level)
    info["after"] = offset_stats(off, r)
    info["samples"] = int(len(P))
    info["seconds"] = time.perf_counter() - t0
    info["config"] = {k: (list(v) if isinstance(v, tuple) else v)
                      for k, v in ((k, getattr(cfg, k)) for k in cfg.__dataclass_fields__)}
    return V.astype(np.float32), info
