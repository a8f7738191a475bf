"""The built-in multi-part scene: four parts that differ in shape and texture, with ground-truth part
labels per mesh vertex and per pixel (for semantic distillation and selection tests/benchmarks).

Parts (signed-distance primitives, united by ``min``; the part of a point is the one with the smallest
distance):

====  ======  ================================================  =========================================
id    name    shape                                             texture (albedo)
====  ======  ================================================  =========================================
0     body    sphere r 0.75 at the origin                       red with dark-red horizontal bands
1     head    sphere r 0.42 on top (overlaps the body)          blue / white 3D checker
2     arm     capsule from the body's side, radius 0.17         yellow with dark dots
3     base    rounded slab the body sits in                     green with pale diagonal stripes
====  ======  ================================================  =========================================

The **same-colour** variant (``make_multipart_scene(..., same_colour=True)``) gives every part the arm's
texture (yellow with dark dots, like a toy moulded in one plastic): the parts then differ in shape only,
which is what the geometric selection features (:mod:`neumesh_core.semantics.geometry`) must see.

Images are sphere-traced (exact distance bounds, so no surface is skipped) with 4 jittered samples
per pixel and shaded like the blob scene (ambient + Lambert + Blinn-Phong); the mesh is marching cubes
of the united distance field (``mesh.ply``), and ``part_labels.npy`` holds each mesh vertex's part.
The dataset is in NeRF-synthetic format, like :func:`neumesh_core.data.synthetic.make_default_scene`.
"""
from __future__ import annotations

import json
import math
import os

import numpy as np
import torch

from ..mesh import Mesh, save_mesh
from .synthetic import (AMBIENT, DIFFUSE, LIGHT_DIR, SHININESS, SPECULAR, _sample_offsets,
                        _torch_single_thread as _single_thread, camera_positions, look_at_opencv)

PART_NAMES = ("body", "head", "arm", "base")
CENTRE = np.array([0.25, 0.0, 0.3])          # middle of the object: cameras look here
BOUND_RADIUS = 1.75                          # a sphere around CENTRE holding every part
CAMERA_RADIUS = 3.6
CAMERA_ANGLE_X = 0.9
_BODY = (np.array([0.0, 0.0, 0.0]), 0.75)
_HEAD = (np.array([0.0, 0.0, 1.0]), 0.42)
_ARM = (np.array([0.6, 0.0, 0.1]), np.array([1.35, 0.0, 0.55]), 0.17)
_BASE = (np.array([0.0, 0.0, -0.72]), np.array([0.62, 0.62, 0.1]), 0.06)   # centre, half size, rounding
SMALL_KWARGS = dict(resolution=64, n_train=30, n_val=4, n_test=4, grid=56)


_T = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in
      (("body", _BODY[0]), ("head", _HEAD[0]), ("a", _ARM[0]), ("ab", _ARM[1] - _ARM[0]), ("base", _BASE[0]),
                                                   ("half", _BASE[1]))}


def part_distances(x: torch.Tensor) -> torch.Tensor:
    """(N,4) exact signed distances of points (N,3) to each part (negative inside)."""
    x = x.to(torch.float64)
    body = (x - _T["body"]).norm(dim=-1) - _BODY[1]
    head = (x - _T["head"]).norm(dim=-1) - _HEAD[1]
    ab = _T["ab"]
    xa = x - _T["a"]
    h = ((xa @ ab) / float(ab @ ab)).clamp(0.0, 1.0)
    arm = (xa - h[:, None] * ab).norm(dim=-1) - _ARM[2]
    q = (x - _T["base"]).abs() - _T["half"]
    base = q.clamp_min(0).norm(dim=-1) + q.max(-1).values.clamp_max(0) - _BASE[2]
    return torch.stack([body, head, arm, base], -1)


def distance(x: torch.Tensor) -> torch.Tensor:
    """Signed distance to the united parts (a lower bound of the true distance outside: safe to trace)."""
    return part_distances(x).min(-1).values


def part_of(x) -> np.ndarray:
    """Part id (0..3) of points (N,3): the part whose surface is nearest."""
    return part_distances(torch.as_tensor(np.asarray(x))).argmin(-1).numpy()


def normals(x: torch.Tensor, eps: float = 1e-5) -> torch.Tensor:
    """Outward unit normals (central differences of the united distance)."""
    x = x.to(torch.float64)
    g = torch.zeros_like(x)
    for i in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[i] = eps
        g[:, i] = distance(x + e) - distance(x - e)
    return g / g.norm(dim=-1, keepdim=True).clamp_min(1e-12)


SHARED_TEXTURE_PART = 2   # the same-colour variant paints every part like the arm


def albedo(x: torch.Tensor, part: torch.Tensor, same_colour: bool = False) -> torch.Tensor:
    """(N,3) albedo of surface points of the given parts (``same_colour``: the arm's texture on all)."""
    if same_colour:
        part = torch.full_like(part, SHARED_TEXTURE_PART)
    x = x.to(torch.float64)
    col = torch.zeros(len(x), 3, dtype=torch.float64)
    c = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    # body: red with dark-red bands
    band = (torch.floor(x[:, 2] / 0.1) % 2 == 0)[:, None]
    body = torch.where(band, c([0.80, 0.15, 0.12]), c([0.45, 0.06, 0.05]))
    # head: blue / white checker
    chk = (torch.floor(x * 6.5).sum(-1) % 2 == 0)[:, None]
    head = torch.where(chk, c([0.15, 0.30, 0.85]), c([0.85, 0.88, 0.95]))
    # arm: yellow with dark dots
    cell = x * 8.0 - torch.floor(x * 8.0) - 0.5
    dot = (cell.norm(dim=-1) < 0.33)[:, None]
    arm = torch.where(dot, c([0.25, 0.18, 0.05]), c([0.95, 0.80, 0.15]))
    # base: green with pale diagonal stripes
    s = x.sum(-1) * 7.0
    stripe = ((s - torch.floor(s)) < 0.3)[:, None]
    base = torch.where(stripe, c([0.60, 0.85, 0.60]), c([0.15, 0.60, 0.25]))
    for i, a in enumerate((body, head, arm, base)):
        col = torch.where((part == i)[:, None], a, col)
    return col


def trace(origins: torch.Tensor, dirs: torch.Tensor, max_iters: int = 200, eps: float = 1e-4,
          min_step: float = 1e-3):
    """Sphere tracing inside the bounding sphere (steps of at least ``min_step``: no part is thinner),
    then bisection of the last step.  Returns (hit (N,) bool, t (N,) float64, inf where missed)."""
    o = origins.to(torch.float64)
    d = dirs.to(torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    cen = torch.as_tensor(CENTRE, dtype=torch.float64)
    oc = o - cen
    bb = (oc * d).sum(-1)
    disc = bb * bb - ((oc * oc).sum(-1) - BOUND_RADIUS ** 2)
    t = (-bb - disc.clamp_min(0).sqrt()).clamp_min(0.0)
    t_end = -bb + disc.clamp_min(0).sqrt()
    alive = (disc > 0) & (t_end > 0)
    t_hit = torch.full((len(o),), float("inf"), dtype=torch.float64)
    idx = alive.nonzero().squeeze(1)
    tc = t[idx]
    prev = tc.clone()
    found, lo, hi = [], [], []
    with _single_thread():
        for _ in range(max_iters):
            if len(idx) == 0:
                break
            dist = distance(o[idx] + tc[:, None] * d[idx])
            hit = dist < eps
            if hit.any():
                found.append(idx[hit])
                lo.append(prev[hit])
                hi.append(tc[hit])
            prev = tc
            tc = tc + dist.clamp_min(min_step)
            keep = ~hit & (prev < t_end[idx])
            idx, tc, prev = idx[keep], tc[keep], prev[keep]
        if found:   # the root lies in [lo, hi]: bisect (a min_step may have stepped past it)
            gi, lo, hi = torch.cat(found), torch.cat(lo), torch.cat(hi)
            for _ in range(12):
                mid = 0.5 * (lo + hi)
                inside = distance(o[gi] + mid[:, None] * d[gi]) <= 0
                hi = torch.where(inside, mid, hi)
                lo = torch.where(inside, lo, mid)
            t_hit[gi] = hi
    return torch.isfinite(t_hit), t_hit


def _pixel_dirs(K, c2w, width, height, off):
    K = np.asarray(K, np.float64)
    c2w = np.asarray(c2w, np.float64)
    ys, xs = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    px, py = xs[None] + off[..., 0], ys[None] + off[..., 1]
    y = (py - K[1, 2]) / K[1, 1]
    x = (px - K[0, 2] - K[0, 1] * y) / K[0, 0]
    d = np.stack([x, y, np.ones_like(x)], -1).reshape(-1, 3) @ c2w[:3, :3].T
    d = torch.as_tensor(d / np.linalg.norm(d, axis=-1, keepdims=True))
    return torch.as_tensor(c2w[:3, 3]).expand_as(d), d


def render(K, c2w, width: int, height: int, spp: int = 4, seed: int = 0, same_colour: bool = False):
    """Un-premultiplied colour (H,W,3) and coverage alpha (H,W) of one OpenCV camera, float32
    (``same_colour``: one texture on every part)."""
    off = _sample_offsets(width, height, spp, seed)
    o, d = _pixel_dirs(K, c2w, width, height, off)
    hit, t = trace(o, d)
    col = torch.zeros(len(d), 3, dtype=torch.float64)
    if hit.any():
        p = o[hit] + t[hit, None] * d[hit]
        n = normals(p)
        alb = albedo(p, part_distances(p).argmin(-1), same_colour)
        light = torch.as_tensor(LIGHT_DIR, dtype=torch.float64)
        ndl = (n @ light).clamp_min(0.0)
        hv = light[None] - d[hit]
        hv = hv / hv.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        spec = (n * hv).sum(-1).clamp_min(0.0) ** SHININESS * (ndl > 0)
        col[hit] = (alb * (AMBIENT + DIFFUSE * ndl[:, None]) + SPECULAR * spec[:, None]).clamp(0, 1)
    col = col.reshape(spp, height, width, 3)
    nh = hit.reshape(spp, height, width).to(torch.float64).sum(0)
    rgb = col.sum(0) / nh.clamp_min(1.0)[..., None]
    return rgb.numpy().astype(np.float32), (nh / spp).numpy().astype(np.float32)


def label_image(K, c2w, width: int, height: int) -> np.ndarray:
    """(H,W) int part id seen through each pixel centre (-1 = background)."""
    o, d = _pixel_dirs(K, c2w, width, height, np.full((1, height, width, 2), 0.5))
    hit, t = trace(o, d)
    lab = np.full(len(d), -1, np.int64)
    if hit.any():
        lab[hit.numpy()] = part_distances(o[hit] + t[hit, None] * d[hit]).argmin(-1).numpy()
    return lab.reshape(height, width)


def multipart_mesh(grid: int = 56) -> tuple:
    """Marching-cubes mesh of the parts (``grid`` cells along the longest side of the box) and the
    part id of every vertex: (Mesh, labels (V,) int64)."""
    from skimage.measure import marching_cubes

    lo = CENTRE - BOUND_RADIUS * np.array([0.75, 0.65, 0.75])
    hi = CENTRE + BOUND_RADIUS * np.array([0.75, 0.65, 0.75])
    h = float((hi - lo).max()) / grid
    axes = [np.arange(lo[i], hi[i] + h, h) for i in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    vol = distance(torch.as_tensor(pts.reshape(-1, 3))).numpy().reshape(pts.shape[:3])
    verts, faces, _, _ = marching_cubes(vol, 0.0, spacing=(h, h, h), allow_degenerate=False)
    verts = verts + lo
    return Mesh(verts.astype(np.float32), faces.astype(np.int64)), part_of(verts).astype(np.int64)


def make_multipart_scene(out_dir: str, resolution: int = 96, n_train: int = 40, n_val: int = 6,
                         n_test: int = 6, grid: int = 72, seed: int = 0,
                         camera_angle_x: float = CAMERA_ANGLE_X, same_colour: bool = False) -> str:
    """Write the multi-part scene in NeRF-synthetic format plus ``mesh.ply``, ``part_labels.npy``
    (per mesh vertex) and ``scene.json`` (written last).  Deterministic.  ``SMALL_KWARGS`` is the
    quick test variant; ``same_colour`` paints every part with one texture (the labels are the same)."""
    from ..imageio import save_image

    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    pos = camera_positions(n_train, n_val, n_test, CAMERA_RADIUS, seed)
    f = 0.5 * resolution / math.tan(0.5 * camera_angle_x)
    K = np.array([[f, 0, resolution / 2], [0, f, resolution / 2], [0, 0, 1]], np.float64)
    gl_flip = np.diag([1.0, -1.0, -1.0, 1.0])
    for s_i, (split, centres) in enumerate(pos.items()):
        if len(centres) == 0:
            continue   # no file for an empty split (a loader would refuse it)
        os.makedirs(os.path.join(out_dir, split), exist_ok=True)
        frames = []
        for i, c in enumerate(centres):
            c2w = look_at_opencv(c + CENTRE, CENTRE)
            rgb, alpha = render(K, c2w, resolution, resolution, seed=seed * 100_003 + 10_000 * s_i + i,
                                same_colour=same_colour)
            save_image(os.path.join(out_dir, split, f"r_{i}.png"), np.concatenate([rgb, alpha[..., None]], -1))
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": (c2w @ gl_flip).tolist()})
        with open(os.path.join(out_dir, f"transforms_{split}.json"), "w", encoding="utf-8") as fh:
            json.dump({"camera_angle_x": float(camera_angle_x), "frames": frames}, fh, indent=1)
    mesh, labels = multipart_mesh(grid)
    save_mesh(mesh, os.path.join(out_dir, "mesh.ply"))
    np.save(os.path.join(out_dir, "part_labels.npy"), labels)
    desc = {"name": "neumesh multi-part scene" + (" (same colour)" if same_colour else ""), "parts": list(PART_NAMES),
            "generator": "neumesh_core.data.multipart.make_multipart_scene",
            "params": {"resolution": resolution, "n_train": n_train, "n_val": n_val, "n_test": n_test,
                       "grid": grid, "seed": seed, "same_colour": bool(same_colour)},
            "mesh": {"file": "mesh.ply", "vertices": int(mesh.num_vertices), "labels": "part_labels.npy"}}
    with open(os.path.join(out_dir, "scene.json"), "w", encoding="utf-8") as fh:
        json.dump(desc, fh, indent=1)
    return out_dir
