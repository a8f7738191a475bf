"""Plain numpy triangle rasterisation: pixel-centre coverage with barycentrics, and a z-buffered
render of a UV-textured mesh with bilinear texture lookup (used to check baked assets without Blender).

Pixel (row r, column c) has its centre at x = c + 0.5, y = r + 0.5 (x right, y down).
"""
from __future__ import annotations

from typing import Iterator, Tuple

import numpy as np


def raster_triangles(tri: np.ndarray, width: int, height: int, eps: float = 1e-7,
                     max_candidates: int = 4_000_000) -> Iterator[Tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Pixel centres inside triangles.

    ``tri`` (T,3,2) float pixel coordinates.  Yields chunks ``(tri_index (n,), pixel (n,) = r*W+c,
    bary (n,3))`` for every (triangle, pixel centre) pair with all barycentrics >= -eps (eps < 0 keeps
    only centres strictly inside by that margin).  Degenerate triangles cover nothing.
    """
    tri = np.asarray(tri, np.float64)
    if len(tri) == 0:
        return
    lo = tri.min(1)
    hi = tri.max(1)
    x0 = np.clip(np.ceil(lo[:, 0] - 0.5), 0, width).astype(np.int64)
    x1 = np.clip(np.floor(hi[:, 0] - 0.5), -1, width - 1).astype(np.int64)
    y0 = np.clip(np.ceil(lo[:, 1] - 0.5), 0, height).astype(np.int64)
    y1 = np.clip(np.floor(hi[:, 1] - 0.5), -1, height - 1).astype(np.int64)
    bw = np.maximum(x1 - x0 + 1, 0)
    bh = np.maximum(y1 - y0 + 1, 0)
    counts = bw * bh
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    counts[np.abs(area) < 1e-12] = 0
    csum = np.cumsum(counts)
    start = 0
    while start < len(tri):
        base = csum[start - 1] if start else 0
        stop = int(np.searchsorted(csum, base + max_candidates, side="right"))
        stop = max(stop, start + 1)
        sel = np.arange(start, stop)
        cnt = counts[sel]
        start = stop
        total = int(cnt.sum())
        if total == 0:
            continue
        ids = np.repeat(sel, cnt)
        first = np.repeat(np.cumsum(cnt) - cnt, cnt)
        local = np.arange(total) - first
        w = bw[ids]
        px = x0[ids] + local % w
        py = y0[ids] + local // w
        fx = px + 0.5
        fy = py + 0.5
        ar = area[ids]
        ta, tb, tc = a[ids], b[ids], c[ids]
        w0 = ((tc[:, 0] - tb[:, 0]) * (fy - tb[:, 1]) - (tc[:, 1] - tb[:, 1]) * (fx - tb[:, 0])) / ar
        w1 = ((ta[:, 0] - tc[:, 0]) * (fy - tc[:, 1]) - (ta[:, 1] - tc[:, 1]) * (fx - tc[:, 0])) / ar
        w2 = 1.0 - w0 - w1
        keep = (w0 >= -eps) & (w1 >= -eps) & (w2 >= -eps)
        if not keep.any():
            continue
        yield (ids[keep], (py * width + px)[keep], np.stack([w0[keep], w1[keep], w2[keep]], 1))


def bilinear(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample ``texture`` (H,W,C) at ``uv`` (n,2) (u right, v up, the OBJ/Blender convention: v=1 is
    the image's first row), bilinear between texel centres, clamped at the borders."""
    h, w = texture.shape[:2]
    x = np.clip(uv[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip((1.0 - uv[:, 1]) * h - 0.5, 0, h - 1)
    xi = np.minimum(np.floor(x).astype(np.int64), w - 2) if w > 1 else np.zeros(len(x), np.int64)
    yi = np.minimum(np.floor(y).astype(np.int64), h - 2) if h > 1 else np.zeros(len(y), np.int64)
    fx = (x - xi)[:, None]
    fy = (y - yi)[:, None]
    x1 = np.minimum(xi + 1, w - 1)
    y1 = np.minimum(yi + 1, h - 1)
    t = texture
    return ((t[yi, xi] * (1 - fx) + t[yi, x1] * fx) * (1 - fy) + (t[y1, xi] * (1 - fx) + t[y1, x1] * fx) * fy)


def project_mesh(vertices, faces: np.ndarray, K, c2w, near: float):
    """Camera-axis depth (M,) and pixel coordinates (M,2) of the vertices seen by an OpenCV camera,
    and the indices of the faces whose corners all lie farther than ``near`` (no clipping)."""
    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    w2c = np.linalg.inv(np.asarray(c2w, np.float64))
    cam = v @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    zc = np.where(z > near, z, 1.0)
    pix = (cam @ np.asarray(K, np.float64).T)[:, :2] / zc[:, None]
    fi = np.nonzero((z[faces] > near).all(1))[0] if len(faces) else np.zeros(0, np.int64)
    return z, pix, fi


def depth_buffer(vertices, faces, K, c2w, width: int, height: int, near: float = 1e-6) -> np.ndarray:
    """Z-buffer of a triangle mesh seen by an OpenCV camera (``K`` 3x3, ``c2w`` 4x4): (H,W) float32
    distance along the camera axis of the nearest surface at each pixel centre (perspective-correct),
    inf where no triangle covers it.  Triangles with a vertex closer than ``near`` are skipped (no
    clipping: an occluder must lie wholly in front of the camera)."""
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    z, pix, fi = project_mesh(vertices, f, K, c2w, near)
    best = np.full(width * height, np.inf)
    for ids, px, bary in raster_triangles(pix[f[fi]], width, height, eps=1e-9):
        depth = 1.0 / (bary / z[f[fi[ids]]]).sum(1)
        np.minimum.at(best, px, depth)
    return best.reshape(height, width).astype(np.float32)


def render_textured_mesh(vertices, faces, uvs, texture, K, c2w, width: int, height: int,
                         background=(1.0, 1.0, 1.0), supersample: int = 1) -> Tuple[np.ndarray, np.ndarray]:
    """Render a UV-textured mesh seen by an OpenCV camera (``K`` 3x3, ``c2w`` 4x4): z-buffer,
    perspective-correct UVs, bilinear texture lookup, no lighting (the texture is the colour).

    ``vertices`` (M,3), ``faces`` (F,3) indices into vertices and ``uvs`` (M,2).  Returns (rgb (H,W,3)
    composited on ``background``, coverage (H,W) in [0,1]); ``supersample`` S averages S x S samples.
    """
    s = int(supersample)
    f = np.asarray(faces, np.int64)
    uv = np.asarray(uvs, np.float64)
    tex = np.asarray(texture, np.float32)[..., :3]
    Kd = np.asarray(K, np.float64).copy()
    Kd[:2] *= s
    W, H = width * s, height * s
    z, pix, fi = project_mesh(vertices, f, Kd, c2w, 1e-6)
    best_z = np.full(W * H, np.inf)
    best_uv = np.zeros((W * H, 2))
    for ids, px, bary in raster_triangles(pix[f[fi]], W, H, eps=1e-9):
        tri = f[fi[ids]]
        inv_z = (bary / z[tri]).sum(1)
        depth = 1.0 / inv_z
        pb = bary / z[tri] * depth[:, None]          # perspective-correct barycentrics
        tuv = (pb[..., None] * uv[tri]).sum(1)
        order = np.lexsort((depth, px))                # by pixel, nearest first
        px, depth, tuv = px[order], depth[order], tuv[order]
        first = np.ones(len(px), bool)
        first[1:] = px[1:] != px[:-1]
        px, depth, tuv = px[first], depth[first], tuv[first]
        closer = depth < best_z[px]
        best_z[px[closer]] = depth[closer]
        best_uv[px[closer]] = tuv[closer]
    hit = np.isfinite(best_z)
    rgb = np.empty((W * H, 3), np.float32)
    rgb[:] = np.asarray(background, np.float32)
    if hit.any():
        rgb[hit] = bilinear(tex, best_uv[hit])
    rgb = rgb.reshape(H, W, 3)
    cov = hit.reshape(H, W).astype(np.float32)
    if s > 1:
        rgb = rgb.reshape(height, s, width, s, 3).mean((1, 3))
        cov = cov.reshape(height, s, width, s).mean((1, 3))
    return rgb.astype(np.float32), cov.astype(np.float32)
