"""As-rigid-as-possible deformation (Sorkine & Alexa 2007): the one ARAP implementation of the core.

The energy over a graph of rest points p (a mesh's edges, or a decimated cage's) with edge weights w:

    E(x, R) = sum_i sum_(j in N(i)) w_ij |(x_i - x_j) - R_i (p_i - p_j)|^2

minimised by alternating a *local* step (per vertex the rotation R_i nearest to its covariance
S_i = sum_j w_ij (x_i - x_j)(p_i - p_j)^T) and a *global* step (the linear system L x = b with the
weighted graph Laplacian L and b_i = sum_j w_ij (R_i + R_j)/2 (p_i - p_j)).  :class:`ArapTerms` holds
these pieces; the swap alignment's non-rigid ICP (``edit/align.py``) builds its system from them too.

:class:`ArapSolver` deforms a mesh: *anchors* stay at rest, *handles* go where they are told, every
other vertex follows as rigidly as possible.  The Laplacian of the free vertices is factorised once per
anchor/handle set (scipy's SuperLU in symmetric mode: a Cholesky-like factor, :func:`factorise_spd`);
every move then costs a few local-global iterations (a batched 3x3 polar decomposition of the vertices
a free vertex can see, three sparse products over the free rows and one factorised solve),
warm-started from the previous move's solution while a handle is dragged.  With
``ArapConfig.cage_vertices`` set, it solves on a decimated cage (:mod:`neumesh_core.deform.cage`) and
carries the cage's positions and rotations to every vertex through a precomputed linear map (float32).
:meth:`ConstrainedArap.solve_reference` is the plain loop the fast one is tested against.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field as dc_field, replace
from typing import Literal, Optional

import numpy as np

from ..errors import DeformError
from .rotations import polar_rotations, polar_rotations_reference

WEIGHTS = ("cotangent", "uniform")


@dataclass
class ArapConfig:
    """How an ARAP deformation is solved.

    ``weights``: "cotangent" (clamped to be positive; the usual ARAP weights, independent of how the
    surface is triangulated) or "uniform" (1 per edge).  ``iterations``: local-global iterations per
    :meth:`ArapSolver.solve` (a drag warm-starts from the previous move, so a few per move suffice; a
    solve from rest needs more for a large rotation).  ``tolerance``: stop early once no vertex moved by
    more than this fraction of the mean edge length in an iteration.  ``cage_vertices``: 0 solves on the
    mesh itself; N > 0 solves on a cage of about N of its vertices and carries the result to all of them
    (the preview resolution).  ``cage_neighbours``: cage vertices blended per mesh vertex.
    ``coarse_start``: a solve that starts from rest (no previous solve to warm-start from) first solves
    on a cage of this many vertices (``coarse_iterations`` iterations) and starts from its result:
    local-global iterations remove large-scale error slowly, so from rest a big bend of a fine mesh
    needs hundreds of them, and the cage provides the large scale cheaply (0: start from rest).
    ``energies``: record the energy after every iteration (``ArapResult.energies``; costs ~10%)."""

    weights: Literal["cotangent", "uniform"] = "cotangent"
    iterations: int = 8
    tolerance: float = 1e-4
    cage_vertices: int = 0
    cage_neighbours: int = 8
    coarse_start: int = 2000
    coarse_iterations: int = 100
    energies: bool = False

    def __post_init__(self):
        if self.weights not in WEIGHTS:
            raise DeformError(f"ArapConfig.weights must be one of {WEIGHTS}, got {self.weights!r}")
        if self.iterations < 1:
            raise DeformError(f"ArapConfig.iterations must be at least 1, got {self.iterations}")
        if self.cage_vertices < 0:
            raise DeformError(f"ArapConfig.cage_vertices must be 0 (full mesh) or a vertex count, "
                              f"got {self.cage_vertices}")
        if self.coarse_start < 0 or self.coarse_iterations < 1:
            raise DeformError("ArapConfig.coarse_start must be >= 0 and coarse_iterations >= 1")
        if self.cage_neighbours < 1:
            raise DeformError(f"ArapConfig.cage_neighbours must be at least 1, got {self.cage_neighbours}")


# ----------------------------------------------------------------------------------------- weights
def edge_weights(rest: np.ndarray, faces: np.ndarray, kind: str = "cotangent"):
    """Undirected edges (E,2) (i<j) of ``faces`` and their ARAP weights (E,).

    "cotangent": w_ij = (cot a + cot b)/2 over the angles opposite the edge, clamped to
    [1e-3, 1e3] x the median weight (negative weights of obtuse triangles would break the local step's
    maximisation, and a degenerate triangle's infinite cotangent the solve); "uniform": 1."""
    from ..mesh import unique_edges

    f = np.asarray(faces, np.int64).reshape(-1, 3)
    edges = unique_edges(f)
    if kind == "uniform" or len(edges) == 0:
        return edges, np.ones(len(edges))
    if kind != "cotangent":
        raise DeformError(f"unknown ARAP weights {kind!r}; use one of {WEIGHTS}")
    p = np.asarray(rest, np.float64)
    n = len(p)
    cots = []
    pairs = []
    for k in range(3):   # the corner k of each face, opposite the edge (k+1, k+2)
        a, b, c = f[:, k], f[:, (k + 1) % 3], f[:, (k + 2) % 3]
        u, v = p[b] - p[a], p[c] - p[a]
        cross = np.linalg.norm(np.cross(u, v), axis=1)
        dot = (u * v).sum(1)
        ok = cross > 1e-12 * np.maximum((u * u).sum(1) + (v * v).sum(1), 1e-300)
        cots.append(np.where(ok, dot / np.where(ok, cross, 1.0), 0.0))
        pairs.append(np.sort(np.stack([b, c], 1), axis=1))
    keys = np.concatenate(pairs)
    keys = keys[:, 0] * n + keys[:, 1]
    pos = np.searchsorted(edges[:, 0] * n + edges[:, 1], keys)
    w = 0.5 * np.bincount(pos, weights=np.concatenate(cots), minlength=len(edges))
    med = float(np.median(np.abs(w[w != 0]))) if np.any(w != 0) else 1.0
    return edges, np.clip(w, 1e-3 * med, 1e3 * med)


# ----------------------------------------------------------------------------------------- the energy
class ArapTerms:
    """The pieces of the ARAP energy on rest points ``rest`` (n,3) joined by ``edges`` (E,2) with
    ``weights`` (E,) (1 when None): the weighted graph Laplacian, the local step (covariances and their
    rotations), the global step's right-hand side and the energy.

    Every per-edge sum runs as three sparse (n,n) products with K_c[i,j] = w_ij (p_i - p_j)_c, so no
    (E,3,3) array is made (the per-edge gathers stay as ``*_reference`` functions)."""

    def __init__(self, rest: np.ndarray, edges: np.ndarray, weights: Optional[np.ndarray] = None):
        import scipy.sparse as sp

        self.rest = np.asarray(rest, np.float64)
        self.edges = np.asarray(edges, np.int64).reshape(-1, 2)
        n = len(self.rest)
        E = len(self.edges)
        self.weights = np.ones(E) if weights is None else np.asarray(weights, np.float64).reshape(E)
        i, j = self.edges[:, 0], self.edges[:, 1]
        w = self.weights
        rows, cols = np.concatenate([i, j]), np.concatenate([j, i])
        ww = np.concatenate([w, w])
        A = sp.csr_matrix((ww, (rows, cols)), shape=(n, n))
        self.laplacian = (sp.diags(np.asarray(A.sum(1)).ravel()) - A).tocsr()
        e = self.rest[rows] - self.rest[cols]                      # p_i - p_j per directed edge
        self._K = [sp.csr_matrix((ww * e[:, c], (rows, cols)), shape=(n, n)) for c in range(3)]
        self._d = np.stack([np.asarray(K.sum(1)).ravel() for K in self._K], 1)   # sum_j w_ij (p_i - p_j)
        self._rest_term = 2.0 * float((w * ((self.rest[i] - self.rest[j]) ** 2).sum(1)).sum())

    def covariances(self, x: np.ndarray) -> np.ndarray:
        """(n,3,3) S_i = sum_j w_ij (x_i - x_j)(p_i - p_j)^T."""
        x = np.asarray(x, np.float64)
        S = np.empty((len(x), 3, 3))
        for c in range(3):
            S[:, :, c] = x * self._d[:, c:c + 1] - self._K[c] @ x
        return S

    def rotations(self, x: np.ndarray) -> np.ndarray:
        """The local step: per vertex the rotation (rest -> current) nearest to its covariance."""
        return polar_rotations(self.covariances(x))

    def rhs(self, R: np.ndarray) -> np.ndarray:
        """(n,3) b_i = sum_j w_ij (R_i + R_j)/2 (p_i - p_j): the global step's right-hand side."""
        R = np.asarray(R, np.float64)
        out = np.einsum("nab,nb->na", R, self._d)
        for c in range(3):
            out += self._K[c] @ R[:, :, c]
        return 0.5 * out

    def rows(self, idx: np.ndarray) -> "TermRows":
        """:meth:`covariances` and :meth:`rhs` restricted to the vertices ``idx`` (their rows of the
        sparse products made once here)."""
        return TermRows(self, idx)

    def energy(self, x: np.ndarray, R: np.ndarray, S: Optional[np.ndarray] = None) -> float:
        """E(x, R) (each edge counted from both ends), for rotations R."""
        x = np.asarray(x, np.float64)
        S = self.covariances(x) if S is None else S
        xLx = float((x * (self.laplacian @ x)).sum())              # sum over edges of w |x_i - x_j|^2
        return max(0.0, 2.0 * xLx + self._rest_term - 2.0 * float(np.einsum("nab,nab->", R, S)))


class TermRows:
    """The rows ``idx`` of :meth:`ArapTerms.covariances` and :meth:`ArapTerms.rhs` (the solver needs the
    right-hand side at the free vertices only, and rotations only where a free vertex can see them)."""

    def __init__(self, terms: ArapTerms, idx: np.ndarray):
        self.idx = np.asarray(idx, np.int64)
        self._K = [K[self.idx] for K in terms._K]
        self._d = terms._d[self.idx]

    def covariances(self, x: np.ndarray) -> np.ndarray:
        xi = x[self.idx]
        S = np.empty((len(self.idx), 3, 3))
        for c in range(3):
            S[:, :, c] = xi * self._d[:, c:c + 1] - self._K[c] @ x
        return S

    def rhs(self, R: np.ndarray) -> np.ndarray:
        out = np.einsum("nab,nb->na", R[self.idx], self._d)
        for c in range(3):
            out += self._K[c] @ R[:, :, c]
        return 0.5 * out


def covariances_reference(rest, x, edges, weights=None) -> np.ndarray:
    """Plain per-edge reference of :meth:`ArapTerms.covariances`."""
    rest, x = np.asarray(rest, np.float64), np.asarray(x, np.float64)
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    w = np.ones(len(edges)) if weights is None else np.asarray(weights, np.float64)
    S = np.zeros((len(rest), 3, 3))
    i, j = edges[:, 0], edges[:, 1]
    outer = w[:, None, None] * (x[i] - x[j])[:, :, None] * (rest[i] - rest[j])[:, None, :]
    np.add.at(S, i, outer)
    np.add.at(S, j, outer)          # (x_j - x_i)(p_j - p_i)^T is the same matrix
    return S


def rhs_reference(rest, R, edges, weights=None) -> np.ndarray:
    """Plain per-edge reference of :meth:`ArapTerms.rhs`."""
    rest, R = np.asarray(rest, np.float64), np.asarray(R, np.float64)
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    w = np.ones(len(edges)) if weights is None else np.asarray(weights, np.float64)
    i, j = edges[:, 0], edges[:, 1]
    r = w[:, None] * np.einsum("eab,eb->ea", 0.5 * (R[i] + R[j]), rest[i] - rest[j])
    b = np.zeros((len(rest), 3))
    np.add.at(b, i, r)
    np.add.at(b, j, -r)
    return b


def energy_reference(rest, x, R, edges, weights=None) -> float:
    """Plain reference of :meth:`ArapTerms.energy`: the sum over both ends of every edge."""
    rest, x, R = (np.asarray(a, np.float64) for a in (rest, x, R))
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    w = np.ones(len(edges)) if weights is None else np.asarray(weights, np.float64)
    total = 0.0
    for a, b in ((0, 1), (1, 0)):
        i, j = edges[:, a], edges[:, b]
        r = (x[i] - x[j]) - np.einsum("eab,eb->ea", R[i], rest[i] - rest[j])
        total += float((w * (r * r).sum(1)).sum())
    return total


# ----------------------------------------------------------------------------------------- solving
def factorise_spd(A):
    """A factorisation of the sparse symmetric positive definite ``A`` (the free vertices' Laplacian) with
    a ``solve(b)`` method: scipy's SuperLU in symmetric mode (minimum-degree ordering of A + A^T, no
    pivoting, which SPD matrices do not need), so that U has the structure of L^T as in a Cholesky
    factorisation. On lego's scaffold (162k unknowns) that is half the fill of the unsymmetric COLAMD
    factorisation (:func:`factorise_reference`), so a solve reads half the numbers. Falls back to the
    reference where the symmetric factorisation fails (a zero pivot: the matrix is not positive definite)."""
    from scipy.sparse.linalg import splu

    try:
        return splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                    options={"SymmetricMode": True})
    except RuntimeError:
        return factorise_reference(A)


def factorise_reference(A):
    """The plain factorisation: scipy's SuperLU with its default partial pivoting and COLAMD ordering."""
    from scipy.sparse.linalg import splu

    return splu(A, permc_spec="COLAMD")


class ConstrainedArap:
    """Local-global ARAP on a graph with a fixed set of constrained vertices; the free vertices' Laplacian
    is factorised once here.  A connected component with no constrained vertex cannot be placed (its
    position is free up to a translation): it is held at rest (``held``)."""

    def __init__(self, terms: ArapTerms, constrained: np.ndarray):
        import scipy.sparse as sp
        from scipy.sparse.csgraph import connected_components

        self.terms = terms
        n = len(terms.rest)
        constrained = np.asarray(constrained, np.int64)
        _, label = connected_components(sp.csr_matrix(terms.laplacian), directed=False)
        has = np.zeros(label.max() + 1 if n else 0, bool)
        has[label[constrained]] = True
        self.constrained = constrained
        self.held = np.nonzero(~has[label])[0] if n else np.zeros(0, np.int64)
        self.fixed = np.concatenate([constrained, self.held])
        mask = np.zeros(n, bool)
        mask[self.fixed] = True
        self.free = np.nonzero(~mask)[0]
        L = terms.laplacian
        Lf = L[self.free]
        self.L_fc = Lf[:, self.fixed].tocsr()
        self.lu = None
        t0 = time.perf_counter()
        if len(self.free):
            self.lu = factorise_spd(Lf[:, self.free].tocsc())
        self.factor_seconds = time.perf_counter() - t0
        # only the free vertices' rows of the right-hand side are used, and they read the rotations of
        # the free vertices and of their neighbours (the *active* ones): the other constrained vertices'
        # rotations are computed once per solve, for the result, not every iteration
        near = np.zeros(n, bool)
        near[self.free] = True
        near[L[self.free].indices] = True
        self.active = np.nonzero(near)[0]
        self.inactive = np.nonzero(~near)[0]
        self._rows_free = terms.rows(self.free)
        self._rows_active = terms.rows(self.active)
        self._rows_inactive = terms.rows(self.inactive)
        adj = L[self.inactive].tocsr(copy=True)          # each inactive row and its neighbours
        adj.data = np.ones_like(adj.data)
        self._inactive_adj = adj
        self._inactive_cache = None
        e = terms.edges
        self.unit = float(np.linalg.norm(terms.rest[e[:, 0]] - terms.rest[e[:, 1]], axis=1).mean()) \
            if len(e) else 1.0

    def solve(self, targets: np.ndarray, x0: np.ndarray, R0: np.ndarray, iterations: int,
              tolerance: float, energies: bool = True):
        """Constrained vertices at ``targets``; start from positions ``x0`` with rotations ``R0``.
        Returns (x, R, energies per iteration, iterations run)."""
        x = np.array(x0, np.float64)
        R = np.array(R0, np.float64)
        xc = np.concatenate([np.asarray(targets, np.float64).reshape(-1, 3), self.terms.rest[self.held]])
        x[self.fixed] = xc
        record = []
        it = 0
        if self.lu is None:   # everything constrained
            R = self.terms.rotations(x)
            return x, R, [self.terms.energy(x, R)] if energies else [], 0
        bc = self.L_fc @ xc
        for it in range(1, iterations + 1):
            b = self._rows_free.rhs(R) - bc
            xf = self.lu.solve(np.ascontiguousarray(b))
            moved = float(np.abs(xf - x[self.free]).max())
            x[self.free] = xf
            if energies:   # every rotation, for the energy
                S = self.terms.covariances(x)
                R = polar_rotations(S)
                record.append(self.terms.energy(x, R, S))
            else:
                R[self.active] = polar_rotations(self._rows_active.covariances(x))
            if moved < tolerance * self.unit:
                break
        if not energies and len(self.inactive):
            R[self.inactive] = self._inactive_rotations(x)
        return x, R, record, it

    def _inactive_rotations(self, x: np.ndarray) -> np.ndarray:
        """Rotations of the inactive vertices: they depend on the constrained positions only, so only
        the rows next to a constrained vertex whose target changed since the last solve are recomputed
        (a drag moves the handles; the anchors' inner rows stay)."""
        xf = x[self.fixed]
        cache = self._inactive_cache
        if cache is None:
            redo = np.arange(len(self.inactive))
            Ri = np.empty((len(self.inactive), 3, 3))
        else:
            last, Ri = cache
            Ri = Ri.copy()
            changed = np.zeros(len(x))
            changed[self.fixed[(xf != last).any(1)]] = 1.0
            redo = np.nonzero((self._inactive_adj @ changed) > 0)[0]
        if len(redo):
            sub = self._rows_inactive if len(redo) == len(self.inactive) else self.terms.rows(self.inactive[redo])
            Ri[redo] = polar_rotations(sub.covariances(x))
        self._inactive_cache = (xf.copy(), Ri)
        return Ri

    def solve_reference(self, targets: np.ndarray, x0: np.ndarray, R0: np.ndarray, iterations: int):
        """The plain local-global loop of :meth:`solve` (every vertex's covariance, rotation and
        right-hand side each iteration; scipy's ``spsolve`` for the global step; no early stop)."""
        from scipy.sparse.linalg import spsolve

        x = np.array(x0, np.float64)
        R = np.array(R0, np.float64)
        xc = np.concatenate([np.asarray(targets, np.float64).reshape(-1, 3), self.terms.rest[self.held]])
        x[self.fixed] = xc
        L = self.terms.laplacian
        A = L[self.free][:, self.free].tocsc()
        for _ in range(iterations):
            b = rhs_reference(self.terms.rest, R, self.terms.edges, self.terms.weights)[self.free] - self.L_fc @ xc
            x[self.free] = spsolve(A, b)
            R = polar_rotations_reference(covariances_reference(self.terms.rest, x, self.terms.edges,
                                                                self.terms.weights))
        return x, R


@dataclass
class ArapResult:
    """One solve: ``vertices`` (N,3) (float64; float32 in cage mode, carried for the viewport),
    ``rotations`` (N,3,3) per-vertex rest -> deformed rotations (computed on first use in cage mode),
    ``energies`` after each iteration (of the system solved: the cage's in cage mode; with
    ``ArapConfig.energies``, else empty), ``iterations`` run, ``seconds`` taken."""

    vertices: np.ndarray
    energies: list
    iterations: int
    seconds: float
    _rotations: Optional[np.ndarray] = dc_field(default=None, repr=False)
    _blend: Optional[np.ndarray] = dc_field(default=None, repr=False)

    @property
    def rotations(self) -> np.ndarray:
        if self._rotations is None:
            self._rotations = polar_rotations(self._blend)
            self._blend = None
        return self._rotations


def _index_set(ix, n: int, what: str) -> np.ndarray:
    a = np.asarray(ix)
    if a.size == 0:
        return np.zeros(0, np.int64)
    if a.dtype == bool:
        if a.shape != (n,):
            raise DeformError(f"{what}: a boolean mask needs one entry per vertex ({n}), got shape {a.shape}")
        return np.nonzero(a)[0]
    if not np.issubdtype(a.dtype, np.integer):
        raise DeformError(f"{what}: give vertex indices (integers) or a boolean mask, got {a.dtype}")
    a = a.astype(np.int64).reshape(-1)
    bad = (a < 0) | (a >= n)
    if bad.any():
        raise DeformError(f"{what}: vertex index {int(a[bad][0])} is out of range (the mesh has {n} vertices, "
                          f"indices 0..{n - 1}); check that the vertex group belongs to this object")
    return np.unique(a)


def _handle_groups(handles, n: int) -> list:
    """``handles``: one index array / mask, or a list of them (groups that move with their own
    transform) -> list of sorted unique index arrays."""
    if handles is None:
        raise DeformError("ARAP needs handles: the vertices to move (a vertex group)")
    if isinstance(handles, (list, tuple)) and len(handles) and not np.isscalar(handles[0]):
        groups = [_index_set(h, n, f"handle group {g}") for g, h in enumerate(handles)]
    else:
        groups = [_index_set(handles, n, "handles")]
    for g, h in enumerate(groups):
        if len(h) == 0:
            raise DeformError(f"handle group {g} is empty: assign at least one vertex to it" if len(groups) > 1
                              else "the handle set is empty: assign the vertices to move to the handle group")
    allh = np.concatenate(groups)
    if len(np.unique(allh)) != len(allh):
        raise DeformError("handle groups overlap: a vertex can belong to one handle group only")
    return groups


class ArapSolver:
    """ARAP deformation of a mesh with *anchors* (stay at rest) and *handles* (moved), factorised once.

    >>> solver = ArapSolver(rest, faces, anchors, handles, ArapConfig())
    >>> res = solver.solve(handle_positions)        # (H,3) targets of solver.handles, in that order
    >>> res.vertices, res.rotations

    ``anchors``: vertex indices or a boolean mask (may be empty: then only the handles hold the mesh);
    ``handles``: indices/mask, or a list of them (groups, see :meth:`targets_from_transforms`).  The two
    sets must not overlap.  ``solver.handles`` is the handles' order for ``handle_positions``.  Solves
    warm-start from the previous solve (a drag); ``warm_start=False`` starts from rest (the same result
    for the same input, as an animation render wants).  A connected piece of the mesh that holds neither
    anchors nor handles stays at rest (``solver.held``)."""

    def __init__(self, rest_vertices, faces, anchors, handles, config: Optional[ArapConfig] = None):
        t0 = time.perf_counter()
        self.config = config or ArapConfig()
        rest = np.asarray(rest_vertices, np.float64)
        if rest.ndim != 2 or rest.shape[1] != 3 or len(rest) == 0:
            raise DeformError(f"rest vertices must be a non-empty (N,3) array, got shape {rest.shape}")
        if not np.isfinite(rest).all():
            raise DeformError("rest vertices contain NaN/inf")
        n = len(rest)
        faces = np.asarray(faces, np.int64).reshape(-1, 3)
        if len(faces) and (faces.min() < 0 or faces.max() >= n):
            raise DeformError(f"faces index vertex {int(faces.max())} but there are {n} vertices")
        if len(faces) == 0:
            raise DeformError("the mesh has no faces: ARAP needs the surface's triangles")
        self.rest, self.faces = rest, faces
        self.anchors = _index_set(anchors if anchors is not None else [], n, "anchors")
        self.groups = _handle_groups(handles, n)
        self.handles = np.concatenate(self.groups)
        both = np.intersect1d(self.anchors, self.handles)
        if len(both):
            raise DeformError(f"{len(both)} vertices are both anchors and handles (e.g. vertex {int(both[0])}): "
                              "a vertex either stays (anchor) or moves (handle); remove it from one of the groups")
        cfg = self.config
        self.cage = None
        if cfg.cage_vertices and cfg.cage_vertices < n:
            from .cage import build_cage

            self.cage = build_cage(rest, faces, cfg.cage_vertices, cfg.weights, cfg.cage_neighbours,
                                   keep=[self.anchors, *self.groups])
            pts = rest[self.cage.samples]
            terms = ArapTerms(pts, self.cage.edges, self.cage.weights)
            slot = np.full(n, -1, np.int64)
            slot[self.cage.samples] = np.arange(len(self.cage.samples))
            hpos = np.full(n, -1, np.int64)
            hpos[self.handles] = np.arange(len(self.handles))
            ca, ch = slot[self.anchors], slot[self.handles]
            self._c_anchor = ca[ca >= 0]
            self._c_handle, self._c_handle_src = ch[ch >= 0], hpos[self.handles[ch >= 0]]
            constrained = np.concatenate([self._c_anchor, self._c_handle])
        else:
            edges, w = edge_weights(rest, faces, cfg.weights)
            terms = ArapTerms(rest, edges, w)
            constrained = np.concatenate([self.anchors, self.handles])
        self.core = ConstrainedArap(terms, constrained)
        self._x = None
        self._R = None
        self._coarse = None
        self.setup_seconds = time.perf_counter() - t0

    # -------------------------------------------------------------------------------------------
    @property
    def held(self) -> np.ndarray:
        """Vertices held at rest because their connected piece has no anchor or handle (in cage mode:
        the cage vertices')."""
        return self.core.held if self.cage is None else self.cage.samples[self.core.held]

    @property
    def num_unknowns(self) -> int:
        return len(self.core.free)

    def targets_from_transforms(self, transforms) -> np.ndarray:
        """(H,3) handle positions: each handle group's rest positions moved by its 4x4 (or 3x4) matrix
        (one matrix for all groups, or one per group)."""
        M = np.asarray(transforms, np.float64)
        if M.ndim == 2:
            M = np.broadcast_to(M, (len(self.groups),) + M.shape)
        if M.ndim != 3 or M.shape[1:] not in ((4, 4), (3, 4)) or len(M) != len(self.groups):
            raise DeformError(f"give one 4x4 transform or one per handle group ({len(self.groups)}), "
                              f"got shape {np.shape(transforms)}")
        if not np.isfinite(M).all():
            raise DeformError("a handle transform contains NaN/inf")
        return np.concatenate([self.rest[g] @ m[:3, :3].T + m[:3, 3] for g, m in zip(self.groups, M)])

    def reset(self) -> None:
        """Forget the previous solve (the next one starts from rest)."""
        self._x = self._R = None

    def solve(self, handle_positions, iterations: Optional[int] = None, warm_start: bool = True) -> ArapResult:
        """Deform: handles at ``handle_positions`` (H,3) (the order of ``self.handles``), anchors at
        rest; ``iterations`` local-global iterations (default ``config.iterations``)."""
        t0 = time.perf_counter()
        q = np.asarray(handle_positions, np.float64)
        if q.shape != (len(self.handles), 3):
            raise DeformError(f"handle positions must have shape ({len(self.handles)}, 3) (one per handle "
                              f"vertex, in solver.handles order), got {q.shape}")
        if not np.isfinite(q).all():
            raise DeformError("handle positions contain NaN/inf")
        iters = self.config.iterations if iterations is None else int(iterations)
        if iters < 1:
            raise DeformError(f"iterations must be at least 1, got {iters}")
        core = self.core
        pts = core.terms.rest
        if self.cage is None:
            cq = q
            targets = np.concatenate([self.rest[self.anchors], cq])
        else:
            targets = np.concatenate([pts[self._c_anchor], q[self._c_handle_src]])
        if warm_start and self._x is not None:
            x0, R0 = self._x, self._R
        elif len(self.anchors) == 0:
            # handles alone: start from their best rigid motion (exact when they moved rigidly)
            src = self.rest[self.handles]
            ms, mq = src.mean(0), q.mean(0)
            Rg = polar_rotations(((q - mq).T @ (src - ms))[None])[0]
            x0 = (pts - ms) @ Rg.T + mq
            R0 = np.broadcast_to(Rg, (len(pts), 3, 3))
        elif self.config.coarse_start and len(pts) > 2 * self.config.coarse_start:
            if self._coarse is None:
                self._coarse = ArapSolver(self.rest, self.faces, self.anchors, self.groups,
                                          replace(self.config, cage_vertices=self.config.coarse_start,
                                                  coarse_start=0))
            rc = self._coarse.solve(q, iterations=self.config.coarse_iterations, warm_start=False)
            if self.cage is None:
                x0, R0 = rc.vertices, rc.rotations
            else:   # the coarse result at this cage's vertices
                x0, R0 = rc.vertices[self.cage.samples], rc.rotations[self.cage.samples]
        else:
            x0, R0 = pts, np.broadcast_to(np.eye(3), (len(pts), 3, 3))
        x, R, energies, it = core.solve(targets, x0, R0, iters, self.config.tolerance, self.config.energies)
        self._x, self._R = x, R
        if self.cage is None:
            return ArapResult(x, energies, it, time.perf_counter() - t0, _rotations=R)
        V, blend = self.cage.carry(x, R, self.rest)
        V[self.anchors] = self.rest[self.anchors]
        V[self.handles] = q
        return ArapResult(V, energies, it, time.perf_counter() - t0, _blend=blend)


def arap(field, anchors, handles, transforms, config: Optional[ArapConfig] = None,
         iterations: Optional[int] = None) -> ArapResult:
    """Deform ``field`` as rigidly as possible from its rest pose: ``anchors`` stay, each handle group
    moves by its transform (one 4x4 world-space matrix, or one per group), and the field's vertices are
    set (``field.set_vertices``: normals, texture frames, neighbour index and occupancy follow).
    Returns the :class:`ArapResult` (vertices, per-vertex rotations).  Solved from rest, so the same
    input gives the same result."""
    rest = field.rest_vertices
    rest = rest.detach().cpu().numpy() if hasattr(rest, "detach") else np.asarray(rest)
    faces = field.faces
    faces = faces.detach().cpu().numpy() if hasattr(faces, "detach") else np.asarray(faces)
    cfg = config or ArapConfig(iterations=50)
    solver = ArapSolver(rest, faces, anchors, handles, cfg)
    res = solver.solve(solver.targets_from_transforms(transforms), iterations=iterations, warm_start=False)
    field.set_vertices(res.vertices.astype(np.float32))
    return res


__all__ = ["ArapConfig", "ArapResult", "ArapSolver", "ArapTerms", "ConstrainedArap", "arap", "edge_weights"]
