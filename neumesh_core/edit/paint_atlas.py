"""Texel paint: the paint atlas of a field (neumesh_core/field/paint_atlas.py) made and painted from one view
at the resolution of the painted image (docs/editing.md, texel paint)."""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch

from ..errors import EditError, NeuMeshError
from .paint_view import PaintConfig, _cancel, _checked_layer, _rays, _render
from .record import EditRecord


def create_paint_atlas(field, resolution: int = 2048, uvs=None, padding: int = 4, method: str = "auto",
                       on_surface: bool = False):
    """Give ``field`` an empty paint atlas (``field.paint_atlas``) and return it.

    ``uvs``: the scaffold's UV map, per face corner (F,3,2) or per vertex (N,2), v up (Blender's and
    OBJ's convention); None makes one: ``method`` "xatlas" unwraps the scaffold's rest pose with
    xatlas (charts ``padding`` texels apart; seconds for 20k faces, about 20 minutes for lego's 417k),
    "grid" lays the faces out in pairs on a regular grid in well under a second
    (:func:`~neumesh_core.field.paint_atlas.grid_atlas`: more seams, even texel density for a scaffold's
    even faces), "auto" (default) xatlas up to 50,000 faces, else the grid.  ``resolution``: the paint
    image's width and height in texels.  ``on_surface``: look surface points up on the scaffold moved
    onto the field's surface (per-vertex offsets along the normals from
    :func:`~neumesh_core.bake.surface.fit_to_field`, vertices only, one iteration; they follow
    deformations with the normals), so that nearby surface points map to nearby texels even where the
    scaffold lies a radius or more off the surface; False (default): on the scaffold itself.  Measured
    on lego's 5,000-pixel stroke (400 px): on_surface 27.55 dB in the stroke and 11 pixels farther than
    2 px changed, against 30.63 dB and 5 on the scaffold, and the fit took 331 s on a loaded machine;
    whether it carries paint to other views better is not measured yet.  A field that has
    an atlas keeps its paint: remove it first (``field.paint_atlas = None``) to start over."""
    from ..field.paint_atlas import PaintAtlas

    if getattr(field, "paint_atlas", None) is not None:
        raise EditError("the field already has a paint atlas; set field.paint_atlas = None first to replace it")
    resolution = int(resolution)
    if not 16 <= resolution <= 16384:
        raise EditError(f"the paint atlas resolution must lie in [16, 16384] texels, got {resolution}")
    F = field.faces.cpu().numpy().astype(np.int64)
    if method not in ("auto", "xatlas", "grid"):
        raise EditError(f"method must be 'auto', 'xatlas' or 'grid', not {method!r}")
    if uvs is None and (method == "grid" or (method == "auto" and len(F) > 50_000)):
        from ..field.paint_atlas import grid_atlas

        try:
            corner, cell = grid_atlas(F, resolution)
        except NeuMeshError as exc:
            raise EditError(str(exc)) from exc
        source = "grid"
    elif uvs is None:
        from ..bake.texture import unwrap

        vmap, faces, uv, _ = unwrap(field.rest_vertices.cpu().numpy(), F, resolution, padding)
        corner = uv[faces]
        source, cell = "xatlas", None
    else:
        uv = np.asarray(uvs, np.float32)
        if uv.shape == (len(F), 3, 2):
            corner = uv
        elif uv.shape == (field.num_vertices, 2):
            corner = uv[F]
        else:
            raise EditError(f"UVs must be per face corner ({len(F)}, 3, 2) or per vertex ({field.num_vertices}, 2) "
                            f"for this scaffold, got {uv.shape}")
        if not np.isfinite(corner).all():
            raise EditError("the UV map holds NaN/inf values")
        source, cell = "given", None
    offsets = None
    if on_surface:
        from ..bake.surface import SurfaceFitConfig, fit_to_field

        V = np.asarray(field.vertices, np.float64)
        moved, _ = fit_to_field(field, V, F, SurfaceFitConfig(face_samples=0, iterations=1))
        n = field.scaffold.normals.detach().cpu().numpy().astype(np.float64)
        offsets = ((moved - V) * n).sum(1)
    field.paint_atlas = PaintAtlas(corner, np.zeros((resolution, resolution, 4), np.float32), source, cell, offsets)
    return field.paint_atlas


@dataclass
class AtlasRecord(EditRecord):
    """What a paint-atlas edit changed: texels (flat indices into the paint image) and their RGBA
    before and after; undo/redo write them back.  ``vertices`` is empty (no per-vertex table changes)."""

    texels: Optional[np.ndarray] = None
    texels_old: Optional[np.ndarray] = None
    texels_new: Optional[np.ndarray] = None

    @property
    def num_changed(self) -> int:
        return int(0 if self.texels is None else len(self.texels))

    def _write_texels(self, field, values) -> None:
        atlas = getattr(field, "paint_atlas", None)
        if atlas is None:
            raise RuntimeError(f"cannot undo/redo '{self.op}': the field has no paint atlas")
        img = atlas.image.view(-1, 4)
        img[torch.as_tensor(self.texels)] = torch.as_tensor(values)
        atlas.changed()

    def undo(self, field) -> None:
        self._write_texels(field, self.texels_old)

    def redo(self, field) -> None:
        self._write_texels(field, self.texels_new)


def _grow_into_gutter(idx: np.ndarray, rgba: np.ndarray, covered: np.ndarray, size: int, steps: int,
                      cell: Optional[float] = None):
    """Add the texels next to painted ones (8-neighbours) that lie in no chart triangle (``covered``:
    the flat texels inside the triangles around the paint), each the mean of its painted neighbours,
    ``steps`` times; with ``cell`` (a grid atlas) only within the painted texel's own cell.  Returns
    the grown (idx, rgba), idx sorted."""
    cov = np.union1d(covered, idx)
    for _ in range(int(steps)):
        y, x = idx // size, idx % size
        cand, src = [], []
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy == 0 and dx == 0:
                    continue
                yy, xx = y + dy, x + dx
                inside = (yy >= 0) & (yy < size) & (xx >= 0) & (xx < size)
                cand.append((yy * size + xx)[inside])
                src.append(np.nonzero(inside)[0])
        cand, src = np.concatenate(cand), np.concatenate(src)
        keep = ~np.isin(cand, cov)
        if cell is not None:
            def cell_of(t):
                return np.floor((t // size + 0.5) / cell) * 1e6 + np.floor((t % size + 0.5) / cell)
            keep &= cell_of(cand) == cell_of(idx[src])
        cand, src = cand[keep], src[keep]
        if len(cand) == 0:
            break
        new, inv = np.unique(cand, return_inverse=True)
        cnt = np.bincount(inv, minlength=len(new)).astype(np.float32)
        val = np.stack([np.bincount(inv, weights=rgba[src, c], minlength=len(new)) for c in range(4)], 1)
        val = (val / cnt[:, None]).astype(np.float32)
        cov = np.union1d(cov, new)
        idx = np.concatenate([idx, new])
        rgba = np.concatenate([rgba, val])
        order = np.argsort(idx, kind="stable")
        idx, rgba = idx[order], rgba[order]
    return idx, rgba


def _forward_texels(atlas, field, layer, pts, hit, face, bary, box, bx, by, x0, y0, bw, bh, sub: int):
    """Texels the render looks up from the painted pixels, with their pixel's paint: the bilinear
    footprint (4 texels) of each painted pixel centre's lookup first, then the nearest texel of
    ``sub`` x ``sub`` sub-pixel points per painted pixel (surface points interpolated between the four
    pixel centres around them when all four hit one surface, else the pixel's own)."""
    size = atlas.size[0]
    a = layer[by, bx, 3]
    live = np.nonzero(hit & (a > 0) & (face >= 0))[0]
    out_i, out_c = [], []
    if len(live) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 4), np.float32)
    col = layer[by[live], bx[live]]
    xy = atlas.texel_coords(atlas.uv_at(face[live], bary[live])) - 0.5
    tx, ty = np.floor(xy[:, 0]).astype(np.int64), np.floor(xy[:, 1]).astype(np.int64)
    for dy in (0, 1):
        for dx in (0, 1):
            out_i.append(np.clip(ty + dy, 0, size - 1) * size + np.clip(tx + dx, 0, size - 1))
            out_c.append(col)
    P = pts.reshape(bh, bw, 3)
    H = hit.reshape(bh, bw)
    depth_span = 0.5 * float(field.radius)
    gx, gy = bx[live] - x0, by[live] - y0
    for j in range(sub):
        for i in range(sub):
            fx, fy = (i + 0.5) / sub - 0.5, (j + 0.5) / sub - 0.5          # from the pixel centre
            ix0 = gx + (fx < 0) * -1
            iy0 = gy + (fy < 0) * -1
            wx, wy = fx - (ix0 - gx), fy - (iy0 - gy)
            ix1, iy1 = ix0 + 1, iy0 + 1
            inb = (ix0 >= 0) & (iy0 >= 0) & (ix1 < bw) & (iy1 < bh)
            c = [np.clip(v, 0, m - 1) for v, m in ((ix0, bw), (iy0, bh), (ix1, bw), (iy1, bh))]
            p00, p10 = P[c[1], c[0]], P[c[1], c[2]]
            p01, p11 = P[c[3], c[0]], P[c[3], c[2]]
            four = inb & H[c[1], c[0]] & H[c[1], c[2]] & H[c[3], c[0]] & H[c[3], c[2]]
            stack = np.stack([p00, p10, p01, p11])
            spread = np.linalg.norm(stack - stack.mean(0), axis=2).max(0)
            four &= spread <= depth_span
            interp = ((1 - wx)[:, None] * (1 - wy)[:, None] * p00 + wx[:, None] * (1 - wy)[:, None] * p10 +
                      (1 - wx)[:, None] * wy[:, None] * p01 + wx[:, None] * wy[:, None] * p11)
            q = np.where(four[:, None], interp, pts[live])
            f_, b_, d_ = atlas.closest_faces(field, q)
            keep = d_ <= 2.5 * float(field.radius)
            t = np.floor(atlas.texel_coords(atlas.uv_at(f_[keep], b_[keep]))).astype(np.int64)
            out_i.append(np.clip(t[:, 1], 0, size - 1) * size + np.clip(t[:, 0], 0, size - 1))
            out_c.append(col[keep])
    return np.concatenate(out_i), np.concatenate(out_c).astype(np.float32)


def _sample_nearest(layer: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(n,4) the painted pixel (nearest: the pixel square) containing each image position q (x, y)."""
    h, w = layer.shape[:2]
    xi = np.clip(np.floor(q[:, 0]).astype(np.int64), 0, w - 1)
    yi = np.clip(np.floor(q[:, 1]).astype(np.int64), 0, h - 1)
    return layer[yi, xi]


def paint_atlas_from_view(field, K, c2w, width: int, height: int, paint_rgba: np.ndarray,
                          config: Optional[PaintConfig] = None, settings=None,
                          progress: Optional[Callable[[float], bool]] = None) -> AtlasRecord:
    """Write a painted layer seen from one view into the field's paint atlas, texel by texel.

    1. The rays of the painted pixels' box (and a margin of 3 pixels) find their expected surface
       points and each point's nearest scaffold point (the render's lookup).
    2. The texels of the faces those points touch (and their one-ring) each search the line through
       their scaffold point along the face normal (turned towards the camera) for where it meets the
       surface this view renders (the first crossing, from the camera's side, of ray distance minus
       rendered depth, over +-2.5 radii).  A texel is painted when it finds one and the pixel it
       projects to has its nearest scaffold point within about a pixel of the texel's: the render
       looks this texel up from that pixel.
    3. Each painted texel takes the painted pixel it projects into (nearest: the paint is as sharp as
       the painted image), composited over the atlas's paint with the layer's alpha.

    The render composites the atlas at every ray's expected surface point via the same nearest-face
    lookup, so re-rendering the painted view shows the painted pixels.  Raises :class:`EditError`
    (nothing changed) when nothing is painted or the paint covers only background.
    """
    from ..render.renderer import RenderSettings
    from ..bake.texture import texel_coverage

    cfg = config or PaintConfig()
    settings = settings or RenderSettings()
    atlas = getattr(field, "paint_atlas", None)
    if atlas is None:
        raise EditError("the field has no paint atlas; make one first (create_paint_atlas)")
    atlas.check(field)
    t0 = time.perf_counter()
    layer = _checked_layer(paint_rgba, width, height)
    layer = np.clip(layer, 0, 1)
    alpha = layer[..., 3]
    ys, xs = np.nonzero(alpha > 0)
    if len(ys) == 0:
        raise EditError("nothing is painted: paint on the image first (alpha > 0 marks painted pixels)")
    K = np.asarray(K, np.float64)
    c2w = np.asarray(c2w, np.float64)
    cam = c2w[:3, 3]
    device = field.rest_vertices.device
    timing = {}
    _cancel(progress, 0.0)

    # 1. the box around the paint: expected surface points, their faces and offsets along the normals
    m = 3
    x0, x1 = max(0, xs.min() - m), min(width, xs.max() + m + 1)
    y0, y1 = max(0, ys.min() - m), min(height, ys.max() + m + 1)
    bw, bh = x1 - x0, y1 - y0
    gy, gx = np.mgrid[y0:y1, x0:x1]
    box = (gy * width + gx).reshape(-1)
    t = time.perf_counter()
    o, d = _rays(K.astype(np.float32), c2w.astype(np.float32), width, height, box, device)
    _, op, depth = _render([field], o, d, settings, cfg.chunk_rays)
    timing["render_s"] = time.perf_counter() - t
    _cancel(progress, 0.4)
    t = time.perf_counter()
    hit = (op >= cfg.hit_opacity).numpy() & np.isfinite(depth.numpy())
    painted_box = alpha[gy, gx].reshape(-1) > 0
    if not (hit & painted_box).any():
        raise EditError(f"the paint covers only background ({len(ys)} painted pixels, none on the field); "
                        "paint over the object")
    pts = (o + d * torch.where(torch.as_tensor(hit), depth, torch.zeros_like(depth))[:, None]).cpu().numpy()
    pts = pts.astype(np.float64)
    face = np.full(len(box), -1, np.int64)
    hf, hb, hd = atlas.closest_faces(field, pts[hit])
    V = atlas.lookup_vertices(field)             # the surface the lookups are made on
    F = field.faces.cpu().numpy().astype(np.int64)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
    near = hd <= 2.5 * field.radius
    hi = np.nonzero(hit)[0]
    face[hi[near]] = hf[near]
    cpt = (hb[near, :, None] * V[F[hf[near]]]).sum(1)
    cbox = np.full((len(box), 3), np.nan)      # each box pixel's nearest scaffold point
    cbox[hi[near]] = cpt
    bbox_bary = np.zeros((len(box), 3))
    bbox_bary[hi[near]] = hb[near]
    timing["surface_s"] = time.perf_counter() - t

    # 2. the texels of the touched faces and their one-ring, on the field's surface, seen from the view
    t = time.perf_counter()
    touched = np.unique(face[face >= 0])
    ring_v = np.unique(F[touched])
    is_v = np.zeros(len(V), bool)
    is_v[ring_v] = True
    cand = np.nonzero(is_v[F].any(1))[0]
    h_img, w_img = atlas.size
    if h_img != w_img:
        raise EditError("the paint atlas image must be square")
    texel, tf, tb = texel_coverage(atlas.uv.numpy()[cand].reshape(-1, 2), np.arange(3 * len(cand)).reshape(-1, 3),
                                   h_img)
    tf = cand[tf]
    ps = (tb[:, :, None] * V[F[tf]]).sum(1)
    # the face normal turned towards the camera: the render's nearest-face lookup does not care how a
    # face is wound, so neither does this (a scaffold may hold flipped faces)
    nrm = fn[tf] * np.where((fn[tf] * (cam[None] - ps)).sum(1) >= 0, 1.0, -1.0)[:, None]
    w2c = np.linalg.inv(c2w)

    def project(x):
        c = x @ w2c[:3, :3].T + w2c[:3, 3]
        z = np.maximum(c[:, 2], 1e-9)
        return np.stack([K[0, 0] * c[:, 0] / z + K[0, 2], K[1, 1] * c[:, 1] / z + K[1, 2]], 1), c[:, 2]

    def box_index(q):
        xi = np.floor(q[:, 0]).astype(np.int64) - x0
        yi = np.floor(q[:, 1]).astype(np.int64) - y0
        inside = (xi >= 0) & (xi < bw) & (yi >= 0) & (yi < bh)
        return np.where(inside, yi * bw + np.clip(xi, 0, bw - 1), -1), inside

    # each texel's line along its face normal: where it meets the surface this view renders (the
    # first crossing from outside of ray distance - rendered depth), found on 41 points over +-2.5 radii
    # (the render paints surface points within 2.5 radii of the scaffold)
    zmap = np.where(hit, depth.numpy().astype(np.float64), np.nan)
    steps = np.linspace(2.5, -2.5, 41) * float(field.radius)
    res_prev, s_prev = None, None
    s_hit = np.full(len(ps), np.nan)
    for sk in steps:
        pk = ps + sk * nrm
        qk, _ = project(pk)
        bi, inside = box_index(qk)
        dist_k = np.linalg.norm(pk - cam[None], axis=1)
        res = np.where(inside, dist_k - zmap[np.maximum(bi, 0)], np.nan)
        if res_prev is not None:
            cross = np.isnan(s_hit) & (res_prev <= 0) & (res > 0)
            frac = res_prev / np.where(res - res_prev != 0, res_prev - res, -1e-30)
            s_hit = np.where(cross, s_prev + np.clip(frac, 0, 1) * (sk - s_prev), s_hit)
        res_prev, s_prev = res, sk
    ok = np.isfinite(s_hit)
    p = ps + np.where(ok, s_hit, 0.0)[:, None] * nrm
    q, z = project(p)
    bi, inside = box_index(q)
    ok &= inside & (z > 0)
    bi_ok = np.maximum(bi, 0)
    # the render looks this texel up from that pixel: the pixel's surface point has its nearest
    # scaffold point within a pixel footprint or so of the texel's scaffold point
    pix_foot = z / max(float(K[0, 0]), 1e-9)
    ok &= hit[bi_ok] & (np.linalg.norm(cbox[bi_ok] - ps, axis=1) <= 2.0 * pix_foot + 0.05 * field.radius)
    timing["texels_s"] = time.perf_counter() - t

    # 3. paint: the painted pixel each texel lies in, over the atlas's paint.  Forward too (the render's
    # own lookup): the texels around each painted pixel's lookup (its bilinear footprint) and those
    # that 4 x 4 sub-pixel surface points (interpolated between pixel centres on one surface) look up
    t = time.perf_counter()
    fwd_idx, fwd_rgba = _forward_texels(atlas, field, layer, pts, hit, face, bbox_bary, box, gx.reshape(-1),
                                        gy.reshape(-1), x0, y0, bw, bh, 4)
    rgba = np.concatenate([fwd_rgba, _sample_nearest(layer, q[ok])])
    idx = np.concatenate([fwd_idx, texel[ok]])
    sel = rgba[:, 3] > 0
    idx = idx[sel]
    rgba = rgba[sel]
    if len(idx) == 0:
        raise EditError("no texel of the paint atlas lies under the paint; paint over the object")
    idx, first = np.unique(idx, return_index=True)
    rgba = rgba[first]
    # bilinear lookups at chart borders read texels outside every chart: grow the paint into those
    # (never into another triangle's texels) by two texels
    idx, rgba = _grow_into_gutter(idx, rgba, texel, h_img, 2, atlas.cell)
    img = atlas.image.view(-1, 4)
    old = img[torch.as_tensor(idx)].numpy().copy()
    a = rgba[:, 3:4]
    out_a = a + (1 - a) * old[:, 3:4]
    out_rgb = (a * rgba[:, :3] + (1 - a) * old[:, 3:4] * old[:, :3]) / np.maximum(out_a, 1e-12)
    new = np.concatenate([out_rgb, out_a], 1).astype(np.float32)
    rec = AtlasRecord(op="paint_atlas", vertices=np.zeros(0, np.int64), old={}, texels=idx,
                      texels_old=old, texels_new=new, decoders_before=field.num_decoders,
                      decoders_after=field.num_decoders)
    img[torch.as_tensor(idx)] = torch.as_tensor(new)
    atlas.changed()
    timing["write_s"] = time.perf_counter() - t
    rec.info.update(painted_pixels=int(len(ys)), hit_pixels=int((hit & painted_box).sum()),
                    painted_texels=int(len(idx)), candidate_faces=int(len(cand)), box_pixels=int(len(box)),
                    atlas_resolution=int(h_img), seconds=time.perf_counter() - t0, **timing)
    if progress is not None:
        progress(1.0)
    return rec


__all__ = ["AtlasRecord", "create_paint_atlas", "paint_atlas_from_view"]
