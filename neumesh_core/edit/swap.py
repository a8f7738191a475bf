"""Texture swap: give a target region the appearance of a source region (of the same field or another).

1. Rigid alignment with uniform scale of the source region onto the target region: Umeyama from
   point pairs, or without pairs an automatic guess (the source's centroid onto the target's, its
   extent scaled to the target's, the rotation searched by ICP about the fixed centroids:
   :func:`~neumesh_core.edit.align.initial_alignment`).
2. Non-rigid refinement: ARAP-regularised non-rigid ICP over the source region's mesh edges.
3. Fit check: the aligned source must cover the target (:mod:`~neumesh_core.edit.fit_check`); a swap
   whose alignment failed is refused with an :class:`EditError` that says what to do, and nothing is
   written.  :func:`swap_alignment` runs steps 1-3 alone (no write): the aligned source region and the
   fit figures, for a preview before the swap.
4. Transfer: each target vertex takes the inverse-distance-weighted mean of the texture codes and
   modification colours of its k=4 nearest aligned source vertices, and the source's decoder binding
   (the source decoder is added to the target field once).  The texture frame of each written vertex
   rotates its normal and view directions into the source's frame (the alignment's rotation, then the
   smallest rotation that matches the normals), so the source decoder sees the surface orientation it
   was trained with.

Geometry codes, vertex positions and every row outside the target region never change.  Alignment
works in the rest (training) pose of both fields.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field as dc_field
from typing import Callable, Optional

import numpy as np

from ..errors import EditError
from ..mesh import unique_edges
from .align import Similarity, arap_icp, initial_alignment, region_edges, rigid_icp, umeyama
from .fit_check import FitFigures, FitThresholds, fit_figures, refusal_message
from .record import EditRecord, as_vertex_ids
from .transfer import TransferPlan, apply_transfer, check_compatible, idw_neighbours, minimal_rotations


@dataclass
class SwapConfig:
    """Parameters of :func:`swap_texture` (defaults suit scaffolds of 10k-3M vertices)."""

    k: int = 4                          # source vertices blended per target vertex
    nonrigid: bool = True               # run the ARAP non-rigid refinement after the similarity
    nonrigid_iterations: int = 12
    stiffness: tuple = (10.0, 3.0, 1.0)  # ARAP weight per iteration, stiff to flexible
    max_match_edges: float = 20.0       # non-rigid matches farther than this (x mean edge) are ignored
    refine_pairs: bool = False          # with pairs: also refine the similarity by rigid ICP
    with_scale: bool = True             # the similarity may scale (Umeyama with scale)
    match_orientation: bool = True      # texture frames: the source decoder sees its own orientation
    check_fit: bool = True              # refuse a swap whose aligned source does not cover the target
    fit: FitThresholds = dc_field(default_factory=FitThresholds)   # the check's thresholds

    def __post_init__(self) -> None:
        if self.k < 1:
            raise EditError("k must be at least 1")
        if self.nonrigid_iterations < 0 or not self.stiffness or min(self.stiffness) <= 0:
            raise EditError("nonrigid_iterations must be >= 0 and stiffness values positive")


def _mean_edge(points: np.ndarray, faces: np.ndarray, region: np.ndarray) -> float:
    """Mean length of the region's mesh edges (of the whole mesh when the region has none)."""
    e = region_edges(faces, region)
    if len(e):
        p = points[region]
        return float(np.linalg.norm(p[e[:, 0]] - p[e[:, 1]], axis=1).mean())
    all_e = unique_edges(np.asarray(faces)) if len(faces) else np.zeros((0, 2), np.int64)
    if len(all_e):
        return float(np.linalg.norm(points[all_e[:, 0]] - points[all_e[:, 1]], axis=1).mean())
    return float(np.ptp(points, axis=0).max()) / max(len(points) ** (1 / 2), 1.0)


def _pairs_points(pairs, source_rest: np.ndarray, target_rest: np.ndarray):
    """(src (P,3), dst (P,3)) from ``pairs``: a (P,2) array of (source vertex, target vertex) indices,
    or a tuple (source points (P,3), target points (P,3)) in the rest pose."""
    if isinstance(pairs, (tuple, list)) and len(pairs) == 2 and np.asarray(pairs[0]).ndim == 2:
        src, dst = (np.asarray(p, np.float64).reshape(-1, 3) for p in pairs)
    else:
        a = np.asarray(pairs)
        if a.ndim != 2 or a.shape[1] not in (2, 6):
            raise EditError("pairs: give (P,2) vertex index pairs (source, target), (P,6) point pairs, or "
                             "a tuple (source points (P,3), target points (P,3))")
        if a.shape[1] == 2:
            ai = a.astype(np.int64)
            if not np.array_equal(ai, a):
                raise EditError("pairs: (P,2) pairs must hold whole vertex indices")
            for col, n, what in ((0, len(source_rest), "source"), (1, len(target_rest), "target")):
                if ai[:, col].min() < 0 or ai[:, col].max() >= n:
                    raise EditError(f"pairs: {what} vertex indices must lie in [0, {n})")
            src, dst = source_rest[ai[:, 0]], target_rest[ai[:, 1]]
        else:
            src, dst = a[:, :3].astype(np.float64), a[:, 3:].astype(np.float64)
    if len(src) != len(dst):
        raise EditError(f"pairs: {len(src)} source points but {len(dst)} target points")
    if len(src) < 3:
        raise EditError(f"pairs: {len(src)} correspondences given; at least 3 are needed (or none, for "
                         "the automatic alignment)")
    return src, dst


def _cancelled(progress, fraction: float) -> None:
    if progress is not None and progress(float(fraction)) is False:
        from ..render.renderer import Cancelled

        raise Cancelled("texture swap cancelled; the field is unchanged")


@dataclass
class SwapAlignment:
    """Where a swap's source region lands on the target, and how well it fits (nothing written).

    Points are in the target field's rest frame (the frame of ``target.rest_vertices``): draw them with
    the target object's transform, e.g. as a temporary wireframe with ``faces`` before accepting.
    """

    transform: Similarity          # source rest -> target rest (the similarity of step 1)
    target_vertices: np.ndarray    # (T,) the target region's vertex ids
    source_vertices: np.ndarray    # (S,) the source region's vertex ids
    rigid_points: np.ndarray       # (S,3) the source region after the similarity
    points: np.ndarray             # (S,3) ... and after the non-rigid step (what the transfer uses)
    faces: np.ndarray              # (F,3) the source region's triangles, indices into ``points``
    figures: FitFigures            # overlap and residuals of ``points`` against the target region
    residual: float                # mean source -> target distance / target mean edge (after non-rigid)
    residual_rigid: float          # the same after the similarity alone
    mean_edge: float               # the target region's mean edge length
    pairs: int                     # point pairs used (0: the automatic alignment)
    problems: list                 # what fails the fit check, in words (empty: it fits)
    message: str                   # the refusal message when ``problems`` ("" otherwise)
    align_s: float = 0.0
    nonrigid_s: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.problems

    def info(self) -> dict:
        """The figures a swap records (``record.info``), JSON-friendly."""
        return {"transform": self.transform.matrix(), "scale": self.transform.scale, "residual": self.residual,
                "residual_rigid": self.residual_rigid, "mean_edge": self.mean_edge,
                "target_vertices": int(len(self.target_vertices)), "source_vertices": int(len(self.source_vertices)),
                "pairs": self.pairs, "align_s": self.align_s, "nonrigid_s": self.nonrigid_s,
                "fit_ok": self.ok, **self.figures.as_dict()}


def _region_faces(faces: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Triangles with all three corners in ``region`` (sorted ids), as indices into ``region``."""
    faces = np.asarray(faces, np.int64)
    if len(faces) == 0:
        return np.zeros((0, 3), np.int64)
    pos = np.full(int(max(faces.max(), region.max())) + 1, -1, np.int64)
    pos[region] = np.arange(len(region))
    f = pos[faces]
    return f[(f >= 0).all(1)]


def swap_alignment(target, target_vertices, source=None, source_vertices=None, pairs=None,
                   config: Optional[SwapConfig] = None,
                   progress: Optional[Callable[[float], bool]] = None) -> SwapAlignment:
    """The alignment :func:`swap_texture` would use, and its fit figures, without writing anything.

    Arguments as for :func:`swap_texture`.  Returns a :class:`SwapAlignment`: the similarity, the
    source region's vertices after it and after the non-rigid step (target rest frame), the region's
    triangles (for a wireframe preview), the fit figures and, when the fit check fails, the message a
    swap would refuse with.  Raises :class:`EditError` for bad input (never for a poor fit);
    ``progress(fraction)`` returning False cancels (``nm.Cancelled``).
    """
    cfg = config or SwapConfig()
    source = target if source is None else source
    if source_vertices is None:
        raise EditError("source_vertices: give the source region (vertex indices or a boolean mask)")
    check_compatible(target, source)
    tv = as_vertex_ids(target_vertices, target.num_vertices, "target region")
    sv = as_vertex_ids(source_vertices, source.num_vertices, "source region")
    t0 = time.perf_counter()
    t_rest = target.rest_vertices.detach().cpu().numpy().astype(np.float64)
    s_rest = source.rest_vertices.detach().cpu().numpy().astype(np.float64)
    t_faces = target.faces.detach().cpu().numpy()
    s_faces = source.faces.detach().cpu().numpy()
    T_pts, S_pts = t_rest[tv], s_rest[sv]
    T_nrm = target.rest_normals.detach().cpu().numpy().astype(np.float64)[tv]
    unit = _mean_edge(t_rest, t_faces, tv)
    _cancelled(progress, 0.0)

    # 1. similarity: both regions in their fields' rest frames (one frame: the fields' world space)
    from ..field.knn import kd_tree

    tree = kd_tree(np.ascontiguousarray(T_pts))
    n_pairs = 0
    if pairs is not None:
        src_p, dst_p = _pairs_points(pairs, s_rest, t_rest)
        n_pairs = len(src_p)
        sim = umeyama(src_p, dst_p, with_scale=cfg.with_scale)
        if cfg.refine_pairs:   # the pairs fix the scale (a free scale can collapse: initial_alignment)
            sim, _ = rigid_icp(S_pts, T_pts, sim, with_scale=False, tree=tree, dst_normals=T_nrm)
    elif len(sv) < 4 or len(tv) < 4:
        raise EditError("automatic alignment needs at least 4 vertices in each region; select larger "
                         "regions or give 3 or more point pairs")
    else:
        S_nrm = source.rest_normals.detach().cpu().numpy().astype(np.float64)[sv]
        sim = initial_alignment(S_pts, T_pts, dst_normals=T_nrm, src_normals=S_nrm)
    if not np.isfinite(sim.matrix()).all() or not sim.scale > 0:
        raise EditError(f"the alignment failed (scale {sim.scale:g}); give 3 or more point pairs")
    rigid = sim.apply(S_pts)
    d_rigid = float(np.asarray(tree.query(np.ascontiguousarray(rigid), k=1)[0]).mean())
    t_sim = time.perf_counter() - t0
    _cancelled(progress, 0.2)

    # 2. non-rigid refinement over the source region's edges
    t1 = time.perf_counter()
    x, residual = rigid, d_rigid
    if cfg.nonrigid and cfg.nonrigid_iterations > 0:
        edges = region_edges(s_faces, sv)

        def nr_progress(f):
            return None if progress is None else progress(0.2 + 0.6 * f)

        nr = arap_icp(rigid, edges, T_pts, iterations=cfg.nonrigid_iterations, stiffness=cfg.stiffness,
                      max_distance=cfg.max_match_edges * unit, tree=tree, progress=nr_progress)
        x, residual = nr.points, nr.residual
    t_nr = time.perf_counter() - t1
    _cancelled(progress, 0.8)

    # 3. the fit of the aligned source to the target
    s_edge = sim.scale * _mean_edge(s_rest, s_faces, sv)
    fig = fit_figures(x, T_pts, unit, s_edge, overlap_edges=cfg.fit.overlap_edges)
    problems = fig.problems(cfg.fit)
    message = refusal_message(fig, cfg.fit, automatic=n_pairs == 0,
                              nonrigid=cfg.nonrigid and cfg.nonrigid_iterations > 0) if problems else ""
    return SwapAlignment(sim, tv, sv, rigid, x, _region_faces(s_faces, sv), fig, residual / unit, d_rigid / unit,
                         unit, n_pairs, problems, message, t_sim, t_nr)


def swap_texture(target, target_vertices, source=None, source_vertices=None, pairs=None,
                 config: Optional[SwapConfig] = None,
                 progress: Optional[Callable[[float], bool]] = None,
                 alignment: Optional[SwapAlignment] = None) -> EditRecord:
    """Give ``target``'s region ``target_vertices`` the texture of ``source``'s region ``source_vertices``.

    ``source`` defaults to ``target`` (a swap within one field).  Regions are vertex index arrays or
    boolean masks.  ``pairs`` (optional, >= 3): (P,2) (source vertex, target vertex) index pairs, (P,6)
    point pairs or a tuple (source points, target points), rest pose.  ``progress(fraction)`` returning
    False cancels (raises ``nm.Cancelled``; the field is unchanged).

    When the aligned source does not cover the target (``config.fit`` thresholds; docs/editing.md) the
    swap is refused: :class:`EditError` with the figures and what to do, and the field is unchanged
    (``config.check_fit=False`` applies it anyway).  :func:`swap_alignment` gives the alignment and its
    figures without writing, for a preview; pass it back as ``alignment`` to apply exactly what was
    shown (the regions must be the ones it was made for; ``pairs`` are then not used).

    Returns the :class:`EditRecord` (undo with ``record.undo(target)``); ``record.info`` holds the
    similarity (``transform``, 4x4, source rest -> target rest), the ``residual`` (mean distance of the
    aligned source vertices to the target region's nearest vertex, in mean edge lengths of the target
    region) before (``residual_rigid``) and after the non-rigid step, the fit figures (``overlap``,
    ``target_residual``, ``centroid_offset``: :class:`~neumesh_core.edit.fit_check.FitFigures`) and the
    timings.
    """
    cfg = config or SwapConfig()
    source = target if source is None else source
    t0 = time.perf_counter()
    if alignment is None:
        al = swap_alignment(target, target_vertices, source, source_vertices, pairs=pairs, config=cfg,
                            progress=progress)
    else:
        al = alignment
        check_compatible(target, source)
        tv = as_vertex_ids(target_vertices, target.num_vertices, "target region")
        sv = as_vertex_ids(source_vertices, source.num_vertices, "source region")
        if not (np.array_equal(tv, al.target_vertices) and np.array_equal(sv, al.source_vertices)):
            raise EditError("the alignment was made for other regions; run swap_alignment again with these "
                             "regions (or leave alignment out)")
    if cfg.check_fit and not al.ok:
        raise EditError(al.message)

    # 4. transfer
    t2 = time.perf_counter()
    tv, sv, sim = al.target_vertices, al.source_vertices, al.transform
    idx, w = idw_neighbours(target.rest_vertices.detach().cpu().numpy().astype(np.float64)[tv], al.points, cfg.k)
    frames = None
    if cfg.match_orientation:
        # target rest normal -> source rest frame: undo the alignment's rotation, then the smallest
        # rotation onto the (weighted) source normal
        n_t = target.rest_normals.detach().cpu().numpy().astype(np.float64)[tv]
        n_s = source.rest_normals.detach().cpu().numpy().astype(np.float64)[sv][idx]
        n_s = (n_s * w[..., None]).sum(1)
        back = n_t @ sim.R            # = R^T n_t
        frames = minimal_rotations(back, n_s) @ sim.R.T[None]
    plan = TransferPlan(tv, sv[idx], w)
    record = apply_transfer("swap_texture", target, plan, source, frames=frames, **al.info())
    record.info["transfer_s"] = time.perf_counter() - t2
    record.info["seconds"] = time.perf_counter() - t0
    if progress is not None:
        progress(1.0)
    return record


__all__ = ["SwapAlignment", "SwapConfig", "Similarity", "swap_alignment", "swap_texture"]
