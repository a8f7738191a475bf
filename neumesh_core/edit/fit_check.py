"""How well an aligned source region fits its target region, and the check that refuses a swap whose
alignment failed (docs/editing.md#when-the-alignment-fails).

A texture swap gives every target vertex the codes of its nearest aligned source vertices, so what
matters is how close the aligned source lies to each *target* vertex:

- ``overlap``: the fraction of target vertices with an aligned source vertex within
  ``overlap_edges`` edge lengths;
- ``target_residual``: the mean distance from a target vertex to its nearest aligned source vertex.

Both are measured in the larger of the two regions' mean edge lengths (the source's scaled by the
alignment), so a coarser source is not penalised for its vertex spacing.  Pure numpy; knows nothing
about fields.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..errors import EditError


@dataclass
class FitThresholds:
    """When an aligned source region is taken to fit its target (defaults measured on the built-in
    scenes; docs/editing.md lists the figures behind them)."""

    min_overlap: float = 0.6            # at least this fraction of target vertices is covered ...
    overlap_edges: float = 2.0          # ... by an aligned source vertex within this many edge lengths
    max_residual_edges: float = 3.0     # mean target -> aligned source distance, in edge lengths

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_overlap <= 1.0:
            raise EditError("min_overlap must lie in [0, 1]")
        if self.overlap_edges <= 0 or self.max_residual_edges <= 0:
            raise EditError("overlap_edges and max_residual_edges must be positive")


@dataclass
class FitFigures:
    """The fit of an aligned source region to a target region (distances in edge lengths ``unit``)."""

    overlap: float            # fraction of target vertices covered (see FitThresholds.overlap_edges)
    target_residual: float    # mean target -> nearest aligned source vertex distance / unit
    source_residual: float    # mean aligned source -> nearest target vertex distance / unit
    centroid_offset: float    # |aligned source centroid - target centroid| / unit
    unit: float               # the larger mean edge length of the two regions (target frame)

    def as_dict(self) -> dict:
        return {"overlap": self.overlap, "target_residual": self.target_residual,
                "source_residual": self.source_residual, "centroid_offset": self.centroid_offset,
                "fit_unit": self.unit}

    def problems(self, limits: FitThresholds) -> list:
        """What fails ``limits``, in words (empty when the fit passes)."""
        out = []
        if not (np.isfinite(self.overlap) and self.overlap >= limits.min_overlap):
            out.append(f"only {100 * self.overlap:.0f}% of the target lies within {limits.overlap_edges:g} edge "
                       f"lengths of the aligned source (at least {100 * limits.min_overlap:.0f}% needed)")
        if not (np.isfinite(self.target_residual) and self.target_residual <= limits.max_residual_edges):
            out.append(f"the target lies {self.target_residual:.2f} edge lengths from the aligned source on "
                       f"average (at most {limits.max_residual_edges:g} allowed)")
        return out


def fit_figures(source_points: np.ndarray, target_points: np.ndarray, target_edge: float,
                source_edge: Optional[float] = None, overlap_edges: float = 2.0) -> FitFigures:
    """The fit of ``source_points`` (S,3, already aligned into the target's frame) to ``target_points``
    (T,3).  ``target_edge``: the target region's mean edge length; ``source_edge``: the aligned source
    region's (None: the target's).  ``overlap_edges``: the radius that counts a target vertex as
    covered, in edge lengths."""
    from ..field.knn import kd_tree

    x = np.ascontiguousarray(source_points, dtype=np.float64)
    t = np.ascontiguousarray(target_points, dtype=np.float64)
    unit = max(float(target_edge), float(source_edge or 0.0), 1e-30)
    if not np.isfinite(x).all():
        return FitFigures(0.0, np.inf, np.inf, np.inf, unit)
    d_t = np.asarray(kd_tree(x).query(t, k=1)[0], np.float64)
    d_s = np.asarray(kd_tree(t).query(x, k=1)[0], np.float64)
    return FitFigures(overlap=float((d_t <= overlap_edges * unit).mean()), target_residual=float(d_t.mean() / unit),
                      source_residual=float(d_s.mean() / unit),
                      centroid_offset=float(np.linalg.norm(x.mean(0) - t.mean(0)) / unit), unit=unit)


def refusal_message(figures: FitFigures, limits: FitThresholds, automatic: bool, nonrigid: bool = True) -> str:
    """The message of a refused swap: what failed and what to do (``automatic``: no point pairs were
    given; ``nonrigid``: the non-rigid fit ran)."""
    what = "; ".join(figures.problems(limits))
    if automatic:
        todo = ("The automatic alignment did not bring the source region onto the target. Pick 3 or more "
                "vertex pairs (the same points on the source and on the target; in Blender: select them "
                "in Edit Mode, source and target in the same order, and tick 'Use selected pairs'), or "
                "select regions of more similar shape and size.")
    else:
        todo = ("The point pairs do not bring the source region onto the target: check that each pair "
                "joins the same point on the source and on the target, in the same order, and spread the "
                "pairs over the region.")
    if not nonrigid:
        todo += " The non-rigid fit was off: turning it on lets the source follow the target's shape."
    return (f"texture swap refused, nothing was changed: {what}. {todo} To apply a swap that fails this "
            "check anyway, turn the fit check off (SwapConfig(check_fit=False), `neumesh edit swap "
            "--no-check`).")


__all__ = ["FitFigures", "FitThresholds", "fit_figures", "refusal_message"]
