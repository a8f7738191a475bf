"""Texel colours from the field's own renders: the colour each texel shows in the views that see it.

A texel's colour from a short ray along its normal (:func:`~neumesh_core.bake.texture.surface_colours`)
is what a camera looking straight at that spot sees.  Where the mesh's geometry differs a little from
the field's (a decimated mesh rounds corners and part edges), that ray lands beside the spot a camera
sees at that texel, and the part edges come out a few pixels off in every view.  Projecting the
field's renders onto the mesh instead gives each texel the colour the cameras actually see there:

1. ``views`` virtual cameras of ``size`` pixels spread over a sphere around the mesh
   (:func:`~neumesh_core.bake.surface.view_cameras`) render the field (colour, opacity, depth);
2. each texel point is projected into every view; it counts there when the mesh's own z-buffer shows
   it (not hidden by another part), it faces the camera (cosine between its normal and the direction
   to the camera at least ``min_cos``), and the field shows a surface at about the same depth (within
   ``tolerance`` field radii plus the pixel's footprint on the slope; otherwise the field sees
   something else at that pixel: an occlusion edge the mesh has a little off);
3. its colour is the mean of the (bilinearly sampled, un-premultiplied) field colours over the views
   that count, weighted by cosine^``power`` (views that look at it squarely weigh most).

Texels no view sees keep their ray colour (the caller's fallback).  The mean over views also averages
view-dependent highlights out, as the tilted rays of ``directions > 1`` do.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np


@dataclass
class ProjectConfig:
    """How :func:`projected_colours` gathers the field's renders onto texels."""

    views: int = 48           # virtual cameras on a sphere around the mesh
    size: int = 512           # their width and height in pixels
    tolerance: float = 1.0    # field radii: |texel depth - mesh z-buffer| and |texel depth - field depth|
    min_cos: float = 0.15     # views seeing the texel more obliquely than this do not count
    power: float = 2.0        # weight = cosine ** power

    def __post_init__(self) -> None:
        if self.views < 1 or self.size < 16:
            raise ValueError("projection needs views >= 1 of size >= 16 pixels")
        if self.tolerance <= 0 or not 0.0 <= self.min_cos < 1.0 or self.power < 0:
            raise ValueError("tolerance must be > 0 radii, min_cos in [0, 1), power >= 0")


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """img (H,W,C) sampled at pixel coordinates x, y (pixel centres at +0.5), edges clamped."""
    h, w = img.shape[:2]
    x = np.clip(x - 0.5, 0, w - 1)
    y = np.clip(y - 0.5, 0, h - 1)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    return ((img[y0, x0] * (1 - fx) + img[y0, x1] * fx) * (1 - fy)
            + (img[y1, x0] * (1 - fx) + img[y1, x1] * fx) * fy)


def projected_colours(field, vertices, faces, points, normals, config: Optional[ProjectConfig] = None,
                      progress: Optional[Callable[[float], bool]] = None, span: tuple = (0.0, 1.0),
                      chunk: int = 1 << 20) -> tuple:
    """(n,3) colours of mesh surface points gathered from the field's renders, and (n,) the summed
    weight of the views that saw each point (0: no view did; its colour is then 0).

    ``vertices``/``faces``: the mesh the points lie on (its z-buffer decides what each view sees);
    ``points``/``normals`` (n,3): the texels' surface points and unit normals."""
    from ..data.cameras import ray_to_axis_depth
    from ..render.raster import depth_buffer
    from ..render.renderer import render_camera
    from .surface import _cancel, view_cameras

    cfg = config or ProjectConfig()
    V = np.asarray(vertices, np.float32)
    F = np.asarray(faces, np.int64)
    P = np.asarray(points, np.float64)
    N = np.asarray(normals, np.float64)
    N = N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
    r = float(field.radius)
    tol = float(cfg.tolerance) * r
    acc = np.zeros((len(P), 3), np.float64)
    wsum = np.zeros(len(P), np.float64)
    cams = view_cameras(V, cfg.views, cfg.size)
    S = int(cfg.size)
    step = (span[1] - span[0]) / len(cams)

    def view_progress(k):   # progress (and cancel) inside each render: one can take a minute on CPU
        if progress is None:
            return None
        return lambda f: progress(span[0] + step * (k + 0.8 * float(f)))

    for k, (K, c2w) in enumerate(cams):
        out = render_camera(field, K, c2w, S, S, background=None, progress=view_progress(k))
        op = out.opacity
        # premultiplied colour and opacity, sampled together and divided after (a silhouette pixel's
        # empty neighbour then adds no black)
        img = np.concatenate([out.rgb, op[..., None]], -1).astype(np.float32)
        fz = ray_to_axis_depth(np.where(op >= 0.5, out.depth, np.inf), K)      # field: axis depth
        mz = depth_buffer(V, F, K, c2w, S, S)                                   # mesh: axis depth
        w2c = np.linalg.inv(np.asarray(c2w, np.float64))
        eye = np.asarray(c2w, np.float64)[:3, 3]
        for s in range(0, len(P), chunk):
            p, n = P[s:s + chunk], N[s:s + chunk]
            cam = p @ w2c[:3, :3].T + w2c[:3, 3]
            z = cam[:, 2]
            ok = z > 1e-6
            zs = np.where(ok, z, 1.0)
            x = K[0, 0] * cam[:, 0] / zs + K[0, 2]
            y = K[1, 1] * cam[:, 1] / zs + K[1, 2]
            ok &= (x >= 0) & (x < S) & (y >= 0) & (y < S)
            to_eye = eye[None] - p
            cos = (n * to_eye).sum(1) / np.maximum(np.linalg.norm(to_eye, axis=1), 1e-12)
            ok &= cos >= cfg.min_cos
            idx = np.nonzero(ok)[0]
            if not len(idx):
                continue
            xi = np.clip(x[idx].astype(np.int64), 0, S - 1)
            yi = np.clip(y[idx].astype(np.int64), 0, S - 1)
            zi = z[idx]
            # a pixel centre lies up to a pixel beside the point: on a slope its depth differs by
            # about the pixel's footprint x tan(angle) (capped at 4 pixels' worth)
            c = cos[idx]
            slack = tol + zi / K[0, 0] * np.minimum(np.sqrt(np.maximum(1 - c * c, 0)) / c, 4.0)
            seen = (zi <= mz[yi, xi] + slack) & (np.abs(fz[yi, xi] - zi) <= slack)
            idx, xs, ys = idx[seen], x[idx][seen], y[idx][seen]
            if not len(idx):
                continue
            smp = _bilinear(img, xs, ys)
            wgt = cos[idx] ** cfg.power
            acc[s + idx] += wgt[:, None] * np.clip(smp[:, :3] / np.maximum(smp[:, 3:], 1e-3), 0, 1)
            wsum[s + idx] += wgt
        _cancel(progress, span[0] + (span[1] - span[0]) * (k + 1) / len(cams))
    colours = np.where((wsum > 0)[:, None], acc / np.maximum(wsum, 1e-12)[:, None], 0.0)
    return colours.astype(np.float32), wsum.astype(np.float32)
