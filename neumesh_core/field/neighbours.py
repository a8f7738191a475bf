"""Neighbour transfer of per-vertex rows between fields: inverse-distance weights over the nearest
vertices, and rows blended from a source field (one decoder per blended row; texture frames carried).

The field needs these to carry itself onto a changed mesh (:mod:`.remap`); the edits (swap, fill) use
them through :mod:`neumesh_core.edit.transfer`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from ..errors import EditError


def idw_neighbours(query: np.ndarray, points: np.ndarray, k: int = 4, tree=None):
    """The ``k`` nearest ``points`` of each query point and their inverse-distance weights.

    Returns (idx (Q,k) int64 into ``points``, w (Q,k) float64 rows summing to 1).  A query that
    coincides with a point (distance below 1e-9 of the points' extent) takes that point alone, so a
    region transferred onto itself is copied exactly.
    """
    from .knn import kd_tree

    pts = np.ascontiguousarray(points, dtype=np.float64)
    q = np.ascontiguousarray(query, dtype=np.float64)
    if len(pts) == 0:
        raise EditError("the source region is empty")
    kk = min(int(k), len(pts))
    tree = tree if tree is not None else kd_tree(pts)
    d, i = tree.query(q, k=kk)
    d = np.asarray(d, np.float64).reshape(len(q), kk)
    i = np.asarray(i, np.int64).reshape(len(q), kk)
    ext = float(np.ptp(pts, axis=0).max()) if len(pts) > 1 else 1.0
    tiny = 1e-9 * max(ext, 1e-12)
    inv = 1.0 / np.maximum(d, tiny)
    exact = d[:, 0] <= tiny
    inv[exact] = 0.0
    inv[exact, 0] = 1.0
    return i, inv / inv.sum(1, keepdims=True)


@dataclass
class BlendedRows:
    """Rows blended from a source field by a plan (CPU tensors): ``decoder`` (T,) the source decoder
    each row is bound to, ``frames`` (T,3,3) float64 the source texture frame of each row's most
    weighted vertex (None when the source has none), ``tables`` name -> (T,C) blended rows."""

    decoder: np.ndarray
    frames: Optional[np.ndarray]
    tables: dict


def blend_rows(source, src: np.ndarray, w: np.ndarray, tables=("tex_codes", "mod_colours")) -> BlendedRows:
    """Blend rows of ``source``: row t is ``sum_j w[t,j] * table[src[t,j]]`` over the source vertices
    bound to the decoder holding the largest share of the row's weight (the others' weights are
    dropped and the rest renormalised, so codes of different decoders are never averaged)."""
    src = np.asarray(src, np.int64)
    w = np.array(w, np.float64)
    src_ids = source.decoder_id.detach().cpu().numpy().astype(np.int64)
    dec = src_ids[src]                                           # (T,J) decoder of each blended vertex
    decs = np.unique(dec[w > 0])
    share = np.stack([(w * (dec == d)).sum(1) for d in decs], 1)
    chosen = decs[share.argmax(1)]
    w[dec != chosen[:, None]] = 0.0
    w /= w.sum(1, keepdims=True)
    out = {}
    with torch.no_grad():
        sdev = source.geo_codes.device
        S = torch.as_tensor(src, device=sdev)
        W = torch.as_tensor(w, dtype=torch.float32, device=sdev)[..., None]
        for name in tables:
            t = getattr(source, name).detach()
            out[name] = (t[S].float() * W).sum(1).cpu() if t.shape[1] else t.new_zeros(len(src), 0).cpu()
    lead = src[np.arange(len(src)), w.argmax(1)]
    frames = None
    if source.tex_frame is not None:
        frames = source.tex_frame.detach().cpu().numpy()[lead].astype(np.float64)
    return BlendedRows(chosen, frames, out)


def snap_identity(Q: np.ndarray) -> np.ndarray:
    """Rotations within 1e-6 of the identity become exactly the identity (rounding noise: no frame)."""
    Q = np.array(Q, np.float64)
    Q[np.abs(Q - np.eye(3)).max(axis=(1, 2)) < 1e-6] = np.eye(3)
    return Q
