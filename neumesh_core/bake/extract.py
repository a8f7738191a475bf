"""A mesh of the surface the field renders, extracted from its own density (the bake's default target).

The scaffold, and a decimated copy of it, sits up to a field radius off the surface the field's
density puts the object on, and decimating it cuts corners through thin parts; moving its vertices
along their normals (:func:`~neumesh_core.bake.surface.fit_to_field`) cannot fix a wrong topology.
This module samples the field's density on a grid of ``voxel`` field radii (only the nodes in and
around the occupancy grid's occupied cells), runs marching cubes at a density level, drops floating
bits, and decimates the result to about ``faces`` triangles (:func:`~neumesh_core.bake.texture.decimate`).

Which density is "the surface" depends on the field; ``level`` None picks it among ``levels`` (each
an opacity gathered over one field radius, turned into a density: -ln(1 - a) / radius): every
candidate's (decimated) mesh is compared with the field's own depth maps from ``views`` virtual
cameras (:func:`~neumesh_core.bake.surface.render_disagreement`: the share of pixels where mesh and
field show another surface) and the best one is kept.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from ..errors import NeuMeshError


@dataclass
class ExtractConfig:
    """How :func:`extract_surface` builds the bake's target mesh from the field's density."""

    voxel: float = 0.35          # grid spacing, field radii
    faces: int = 0               # decimate to about this many triangles (0: keep marching cubes' mesh)
    # density level of the surface as an opacity over one field radius; None: the best of ``levels``
    level: Optional[float] = None
    levels: tuple = (0.3, 0.5, 0.7, 0.85, 0.95)
    views: int = 6
    view_size: int = 128
    min_component: float = 0.0005   # drop connected pieces with fewer faces than this x the largest
    chunk: int = 262144

    def __post_init__(self) -> None:
        if self.voxel <= 0 or self.faces < 0:
            raise ValueError("voxel must be > 0 field radii and faces >= 0")
        for lv in ([self.level] if self.level is not None else list(self.levels)):
            if not 0.0 < float(lv) < 1.0:
                raise ValueError(f"a level is an opacity in (0, 1), got {lv}")
        if self.level is None and (len(self.levels) < 1 or self.views < 1 or self.view_size < 16):
            raise ValueError("level None calibrates over levels (at least one), views >= 1 of view_size >= 16")


@torch.no_grad()
def density_grid(field, voxel: float, chunk: int = 262144,
                 progress: Optional[Callable[[float], bool]] = None, span: tuple = (0.0, 1.0)) -> tuple:
    """The field's density on a grid of ``voxel`` world units over its occupancy grid's box: (values
    (X,Y,Z) float32, lo (3,) the first node's position).  Nodes outside the occupied cells (grown by
    one cell) are 0 and not queried."""
    from .surface import _cancel

    g = field.grid
    lo = g.aabb[0].detach().cpu().double().numpy()
    hi = g.aabb[1].detach().cpu().double().numpy()
    dims = np.ceil((hi - lo) / voxel).astype(np.int64) + 1
    if int(np.prod(dims)) > 600 ** 3:
        raise NeuMeshError(f"a density grid of {dims.tolist()} nodes is too large: raise the voxel size")
    occ = g.occ.detach().cpu().float()[None, None]
    occ = (torch.nn.functional.max_pool3d(occ, 3, 1, 1)[0, 0] > 0).numpy()
    cell = g.cell.detach().cpu().double().numpy()
    res = g.resolution.detach().cpu().numpy()
    axes = [lo[i] + voxel * np.arange(dims[i]) for i in range(3)]
    ci = [np.clip(np.floor((axes[i] - lo[i]) / cell[i]).astype(np.int64), 0, res[i] - 1) for i in range(3)]
    idx = np.nonzero(occ[np.ix_(ci[0], ci[1], ci[2])].reshape(-1))[0]
    vals = np.zeros(int(np.prod(dims)), np.float32)
    dev = field.geo_codes.device
    for s in range(0, len(idx), int(chunk)):
        ii = np.unravel_index(idx[s:s + chunk], tuple(dims))
        pts = np.stack([axes[0][ii[0]], axes[1][ii[1]], axes[2][ii[2]]], 1).astype(np.float32)
        sigma, _ = field.sigma_fn(torch.from_numpy(pts).to(dev))
        vals[idx[s:s + chunk]] = sigma.float().cpu().numpy()
        _cancel(progress, span[0] + (span[1] - span[0]) * min(1.0, (s + chunk) / max(1, len(idx))))
    return vals.reshape(tuple(dims)), lo.astype(np.float32)


def _mesh_at(vals, density, lo, voxel, faces, min_component):
    from ..reconstruct.meshing import clean_mesh, keep_large_components, marching_cubes
    from .simplify import decimate

    m = marching_cubes(vals, density, lo, voxel)
    if len(m.faces) == 0:
        return None, 0
    m = clean_mesh(m, merge_eps=voxel * 1e-3)
    m, _, _ = keep_large_components(m, min_fraction=min_component)
    full = len(m.faces)
    if faces and faces < full:
        v, f = decimate(m.vertices, m.faces, faces / full)
        return (np.asarray(v, np.float32), np.asarray(f, np.int64)), full
    return (np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.int64)), full


def extract_surface(field, config: Optional[ExtractConfig] = None,
                    progress: Optional[Callable[[float], bool]] = None) -> tuple:
    """Mesh the surface the field renders: ((vertices (V,3) float32, faces (F,3) int64), info).

    ``info``: the level used (opacity over a radius and the density), each candidate's score when
    calibrated, the grid's size, marching cubes' face count before decimation, and the seconds."""
    from .surface import _cancel, render_disagreement, view_cameras

    cfg = config or ExtractConfig()
    t0 = time.perf_counter()
    r = float(field.radius)
    voxel = float(cfg.voxel) * r
    vals, lo = density_grid(field, voxel, cfg.chunk, progress, (0.0, 0.5))
    info = {"voxel_radii": float(cfg.voxel), "grid": list(vals.shape), "grid_s": time.perf_counter() - t0}
    levels = [float(cfg.level)] if cfg.level is not None else [float(x) for x in cfg.levels]
    to_density = [-math.log(1.0 - a) / r for a in levels]
    if float(vals.max()) <= min(to_density):
        raise NeuMeshError("the field's density never reaches a surface level: nothing to bake onto "
                           "(is the field trained?)")
    best = None
    if len(levels) == 1:
        best = (0.0, levels[0], to_density[0]) + _mesh_at(vals, to_density[0], lo, voxel, cfg.faces,
                                                          cfg.min_component)
    else:
        from ..render.renderer import render_camera

        cams = view_cameras(np.asarray(field.vertices), cfg.views, cfg.view_size)
        refs = []
        for K, c2w in cams:
            out = render_camera(field, K, c2w, cfg.view_size, cfg.view_size, background=None,
                                progress=None if progress is None else (lambda f: progress(0.5)))
            refs.append(np.where(out.opacity >= 0.5, out.depth, np.inf))
            _cancel(progress, 0.5)
        scores = {}
        for i, (a, dens) in enumerate(zip(levels, to_density)):
            mesh, full = _mesh_at(vals, dens, lo, voxel, cfg.faces, cfg.min_component)
            if mesh is None:
                continue
            sc = render_disagreement(refs, mesh[0], mesh[1], cams, cfg.view_size, r)
            scores[f"{a:g}"] = sc
            if best is None or sc < best[0]:
                best = (sc, a, dens, mesh, full)
            _cancel(progress, 0.5 + 0.5 * (i + 1) / len(levels))
        info["level_scores"] = scores
    if best is None or best[3] is None:
        raise NeuMeshError("marching cubes found no surface in the field's density")
    _, a, dens, mesh, full = best
    info.update({"level": a, "density": dens, "marching_cubes_faces": int(full),
                 "vertices": int(len(mesh[0])), "faces": int(len(mesh[1])),
                 "seconds": time.perf_counter() - t0})
    return mesh, info
