"""K nearest scaffold vertices within a radius, as a Triton kernel (the GPU fast path of
:class:`~neumesh_core.field.knn.HashGridIndex`; reference: :func:`~neumesh_core.field.knn.knn_radius_reference`).

The vertices are sorted by the cell of a uniform grid whose cells are at least one radius wide, and a
dense table gives each cell's first sorted vertex and count (:class:`TritonHashGrid`, built in plain
torch on the vertices' device).  A query looks at the (up to 27) cells around its point whose box lies
within the radius, measures every vertex there and keeps the K nearest within the radius.  One program
handles a block of queries; nothing is synchronised with the host.

The kernel keeps each query's K best candidates as 64-bit keys ``(float bits of the distance) << 32 |
vertex id`` (non-negative float32 bits order like the floats), replacing the largest key whenever a
closer vertex turns up; the keys sort by distance, then by vertex id.  :func:`knn_keys` is the
``@triton.jit`` building block the fused renderer (:mod:`neumesh_core.kernels.fused`) calls
per sample; :class:`TritonKNNIndex` has the ``query`` interface of the other indices.

Triton is optional (``pip install neumesh[gpu]``, or the wheel that comes with CUDA builds of torch):
:func:`triton_available` says whether it imports.  Kernels run on CUDA tensors, or on CPU tensors when
``TRITON_INTERPRET=1`` is set before triton is imported (the tests do this; slow, for checking logic).
"""
from __future__ import annotations

import contextlib
import os

import numpy as np
import torch

try:  # optional dependency
    import triton
    import triton.language as tl
    _TRITON_ERROR = None
except Exception as e:  # pragma: no cover - depends on the environment
    triton = None
    tl = None
    _TRITON_ERROR = e

# largest dense cell table (cells; 8M: 64 MB of int32 starts and counts): the grid's cells are widened
# (a power of two times the radius) until the table fits, which keeps every neighbour within the 27
# cells around a point's cell
MAX_TABLE_CELLS = 1 << 23


def triton_available() -> bool:
    """True when triton imports (its kernels then run on CUDA tensors, or anywhere with TRITON_INTERPRET=1)."""
    return triton is not None


def triton_runs_on(device) -> bool:
    """Whether Triton kernels can run on tensors of ``device``: CUDA with triton importable, or any
    device when the interpreter is on (``TRITON_INTERPRET=1``)."""
    if triton is None:
        return False
    if torch.device(device).type == "cuda":
        return True
    return os.environ.get("TRITON_INTERPRET", "0") not in ("", "0")


def require_triton(device) -> None:
    """Raise a NeuMeshError that says what to do when the Triton kernels cannot run on ``device``."""
    from ..errors import NeuMeshError

    if triton is None:
        raise NeuMeshError(f"the Triton kernels need the 'triton' package, which does not import here "
                           f"({_TRITON_ERROR}); install it (`pip install triton`, it comes with CUDA builds "
                           "of torch) or render with RenderSettings(backend='torch')")
    if not triton_runs_on(device):
        raise NeuMeshError(f"the Triton kernels run on CUDA tensors, not on {torch.device(device)}; move the "
                           "field to a GPU, render with RenderSettings(backend='torch'), or set "
                           "TRITON_INTERPRET=1 before importing triton to run them (slowly) on the CPU")


def cell_order(cells_per_radius: int) -> torch.Tensor:
    """The (2C+1)^3 cells around a point's own, nearest first: their row-major indices (int32) sorted by
    the length of their offset.  :func:`knn_keys` reads them in this order, so the cells read last can
    be left out once a point's K nearest so far are nearer than those cells."""
    c = int(cells_per_radius)
    r = torch.arange(-c, c + 1)
    off = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    return torch.sort((off * off).sum(1), stable=True).indices.to(torch.int32).contiguous()


class TritonHashGrid:
    """The tables the kernel reads: vertices sorted by cell, (N,4) float32 positions (padded) and their
    int32 ids, and per cell (dense, X*Y*Z) the first sorted vertex and the count, int32.

    ``cell`` is ``radius / cells_per_radius`` times the smallest power of two that keeps the table under
    :data:`MAX_TABLE_CELLS` cells; a query reads the ``(2 cells_per_radius + 1)^3`` cells around its
    own (1: 27 cells one radius wide; 2: 125 cells half a radius wide, fewer vertices measured)."""

    #: cells the kernel reads side by side (a (block, 32) tile per round: 1 round for C=1, 4 for C=2)
    ncp = 32

    def __init__(self, vertices: torch.Tensor, radius: float, cells_per_radius: int = 2):
        radius = float(radius)
        self.c = int(cells_per_radius)
        if self.c not in (1, 2):
            raise ValueError(f"cells_per_radius must be 1 or 2, got {cells_per_radius}")
        if not (np.isfinite(radius) and radius > 0):
            raise ValueError(f"the Triton neighbour search needs a finite positive radius, got {radius}")
        v = vertices.detach().float().contiguous()
        dev = v.device
        self.n = len(v)
        self.radius = radius
        if self.n == 0:
            lo = torch.zeros(3, device=dev)
            hi = lo
        else:
            lo, hi = v.min(0).values, v.max(0).values
        cell = radius / self.c
        extent = (hi - lo).cpu().double().numpy()
        while True:
            dims = np.floor(extent / cell).astype(np.int64) + 1
            if int(np.prod(dims)) <= MAX_TABLE_CELLS:
                break
            cell *= 2.0
        self.lo = [float(x) for x in lo.cpu().tolist()]
        self.cell = float(cell)
        self.dims = [int(x) for x in dims]
        lo_t = torch.tensor(self.lo, device=dev)
        ijk = torch.floor((v - lo_t) / self.cell).long()
        d = torch.tensor(self.dims, device=dev)
        ijk = torch.minimum(ijk.clamp_min(0), d - 1)
        key = (ijk[:, 0] * self.dims[1] + ijk[:, 1]) * self.dims[2] + ijk[:, 2]
        key_sorted, order = torch.sort(key, stable=True)
        n_cells = int(np.prod(dims))
        count = torch.bincount(key_sorted, minlength=n_cells)
        start = torch.cumsum(count, 0) - count
        self.cell_start = start.to(torch.int32).contiguous()
        self.cell_count = count.to(torch.int32).contiguous()
        vs = torch.zeros(self.n, 4, device=dev)
        vs[:, :3] = v.index_select(0, order)
        self.v_sorted = vs.contiguous()
        self.ids_sorted = order.to(torch.int32).contiguous()
        self.cell_order = cell_order(self.c).to(dev)

    def args(self):
        """The kernel arguments of the grid, in :func:`knn_keys`'s order."""
        return (self.lo[0], self.lo[1], self.lo[2], self.cell, self.dims[0], self.dims[1], self.dims[2],
                self.cell_start, self.cell_count, self.v_sorted, self.ids_sorted, self.cell_order, self.radius)


if triton is not None:
    _INF_BITS = tl.constexpr(0x7F800000)   # float32 +inf
    _NONE_KEY = tl.constexpr(0x7FFFFFFFFFFFFFFF)

    @triton.jit
    def _merge_best(keys, cand, none):
        """The best candidate of each row replaces the row's worst key where it is better; then it is
        struck from the candidates (K of these in a row merge a row's K best, nearest first)."""
        best = tl.min(cand, 1)
        worst = tl.max(keys, 1)
        better = best < worst
        keys = tl.where((keys == worst[:, None]) & better[:, None], best[:, None], keys)
        cand = tl.where(cand == best[:, None], none, cand)
        return keys, cand

    @triton.jit
    def knn_keys(px, py, pz, live,
                 lo_x, lo_y, lo_z, cell, dim_x, dim_y, dim_z,
                 cell_start, cell_count, v_sorted, ids_sorted, cell_order, radius,
                 BLOCK: tl.constexpr, KP: tl.constexpr, K: tl.constexpr, C: tl.constexpr,
                 NCP: tl.constexpr, EARLY_OUT: tl.constexpr):
        """The K nearest vertices within ``radius`` of points (px, py, pz) (BLOCK,) where ``live``:
        (BLOCK, KP) int64 keys, unsorted (C: grid cells per radius; NCP: cells per tile, read nearest
        first, a tile's cells beyond a row's K-th nearest vertex so far left out); a key's high
        word is the float bits of the distance (+inf for a slot that found nothing), the low word the
        vertex id.  Slots K..KP-1 are padding (-1).  EARLY_OUT: each round merges only as many of its
        candidates as the block's row with the most candidates nearer than its worst key has (at most
        K): the same keys, fewer merges once the rows hold near vertices."""
        slot = tl.arange(0, KP)
        inf_key = (tl.full([BLOCK, KP], _INF_BITS, tl.int64) << 32) + slot[None, :].to(tl.int64)
        keys = tl.where(slot[None, :] < K, inf_key, tl.full([BLOCK, KP], -1, tl.int64))
        big = (dim_x + dim_y + dim_z + 4).to(tl.float32)
        qx = tl.minimum(tl.maximum(tl.floor((px - lo_x) / cell), -2.0), big).to(tl.int32)
        qy = tl.minimum(tl.maximum(tl.floor((py - lo_y) / cell), -2.0), big).to(tl.int32)
        qz = tl.minimum(tl.maximum(tl.floor((pz - lo_z) / cell), -2.0), big).to(tl.int32)
        r2 = radius * radius
        # the (2C+1)^3 cells around each point's cell, nearest first (cell_order), NCP at a time side by
        # side: (BLOCK, NCP) tiles
        S: tl.constexpr = 2 * C + 1
        none = tl.full([BLOCK, NCP], _NONE_KEY, tl.int64)
        for c0 in range(0, S * S * S, NCP):
            rank = c0 + tl.arange(0, NCP)
            o = tl.load(cell_order + rank, mask=rank < S * S * S, other=0)
            cx = qx[:, None] + (o // (S * S) - C)[None, :]
            cy = qy[:, None] + ((o // S) % S - C)[None, :]
            cz = qz[:, None] + (o % S - C)[None, :]
            inside = (rank[None, :] < S * S * S) & (cx >= 0) & (cx < dim_x) & (cy >= 0) & (cy < dim_y) & \
                (cz >= 0) & (cz < dim_z)
            bx = lo_x + cx.to(tl.float32) * cell
            by = lo_y + cy.to(tl.float32) * cell
            bz = lo_z + cz.to(tl.float32) * cell
            gx = tl.maximum(bx - px[:, None], 0.0) + tl.maximum(px[:, None] - (bx + cell), 0.0)
            gy = tl.maximum(by - py[:, None], 0.0) + tl.maximum(py[:, None] - (by + cell), 0.0)
            gz = tl.maximum(bz - pz[:, None], 0.0) + tl.maximum(pz[:, None] - (bz + cell), 0.0)
            # a cell farther than a row's K-th nearest vertex so far cannot hold a nearer one (with a
            # margin for the rounding of the cell's bounds); until K are found, the radius bounds it
            far_k = (tl.max(keys, 1) >> 32).to(tl.int32).to(tl.float32, bitcast=True)
            lim2 = tl.minimum(far_k * far_k * 1.0001, r2)
            near = live[:, None] & inside & (gx * gx + gy * gy + gz * gz <= lim2[:, None])
            ckey = (cx * dim_y + cy) * dim_z + cz
            start = tl.load(cell_start + ckey, mask=near, other=0)
            cnt = tl.load(cell_count + ckey, mask=near, other=0)
            n_max = tl.max(tl.max(cnt, 1), 0)
            for c in range(n_max):
                # the c-th vertex of every cell at once, then the K smallest of them merged into the keys
                m = c < cnt
                j = start + c
                vx = tl.load(v_sorted + j * 4, mask=m, other=0.0)
                vy = tl.load(v_sorted + j * 4 + 1, mask=m, other=0.0)
                vz = tl.load(v_sorted + j * 4 + 2, mask=m, other=0.0)
                vid = tl.load(ids_sorted + j, mask=m, other=0)
                dx = px[:, None] - vx
                dy = py[:, None] - vy
                dz = pz[:, None] - vz
                d = tl.sqrt(dx * dx + dy * dy + dz * dz)
                ok = m & (d <= radius)
                cand = tl.where(ok, (d.to(tl.int32, bitcast=True).to(tl.int64) << 32) | vid.to(tl.int64), none)
                if EARLY_OUT:
                    # a candidate no nearer than the row's worst key now never enters it (the worst only
                    # gets nearer): min(K, the most such candidates of a row) merges give the same keys
                    worst = tl.max(keys, 1)
                    n_near = tl.sum((cand < worst[:, None]).to(tl.int32), 1)
                    for _r in range(tl.minimum(tl.max(n_near, 0), K)):
                        keys, cand = _merge_best(keys, cand, none)
                else:
                    for _r in tl.static_range(K):
                        keys, cand = _merge_best(keys, cand, none)
        return keys

    @triton.jit
    def _knn_kernel(points, n_points, out_keys,
                    lo_x, lo_y, lo_z, cell, dim_x, dim_y, dim_z,
                    cell_start, cell_count, v_sorted, ids_sorted, cell_order, radius,
                    BLOCK: tl.constexpr, KP: tl.constexpr, K: tl.constexpr, C: tl.constexpr,
                    NCP: tl.constexpr, EARLY_OUT: tl.constexpr):
        rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        live = rows < n_points
        px = tl.load(points + rows * 3, mask=live, other=0.0)
        py = tl.load(points + rows * 3 + 1, mask=live, other=0.0)
        pz = tl.load(points + rows * 3 + 2, mask=live, other=0.0)
        keys = knn_keys(px, py, pz, live, lo_x, lo_y, lo_z, cell, dim_x, dim_y, dim_z,
                        cell_start, cell_count, v_sorted, ids_sorted, cell_order, radius, BLOCK, KP, K, C,
                        NCP, EARLY_OUT)
        slot = tl.arange(0, KP)
        tl.store(out_keys + rows[:, None] * KP + slot[None, :], keys, mask=live[:, None])


def next_pow2(n: int, least: int = 1) -> int:
    return max(int(least), 1 << max(0, int(n) - 1).bit_length())


def decode_keys(keys: torch.Tensor, k: int):
    """(M,KP) int64 kernel keys -> (idx (M,K) long, dist (M,K) float32) sorted by distance, -1 / inf
    where fewer than K vertices lie within the radius (the other indices' convention)."""
    keys = torch.sort(keys, 1).values
    keys = keys[:, keys.shape[1] - k:] if keys.shape[1] > k else keys   # padding (-1) sorts first
    hi = (keys >> 32).to(torch.int32)
    dist = hi.view(torch.float32).clone()
    idx = (keys & 0xFFFFFFFF).long()
    missing = torch.isinf(dist)
    idx = torch.where(missing, torch.full_like(idx, -1), idx)
    return idx, dist


def knn_radius_triton(points: torch.Tensor, grid: TritonHashGrid, k: int, block: int = 64,
                      early_out: bool = False):
    """K nearest vertices of ``grid`` within its radius of ``points`` (M,3): (idx (M,K) long,
    dist (M,K) float32) sorted by distance, as :func:`~neumesh_core.field.knn.knn_radius_reference`.
    ``early_out``: skip the merges no candidate needs (:func:`knn_keys`; the same result)."""
    require_triton(points.device)
    p = points.detach().float().contiguous()
    m = len(p)
    kp = next_pow2(k)
    keys = torch.empty(m, kp, dtype=torch.int64, device=p.device)
    if m == 0:
        return decode_keys(keys, k)
    if grid.n == 0:
        return (torch.full((m, k), -1, dtype=torch.long, device=p.device),
                torch.full((m, k), float("inf"), device=p.device))
    with torch.cuda.device(p.device) if p.device.type == "cuda" else contextlib.nullcontext():
        _knn_kernel[(triton.cdiv(m, block),)](p, m, keys, *grid.args(), BLOCK=block, KP=kp, K=k, C=grid.c,
                                               NCP=grid.ncp, EARLY_OUT=bool(early_out))
    return decode_keys(keys, k)


class TritonKNNIndex:
    """The ``query`` interface of :class:`~neumesh_core.field.knn.HashGridIndex`, answered by the
    Triton kernel (CUDA tensors, or the interpreter)."""

    def __init__(self, vertices, k: int = 4, radius: float = 0.0, block: int = 64, cells_per_radius: int = 2):
        v = vertices if torch.is_tensor(vertices) else torch.as_tensor(np.asarray(vertices))
        self.grid = TritonHashGrid(v, radius, cells_per_radius)
        self.k = int(k)
        self.radius = float(radius)
        self.block = int(block)
        self.n = self.grid.n

    def query(self, points: torch.Tensor):
        dev = points.device
        idx, dist = knn_radius_triton(points.to(self.grid.v_sorted.device), self.grid, self.k, self.block)
        return idx.to(dev), dist.to(dev)
