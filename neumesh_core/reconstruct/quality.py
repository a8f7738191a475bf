"""Scaffold quality figures: silhouette IoU (vectorised triangle rasteriser) and Chamfer distance."""
from __future__ import annotations

import numpy as np
import torch

from ..data.cameras import Cameras
from ..mesh import Mesh


def rasterize_silhouette(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, c2w: np.ndarray,
                         width: int, height: int, near: float = 1e-4, chunk: int = 1 << 21) -> np.ndarray:
    """Binary (H,W) coverage of a triangle mesh seen by one pinhole camera (OpenCV c2w).

    A pixel is covered when its centre (x+0.5, y+0.5) lies inside (or on the edge of) the projection
    of any triangle; no depth test is needed for a silhouette.  Triangles with a vertex behind the
    near plane are skipped.  Vectorised: triangles are bucketed by the size of their pixel bounding
    box and every candidate pixel of a bucket is tested with edge functions at once.
    """
    v = torch.as_tensor(np.asarray(vertices), dtype=torch.float64)
    f = torch.as_tensor(np.asarray(faces), dtype=torch.long)
    c2w = torch.as_tensor(np.asarray(c2w), dtype=torch.float64)
    K = torch.as_tensor(np.asarray(K), dtype=torch.float64)
    R = c2w[:3, :3].T
    pc = (v - c2w[:3, 3]) @ R.T
    z = pc[:, 2]
    zs = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
    x, y = pc[:, 0] / zs, pc[:, 1] / zs
    u = K[0, 0] * x + K[0, 1] * y + K[0, 2]
    w = K[1, 1] * y + K[1, 2]
    out = torch.zeros(height * width, dtype=torch.bool)
    if len(f) == 0:
        return out.reshape(height, width).numpy()
    front = (z[f] > near).all(1)
    f = f[front]
    tu, tv = u[f], w[f]  # (T,3)
    # pixel index ranges whose centres may fall in the triangle
    x0 = torch.ceil(tu.min(1).values - 0.5).clamp(0, width)
    x1 = torch.floor(tu.max(1).values - 0.5).clamp(-1, width - 1)
    y0 = torch.ceil(tv.min(1).values - 0.5).clamp(0, height)
    y1 = torch.floor(tv.max(1).values - 0.5).clamp(-1, height - 1)
    bw = (x1 - x0 + 1).clamp_min(0).long()
    bh = (y1 - y0 + 1).clamp_min(0).long()
    valid = (bw > 0) & (bh > 0)
    side = torch.maximum(bw, bh)
    # edge function coefficients: e_i(p) = A_i*px + B_i*py + C_i (sign consistent inside)
    ax, ay = tu, tv
    bx, by = tu.roll(-1, 1), tv.roll(-1, 1)
    A = ay - by
    B = bx - ax
    C = ax * by - ay * bx
    area = (A[:, 0] * tu[:, 2] + B[:, 0] * tv[:, 2] + C[:, 0])
    sgn = torch.sign(area)
    valid &= area.abs() > 1e-14
    if not bool(valid.any()):
        return out.reshape(height, width).numpy()
    A, B, C = A * sgn[:, None], B * sgn[:, None], C * sgn[:, None]
    s = 1
    max_side = int(side[valid].max())
    while s // 2 < max_side:
        sel = torch.nonzero(valid & (side <= s) & (side > s // 2)).reshape(-1)
        if len(sel):
            offs = torch.arange(s, dtype=torch.float64)
            oy, ox = torch.meshgrid(offs, offs, indexing="ij")
            ox, oy = ox.reshape(-1), oy.reshape(-1)
            per = max(1, chunk // (s * s))
            for c in range(0, len(sel), per):
                idx = sel[c:c + per]
                px = x0[idx, None] + ox[None]
                py = y0[idx, None] + oy[None]
                inb = (px <= x1[idx, None]) & (py <= y1[idx, None])
                cx, cy = px + 0.5, py + 0.5
                a, b, cc = A[idx], B[idx], C[idx]
                inside = inb
                for e in range(3):
                    inside = inside & ((a[:, e, None] * cx + b[:, e, None] * cy + cc[:, e, None]) >= 0)
                lin = (py * width + px)[inside].long()
                out[lin] = True
        s *= 2
    return out.reshape(height, width).numpy()


def silhouette_iou(mesh: Mesh, cameras: Cameras, masks: np.ndarray, threshold: float = 0.5,
                   max_views: int | None = None) -> dict:
    """IoU between the rasterised mesh silhouette and the masks (N,H,W) of ``cameras``.

    Returns {"mean": mean per-view IoU, "min": worst view, "per_view": [...], "pooled": IoU over all
    pixels of all views}.  ``max_views`` evaluates an evenly spaced subset.
    """
    n = len(cameras)
    idx = np.arange(n)
    if max_views and n > max_views:
        idx = np.unique(np.linspace(0, n - 1, max_views).round().astype(int))
    ious, inter_t, union_t = [], 0, 0
    for i in idx:
        sil = rasterize_silhouette(mesh.vertices, mesh.faces, cameras.K[i], cameras.c2w[i],
                                   cameras.width, cameras.height)
        m = np.asarray(masks[i]) > threshold
        inter = int(np.logical_and(sil, m).sum())
        union = int(np.logical_or(sil, m).sum())
        ious.append(1.0 if union == 0 else inter / union)
        inter_t += inter
        union_t += union
    return {"mean": float(np.mean(ious)), "min": float(np.min(ious)),
            "per_view": [float(x) for x in ious], "pooled": float(inter_t / max(union_t, 1))}


def sample_surface(mesh: Mesh, n: int, seed: int = 0) -> np.ndarray:
    """Area-weighted uniform samples (n,3) on the triangles of a mesh."""
    v = mesh.vertices.astype(np.float64)
    f = mesh.faces
    if len(f) == 0:
        raise ValueError("cannot sample the surface of a mesh with no faces")
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    rng = np.random.default_rng(seed)
    tri = rng.choice(len(f), size=n, p=area / area.sum())
    r1 = np.sqrt(rng.random(n))
    r2 = rng.random(n)
    p = (1 - r1)[:, None] * a[tri] + (r1 * (1 - r2))[:, None] * b[tri] + (r1 * r2)[:, None] * c[tri]
    return p


def chamfer_distance(mesh_a: Mesh, mesh_b: Mesh, n_samples: int = 100_000, seed: int = 0) -> dict:
    """Symmetric Chamfer distance between two surfaces from area-weighted samples (pykdtree).

    Returns {"chamfer": (acc + comp)/2, "accuracy": mean dist a->b, "completeness": mean dist b->a,
    "p90_a_to_b", "p90_b_to_a"} in world units (L1-style mean of Euclidean distances, as DTU).
    """
    from ..field.knn import kd_tree

    pa = sample_surface(mesh_a, n_samples, seed)
    pb = sample_surface(mesh_b, n_samples, seed + 1)
    da, _ = kd_tree(pb).query(pa, k=1)
    db, _ = kd_tree(pa).query(pb, k=1)
    return {"chamfer": float(0.5 * (da.mean() + db.mean())), "accuracy": float(da.mean()),
            "completeness": float(db.mean()), "p90_a_to_b": float(np.percentile(da, 90)),
            "p90_b_to_a": float(np.percentile(db, 90))}
