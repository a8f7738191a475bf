"""Closest points of triangles: the nearest-face lookup of the paint atlas (paint_atlas.py) and its
plain reference."""
from __future__ import annotations

import numpy as np


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Closest points of triangles (a, b, c) (n,3) to points p (n,3) (Ericson, Real-Time Collision
    Detection 5.1.5, vectorised).  Returns barycentric coordinates (n,3) of the closest points."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    n = len(p)
    out = np.zeros((n, 3))
    done = np.zeros(n, bool)

    def put(mask, bary):
        m = mask & ~done
        out[m] = bary[m] if bary.ndim == 2 else bary
        done[m] = True

    eps = 1e-30
    put((d1 <= 0) & (d2 <= 0), np.array([1.0, 0, 0]))
    put((d3 >= 0) & (d4 <= d3), np.array([0, 1.0, 0]))
    put((d6 >= 0) & (d5 <= d6), np.array([0, 0, 1.0]))
    v = d1 / np.where(np.abs(d1 - d3) > eps, d1 - d3, eps)
    put((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - v, v, np.zeros(n)], 1))
    w = d2 / np.where(np.abs(d2 - d6) > eps, d2 - d6, eps)
    put((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - w, np.zeros(n), w], 1))
    den = (d4 - d3) + (d5 - d6)
    w = (d4 - d3) / np.where(np.abs(den) > eps, den, eps)
    put((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), np.stack([np.zeros(n), 1 - w, w], 1))
    den = va + vb + vc
    den = np.where(np.abs(den) > eps, den, eps)
    v, w = vb / den, vc / den
    put(np.ones(n, bool), np.stack([1 - v - w, v, w], 1))
    return out


def closest_faces_reference(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray):
    """Plain reference of :meth:`PaintAtlas.closest_faces`: every point against every face."""
    p = np.asarray(points, np.float64)
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    face = np.zeros(len(p), np.int64)
    bary = np.zeros((len(p), 3))
    dist = np.full(len(p), np.inf)
    for i in range(len(p)):
        q = np.repeat(p[i:i + 1], len(F), 0)
        b = closest_points_on_triangles(q, V[F[:, 0]], V[F[:, 1]], V[F[:, 2]])
        x = (b[:, :, None] * V[F]).sum(1)
        d = np.linalg.norm(x - p[i], axis=1)
        j = int(np.argmin(d))
        face[i], bary[i], dist[i] = j, b[j], d[j]
    return face, bary, dist
