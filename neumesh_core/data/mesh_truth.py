"""Ground truth for deformed renders of the built-in scene: a triangle-mesh mode of the ground-truth tracer.

A deformed copy of the built-in scene's mesh is ray traced exactly (primary rays only, vectorised
Moeller-Trumbore over each triangle's pixel bounding box, nearest hit per sample: a z-buffer), with
the same jittered sub-pixel samples as :func:`~neumesh_core.data.synthetic.render_truth`.  Each
hit is coloured by the appearance its *rest-pose* point had, i.e. "the trained appearance carried
with the surface":

* the hit's barycentric coordinates give its rest position on the rest triangle, which is moved
  radially onto the analytic surface (the mesh's vertices lie on it) and textured there;
* shading is :func:`~neumesh_core.data.synthetic.shade` at that rest point with the **view direction
  rotated into the rest pose** by the triangle's rest->deformed rotation (the rotation part of the
  triangle's deformation gradient, polar decomposition).  The light stays fixed in the rest frame.

That is exactly what a NeuMesh field can represent: its radiance decoder sees the rest normal and the
view direction in each vertex's rest frame, so the lighting it learned (ambient + Lambert with the
scene's light) is baked into the rest pose and travels with the surface, and view-dependent
highlights move with the local rotation.  A world-fixed light would need relighting, which the field
does not do, so it would measure something no deformation method of this kind can reproduce.
"""
from __future__ import annotations

import numpy as np
import torch

from .synthetic import _sample_offsets, _torch_single_thread, shade, surface_radius


def triangle_rotations(rest_vertices, vertices, faces) -> np.ndarray:
    """(F,3,3) rotation of each triangle from rest to deformed pose (float64).

    The rotation part (polar decomposition) of the linear map taking the rest triangle's frame
    (edge1, edge2, unit normal) to the deformed one's; exact for rigid motions, and for stretches
    the closest rotation to the triangle's deformation.
    """
    rv = np.asarray(rest_vertices, np.float64)
    dv = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)

    def frame(v):
        e1 = v[f[:, 1]] - v[f[:, 0]]
        e2 = v[f[:, 2]] - v[f[:, 0]]
        n = np.cross(e1, e2)
        n /= np.linalg.norm(n, axis=1, keepdims=True).clip(1e-20)
        return np.stack([e1, e2, n], -1)  # columns

    A = frame(dv) @ np.linalg.inv(frame(rv))
    U, _, Vt = np.linalg.svd(A)
    d = np.sign(np.linalg.det(U @ Vt))
    U[:, :, 2] *= d[:, None]
    return U @ Vt


def raster_mesh(K, c2w, width: int, height: int, vertices, faces, offsets: np.ndarray,
                chunk: int = 2_000_000):
    """Nearest ray-triangle hit of every sub-pixel sample of a pinhole camera (OpenCV c2w).

    ``offsets`` (S,H,W,2): sample positions within each pixel, in [0,1). Returns ``face`` (S,H,W)
    int64 (-1 where missed), ``bary`` (S,H,W,3) barycentric weights of the face's vertices and ``t``
    (S,H,W) distances along the unit ray (inf where missed).  Exact for primary rays: every triangle
    is tested against the samples of the pixels its projection's bounding box covers.
    """
    K = np.asarray(K, np.float64)
    c2w = np.asarray(c2w, np.float64)
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    S = offsets.shape[0]
    W, H = int(width), int(height)
    R, c = c2w[:3, :3], c2w[:3, 3]
    xc = (V - c) @ R  # camera coordinates
    z = xc[:, 2]
    front = (z[F] > 1e-6).all(1)  # triangles crossing the camera plane are not supported (never here)
    zs = np.where(z > 1e-6, z, 1.0)
    py = K[1, 1] * xc[:, 1] / zs + K[1, 2]
    px = K[0, 0] * xc[:, 0] / zs + K[0, 1] * xc[:, 1] / zs + K[0, 2]
    fx, fy = px[F], py[F]
    x0 = np.floor(fx.min(1)).astype(np.int64).clip(0, W)
    x1 = np.floor(fx.max(1)).astype(np.int64).clip(-1, W - 1)
    y0 = np.floor(fy.min(1)).astype(np.int64).clip(0, H)
    y1 = np.floor(fy.max(1)).astype(np.int64).clip(-1, H - 1)
    bw, bh = x1 - x0 + 1, y1 - y0 + 1
    ok = front & (bw > 0) & (bh > 0)
    fid = np.nonzero(ok)[0]
    counts = (bw[fid] * bh[fid])
    n_pix = H * W
    best_t = np.full(S * n_pix, np.inf)
    best_f = np.full(S * n_pix, -1, np.int64)
    best_b = np.zeros((S * n_pix, 2))
    e1 = V[F[:, 1]] - V[F[:, 0]]
    e2 = V[F[:, 2]] - V[F[:, 0]]
    Kinv = np.linalg.inv(K)
    # split the triangles into groups of at most ``chunk`` (triangle, pixel, sample) tests
    cum = np.cumsum(counts * S)
    starts = np.searchsorted(cum, np.arange(0, cum[-1] if len(cum) else 0, chunk), side="right")
    bounds = list(starts) + [len(fid)]
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b <= a:
            continue
        ff, cc = fid[a:b], counts[a:b]
        rep = np.repeat(np.arange(len(ff)), cc)
        first = np.repeat(np.cumsum(cc) - cc, cc)
        local = np.arange(len(rep)) - first
        tri = ff[rep]
        qx = x0[tri] + local % bw[tri]
        qy = y0[tri] + local // bw[tri]
        for s in range(S):
            sx = qx + offsets[s, qy, qx, 0]
            sy = qy + offsets[s, qy, qx, 1]
            d = np.stack([sx, sy, np.ones_like(sx)], -1) @ Kinv.T @ R.T
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            E1, E2 = e1[tri], e2[tri]
            pv = np.cross(d, E2)
            det = (E1 * pv).sum(1)
            inv = 1.0 / np.where(np.abs(det) > 1e-14, det, np.inf)
            tv = c - V[F[tri, 0]]
            u = (tv * pv).sum(1) * inv
            qv = np.cross(tv, E1)
            v = (d * qv).sum(1) * inv
            t = (E2 * qv).sum(1) * inv
            hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (inv != 0)
            key = s * n_pix + qy[hit] * W + qx[hit]
            th, fh, uh, vh = t[hit], tri[hit], u[hit], v[hit]
            order = np.lexsort((th, key))
            key, th, fh, uh, vh = key[order], th[order], fh[order], uh[order], vh[order]
            firsts = np.ones(len(key), bool)
            firsts[1:] = key[1:] != key[:-1]
            key, th, fh, uh, vh = key[firsts], th[firsts], fh[firsts], uh[firsts], vh[firsts]
            better = th < best_t[key]
            k2 = key[better]
            best_t[k2] = th[better]
            best_f[k2] = fh[better]
            best_b[k2, 0] = uh[better]
            best_b[k2, 1] = vh[better]
    bary = np.stack([1.0 - best_b[:, 0] - best_b[:, 1], best_b[:, 0], best_b[:, 1]], -1)
    return (best_f.reshape(S, H, W), bary.reshape(S, H, W, 3), best_t.reshape(S, H, W))


def render_mesh_truth(K, c2w, width: int, height: int, vertices, faces, rest_vertices=None,
                      background=(1.0, 1.0, 1.0), spp: int = 4, seed: int = 0, project: bool = True):
    """Image of the built-in scene's mesh in pose ``vertices`` with its rest-pose appearance.

    ``rest_vertices`` (default: ``vertices``) are the same mesh's rest positions (vertices of the
    built-in scene's :func:`~neumesh_core.data.synthetic.default_mesh`). Each sample's hit is mapped
    to its rest point (barycentric), moved radially onto the analytic surface when ``project`` and
    shaded there with the view direction rotated into the rest pose (module docstring). Same sample
    pattern (``spp``, ``seed``) and return values as :func:`~neumesh_core.data.synthetic.render_truth`.
    """
    W, H = int(width), int(height)
    V = np.asarray(vertices, np.float64)
    RV = V if rest_vertices is None else np.asarray(rest_vertices, np.float64)
    Fc = np.asarray(faces, np.int64)
    off = _sample_offsets(W, H, spp, seed)
    face, bary, _ = raster_mesh(K, c2w, W, H, V, Fc, off)
    hit = face >= 0
    col = np.zeros(face.shape + (3,))
    if hit.any():
        fh = face[hit]
        p = (bary[hit][:, :, None] * RV[Fc[fh]]).sum(1)
        if project:
            p = p * (surface_radius(p) / np.linalg.norm(p, axis=1))[:, None]
        # view directions of the hit samples, rotated into the rest pose
        K64 = np.asarray(K, np.float64)
        c2w64 = np.asarray(c2w, np.float64)
        s_i, y_i, x_i = np.nonzero(hit)
        sx = x_i + off[s_i, y_i, x_i, 0]
        sy = y_i + off[s_i, y_i, x_i, 1]
        d = np.stack([sx, sy, np.ones_like(sx)], -1) @ np.linalg.inv(K64).T @ c2w64[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        if rest_vertices is not None:
            rot = triangle_rotations(RV, V, Fc)[fh]
            d = np.einsum("nji,nj->ni", rot, d)  # R^T d
        with _torch_single_thread():
            col[hit] = shade(torch.as_tensor(p), torch.as_tensor(d)).numpy()
    nh = hit.sum(0).astype(np.float64)
    alpha = nh / spp
    rgb = col.sum(0) / np.maximum(nh, 1.0)[..., None]
    if background is not None:
        bg = np.asarray(background, np.float64).reshape(1, 1, 3)
        rgb = rgb * alpha[..., None] + bg * (1.0 - alpha[..., None])
    return rgb.astype(np.float32), alpha.astype(np.float32)
