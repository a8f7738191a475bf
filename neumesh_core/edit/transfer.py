"""Code transfer shared by texture swap and fill: inverse-distance weights over nearest neighbours, and
the write of texture codes, modification colours, decoder binding and texture frames into a region.

A transfer is a sparse matrix ``W`` (target rows x source vertices, rows summing to 1): target vertex t
takes ``sum_s W[t, s] * row_s`` of the source's texture codes and modification colours.  Texture codes
mean something only to the decoder they were trained with, so a target vertex is bound to one source
decoder (the one holding the largest share of its weight), its weights over source vertices bound to
other decoders are dropped and the rest renormalised, and that decoder is added to the target field
(once; :meth:`NeuMeshField.add_decoder`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from ..errors import EditError
from ..field.neighbours import BlendedRows, blend_rows, idw_neighbours, snap_identity  # noqa: F401
from .record import EditRecord


def minimal_rotations(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,3,3) rotations taking unit vectors ``a`` (N,3) to ``b`` (N,3) by the smallest angle
    (Rodrigues); opposite vectors turn by 180 degrees about an axis perpendicular to ``a``."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    a = a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
    b = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
    v = np.cross(a, b)
    c = (a * b).sum(1)
    K = np.zeros((len(a), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 0] = -v[:, 2], v[:, 1], v[:, 2]
    K[:, 1, 2], K[:, 2, 0], K[:, 2, 1] = -v[:, 0], -v[:, 1], v[:, 0]
    R = np.eye(3)[None] + K + (K @ K) / np.maximum(1.0 + c, 1e-12)[:, None, None]
    opp = c < -1.0 + 1e-9
    if opp.any():
        ao = a[opp]
        axis = np.where(np.abs(ao[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
        axis = axis - (axis * ao).sum(1, keepdims=True) * ao
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        R[opp] = 2 * axis[:, :, None] * axis[:, None, :] - np.eye(3)[None]
    return R


@dataclass
class TransferPlan:
    """Which source vertices each target vertex blends: ``rows`` (T,) target vertex ids, ``src``
    (T,J) source vertex ids and ``w`` (T,J) weights (rows sum to 1; padding has weight 0)."""

    rows: np.ndarray
    src: np.ndarray
    w: np.ndarray

    @staticmethod
    def from_queries(rows: np.ndarray, query_row: np.ndarray, src: np.ndarray, w: np.ndarray) -> "TransferPlan":
        """Several queries per target vertex (e.g. one per UV corner on a seam): query q belongs to
        target position ``query_row[q]`` and its weights are averaged with equal weight per query."""
        T = len(rows)
        counts = np.bincount(query_row, minlength=T)
        if (counts == 0).any():
            raise EditError("every target vertex needs at least one query")
        J = int(counts.max()) * src.shape[1]
        order = np.argsort(query_row, kind="stable")
        qr = query_row[order]
        slot = np.arange(len(qr)) - np.searchsorted(qr, qr)   # rank of each query within its row
        out_src = np.zeros((T, J), np.int64)
        out_w = np.zeros((T, J), np.float64)
        k = src.shape[1]
        cols = slot[:, None] * k + np.arange(k)[None]
        out_src[qr[:, None], cols] = src[order]
        out_w[qr[:, None], cols] = w[order] / counts[qr][:, None]
        return TransferPlan(rows, out_src, out_w)


def apply_transfer(op: str, target, plan: TransferPlan, source,
                   frames: Optional[np.ndarray] = None, **info) -> EditRecord:
    """Write the blended texture codes and modification colours of ``source`` into ``target``'s rows
    ``plan.rows``, bind them to the source decoders (added to ``target`` once) and set their texture
    frames.  ``frames`` (T,3,3): rotation from each target vertex's rest frame into the rest frame of
    the source it copies (before the source's own texture frame); None = identity.
    Returns the :class:`EditRecord` (nothing outside ``plan.rows`` changes).
    """
    check_compatible(target, source)
    rows = np.asarray(plan.rows, np.int64)
    tables = ("tex_codes", "mod_colours", "decoder_id", "tex_frame")
    record = EditRecord.begin(op, target, rows, tables)
    if not np.array_equal(record.vertices, rows):
        raise EditError("the target region holds repeated vertices")
    b = blend_rows(source, plan.src, plan.w)
    Q = np.broadcast_to(np.eye(3), (len(rows), 3, 3)) if frames is None else np.asarray(frames, np.float64)
    if b.frames is not None:   # the source's own texture frame, after the geometric frame
        Q = b.frames @ Q
    Q = snap_identity(Q)
    with torch.no_grad():
        dev = target.geo_codes.device
        # decoders: each distinct source decoder used is added to the target once
        mapping = {int(d): target.add_decoder(source.rad_decoders[int(d)]) for d in np.unique(b.decoder)}
        new_ids = np.array([mapping[int(d)] for d in b.decoder], np.int64)
        idx = torch.as_tensor(rows, device=dev)
        target.tex_codes[idx] = b.tables["tex_codes"].to(dev, target.tex_codes.dtype)
        target.mod_colours[idx] = b.tables["mod_colours"].to(dev, target.mod_colours.dtype)
        target.decoder_id[idx] = torch.as_tensor(new_ids, device=dev, dtype=target.decoder_id.dtype)
        target.ensure_tex_frame()[idx] = torch.as_tensor(Q, dtype=torch.float32, device=dev)
    return record.finish(target, **info)


def check_compatible(target, source) -> None:
    """Texture codes can move between two fields only when their radiance decoders read the same
    inputs: same texture-code size, positional and view encodings."""
    a, b = target.config, source.config
    diffs = [f"{name} {getattr(b, name)} (source) vs {getattr(a, name)} (target)"
             for name in ("tex_dim", "pos_freqs", "sh_degree") if getattr(a, name) != getattr(b, name)]
    if diffs:
        raise EditError("the two fields' texture codes are not interchangeable: " + "; ".join(diffs) +
                         ". Use a source field trained with the same code size and encodings")
