"""K nearest scaffold vertices within a radius.

Fast paths: :class:`KDTreeIndex` (pykdtree, multi-threaded C, on the CPU), :class:`HashGridIndex`
(a uniform grid in plain torch, so it runs where the vertices are, a GPU included) and, on a GPU,
:class:`~neumesh_core.kernels.knn.TritonKNNIndex` (the same grid searched by one Triton kernel).
Reference: :func:`knn_radius_reference` (brute force in torch).  All return ``(idx, dist)`` of shape
(M,K), sorted by distance, with ``idx == -1`` and ``dist == inf`` where fewer than K vertices lie within
the radius.  :func:`make_index` picks one by name ("auto": the device's own).
"""
from __future__ import annotations

import numpy as np
import torch


def knn_radius_reference(points: torch.Tensor, verts: torch.Tensor, k: int, radius: float,
                         chunk: int = 4096):
    """Brute-force reference KNN-within-radius (O(M*N); use for tests and tiny meshes)."""
    idx_out, dist_out = [], []
    kk = min(k, len(verts))
    for s in range(0, len(points), chunk):
        p = points[s:s + chunk]
        d2 = torch.cdist(p.double(), verts.double()).pow(2)
        d2v, ii = torch.topk(d2, kk, dim=1, largest=False)
        dist = d2v.sqrt().float()
        ii = ii.long()
        far = dist > radius
        ii = torch.where(far, torch.full_like(ii, -1), ii)
        dist = torch.where(far, torch.full_like(dist, float("inf")), dist)
        if kk < k:
            pad = k - kk
            ii = torch.cat([ii, ii.new_full((len(p), pad), -1)], 1)
            dist = torch.cat([dist, dist.new_full((len(p), pad), float("inf"))], 1)
        idx_out.append(ii)
        dist_out.append(dist)
    if not idx_out:
        return (torch.empty(0, k, dtype=torch.long, device=points.device),
                torch.empty(0, k, device=points.device))
    return torch.cat(idx_out), torch.cat(dist_out)


def kd_tree(points: np.ndarray):
    """A KD-tree over (N,3) points with pykdtree's ``query(p, k=, distance_upper_bound=)``: pykdtree's
    (multi-threaded C), or scipy's cKDTree where pykdtree is not installed (e.g. a GPU machine that
    renders with the hash grid or the Triton kernels and needs a tree only for rare set-up queries).
    Both report a missing neighbour as index N and distance inf."""
    try:
        from pykdtree.kdtree import KDTree
    except ImportError:   # pragma: no cover - pykdtree is a dependency; scipy covers its absence
        from scipy.spatial import cKDTree

        return cKDTree(points, leafsize=16)
    return KDTree(points, leafsize=16)


class KDTreeIndex:
    """KD-tree over scaffold vertices, on the CPU; rebuilt cheaply when vertices move."""

    def __init__(self, vertices, k: int = 4, radius: float = float("inf")):
        v = vertices.detach().cpu().numpy() if torch.is_tensor(vertices) else np.asarray(vertices)
        self._v = np.ascontiguousarray(v, dtype=np.float32)
        self.n = len(self._v)
        self.k = int(k)
        self.radius = float(radius)
        self._tree = kd_tree(self._v)

    def query(self, points: torch.Tensor):
        """points (M,3) float tensor -> (idx (M,K) long, dist (M,K) float32) on points' device."""
        device = points.device
        p = np.ascontiguousarray(points.detach().cpu().numpy(), dtype=np.float32)
        if len(p) == 0:
            return (torch.empty(0, self.k, dtype=torch.long, device=device),
                    torch.empty(0, self.k, device=device))
        kk = min(self.k, self.n)
        ub = self.radius if np.isfinite(self.radius) else None
        dist, idx = self._tree.query(p, k=kk, **({} if ub is None else {"distance_upper_bound": ub}))
        dist = np.asarray(dist, dtype=np.float32).reshape(len(p), kk)
        idx = np.asarray(idx).reshape(len(p), kk).astype(np.int64)
        missing = idx >= self.n
        idx[missing] = -1
        dist[missing] = np.inf
        if kk < self.k:
            idx = np.concatenate([idx, np.full((len(p), self.k - kk), -1, np.int64)], 1)
            dist = np.concatenate([dist, np.full((len(p), self.k - kk), np.inf, np.float32)], 1)
        return torch.from_numpy(idx).to(device), torch.from_numpy(dist).to(device)


# the 27 cells around a cell, (27,3)
_OFFSETS = torch.stack(torch.meshgrid(*(torch.arange(-1, 2),) * 3, indexing="ij"), -1).reshape(-1, 3)


class HashGridIndex:
    """K nearest vertices within a finite radius from a uniform grid with cells one radius wide.

    The vertices are sorted by cell; a query gathers the vertices of the (up to 27) cells whose box
    lies within the radius of the point, keeps those within the radius and takes the K nearest.  All
    plain torch on the vertices' device (no host round trip on a GPU); memory grows with the number
    of candidate pairs, so queries run in chunks of ``chunk`` points.
    """

    def __init__(self, vertices, k: int = 4, radius: float = 0.0, chunk: int = 65536):
        radius = float(radius)
        if not (np.isfinite(radius) and radius > 0):
            raise ValueError(f"HashGridIndex needs a finite positive radius, got {radius}; "
                             "use KDTreeIndex (KD-tree) for unbounded queries")
        v = vertices.detach() if torch.is_tensor(vertices) else torch.as_tensor(np.asarray(vertices))
        self.v = v.float().contiguous()
        self.n = len(self.v)
        self.k = int(k)
        self.radius = radius
        self.chunk = int(chunk)
        dev = self.v.device
        if self.n == 0:
            self.lo = torch.zeros(3, device=dev)
            self.dims = torch.ones(3, dtype=torch.long, device=dev)
            self.keys = torch.empty(0, dtype=torch.long, device=dev)
            self.counts = self.starts = self.order = self.keys
            return
        self.lo = self.v.min(0).values
        ijk = torch.floor((self.v - self.lo) / radius).long()
        self.dims = ijk.max(0).values + 1
        key_sorted, self.order = torch.sort(self._key(ijk))
        self.keys, self.counts = torch.unique_consecutive(key_sorted, return_counts=True)
        self.starts = torch.cumsum(self.counts, 0) - self.counts

    def _key(self, ijk: torch.Tensor) -> torch.Tensor:
        return (ijk[..., 0] * self.dims[1] + ijk[..., 1]) * self.dims[2] + ijk[..., 2]

    def query(self, points: torch.Tensor):
        """points (M,3) float tensor -> (idx (M,K) long, dist (M,K) float32) on points' device."""
        out_dev = points.device
        p_all = points.detach().float().to(self.v.device)
        m_all = len(p_all)
        idx = torch.full((m_all, self.k), -1, dtype=torch.long, device=self.v.device)
        dist = torch.full((m_all, self.k), float("inf"), device=self.v.device)
        if self.n > 0:
            for s in range(0, m_all, self.chunk):
                self._query_chunk(p_all[s:s + self.chunk], idx[s:s + self.chunk], dist[s:s + self.chunk])
        return idx.to(out_dev), dist.to(out_dev)

    def _query_chunk(self, p: torch.Tensor, idx_out: torch.Tensor, dist_out: torch.Tensor) -> None:
        dev, r, m = p.device, self.radius, len(p)
        offs = _OFFSETS.to(dev)
        n_off = len(offs)
        # cell coordinates, clamped first so that far-away points cannot overflow the integer cast
        qc = torch.floor((p - self.lo) / r).clamp(-2, float(self.dims.max()) + 1).long()
        nb = qc[:, None, :] + offs[None]                                        # (m,27,3)
        inside = ((nb >= 0) & (nb < self.dims)).all(-1)
        box_lo = self.lo + nb.float() * r
        gap = (box_lo - p[:, None]).clamp_min(0) + (p[:, None] - (box_lo + r)).clamp_min(0)
        near = inside & (gap.pow(2).sum(-1) <= r * r)
        key = self._key(torch.minimum(nb.clamp_min(0), self.dims - 1))
        pos = torch.searchsorted(self.keys, key.reshape(-1)).clamp_max(len(self.keys) - 1)
        hit = near.reshape(-1) & (self.keys[pos] == key.reshape(-1))
        cnt = torch.where(hit, self.counts[pos], torch.zeros_like(pos))
        total = int(cnt.sum())
        if total == 0:
            return
        # one row per (point, candidate vertex) pair
        pair = torch.repeat_interleave(torch.arange(m * n_off, device=dev), cnt, output_size=total)
        within = torch.arange(total, device=dev) - (torch.cumsum(cnt, 0) - cnt)[pair]
        cand = self.order[self.starts[pos][pair] + within]
        qid = torch.div(pair, n_off, rounding_mode="floor")
        d = (p[qid] - self.v[cand]).norm(dim=-1)
        keep = d <= r
        qid, cand, d = qid[keep], cand[keep], d[keep]
        if len(qid) == 0:
            return
        # pairs are grouped by point (pair = point * n_off + cell): lay each point's run out in a row
        # of a dense (m, longest run) matrix and take the K smallest per row
        per = torch.bincount(qid, minlength=m)
        col = torch.arange(len(qid), device=dev) - (torch.cumsum(per, 0) - per)[qid]
        width = max(int(per.max()), self.k)
        dd = torch.full((m, width), float("inf"), device=dev)
        dd[qid, col] = d
        cc = torch.full((m, width), -1, dtype=torch.long, device=dev)
        cc[qid, col] = cand
        kd, kc = torch.topk(dd, self.k, dim=1, largest=False, sorted=True)
        ki = torch.gather(cc, 1, kc)
        ki[torch.isinf(kd)] = -1
        idx_out.copy_(ki)
        dist_out.copy_(kd)


KNN_BACKENDS = ("auto", "hashgrid", "triton")
# older names of a backend, as saved field configs and scripts spell them ("kdtree" always meant "auto")
KNN_ALIASES = {"kdtree": "auto"}


def knn_backend(name: str) -> str:
    """``name`` as one of :data:`KNN_BACKENDS` (an alias resolved); ValueError for an unknown one."""
    backend = KNN_ALIASES.get(name, name)
    if backend not in KNN_BACKENDS:
        raise ValueError(f"unknown neighbour-search backend {name!r}; use one of {', '.join(KNN_BACKENDS)}")
    return backend


def make_index(vertices, k: int, radius: float, backend: str = "auto"):
    """The neighbour index for ``backend``: "auto" (the device's own: :class:`KDTreeIndex` on the CPU;
    for vertices on a GPU with a finite radius the Triton index where triton imports, else the hash
    grid, both answering on the GPU, where a KD-tree would copy every query to the host and back),
    "hashgrid" (:class:`HashGridIndex`, plain torch on the vertices' device; needs a finite radius) or
    "triton" (:class:`~neumesh_core.kernels.knn.TritonKNNIndex`, one kernel launch a query and no host
    synchronisation; CUDA, or Triton's interpreter; elsewhere, e.g. a field saved so and loaded on a
    CPU, what "auto" gives).  "kdtree" is accepted for "auto" (:data:`KNN_ALIASES`)."""
    backend = knn_backend(backend)
    if backend == "auto":
        on_gpu = torch.is_tensor(vertices) and vertices.device.type != "cpu"
        if on_gpu and np.isfinite(float(radius)) and float(radius) > 0:
            from ..kernels.knn import TritonKNNIndex, triton_runs_on

            if triton_runs_on(vertices.device):
                return TritonKNNIndex(vertices, k, radius)
            return HashGridIndex(vertices, k, radius)
        return KDTreeIndex(vertices, k, radius)
    if backend == "hashgrid":
        return HashGridIndex(vertices, k, radius)
    if backend == "triton":
        from ..kernels.knn import TritonKNNIndex, triton_runs_on

        v = vertices if torch.is_tensor(vertices) else torch.as_tensor(np.asarray(vertices))
        if triton_runs_on(v.device) and np.isfinite(float(radius)) and float(radius) > 0:
            return TritonKNNIndex(v, k, radius)
        return make_index(v, k, radius, "auto")   # a field saved so still loads where triton cannot run


def vertex_neighbours(vertices, k: int) -> np.ndarray:
    """(N,k) indices of each vertex's k nearest *other* vertices (for the TV loss)."""
    v = np.ascontiguousarray(np.asarray(vertices), dtype=np.float32)
    kk = min(k + 1, len(v))
    _, idx = kd_tree(v).query(v, k=kk)
    idx = np.asarray(idx).reshape(len(v), kk)
    return idx[:, 1:].astype(np.int64)
