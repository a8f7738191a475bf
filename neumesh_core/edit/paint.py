"""Texture painting from one view: a painted layer on one rendered image becomes surface paint that
every other view sees.

1. The painted pixels' rays find their surface points (the rendered depth, where the ray hits the
   object); the *affected* vertices are those within the field radius of such a point that face the
   camera (a vertex on the far side of a thin part is left alone, so paint does not come through).
2. Only the modification colours of the affected vertices change.  The loss compares rendered and
   painted colours on the painted pixels, and rendered and original colours on every other pixel of
   the view whose rays look up an affected vertex (the ring around the stroke: exactly the pixels the
   edit could otherwise change), plus a small damping towards the current colours.
3. With the geometry frozen, a ray's colour is affine in the modification colours
   (:func:`~neumesh_core.render.renderer.mod_colour_weights`), so this fine-tuning is a linear least
   squares problem: it is solved exactly (sparse normal equations, one factorisation for the three
   channels) rather than by gradient steps.  The modification colour is free in sign and range (the
   final colour is clamped only for display), so a target far from what the decoder produces - black
   on white, a saturated sticker - is reached.

The paint layer is straight-alpha RGBA: alpha > 0 marks painted pixels and the target colour is the
layer composited over the render (``alpha * paint + (1 - alpha) * render``).  :func:`paint_layer`
derives it from a painted image and the unpainted render by their difference.
"""

from __future__ import annotations

import time
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from ..errors import EditError, PaintMissError
from .paint_atlas import AtlasRecord, create_paint_atlas, paint_atlas_from_view
from .paint_view import PaintConfig, _cancel, _checked_layer, _rays, _render, paint_layer
from .record import EditRecord


def _affected(field, points: np.ndarray, cam_centre: np.ndarray, facing: bool) -> np.ndarray:
    from scipy.spatial import cKDTree

    v = field.vertices.astype(np.float64)
    hits = cKDTree(v).query_ball_point(points, r=field.radius, return_sorted=False)
    ids = np.unique(np.fromiter((i for h in hits for i in h), dtype=np.int64)) if len(hits) else \
        np.zeros(0, np.int64)
    if facing and len(ids):
        n = field.scaffold.normals.detach().cpu().numpy().astype(np.float64)[ids]
        ids = ids[(n * (cam_centre[None] - v[ids])).sum(1) > 0]
    return ids


def paint_fields(fields: Sequence, K, c2w, width: int, height: int, paint_rgba: np.ndarray,
                 config: Optional[PaintConfig] = None, settings=None,
                 progress: Optional[Callable[[float], bool]] = None) -> list:
    """Paint on the view (K, c2w, width, height) of ``fields`` (rendered jointly, as in a scene).

    Returns one :class:`EditRecord` per field, or None for a field the painted rays do not reach.
    Raises :class:`EditError` (nothing changed) when nothing is painted, its :class:`PaintMissError`
    when the paint covers only background, and ``Cancelled`` when ``progress`` returns False.
    """
    from ..render.renderer import RenderSettings, mod_colour_weights

    cfg = config or PaintConfig()
    settings = settings or RenderSettings()
    fl = list(fields)
    if not fl:
        raise EditError("paint needs at least one field")
    t0 = time.perf_counter()
    layer = _checked_layer(paint_rgba, width, height)
    alpha = np.clip(layer[..., 3], 0, 1).reshape(-1)
    painted = np.nonzero(alpha > 0)[0]
    if len(painted) == 0:
        raise EditError("nothing is painted: paint on the image first (alpha > 0 marks painted pixels)")
    device = fl[0].rest_vertices.device
    K = np.asarray(K, np.float32)
    c2w = np.asarray(c2w, np.float32)
    cam = c2w[:3, 3].astype(np.float64)
    _cancel(progress, 0.0)

    # 1. surface points of the painted rays
    timing = {}
    t = time.perf_counter()
    o, d = _rays(K, c2w, width, height, painted, device)
    rgb_p, op_p, depth_p = _render(fl, o, d, settings, cfg.chunk_rays)
    timing["render_s"] = time.perf_counter() - t
    hit = (op_p >= cfg.hit_opacity).numpy() & np.isfinite(depth_p.numpy())
    if not hit.any():
        raise PaintMissError(f"the paint covers only background ({len(painted)} painted pixels, none on a field); "
                        "paint over the object")
    t = time.perf_counter()
    pts = (o[hit] + d[hit] * depth_p[hit, None].to(o.device)).cpu().numpy().astype(np.float64)
    affected = [_affected(f, pts, cam, cfg.facing) for f in fl]
    timing["surface_s"] = time.perf_counter() - t
    if sum(len(a) for a in affected) == 0:
        raise PaintMissError("no scaffold vertex lies near the painted surface; paint over the object")
    _cancel(progress, 0.2)

    # 2. the pixels the affected vertices can change: look around the stroke, as far as the influence
    # of a vertex (two radii) projects at the nearest painted depth
    box = _stroke_box(painted, pts, cam, float(K[0, 0]), max(f.radius for f in fl), width, height)
    t = time.perf_counter()
    ob, db = _rays(K, c2w, width, height, box, device)
    rgb_b, _, _ = _render(fl, ob, db, settings, cfg.chunk_rays)
    timing["render_s"] += time.perf_counter() - t
    t = time.perf_counter()
    _cancel(progress, 0.5)
    W = []
    for s in range(0, len(box), cfg.chunk_rays):
        parts = mod_colour_weights(fl, ob[s:s + cfg.chunk_rays], db[s:s + cfg.chunk_rays], settings)
        W.append(parts)
    import scipy.sparse as sp

    Wf = [sp.vstack([w[i] for w in W]).tocsr() for i in range(len(fl))]
    cols = [Wf[i][:, affected[i]] for i in range(len(fl))]
    A = sp.hstack(cols).tocsr()                                  # rays of the box x affected vertices
    touched = np.asarray(np.abs(A).sum(1)).reshape(-1) > 0
    is_painted = np.zeros(height * width, bool)
    is_painted[painted[hit]] = True
    paint_rows = is_painted[box] & touched
    ring_rows = ~np.isin(box, painted) & touched
    # targets: the paint over the render on painted pixels, no change on the ring
    lay = layer.reshape(-1, 4)
    tgt = lay[box[paint_rows], :3] * alpha[box[paint_rows], None] + \
        rgb_b.numpy()[paint_rows] * (1 - alpha[box[paint_rows], None])
    b = np.concatenate([tgt - rgb_b.numpy()[paint_rows], np.zeros((int(ring_rows.sum()), 3))])
    rw = np.sqrt(cfg.ring_weight)
    M = sp.vstack([A[paint_rows], rw * A[ring_rows]]).tocsr()
    b[paint_rows.sum():] *= rw
    timing["weights_s"] = time.perf_counter() - t
    _cancel(progress, 0.7)
    t = time.perf_counter()

    # 3. solve
    delta = _damped_least_squares(M, b, cfg.damping)
    timing["solve_s"] = time.perf_counter() - t
    _cancel(progress, 0.9)

    # 4. write the affected rows of each field
    fit_res = (M @ delta - b)[: int(paint_rows.sum())]
    records = _add_to_fields(fl, affected, delta, t0, painted_pixels=int(len(painted)), hit_pixels=int(hit.sum()),
                             ring_pixels=int(ring_rows.sum()), box_pixels=int(len(box)),
                             predicted_rmse=float(np.sqrt(np.mean(fit_res ** 2))) if len(fit_res) else 0.0, **timing)
    if progress is not None:
        progress(1.0)
    return records


def _stroke_box(painted, pts, cam, fx: float, radius: float, width: int, height: int) -> np.ndarray:
    """Flat ids of the pixels the affected vertices can change: the stroke's bounding box, padded by
    how far a vertex's influence (two radii, plus a margin) projects at the nearest painted depth."""
    zmin = max(float(np.min(np.linalg.norm(pts - cam[None], axis=1))), 1e-6)
    pad = int(np.ceil(3.0 * radius * fx / zmin)) + 2
    ys, xs = painted // width, painted % width
    x0, x1 = max(0, xs.min() - pad), min(width, xs.max() + pad + 1)
    y0, y1 = max(0, ys.min() - pad), min(height, ys.max() + pad + 1)
    gy, gx = np.mgrid[y0:y1, x0:x1]
    return (gy * width + gx).reshape(-1)


def _damped_least_squares(M, b: np.ndarray, damping: float) -> np.ndarray:
    """delta solving (M^T M + damping * max diag) delta = M^T b, one factorisation for the three
    channels; EditError when it does not converge."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    n_a = M.shape[1]
    diag = np.asarray(M.multiply(M).sum(0)).reshape(-1)
    lam = damping * max(float(diag.max()), 1e-12)
    solver = splu((M.T @ M + sp.diags(np.full(n_a, lam))).tocsc())
    rhs = np.asarray(M.T @ b)
    delta = np.stack([solver.solve(np.ascontiguousarray(rhs[:, c])) for c in range(3)], 1)
    if not np.isfinite(delta).all():
        raise EditError("painting did not converge (non-finite colours); paint a larger area")
    return delta


def _add_to_fields(fl, affected, delta: np.ndarray, t0: float, **facts) -> list:
    """Add each field's rows of ``delta`` (the fields' affected vertices, in order) to its
    modification colours; one EditRecord per field (None where no vertex is affected)."""
    records, offset = [], 0
    for f, ids in zip(fl, affected):
        dd = delta[offset:offset + len(ids)]
        offset += len(ids)
        if len(ids) == 0:
            records.append(None)
            continue
        rec = EditRecord.begin("paint_texture", f, ids, ("mod_colours",))
        with torch.no_grad():
            idx = torch.as_tensor(ids, device=f.mod_colours.device)
            f.mod_colours[idx] = f.mod_colours[idx] + torch.as_tensor(dd, dtype=f.mod_colours.dtype,
                                                                     device=f.mod_colours.device)
        records.append(rec.finish(f, affected_vertices=int(len(ids)), seconds=time.perf_counter() - t0, **facts))
    return records


def paint_texture(field, K, c2w, width: int, height: int, paint_rgba: np.ndarray,
                  config: Optional[PaintConfig] = None, settings=None,
                  progress: Optional[Callable[[float], bool]] = None, target: Optional[str] = None,
                  surface=None) -> EditRecord:
    """Paint ``paint_rgba`` (H,W,4 straight alpha, see :func:`paint_layer`) seen from (K, c2w) onto
    ``field``'s surface.

    ``target``: "atlas" writes the paint into the field's paint atlas at the resolution of the painted
    image (:func:`paint_atlas_from_view`; an atlas is made first when the field has none,
    :func:`create_paint_atlas`); "colours" solves for the per-vertex modification colours (paint at the
    vertex spacing: broad colour changes); None (default): the atlas when the field has one, else the
    colours.  ``surface`` (atlas only): the render the layer was painted on (``render_camera``'s result
    for this view of the field as it is now), so the painted pixels are not rendered again.  Returns
    the :class:`EditRecord`: ``record.undo(field)`` restores what it changed exactly."""
    if target not in (None, "atlas", "colours"):
        raise EditError(f"target must be 'atlas', 'colours' or None, not {target!r}")
    if target is None:
        target = "atlas" if getattr(field, "paint_atlas", None) is not None else "colours"
    if target == "atlas":
        if getattr(field, "paint_atlas", None) is None:
            create_paint_atlas(field)
        return paint_atlas_from_view(field, K, c2w, width, height, paint_rgba, config, settings, progress,
                                     surface=surface)
    return paint_fields([field], K, c2w, width, height, paint_rgba, config, settings, progress)[0]


__all__ = ["AtlasRecord", "PaintConfig", "create_paint_atlas", "paint_atlas_from_view", "paint_fields", "paint_layer",
           "paint_texture"]


def paint_onto_source(record: EditRecord, shown, source, ids: np.ndarray) -> Optional[EditRecord]:
    """Carry a paint record of a remapped field onto the field it was remapped from.

    ``shown`` is the painted remapped field (its vertex i is ``source`` vertex ``ids[i]``, or a new
    vertex where ``ids[i]`` is -1, as :func:`~neumesh_core.field.remap.resolve_ids` gives).  Each
    painted source vertex takes the mean of the painted modification colours of its copies; new
    vertices have no colour of their own and are left out.  Returns the record of the change to
    ``source`` (its ``info`` is the paint record's), or None when no painted vertex has a source.
    """
    rows = np.asarray(record.vertices)
    src = np.asarray(ids)[rows]
    keep = src >= 0
    if not keep.any():
        return None
    new = shown.mod_colours.detach().cpu().numpy()[rows[keep]]
    uniq, inv = np.unique(src[keep], return_inverse=True)
    acc = np.zeros((len(uniq), 3))
    np.add.at(acc, inv, new)
    acc /= np.bincount(inv, minlength=len(uniq))[:, None]
    rec = EditRecord.begin("paint_texture", source, uniq, ("mod_colours",))
    with torch.no_grad():
        source.mod_colours[torch.as_tensor(uniq, device=source.mod_colours.device)] = \
            torch.as_tensor(acc, dtype=source.mod_colours.dtype, device=source.mod_colours.device)
    return rec.finish(source, **record.info)
