"""Nearest rotations of batches of 3x3 matrices (the ARAP local step; also Kabsch fits).

Moved here from ``edit/align.py`` (which re-exports them) so that the one ARAP implementation in
:mod:`neumesh_core.deform.arap` serves both the deformation tool and the swap alignment's non-rigid ICP.
"""
from __future__ import annotations

import numpy as np


def polar_rotations_reference(S: np.ndarray) -> np.ndarray:
    """(n,3,3) proper rotations nearest to the (n,3,3) matrices ``S``: U diag(1,1,det(U V^T)) V^T from a
    batched SVD (the rotation factor of the polar decomposition; identity for a zero matrix).  The plain
    reference of :func:`polar_rotations`."""
    U, _, Vt = np.linalg.svd(np.asarray(S, np.float64))
    det = np.linalg.det(U @ Vt)
    U[:, :, 2] *= np.where(det < 0, -1.0, 1.0)[:, None]
    R = U @ Vt
    bad = ~np.isfinite(R).all(axis=(1, 2))
    R[bad] = np.eye(3)
    return R


def _horn_matrix(m) -> list:
    """Horn's symmetric 4x4 matrix of 3x3 matrices given as 9 contiguous (n,) arrays (row-major), as a
    4x4 nested list of (n,) arrays: q^T N q = tr(R(q)^T M) for a unit quaternion q."""
    Sxx, Sxy, Sxz, Syx, Syy, Syz, Szx, Szy, Szz = m
    n01, n02, n03 = Szy - Syz, Sxz - Szx, Syx - Sxy
    n12, n13, n23 = Sxy + Syx, Sxz + Szx, Syz + Szy
    return [[Sxx + Syy + Szz, n01, n02, n03],
            [n01, Sxx - Syy - Szz, n12, n13],
            [n02, n12, -Sxx + Syy - Szz, n23],
            [n03, n13, n23, -Sxx - Syy + Szz]]


def _minors(a):
    """The twelve 2x2 minors of rows (0,1) and (2,3) of 4x4 matrices (nested lists of arrays)."""
    s = [a[0][0] * a[1][1] - a[1][0] * a[0][1], a[0][0] * a[1][2] - a[1][0] * a[0][2],
         a[0][0] * a[1][3] - a[1][0] * a[0][3], a[0][1] * a[1][2] - a[1][1] * a[0][2],
         a[0][1] * a[1][3] - a[1][1] * a[0][3], a[0][2] * a[1][3] - a[1][2] * a[0][3]]
    c = [a[2][0] * a[3][1] - a[3][0] * a[2][1], a[2][0] * a[3][2] - a[3][0] * a[2][2],
         a[2][0] * a[3][3] - a[3][0] * a[2][3], a[2][1] * a[3][2] - a[3][1] * a[2][2],
         a[2][1] * a[3][3] - a[3][1] * a[2][3], a[2][2] * a[3][3] - a[3][2] * a[2][3]]
    return s, c


def _det4(a) -> np.ndarray:
    s, c = _minors(a)
    return s[0] * c[5] - s[1] * c[4] + s[2] * c[3] + s[3] * c[2] - s[4] * c[1] + s[5] * c[0]


def _adjugate4(a) -> list:
    """Adjugate (det x inverse) of 4x4 matrices given as nested lists of (n,) arrays."""
    s, c = _minors(a)
    return [[a[1][1] * c[5] - a[1][2] * c[4] + a[1][3] * c[3], -a[0][1] * c[5] + a[0][2] * c[4] - a[0][3] * c[3],
             a[3][1] * s[5] - a[3][2] * s[4] + a[3][3] * s[3], -a[2][1] * s[5] + a[2][2] * s[4] - a[2][3] * s[3]],
            [-a[1][0] * c[5] + a[1][2] * c[2] - a[1][3] * c[1], a[0][0] * c[5] - a[0][2] * c[2] + a[0][3] * c[1],
             -a[3][0] * s[5] + a[3][2] * s[2] - a[3][3] * s[1], a[2][0] * s[5] - a[2][2] * s[2] + a[2][3] * s[1]],
            [a[1][0] * c[4] - a[1][1] * c[2] + a[1][3] * c[0], -a[0][0] * c[4] + a[0][1] * c[2] - a[0][3] * c[0],
             a[3][0] * s[4] - a[3][1] * s[2] + a[3][3] * s[0], -a[2][0] * s[4] + a[2][1] * s[2] - a[2][3] * s[0]],
            [-a[1][0] * c[3] + a[1][1] * c[1] - a[1][2] * c[0], a[0][0] * c[3] - a[0][1] * c[1] + a[0][2] * c[0],
             -a[3][0] * s[3] + a[3][1] * s[1] - a[3][2] * s[0], a[2][0] * s[3] - a[2][1] * s[1] + a[2][2] * s[0]]]


def _quaternion_rotations(w, x, y, z) -> np.ndarray:
    """(n,3,3) rotations of unit quaternions (w, x, y, z) (each (n,)), written as (9,n) and transposed."""
    ww, xx, yy, zz = w * w, x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    R = np.stack([ww + xx - yy - zz, 2 * (xy - wz), 2 * (xz + wy),
                  2 * (xy + wz), ww - xx + yy - zz, 2 * (yz - wx),
                  2 * (xz - wy), 2 * (yz + wx), ww - xx - yy + zz])
    return np.ascontiguousarray(R.T).reshape(-1, 3, 3)


def polar_rotations(S: np.ndarray) -> np.ndarray:
    """The rotations of :func:`polar_rotations_reference` (the proper rotation R maximising
    tr(R^T S)), with no per-matrix LAPACK call: Horn's quaternion method solved as in QCP (Theobald
    2005).  The largest eigenvalue of Horn's symmetric 4x4 matrix N is the largest root of its
    characteristic quartic (coefficients in closed form), found by Newton's method from an upper bound
    (monotone: the quartic is convex right of that root); its eigenvector is the
    best-conditioned column of adj(N - lambda I), all as elementwise arithmetic on arrays of the n
    inputs (an order of magnitude faster than a batched 3x3 SVD; the ARAP local step runs it every
    iteration).  Where the largest eigenvalue is (nearly) double, the maximiser is not unique (rank <= 1,
    e.g. collinear edges) and those rows go to the reference; a zero matrix gives the identity.  Runs in
    blocks of ``_BLOCK`` matrices so that its ~100 temporaries stay in the CPU cache."""
    M = np.asarray(S, np.float64).reshape(-1, 3, 3)
    n = len(M)
    if n <= _BLOCK:
        return _polar_block(M)
    out = np.empty((n, 3, 3))
    for i in range(0, n, _BLOCK):
        out[i:i + _BLOCK] = _polar_block(M[i:i + _BLOCK])
    return out


_BLOCK = 4096


def _polar_block(M: np.ndarray) -> np.ndarray:
    n = len(M)
    if n == 0:
        return np.zeros((0, 3, 3))
    flat = M.reshape(n, 9)
    finite = np.isfinite(flat).all(1)
    if not finite.all():
        flat = np.where(finite[:, None], flat, 0.0)
    m = list(np.ascontiguousarray(flat.T))                 # nine contiguous (n,) components
    fro2 = sum(e * e for e in m)
    detS = (m[0] * (m[4] * m[8] - m[5] * m[7]) - m[1] * (m[3] * m[8] - m[5] * m[6])
            + m[2] * (m[3] * m[7] - m[4] * m[6]))
    Nd = _horn_matrix(m)
    c0 = _det4(Nd)
    c2, c1 = -2.0 * fro2, -8.0 * detS
    # start Newton at an upper bound of sigma1+sigma2+sigma3 (>= the root): (sum sigma)^2 = |S|^2 +
    # 2 sqrt(|cof S|^2 + 2 |det S| sum sigma), with sum sigma <= sqrt(3)|S| inside; far tighter than
    # sqrt(3)|S| for the near-planar covariances of surface 1-rings (3-4 Newton steps instead of 12)
    cof2 = sum((m[i] * m[j] - m[k] * m[l]) ** 2 for i, j, k, l in
               ((4, 8, 5, 7), (3, 8, 5, 6), (3, 7, 4, 6), (1, 8, 2, 7), (0, 8, 2, 6), (0, 7, 1, 6),
                (1, 5, 2, 4), (0, 5, 2, 3), (0, 4, 1, 3)))
    lam = np.sqrt(fro2 + 2.0 * np.sqrt(cof2 + 2.0 * np.abs(detS) * np.sqrt(3.0 * fro2)))
    tol = 1e-13 * np.maximum(lam, 1e-300)
    low = np.sqrt(fro2 / 3.0)   # sigma1 <= the largest eigenvalue
    for _ in range(60):   # Newton from the right: quadratic for a simple root, a few steps
        l2 = lam * lam
        p = (l2 + c2) * l2 + c1 * lam + c0
        dp = (4.0 * l2 + 2.0 * c2) * lam + c1
        step = np.maximum(p / np.where(dp > 0, dp, np.inf), 0.0)   # never left: rounding near a double
        lam = np.maximum(lam - step, low)                              # root must not throw it off
        if not (np.abs(step) > tol).any():
            break
    A = [[Nd[r][c] - lam if r == c else Nd[r][c] for c in range(4)] for r in range(4)]
    scale = np.maximum(fro2, 1e-300) ** 1.5
    # adj(N - lam I) = c v v^T (rank one): column 0 is c v_0 v, well conditioned unless the quaternion's
    # w = v_0 is small (a rotation near 180 degrees), so it is computed alone (a quarter of the
    # adjugate); the other rows take the best-conditioned column of the whole adjugate
    a1, a2, a3 = A[1], A[2], A[3]
    m0, m1, m2 = a2[0] * a3[1] - a3[0] * a2[1], a2[0] * a3[2] - a3[0] * a2[2], a2[0] * a3[3] - a3[0] * a2[3]
    m3, m4, m5 = a2[1] * a3[2] - a3[1] * a2[2], a2[1] * a3[3] - a3[1] * a2[3], a2[2] * a3[3] - a3[2] * a2[3]
    q = np.empty((n, 4))
    q[:, 0] = a1[1] * m5 - a1[2] * m4 + a1[3] * m3
    q[:, 1] = -a1[0] * m5 + a1[2] * m2 - a1[3] * m1
    q[:, 2] = a1[0] * m4 - a1[1] * m2 + a1[3] * m0
    q[:, 3] = -a1[0] * m3 + a1[1] * m1 - a1[2] * m0
    qn = np.sqrt((q * q).sum(1))
    good = finite & (np.abs(q[:, 0]) >= 0.25 * qn) & (np.abs(q[:, 0]) > 1e-10 * scale)
    other = np.nonzero(~good)[0]
    if len(other):
        As = [[e[other] for e in row] for row in A]
        adj = _adjugate4(As)
        diag = np.abs(np.stack([adj[k][k] for k in range(4)], 1))
        k = diag.argmax(1)
        cols = np.array(adj)                                   # (4 rows, 4 columns, m)
        qo = cols[:, k, np.arange(len(other))].T               # column k of the adjugate
        qon = np.sqrt((qo * qo).sum(1))
        q[other], qn[other] = qo, qon
        good[other] = finite[other] & (diag.max(1) > 1e-9 * scale[other]) & (qon > 0)
    q = q / np.where(good, qn, 1.0)[:, None]
    R = _quaternion_rotations(q[:, 0], q[:, 1], q[:, 2], q[:, 3])
    # every answer checked: tr(R^T S) must reach the largest eigenvalue (else, e.g. a nearly double root
    # where the adjugate mixes eigenvectors, the row goes to the reference)
    reached = (R.reshape(n, 9) * flat).sum(1)
    good &= np.abs(reached - lam) <= 1e-7 * np.sqrt(np.maximum(fro2, 1e-300))
    bad = ~good
    if bad.any():
        R[bad] = polar_rotations_reference(np.where(finite[bad][:, None, None], M[bad], 0.0))
    R[fro2 == 0] = np.eye(3)
    return R
