"""Decimating a triangle mesh (the bake's lighter targets): fast-simplification's quadric decimation,
or libigl's edge collapse where it is not installed."""
from __future__ import annotations

import numpy as np

from ..errors import NeuMeshError


def decimate(vertices: np.ndarray, faces: np.ndarray, ratio: float) -> tuple:
    """Quadric decimation of a triangle mesh to about ``ratio`` x its faces (0 < ratio <= 1) with the
    ``fast-simplification`` package (an optional dependency: ``pip install fast-simplification``), or,
    without it, libigl's edge collapse (``igl.decimate``; slower, setup.sh installs libigl).

    Returns (vertices (V',3) float32, faces (F',3) int64).  ``ratio`` 1 returns the mesh unchanged."""
    ratio = float(ratio)
    if not 0.0 < ratio <= 1.0:
        raise ValueError(f"decimation ratio must be in (0, 1], got {ratio}")
    v = np.ascontiguousarray(vertices, np.float32)
    f = np.ascontiguousarray(faces, np.int64)
    if ratio >= 1.0:
        return v, f
    try:
        import fast_simplification
    except ImportError:
        fast_simplification = None
    if fast_simplification is not None:
        dv, df = fast_simplification.simplify(v, f.astype(np.int32), target_reduction=1.0 - ratio)
        return np.asarray(dv, np.float32), np.asarray(df, np.int64)
    return _decimate_igl(v, f, ratio)


def _decimate_igl(v: np.ndarray, f: np.ndarray, ratio: float) -> tuple:
    """libigl's shortest-edge collapse to about ``ratio`` x the faces (the fallback of :func:`decimate`)."""
    try:
        import igl
    except ImportError as exc:
        raise NeuMeshError("decimating needs the 'fast-simplification' package (pip install "
                           "fast-simplification) or libigl (pip install libigl); or decimate the mesh elsewhere "
                           "(e.g. Blender's Decimate modifier) and pass it as the target mesh (--mesh)") from exc
    out = igl.decimate(np.asarray(v, np.float64), np.asarray(f, np.int64), max(4, int(round(ratio * len(f)))))
    if len(out) == 5:          # older libigl: (success, U, G, J, I)
        out = out[1:]
    U, G = out[0], out[1]
    return np.asarray(U, np.float32), np.asarray(G, np.int64)
