"""Iso-surface extraction, clean-up, connected components and vertex-count targeting."""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from ..mesh import Mesh


def marching_cubes(values: np.ndarray, level: float, lo, voxel: float, mask: np.ndarray | None = None) -> Mesh:
    """Iso-surface of node values (nx,ny,nz) at ``level`` (inside = values > level), outward CCW faces.

    The grid is padded with an outside layer so the surface is always closed.  With ``mask`` (bool per
    node) only the cubes whose nodes are all in the mask make faces: an open surface where the mask
    ends (no padding), its faces towards the lower values.
    """
    from skimage.measure import marching_cubes as _mc

    v = np.asarray(values, np.float32)
    if v.size == 0 or not v.max() > level:
        return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64))
    if mask is not None:
        if not (mask.any() and v[mask].max() > level and v[mask].min() < level):
            return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64))
        try:
            verts, faces, _, _ = _mc(v, level=level, spacing=(voxel, voxel, voxel), allow_degenerate=False,
                                     mask=_cube_mask(mask))
        except RuntimeError:   # no cube wholly in the mask crosses the level
            return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64))
        return Mesh((verts + np.asarray(lo, np.float32)[None]).astype(np.float32), faces.astype(np.int64))
    outside = np.float32(min(float(v.min()), level) - 1.0)
    v = np.pad(v, 1, mode="constant", constant_values=outside)
    verts, faces, _, _ = _mc(v, level=level, spacing=(voxel, voxel, voxel), allow_degenerate=False)
    verts = verts - voxel + np.asarray(lo, np.float32)[None]
    # skimage orients faces so that normals point towards decreasing values = outward here when
    # inside is "values > level"; make sure the winding is counter-clockwise seen from outside.
    mesh = Mesh(verts.astype(np.float32), faces.astype(np.int64))
    if len(mesh.faces) and _signed_volume(mesh) < 0:
        mesh = Mesh(mesh.vertices, mesh.faces[:, ::-1].copy())
    return mesh


def _cube_mask(mask: np.ndarray) -> np.ndarray:
    """scikit-image's mask tests one node per cube (its last corner, the one at +1 on every axis): the
    cubes whose eight nodes are all in ``mask``, marked at that corner."""
    m = np.asarray(mask, bool)
    out = np.zeros_like(m)
    out[1:, 1:, 1:] = np.logical_and.reduce([m[i:m.shape[0] - 1 + i, j:m.shape[1] - 1 + j, k:m.shape[2] - 1 + k]
                                             for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    return out


def _signed_volume(mesh: Mesh) -> float:
    v = mesh.vertices.astype(np.float64)
    f = mesh.faces
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)


def clean_mesh(mesh: Mesh, merge_eps: float = 0.0) -> Mesh:
    """Merge (near-)coincident vertices, drop degenerate / duplicate faces and unreferenced vertices."""
    v, f = mesh.vertices, mesh.faces
    if len(f) == 0:
        return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64))
    if merge_eps > 0:
        key = np.round(v / merge_eps).astype(np.int64)
        _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
        inv = inv.reshape(-1)
        f = inv[f]
        v = v[first]
    # degenerate: repeated index or (almost) zero area
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[ok]
    if len(f):
        a = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        area2 = np.linalg.norm(a, axis=1)
        scale = float(np.median(area2)) if len(area2) else 0.0
        f = f[area2 > max(1e-12, 1e-8 * scale)]
    # duplicate faces (same vertex set, any winding)
    if len(f):
        _, keep = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
        f = f[np.sort(keep)]
    # unreferenced vertices
    used = np.zeros(len(v), bool)
    used[f.reshape(-1)] = True
    remap = -np.ones(len(v), np.int64)
    remap[used] = np.arange(int(used.sum()))
    return Mesh(v[used], remap[f])


def keep_large_components(mesh: Mesh, min_fraction: float = 0.002, min_faces: int = 16,
                          max_components: int = 0) -> tuple[Mesh, int, int]:
    """Keep connected components with >= max(min_faces, min_fraction * largest) faces.

    Returns (mesh, components_found, components_kept).  Connectivity is through shared vertices.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = mesh.faces
    if len(f) == 0:
        return mesh, 0, 0
    nv = len(mesh.vertices)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    g = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(nv, nv))
    ncomp, labels = connected_components(g, directed=False)
    flab = labels[f[:, 0]]
    counts = np.bincount(flab, minlength=ncomp)
    thr = max(min_faces, int(min_fraction * counts.max()))
    keep_ids = np.nonzero(counts >= thr)[0]
    if len(keep_ids) == 0:
        keep_ids = np.array([int(np.argmax(counts))])
    if max_components and len(keep_ids) > max_components:
        keep_ids = keep_ids[np.argsort(-counts[keep_ids])[:max_components]]
    keep = np.isin(flab, keep_ids)
    return clean_mesh(Mesh(mesh.vertices, f[keep])), int(ncomp), int(len(keep_ids))


def resample_grid(values: np.ndarray, lo, voxel: float, new_voxel: float):
    """Trilinearly resample node values to a grid with spacing ``new_voxel`` over the same box."""
    dims = np.asarray(values.shape)
    ext = (dims - 1) * voxel
    new_dims = np.maximum(2, np.ceil(ext / new_voxel).astype(int) + 1)
    t = torch.from_numpy(np.ascontiguousarray(values, np.float32))[None, None]
    r = F.interpolate(t, size=tuple(int(d) for d in new_dims), mode="trilinear", align_corners=True)
    # align_corners keeps the box: the actual spacing is ext/(n-1) per axis; use the largest one
    actual = float((ext / (new_dims - 1)).max())
    return r[0, 0].numpy(), np.asarray(lo, np.float32), actual


def _resample_mask(mask: np.ndarray, shape) -> np.ndarray:
    """A node mask on a resampled grid: the nodes whose trilinear neighbourhood is wholly in ``mask``."""
    t = torch.from_numpy(np.ascontiguousarray(mask, np.float32))[None, None]
    r = F.interpolate(t, size=tuple(int(d) for d in shape), mode="trilinear", align_corners=True)
    return r[0, 0].numpy() > 0.999


def extract_with_target(values: np.ndarray, level: float, lo, voxel: float, target_vertices: int,
                        min_fraction: float, max_grid_nodes: int = 420 ** 3, tolerance: float = 0.12,
                        max_rounds: int = 3, check=None, mask: np.ndarray | None = None):
    """Marching cubes, clean, drop floaters, and re-extract on a resampled grid so that the vertex
    count lands within ``tolerance`` of ``target_vertices`` (0 = keep the grid resolution).
    ``mask``: the nodes that may make faces (an open surface; :func:`marching_cubes`).

    Returns (mesh, info dict).
    """
    info = {"rounds": []}
    cur_vals, cur_lo, cur_voxel = values, np.asarray(lo, np.float32), voxel
    cur_mask = mask
    best = None
    for rnd in range(max_rounds):
        m = marching_cubes(cur_vals, level, cur_lo, cur_voxel, mask=cur_mask)
        m = clean_mesh(m, merge_eps=cur_voxel * 1e-3)
        faces_before = len(m.faces)
        m, ncomp, nkept = keep_large_components(m, min_fraction=min_fraction)
        nv = m.num_vertices
        info["rounds"].append({"voxel": float(cur_voxel), "grid": list(map(int, cur_vals.shape)),
                               "vertices": int(nv), "faces": int(len(m.faces)),
                               "components": ncomp, "components_kept": nkept,
                               "faces_dropped_as_floaters": int(faces_before - len(m.faces))})
        if best is None or (target_vertices and abs(nv - target_vertices) < abs(best.num_vertices - target_vertices)):
            best = m
        if check is not None:
            check((rnd + 1) / max_rounds)
        if not target_vertices or nv == 0 or abs(nv - target_vertices) <= tolerance * target_vertices:
            break
        # vertex count of marching cubes scales with area / voxel^2
        new_voxel = cur_voxel * math.sqrt(nv / target_vertices)
        ext = (np.asarray(values.shape) - 1) * voxel
        nodes = np.prod(np.ceil(ext / new_voxel) + 1)
        if nodes > max_grid_nodes:
            new_voxel = float((np.prod(ext) / max_grid_nodes) ** (1 / 3)) * 1.01
            if new_voxel >= cur_voxel * 0.999:
                break
        cur_vals, cur_lo, cur_voxel = resample_grid(values, lo, voxel, new_voxel)
        if mask is not None:
            cur_mask = _resample_mask(mask, cur_vals.shape)
    info["final_voxel"] = float(cur_voxel)
    # the grid cap stopped us well short of the target: split triangles (x4 vertices) if that is closer
    if target_vertices and best is not None and best.num_vertices and \
            abs(4 * best.num_vertices - target_vertices) < abs(best.num_vertices - target_vertices):
        best = midpoint_subdivide(best)
        info["subdivided"] = True
    return best, info


def midpoint_subdivide(mesh: Mesh) -> Mesh:
    """Split every triangle into four (new vertices at edge midpoints)."""
    f = mesh.faces
    v = mesh.vertices
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e_sorted = np.sort(e, axis=1)
    uniq, inv = np.unique(e_sorted, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    mids = 0.5 * (v[uniq[:, 0]] + v[uniq[:, 1]])
    base = len(v)
    nf = len(f)
    m01, m12, m20 = (inv[:nf] + base, inv[nf:2 * nf] + base, inv[2 * nf:] + base)
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    nfaces = np.concatenate([
        np.stack([a, m01, m20], 1), np.stack([m01, b, m12], 1),
        np.stack([m20, m12, c], 1), np.stack([m01, m12, m20], 1)])
    return Mesh(np.concatenate([v, mids]), nfaces)
