"""A decimated cage for ARAP previews: a subset of the mesh's own vertices joined into a coarser graph,
and the linear map that carries a cage deformation back to every vertex.

- *Cage vertices* are mesh vertices, one per occupied cell of a voxel grid split by the normal's main
  direction (so the two sides of a thin plate get their own), the voxel size tuned to about the asked
  count; every anchor/handle group and every connected piece keeps at least one.
- Every mesh vertex joins the cage vertex nearest to it *along the surface* (multi-source Dijkstra over
  the mesh edges), so clusters never jump across a gap; two cage vertices are joined where their
  clusters touch, with the weight (crossing mesh edges) x (mean edge length) / (cage edge length): the
  dual/primal length ratio that cotangent weights measure on a mesh.
- Carrying (linear blend skinning with the cage's ARAP rotations): mesh vertex i takes the cage
  vertices k among its ``neighbours`` nearest that are its own cluster or a cluster next to it, with
  Gaussian weights w_ik over the local cage spacing, and goes to
  x_i = sum_k w_ik (y_k + R_k (p_i - p_k)): one sparse (N,M) matrix W applied to y, to the rotations
  and to R_k p_k.  Its rotation is the polar factor of sum_k w_ik R_k.

No decimation package is needed, and the mesh need not be manifold.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import DeformError


@dataclass
class Cage:
    samples: np.ndarray     # (M,) mesh vertex index of every cage vertex
    edges: np.ndarray       # (Ec,2) cage edges (indices into samples)
    weights: np.ndarray     # (Ec,) ARAP weights
    cluster: np.ndarray     # (N,) the cage vertex (index into samples) each mesh vertex belongs to
    W: object               # scipy CSR (N,M) carry weights (rows sum to 1)

    def carry(self, y: np.ndarray, R: np.ndarray, rest: np.ndarray):
        """Mesh positions (N,3) from cage positions ``y`` (M,3) and rotations ``R`` (M,3,3), and the
        per-vertex blended rotation matrices (N,3,3) (not yet orthonormal; see ArapResult.rotations).

        In float32 (what the viewport and the field take), as one sparse product of the (N,M) weights
        with the (M,12) block [y - R p | R]: the same numbers as :meth:`carry_reference` to float32's
        precision, in about half the time."""
        W32, rest32 = self._float32(rest)
        m = len(self.samples)
        Z = np.empty((m, 12), np.float32)
        Z[:, 3:] = R.reshape(m, 9)
        Z[:, :3] = y - np.einsum("mab,mb->ma", R, rest[self.samples])
        WZ = W32 @ Z
        A = WZ[:, 3:].reshape(-1, 3, 3)
        x = WZ[:, :3] + np.einsum("nab,nb->na", A, rest32)
        return x, A

    def _float32(self, rest: np.ndarray):
        cached = getattr(self, "_cache32", None)
        if cached is None or cached[0] is not rest:
            cached = self._cache32 = (rest, self.W.astype(np.float32), np.asarray(rest, np.float32))
        return cached[1], cached[2]

    def carry_reference(self, y: np.ndarray, R: np.ndarray, rest: np.ndarray):
        """The plain float64 form of :meth:`carry`: x_i = sum_k w_ik (y_k + R_k (p_i - p_k))."""
        pc = rest[self.samples]
        A = np.asarray(self.W @ R.reshape(-1, 9)).reshape(-1, 3, 3)
        Rp = np.einsum("mab,mb->ma", R, pc)
        x = np.asarray(self.W @ (y - Rp)) + np.einsum("nab,nb->na", A, rest)
        return x, A


def _normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.stack([np.bincount(f.reshape(-1), weights=np.repeat(fn[:, c], 3), minlength=len(v))
                  for c in range(3)], 1)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def _voxel_samples(v: np.ndarray, normals: np.ndarray, size: float) -> np.ndarray:
    """One vertex per (voxel, main normal direction): the one nearest the cell's vertex centroid."""
    cell = np.floor((v - v.min(0)) / size).astype(np.int64)
    ax = np.abs(normals).argmax(1)
    sign = normals[np.arange(len(v)), ax] > 0
    dims = cell.max(0) + 1
    key = ((cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]) * 6 + ax * 2 + sign
    _, inv = np.unique(key, return_inverse=True)
    cnt = np.bincount(inv)
    cen = np.stack([np.bincount(inv, weights=v[:, c]) for c in range(3)], 1) / cnt[:, None]
    d = ((v - cen[inv]) ** 2).sum(1)
    order = np.lexsort((d, inv))
    first = np.ones(len(order), bool)
    first[1:] = inv[order][1:] != inv[order][:-1]
    return np.sort(order[first])


def build_cage(rest: np.ndarray, faces: np.ndarray, target: int, weights: str = "cotangent",
               neighbours: int = 8, keep=()) -> Cage:
    """A cage of about ``target`` of the mesh's vertices (see the module text).  ``keep``: index sets
    (anchor set, handle groups) each of which must hold at least one cage vertex.  ``weights`` "uniform"
    gives every cage edge weight 1."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components, dijkstra

    from ..mesh import unique_edges

    v = np.asarray(rest, np.float64)
    f = np.asarray(faces, np.int64)
    n = len(v)
    if target < 4:
        raise DeformError(f"a cage needs at least 4 vertices, asked for {target}")
    e = unique_edges(f)
    le = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    mean_len = float(le.mean())
    area = 0.5 * float(np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum())
    normals = _normals(v, f)
    size = max(np.sqrt(area / target), 1e-9)
    for _ in range(4):   # the count goes about as 1/size^2 on a surface
        samples = _voxel_samples(v, normals, size)
        ratio = len(samples) / target
        if 0.9 < ratio < 1.1:
            break
        size *= float(np.sqrt(ratio))
    G = sp.csr_matrix((np.concatenate([le, le]) + 1e-12 * mean_len,
                       (np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]]))), shape=(n, n))
    ncomp, comp = connected_components(G, directed=False)
    extra = []
    has = np.zeros(ncomp, bool)
    has[comp[samples]] = True
    if not has.all():   # one cage vertex in every piece that has none (its first vertex)
        first = np.full(ncomp, n, np.int64)
        np.minimum.at(first, comp, np.arange(n))
        extra.append(first[~has])
    chosen = np.zeros(n, bool)
    chosen[samples] = True
    for group in keep:
        group = np.asarray(group, np.int64)
        if len(group) and not chosen[group].any():   # the group's vertex nearest its centroid
            g = group[np.argmin(((v[group] - v[group].mean(0)) ** 2).sum(1))]
            extra.append(np.array([g]))
    if extra:
        samples = np.unique(np.concatenate([samples, *extra]))
    m = len(samples)
    _, _, src = dijkstra(G, directed=False, indices=samples, min_only=True, return_predecessors=True)
    slot = np.full(n, -1, np.int64)
    slot[samples] = np.arange(m)
    cluster = slot[src]
    if (cluster < 0).any():   # cannot happen: every piece holds a sample
        raise DeformError("internal error: a vertex reached no cage vertex")
    a, b = cluster[e[:, 0]], cluster[e[:, 1]]
    cross = a != b
    lo, hi = np.minimum(a[cross], b[cross]), np.maximum(a[cross], b[cross])
    keys, counts = np.unique(lo * m + hi, return_counts=True)
    cedges = np.stack([keys // m, keys % m], 1)
    pc = v[samples]
    clen = np.linalg.norm(pc[cedges[:, 0]] - pc[cedges[:, 1]], axis=1)
    if weights == "uniform":
        cw = np.ones(len(cedges))
    else:
        cw = counts * mean_len / np.maximum(clen, 1e-6 * mean_len)
    W = _carry_weights(v, samples, cluster, cedges, clen, neighbours)
    return Cage(samples, cedges, cw, cluster, W)


def _carry_weights(v, samples, cluster, cedges, clen, neighbours: int):
    import scipy.sparse as sp
    from ..field.knn import kd_tree

    n, m = len(v), len(samples)
    pc = np.ascontiguousarray(v[samples])
    k = int(min(neighbours, m))
    _, idx = kd_tree(pc).query(np.ascontiguousarray(v), k=k)
    idx = np.asarray(idx, np.int64).reshape(n, k)
    # allowed: the vertex's own cluster and the clusters next to it in the cage
    adj_keys = np.concatenate([cedges[:, 0] * m + cedges[:, 1], cedges[:, 1] * m + cedges[:, 0],
                               np.arange(m) * m + np.arange(m)])
    adj_keys.sort()
    q = cluster[:, None] * m + idx
    pos = np.minimum(np.searchsorted(adj_keys, q), len(adj_keys) - 1)
    ok = adj_keys[pos] == q
    own_in = (idx == cluster[:, None]).any(1)
    idx[~own_in, -1] = cluster[~own_in]       # the own cage vertex always takes part
    ok[~own_in, -1] = True
    # local spacing: mean cage edge length at the own cage vertex
    deg = np.bincount(cedges.reshape(-1), minlength=m)
    tot = np.bincount(cedges.reshape(-1), weights=np.repeat(clen, 2), minlength=m)
    spacing = np.where(deg > 0, tot / np.maximum(deg, 1), np.median(clen) if len(clen) else 1.0)
    s = spacing[cluster][:, None]
    d2 = ((v[:, None, :] - pc[idx]) ** 2).sum(-1)
    w = np.exp(-0.5 * d2 / np.maximum(s * s, 1e-30)) * ok
    w[~ok] = 0.0
    tot_w = w.sum(1, keepdims=True)
    w = np.where(tot_w > 0, w / np.maximum(tot_w, 1e-300), (idx == cluster[:, None]).astype(np.float64))
    W = sp.csr_matrix((w.reshape(-1), (np.repeat(np.arange(n), k), idx.reshape(-1))), shape=(n, m))
    W.eliminate_zeros()
    return W
