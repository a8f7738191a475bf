"""Texture fill through UV maps: tile a template region's texture over a target region.

The template's UV layout is taken modulo 1 (its UV square is one tile), scaled by 1/s and repeated
over the target's UV square: a target vertex with UV u looks up the template at ``frac(s * u)``.  It
takes the inverse-distance-weighted texture codes and modification colours of its k=4 nearest template
samples in UV space, where distances wrap across tile borders (the UV plane is a torus), and the
template's decoder binding.

UVs are given per *corner* (:class:`CornerUVs`: one (vertex, uv) pair per face corner, as Blender
stores them per loop) or per vertex.  A vertex on a UV seam has several UVs: on the template each of
them is a sample; on the target the vertex looks up each of its distinct UVs and takes the mean of the
results, so both sides of a seam contribute equally.  The texture frame of a written vertex is the
smallest rotation from its normal onto the (weighted) template normal, so the template's decoder sees
the orientation it was trained with (the spin about the normal is not defined by UVs alone and stays).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from ..errors import EditError
from .record import EditRecord, as_vertex_ids
from .transfer import TransferPlan, apply_transfer, check_compatible, idw_neighbours, minimal_rotations


@dataclass
class CornerUVs:
    """UV coordinates per face corner: ``vertex`` (C,) field vertex ids and ``uv`` (C,2)."""

    vertex: np.ndarray
    uv: np.ndarray

    def __post_init__(self) -> None:
        self.vertex = np.asarray(self.vertex).reshape(-1)
        self.uv = np.asarray(self.uv, np.float64).reshape(-1, 2)
        if len(self.vertex) != len(self.uv):
            raise EditError(f"UVs: {len(self.vertex)} corner vertices but {len(self.uv)} UV pairs")
        if not np.issubdtype(self.vertex.dtype, np.integer):
            raise EditError("UVs: corner vertices must be whole vertex indices")
        self.vertex = self.vertex.astype(np.int64)
        if not np.isfinite(self.uv).all():
            raise EditError("UVs hold NaN/inf; repair the UV map")

    @staticmethod
    def per_vertex(vertices, uv) -> "CornerUVs":
        """One UV per vertex: ``uv`` (V,2) aligned with ``vertices`` (V,) as given."""
        v = np.asarray(vertices).reshape(-1)
        uv = np.asarray(uv, np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2 or len(uv) != len(v):
            raise EditError(f"UVs: expected ({len(v)}, 2) UVs, one per region vertex, got {uv.shape}")
        return CornerUVs(v, uv)

    @staticmethod
    def from_faces(faces: np.ndarray, face_uv: np.ndarray) -> "CornerUVs":
        """From triangles ``faces`` (F,3) and their corners' UVs ``face_uv`` (F,3,2)."""
        return CornerUVs(np.asarray(faces).reshape(-1), np.asarray(face_uv, np.float64).reshape(-1, 2))

    def restricted(self, vertices: np.ndarray, what: str) -> "CornerUVs":
        """The distinct (vertex, uv) corners of ``vertices`` (sorted ids); every vertex must have one."""
        keep = np.isin(self.vertex, vertices)
        v, uv = self.vertex[keep], self.uv[keep]
        missing = np.setdiff1d(vertices, v)
        if len(missing):
            raise EditError(f"{what}: {len(missing)} of the region's {len(vertices)} vertices have no UV "
                             f"(e.g. vertex {int(missing[0])}); unwrap the region or choose the right UV map")
        key = np.concatenate([v[:, None].astype(np.float64), np.round(uv, 7)], 1)
        _, first = np.unique(key, axis=0, return_index=True)
        first = np.sort(first)
        return CornerUVs(v[first], uv[first])


def _as_corners(uv, vertices_given, vertices_sorted, what: str) -> CornerUVs:
    if isinstance(uv, CornerUVs):
        c = uv
    else:
        c = CornerUVs.per_vertex(vertices_given, uv)
    return c.restricted(vertices_sorted, what)


def planar_uvs(points: np.ndarray) -> np.ndarray:
    """(N,2) UVs in [0,1] by projecting ``points`` (N,3) on their two widest principal axes (a quick
    unwrap for a roughly flat region; keeps aspect: the longer side spans [0,1])."""
    x = np.asarray(points, np.float64)
    x = x - x.mean(0)
    _, _, vt = np.linalg.svd(x, full_matrices=False)
    uv = x @ vt[:2].T
    uv -= uv.min(0)
    return uv / max(float(uv.max()), 1e-12)


_WRAP = np.array([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)], np.float64)


@dataclass
class FillConfig:
    k: int = 4                          # template samples blended per target UV
    match_orientation: bool = True      # texture frames from target normal onto template normal

    def __post_init__(self) -> None:
        if self.k < 1:
            raise EditError("k must be at least 1")


def fill_plan(target_rows: np.ndarray, target_uv: CornerUVs, template_uv: CornerUVs, scale: float,
              k: int = 4):
    """The transfer plan of a fill (which template vertices each target vertex blends, and how much)."""
    tile = np.mod(template_uv.uv, 1.0)
    pts = (tile[None] + _WRAP[:, None]).reshape(-1, 2)        # the tile and its 8 neighbours
    owner = np.tile(template_uv.vertex, len(_WRAP))
    q = np.mod(scale * target_uv.uv, 1.0)
    idx, w = idw_neighbours(q, pts, k)
    pos = np.searchsorted(target_rows, target_uv.vertex)
    return TransferPlan.from_queries(target_rows, pos, owner[idx], w)


def fill_texture(target, target_vertices, target_uv, template=None, template_vertices=None, template_uv=None,
                 scale: float = 1.0, config: Optional[FillConfig] = None,
                 progress: Optional[Callable[[float], bool]] = None) -> EditRecord:
    """Tile ``template``'s region texture over ``target``'s region through their UV maps.

    ``target_uv`` / ``template_uv``: :class:`CornerUVs` (per face corner; seams allowed) or (V,2) arrays
    aligned with ``target_vertices`` / ``template_vertices`` as given.  ``template`` defaults to
    ``target``.  ``scale`` s: the template repeats s times across the target's UV square.  Returns the
    :class:`EditRecord` (``info``: scale, counts, seconds).  Only the target region's texture codes,
    modification colours, decoder binding and texture frames change.
    """
    cfg = config or FillConfig()
    template = target if template is None else template
    if template_vertices is None or template_uv is None or target_uv is None:
        raise EditError("fill_texture needs target UVs, a template region and its UVs")
    if not np.isfinite(scale) or scale <= 0:
        raise EditError(f"scale must be a positive number, got {scale}")
    check_compatible(target, template)
    t0 = time.perf_counter()
    tv = as_vertex_ids(target_vertices, target.num_vertices, "target region")
    sv = as_vertex_ids(template_vertices, template.num_vertices, "template region")
    tuv = _as_corners(target_uv, target_vertices, tv, "target UVs")
    suv = _as_corners(template_uv, template_vertices, sv, "template UVs")
    if progress is not None and progress(0.0) is False:
        from ..render.renderer import Cancelled

        raise Cancelled("texture fill cancelled; the field is unchanged")
    plan = fill_plan(tv, tuv, suv, float(scale), cfg.k)
    frames = None
    if cfg.match_orientation:
        n_t = target.rest_normals.detach().cpu().numpy().astype(np.float64)[tv]
        n_s = template.rest_normals.detach().cpu().numpy().astype(np.float64)[plan.src]
        n_s = (n_s * plan.w[..., None]).sum(1)
        frames = minimal_rotations(n_t, n_s)
    record = apply_transfer("fill_texture", target, plan, template, frames=frames, scale=float(scale),
                            target_vertices=int(len(tv)), template_vertices=int(len(sv)),
                            target_corners=int(len(tuv.vertex)), template_samples=int(len(suv.vertex)))
    record.info["seconds"] = time.perf_counter() - t0
    if progress is not None:
        progress(1.0)
    return record


__all__ = ["CornerUVs", "FillConfig", "fill_plan", "fill_texture", "planar_uvs"]
