"""Aligning one surface region onto another: a similarity transform (Umeyama), an automatic initial
guess without correspondences (centroids, principal axes, extents), rigid ICP, and an
as-rigid-as-possible regularised non-rigid ICP over the source region's mesh edges.

Everything here works on plain numpy arrays (points, edges) and knows nothing about fields.
"""
from __future__ import annotations

from dataclasses import dataclass, field as dc_field
from itertools import product
from typing import Callable, Optional

import numpy as np

from ..deform.rotations import polar_rotations, polar_rotations_reference  # noqa: F401  (re-exported)
from ..errors import EditError


@dataclass
class Similarity:
    """x -> scale * R @ x + t."""

    scale: float
    R: np.ndarray   # (3,3) proper rotation
    t: np.ndarray   # (3,)

    def apply(self, x: np.ndarray) -> np.ndarray:
        return (self.scale * (np.asarray(x, np.float64) @ self.R.T) + self.t).astype(np.float64)

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix."""
        M = np.eye(4)
        M[:3, :3] = self.scale * self.R
        M[:3, 3] = self.t
        return M

    @staticmethod
    def identity() -> "Similarity":
        return Similarity(1.0, np.eye(3), np.zeros(3))


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True,
            weights: Optional[np.ndarray] = None) -> Similarity:
    """Least-squares similarity (Umeyama 1991) mapping points ``src`` (P,3) onto ``dst`` (P,3).

    ``weights`` (P,) optional non-negative point weights.  Needs at least 3 non-collinear pairs.
    """
    src = np.asarray(src, np.float64).reshape(-1, 3)
    dst = np.asarray(dst, np.float64).reshape(-1, 3)
    if src.shape != dst.shape:
        raise EditError(f"umeyama: {len(src)} source points but {len(dst)} target points; give pairs")
    if len(src) < 3:
        raise EditError(f"umeyama: {len(src)} point pairs given; at least 3 are needed")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, np.float64).reshape(-1)
    if w.sum() <= 0:
        raise EditError("umeyama: all weights are zero")
    w = w / w.sum()
    mu_s, mu_d = w @ src, w @ dst
    xs, xd = src - mu_s, dst - mu_d
    var_s = float(w @ (xs * xs).sum(1))
    cov = (xd * w[:, None]).T @ xs
    U, D, Vt = np.linalg.svd(cov)
    if var_s <= 1e-30 or D[1] <= 1e-12 * max(D[0], 1e-300):
        raise EditError("umeyama: the source points are (nearly) collinear or coincide; give at least 3 "
                         "pairs of points that span a triangle")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    scale = float((D * np.diag(S)).sum() / var_s) if with_scale else 1.0
    t = mu_d - scale * R @ mu_s
    return Similarity(scale, R, t)


def _nn(points: np.ndarray):
    from ..field.knn import kd_tree

    return kd_tree(np.ascontiguousarray(points, dtype=np.float64))


def _query(tree, x: np.ndarray, k: int = 1):
    d, i = tree.query(np.ascontiguousarray(x, dtype=np.float64), k=k)
    return np.asarray(d), np.asarray(i).astype(np.int64)


def principal_frame(points: np.ndarray):
    """(centroid (3,), axes (3,3) columns sorted by decreasing spread, rms radius)."""
    p = np.asarray(points, np.float64)
    c = p.mean(0)
    x = p - c
    evals, evecs = np.linalg.eigh(x.T @ x / max(len(p), 1))
    order = np.argsort(evals)[::-1]
    return c, evecs[:, order], float(np.sqrt(max(evals.sum(), 1e-30)))


def _proper_signed_permutations() -> list:
    """The 24 rotations that map the coordinate axes onto (signed) coordinate axes; the four that keep
    every axis on itself (sign flips of pairs of axes) first."""
    out = []
    for perm in ((0, 1, 2), (1, 0, 2), (0, 2, 1), (2, 1, 0), (1, 2, 0), (2, 0, 1)):
        for signs in product((1.0, -1.0), repeat=3):
            P = np.zeros((3, 3))
            P[np.arange(3), perm] = signs
            if np.linalg.det(P) > 0:
                out.append(P)
    return out


def _kabsch(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """The proper rotation R minimising sum |R p_i - q_i|^2 (both point sets already centred)."""
    U, _, Vt = np.linalg.svd(Q.T @ P)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    return U @ D @ Vt


def _trimmed(d: np.ndarray) -> np.ndarray:
    return d <= np.quantile(d, TRIM) if len(d) > 10 else np.ones(len(d), bool)


def _centred_icp(a: np.ndarray, dst: np.ndarray, cd: np.ndarray, scale: float, R: np.ndarray,
                 iterations: int, tree, a_normals: Optional[np.ndarray] = None,
                 dst_normals: Optional[np.ndarray] = None):
    """ICP for the rotation alone about fixed centroids: x = scale R a + cd, with ``a`` the source points
    minus their centroid.  Matches run both ways (every aligned source point to its nearest target point
    and every target point to its nearest aligned source point, each trimmed to its closest 90%), so a
    source larger than the target (or smaller) is held by the target's points too.  Point-to-point
    (Kabsch) without normals; point-to-plane (linearised rotation, least squares) with both normal sets,
    which reaches the exact pose of a copy where point-to-point stalls at the vertex spacing.
    Returns (R, score): the score is the sum of the two trimmed mean nearest-neighbour distances."""
    plane = a_normals is not None and dst_normals is not None
    for _ in range(iterations):
        x = scale * a @ R.T + cd
        d1, i1 = _query(tree, x)
        d2, i2 = _query(_nn(x), dst)
        k1, k2 = _trimmed(d1), _trimmed(d2)
        if plane:
            # one row per match: n . (x + w x (x - cd) - q) = 0, linear in the small rotation w
            xs = np.concatenate([x[k1], x[i2[k2]]])
            q = np.concatenate([dst[i1[k1]], dst[k2]])
            n = np.concatenate([dst_normals[i1[k1]], a_normals[i2[k2]] @ R.T])
            A = np.cross(xs - cd, n)
            w = np.linalg.lstsq(A, -(n * (xs - q)).sum(1), rcond=None)[0]
            step = _rotvec(w)
        else:
            P = np.concatenate([a[k1], a[i2[k2]]])
            Q = np.concatenate([dst[i1[k1]], dst[k2]]) - cd
            step = _kabsch(scale * P @ R.T, Q)
        R = step @ R
        if np.abs(step - np.eye(3)).max() < 1e-12:   # converged (a copy's pose to float rounding)
            break
    x = scale * a @ R.T + cd
    d1, _ = _query(tree, x)
    d2, _ = _query(_nn(x), dst)
    return R, float(d1[_trimmed(d1)].mean() + d2[_trimmed(d2)].mean())


def initial_alignment(src: np.ndarray, dst: np.ndarray, icp_iterations: int = 10,
                      dst_normals: Optional[np.ndarray] = None, max_points: int = 2000,
                      src_normals: Optional[np.ndarray] = None) -> Similarity:
    """An automatic similarity from ``src`` onto ``dst`` (no correspondences needed).

    The centroid of ``src`` goes onto the centroid of ``dst`` and its rms radius (extent) onto the
    target's: both are fixed, only the rotation is searched.  Both point sets must be in one coordinate
    frame (a swap passes both fields' rest vertices).  Rotation candidates: the principal axes of the
    source mapped onto the target's in each of the 24 ways that send axes onto signed axes (the signs
    of principal axes are arbitrary, and near-equal spreads leave their order undetermined too; regions
    of different shapes may fit best with axes of different rank).  Each candidate gets 3 iterations of ICP for the
    rotation about the fixed centroids, matching both ways, on subsamples of ``max_points / 4``; the
    best three get ``icp_iterations`` more on subsamples of ``max_points`` and the best of them
    ``3 * icp_iterations`` on 10x larger ones (point-to-plane when both ``src_normals`` and
    ``dst_normals`` are given).

    Why fixed centroids: a free translation is not constrained when the regions differ in shape; ICP
    then slides the source along the target's surface and off it (docs/editing.md, "When the alignment
    fails").  A free scale likewise collapses onto a patch of the target, so the scale is the extents'
    ratio.  Use point pairs (:func:`umeyama`) where the regions correspond only in part.
    """
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    cs, As, rs = principal_frame(src)
    cd, Ad, rd = principal_frame(dst)
    As, Ad = As * np.sign(np.linalg.det(As)), Ad * np.sign(np.linalg.det(Ad))   # right-handed: Ad P As^T proper
    scale = rd / rs
    a = src - cs
    # candidates told apart on small subsamples (wrong rotations put points off the surface, where
    # nearest-neighbour queries are slowest), the best three refined on larger ones
    hs, hd = _subsample(len(src), max(max_points // 4, 50)), _subsample(len(dst), max(max_points // 4, 50))
    tree = _nn(dst[hd])
    scored = []
    for P in _proper_signed_permutations():
        R, err = _centred_icp(a[hs], dst[hd], cd, scale, Ad @ P @ As.T, 3, tree)
        scored.append((err, R))
    scored.sort(key=lambda e: e[0])
    ss, sd = _subsample(len(src), max_points), _subsample(len(dst), max_points)
    tree = _nn(dst[sd])
    best = [_centred_icp(a[ss], dst[sd], cd, scale, R, icp_iterations, tree) for _, R in scored[:3]]
    R = min(best, key=lambda e: e[1])[0]
    fs, fd = _subsample(len(src), 10 * max_points), _subsample(len(dst), 10 * max_points)
    plane = src_normals is not None and dst_normals is not None
    R, _ = _centred_icp(a[fs], dst[fd], cd, scale, R, 3 * icp_iterations, _nn(dst[fd]),
                        a_normals=np.asarray(src_normals, np.float64)[fs] if plane else None,
                        dst_normals=np.asarray(dst_normals, np.float64)[fd] if plane else None)
    return Similarity(scale, R, cd - scale * R @ cs)


def _subsample(n: int, m: int) -> np.ndarray:
    """At most ``m`` of ``n`` indices, evenly spread (deterministic)."""
    if n <= m:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, m).round().astype(np.int64))


TRIM = 0.9   # ICP uses the closest 90% of matches: parts of one region with no counterpart in the other


def _rotvec(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    if th < 1e-15:
        return np.eye(3)
    k = w / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def rigid_icp(src: np.ndarray, dst: np.ndarray, init: Similarity, iterations: int = 20,
              with_scale: bool = True, tree=None, dst_normals: Optional[np.ndarray] = None):
    """Refine ``init`` by ICP; returns (Similarity, mean nearest-neighbour distance).

    Point-to-point (closest points, Umeyama) without ``dst_normals``; point-to-plane (linearised
    rotation, translation and scale, least squares) with them, which does not stall where the vertex
    sampling makes point-to-point distances flat (sliding along a smooth surface).
    """
    tree = tree if tree is not None else _nn(dst)
    dst = np.asarray(dst, np.float64)
    normals = None if dst_normals is None else np.asarray(dst_normals, np.float64)
    T = init
    for _ in range(iterations):
        x = T.apply(src)
        d, i = _query(tree, x)
        keep = d <= np.quantile(d, TRIM) if len(d) > 10 else np.ones(len(d), bool)
        if normals is None:
            try:
                step = umeyama(x[keep], dst[i[keep]], with_scale=with_scale)
            except ValueError:
                break
        else:
            xs, c, n = x[keep], dst[i[keep]], normals[i[keep]]
            mu = xs.mean(0)
            xc = xs - mu
            cols = [np.cross(xc, n), n] + ([(n * xc).sum(1, keepdims=True)] if with_scale else [])
            sol = np.linalg.lstsq(np.concatenate(cols, 1), -(n * (xs - c)).sum(1), rcond=None)[0]
            s = 1.0 + (float(sol[6]) if with_scale else 0.0)
            R = _rotvec(sol[:3])
            step = Similarity(s, R, mu + sol[3:6] - s * R @ mu)
        T = Similarity(step.scale * T.scale, step.R @ T.R, step.scale * step.R @ T.t + step.t)
        if np.abs(step.R - np.eye(3)).max() < 1e-9 and abs(step.scale - 1) < 1e-9 and \
                np.abs(step.t).max() < 1e-12 * max(1.0, np.abs(dst).max()):
            break
    d, _ = _query(tree, T.apply(src))
    return T, float(d.mean())


@dataclass
class NonRigidResult:
    points: np.ndarray          # (N,3) the source region's vertices after the non-rigid step
    residual: float             # mean distance to the target region's nearest vertex
    residuals: list = dc_field(default_factory=list)  # per iteration


def arap_icp(src_points: np.ndarray, src_edges: np.ndarray, dst_points: np.ndarray,
             iterations: int = 12, stiffness=(10.0, 3.0, 1.0), max_distance: Optional[float] = None,
             tree=None, progress: Optional[Callable[[float], bool]] = None) -> NonRigidResult:
    """As-rigid-as-possible regularised non-rigid ICP of a source region onto target points.

    ``src_points`` (N,3) are the (already similarity-aligned) source vertices and ``src_edges`` (E,2)
    the region's mesh edges (indices into ``src_points``).  Each iteration finds every source vertex's
    closest target point c_i and solves the sparse least-squares problem

        min_X  sum_i |x_i - c_i|^2 + lam * sum_(i,j) |(x_i - x_j) - (R_i + R_j)/2 (p_i - p_j)|^2

    (p the aligned rest positions, R_i the ARAP local rotations of the current estimate), alternating
    the local rotations and the global solve (the ARAP pieces of :class:`neumesh_core.deform.ArapTerms`,
    uniform weights).  A vertex whose closest target point is farther than
    ``max_distance`` has no counterpart: its data target is its current position instead (it follows
    its neighbours through the ARAP term), so the system matrix depends on ``lam`` alone and is
    factorised once per stiffness (scipy sparse LU).  ``stiffness`` lam runs from stiff to flexible
    over the iterations (in units of the data weight); it stops early once converged at the final
    stiffness.  ``progress(fraction)`` returning False stops.
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    from ..deform.arap import ArapTerms

    p = np.asarray(src_points, np.float64)
    dst = np.asarray(dst_points, np.float64)
    edges = np.asarray(src_edges, np.int64).reshape(-1, 2)
    n = len(p)
    tree = tree if tree is not None else _nn(dst)
    if len(edges) == 0 or iterations <= 0:
        d, _ = _query(tree, p)
        return NonRigidResult(p.copy(), float(d.mean()), [float(d.mean())])
    terms = ArapTerms(p, edges)                 # uniform weights: L = D - A, the ARAP local/global pieces
    unit = float(np.linalg.norm(p[edges[:, 0]] - p[edges[:, 1]], axis=1).mean())
    x = p.copy()
    residuals = []
    lams = list(stiffness) + [stiffness[-1]] * max(0, iterations - len(stiffness))
    solvers = {}
    for it in range(iterations):
        d, idx = _query(tree, x)
        residuals.append(float(d.mean()))
        c = dst[idx]
        if max_distance is not None:
            far = d > max_distance
            c[far] = x[far]
        lam = lams[it]
        b = terms.rhs(terms.rotations(x))
        if lam not in solvers:
            solvers[lam] = splu((sp.identity(n) + lam * terms.laplacian).tocsc())
        rhs = c + lam * b
        x_new = solvers[lam].solve(np.ascontiguousarray(rhs))
        moved = float(np.abs(x_new - x).max())
        x = x_new
        if progress is not None and progress((it + 1) / iterations) is False:
            break
        if lam == lams[-1] and moved < 1e-4 * unit:   # converged at the final stiffness
            break
    d, _ = _query(tree, x)
    residuals.append(float(d.mean()))
    return NonRigidResult(x, float(d.mean()), residuals)


def region_edges(faces: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Mesh edges with both ends in ``vertices`` (sorted unique indices), re-indexed into positions of
    ``vertices`` (so they index the region's own point array)."""
    from ..mesh import unique_edges

    faces = np.asarray(faces, np.int64)
    if len(faces) == 0:
        return np.zeros((0, 2), np.int64)
    e = unique_edges(faces)
    pos = np.full(int(max(faces.max(), vertices.max())) + 1, -1, np.int64)
    pos[vertices] = np.arange(len(vertices))
    a, b = pos[e[:, 0]], pos[e[:, 1]]
    keep = (a >= 0) & (b >= 0)
    return np.stack([a[keep], b[keep]], 1)
