"""Texel paint: the paint atlas of a field (neumesh_core/field/paint_atlas.py) made and painted from one view
at the resolution of the painted image (docs/editing.md, texel paint)."""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, NamedTuple, Optional

import numpy as np
import torch

from ..errors import EditError, NeuMeshError, PaintMissError
from .paint_view import PaintConfig, _cancel, _checked_layer, _checked_surface, _rays, _render_pixels
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
    scaffold lies a radius or more off the surface; False (default): on the scaffold itself (docs/editing.md,
    "Texel paint").  A field that has
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
        from ..bake.uv import unwrap

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
        atlas.changed(self.texels)

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


def _lookup_texels(atlas, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """(n,4) flat indices of the four texels a render's bilinear lookup at (face, bary) reads
    (:meth:`PaintAtlas.sample`: between texel centres, clamped at the border)."""
    h, w = atlas.size
    xy = atlas.texel_coords(atlas.uv_at(face, bary)) - 0.5
    tx, ty = np.floor(xy[:, 0]).astype(np.int64), np.floor(xy[:, 1]).astype(np.int64)
    out = [np.clip(ty + dy, 0, h - 1) * w + np.clip(tx + dx, 0, w - 1) for dy in (0, 1) for dx in (0, 1)]
    return np.stack(out, 1)


def paint_atlas_from_view(field, K, c2w, width: int, height: int, paint_rgba: np.ndarray,
                          config: Optional[PaintConfig] = None, settings=None,
                          progress: Optional[Callable[[float], bool]] = None, surface=None) -> AtlasRecord:
    """Write a painted layer seen from one view into the field's paint atlas, texel by texel.

    1. The pixels of the paint's box (and a margin of 6 pixels) find their expected surface points
       (from ``surface``, the render the layer was painted on: :class:`RenderResult` or (opacity,
       depth) (H,W) arrays of this view of the field as it is now; else by rendering the box) and each
       point's nearest scaffold point: the render's own lookup of the paint atlas.
    2. Forward: the four texels each painted pixel's bilinear lookup reads take its paint, so the
       painted view shows the painted pixels.
    3. Backward, for other views and finer renders: every texel of the faces the painted pixels look up
       takes the paint of the pixel whose lookup point lies nearest to it (within about a pixel's
       footprint), painted or not: a texel between two painted pixels is painted, one nearer an
       unpainted pixel is not.  Texels along chart borders that a bilinear lookup reads take the paint
       of their painted neighbours (two texels into the gutter).
    4. Texels that a pixel more than 2 px from the paint reads (its bilinear footprint; with
       ``surface``, any pixel of the view whose surface point lies near the paint) are never written:
       nothing farther than 2 px from the paint changes in the painted view.
    5. Each painted texel takes its paint composited over the atlas's paint with the layer's alpha.

    Raises :class:`EditError` (nothing changed) when nothing is painted, its :class:`PaintMissError`
    when the paint covers only background or no texel.
    """
    from ..render.renderer import RenderSettings

    cfg = config or PaintConfig()
    settings = settings or RenderSettings()
    atlas = _checked_atlas(field)
    t0 = time.perf_counter()
    layer = np.clip(_checked_layer(paint_rgba, width, height), 0, 1)
    given = None if surface is None else _checked_surface(surface, width, height)
    ys, xs = np.nonzero(layer[..., 3] > 0)
    if len(ys) == 0:
        raise EditError("nothing is painted: paint on the image first (alpha > 0 marks painted pixels)")
    view = (np.asarray(K, np.float64), np.asarray(c2w, np.float64), width, height)
    timing = {}
    _cancel(progress, 0.0)

    # 1. the box around the paint: expected surface points and their lookups
    t = time.perf_counter()
    box, op, depth = _box_surface(field, view, xs, ys, given, settings, cfg.chunk_rays)
    timing["render_s"] = time.perf_counter() - t
    _cancel(progress, 0.3)
    t = time.perf_counter()
    look = _lookups(field, atlas, view, layer, box, op, depth, given, cfg.hit_opacity)
    timing["surface_s"] = time.perf_counter() - t
    _cancel(progress, 0.5)

    # 2.-4. the texels the paint goes to
    t = time.perf_counter()
    idx, rgba, protected, touched = _paint_texels(field, atlas, view[0], layer, look)
    timing["texels_s"] = time.perf_counter() - t
    _cancel(progress, 0.8)

    # 5. write: the paint over the atlas's paint
    t = time.perf_counter()
    rec = _write_paint(field, atlas, idx, rgba)
    timing["write_s"] = time.perf_counter() - t
    rec.info.update(painted_pixels=int(len(ys)), hit_pixels=int(look.painted.sum()), painted_texels=int(len(idx)),
                    protected_texels=int(len(protected)), candidate_faces=int(len(touched)),
                    box_pixels=int(len(box)), lookup_pixels=int(len(look.pix)), atlas_resolution=int(atlas.size[0]),
                    surface_given=given is not None, seconds=time.perf_counter() - t0, **timing)
    if progress is not None:
        progress(1.0)
    return rec


def _checked_atlas(field):
    """The field's paint atlas, checked against the field; an EditError when there is none."""
    atlas = getattr(field, "paint_atlas", None)
    if atlas is None:
        raise EditError("the field has no paint atlas; make one first (create_paint_atlas)")
    atlas.check(field)
    h_img, w_img = atlas.size
    if h_img != w_img:
        raise EditError("the paint atlas image must be square")
    return atlas


def _box_surface(field, view, xs, ys, given, settings, chunk: int):
    """The pixels of the paint's box with a margin of 6 (flat ids) and their opacity and expected depth:
    rendered, or read from the render painted on (``given``)."""
    K, c2w, width, height = view
    m = 6
    x0, x1 = max(0, xs.min() - m), min(width, xs.max() + m + 1)
    y0, y1 = max(0, ys.min() - m), min(height, ys.max() + m + 1)
    gy, gx = np.mgrid[y0:y1, x0:x1]
    box = (gy * width + gx).reshape(-1)
    if given is None:
        op, depth = _render_pixels(field, K, c2w, width, height, box, settings, chunk)
    else:
        op, depth = given[0][box], given[1][box]
    return box, op, depth


class _Lookups(NamedTuple):
    """The pixels whose surface point looks the paint atlas up, and where: flat pixel ids, nearest scaffold
    face and barycentrics, depth; which of them are painted, which lie farther than 2 px from the paint."""

    pix: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    z: np.ndarray
    painted: np.ndarray
    far: np.ndarray


def _lookups(field, atlas, view, layer, box, op, depth, given, hit_opacity: float) -> _Lookups:
    """Step 1's second half: the box's pixels on the surface (with ``given``, also every other pixel of
    the view whose surface point lies near the paint's), each one's nearest scaffold point within the
    distance the render paints at; an EditError when the paint covers only background."""
    from scipy.ndimage import binary_dilation

    K, c2w, width, height = view
    alpha = layer[..., 3]
    lim = 2.5 * float(field.radius)          # the render paints surface points this near the scaffold
    stroke = alpha > 0
    near_stroke = binary_dilation(stroke, iterations=2)       # "within 2 px" as the figures count it
    hit = (op >= hit_opacity) & np.isfinite(depth)
    if not (hit & stroke.reshape(-1)[box]).any():
        raise PaintMissError(f"the paint covers only background ({int(stroke.sum())} painted pixels, none on the "
                        "field); paint over the object")
    pix = box[hit]
    zpix = depth[hit].astype(np.float32)
    if given is not None:
        # every other pixel of the view whose surface point lies near the paint's surface points
        g_op, g_depth = given
        o_all, d_all = _rays(K.astype(np.float32), c2w.astype(np.float32), width, height, pix, "cpu")
        p_box = (o_all + d_all * torch.as_tensor(zpix)[:, None]).numpy()
        lo, hi = p_box.min(0) - 2 * lim, p_box.max(0) + 2 * lim
        rest = np.ones(width * height, bool)
        rest[box] = False
        rest &= (g_op >= hit_opacity) & np.isfinite(g_depth)
        cand = np.nonzero(rest)[0]
        if len(cand):
            o_c, d_c = _rays(K.astype(np.float32), c2w.astype(np.float32), width, height, cand, "cpu")
            p_c = (o_c + d_c * torch.as_tensor(g_depth[cand])[:, None]).numpy()
            inside = ((p_c >= lo) & (p_c <= hi)).all(1)
            pix = np.concatenate([pix, cand[inside]])
            zpix = np.concatenate([zpix, g_depth[cand[inside]]])
    o, d = _rays(K.astype(np.float32), c2w.astype(np.float32), width, height, pix, field.rest_vertices.device)
    pts = (o + d * torch.as_tensor(zpix, device=o.device)[:, None]).cpu().numpy().astype(np.float64)
    face, bary, dist = atlas.closest_faces(field, pts)
    near = dist <= lim
    pix, face, bary, z = pix[near], face[near], bary[near], zpix[near].astype(np.float64)
    return _Lookups(pix, face, bary, z, stroke.reshape(-1)[pix], ~near_stroke.reshape(-1)[pix])


def _paint_texels(field, atlas, K, layer, look: _Lookups):
    """Steps 2-4: the texels the paint goes to and their paint (flat ids sorted, RGBA), the texels that
    pixels far from the paint read (never written), and the faces the painted pixels look up."""
    from scipy.spatial import cKDTree

    from ..bake.uv import texel_coverage

    h_img = atlas.size[0]
    face, bary, painted = look.face, look.bary, look.painted
    # 2. forward: what the painted pixels read; 4. what pixels far from the paint read
    reads = _lookup_texels(atlas, face, bary)
    col = layer.reshape(-1, 4)[look.pix]
    fwd_idx = reads[painted].reshape(-1)
    fwd_rgba = np.repeat(col[painted], 4, 0)
    protected = np.unique(reads[look.far].reshape(-1))

    # 3. backward: texels of the faces the painted pixels look up take the paint of the nearest lookup
    V = atlas.lookup_vertices(field)
    F = field.faces.cpu().numpy().astype(np.int64)
    touched = np.unique(face[painted])
    texel, tf, tb = texel_coverage(atlas.uv.numpy()[touched].reshape(-1, 2),
                                   np.arange(3 * len(touched)).reshape(-1, 3), h_img)
    tf = touched[tf]
    ps = (tb[:, :, None] * V[F[tf]]).sum(1)
    cpt = (bary[:, :, None] * V[F[face]]).sum(1)                   # each pixel's lookup point
    dj, j = cKDTree(cpt).query(ps, k=1)
    foot = look.z[j] / max(float(K[0, 0]), 1e-9)                    # a pixel's footprint at its depth
    back = painted[j] & (dj <= 1.5 * foot)
    idx = np.concatenate([fwd_idx, texel[back]])
    rgba = np.concatenate([fwd_rgba, col[j[back]]]).astype(np.float32)
    idx, first = np.unique(idx, return_index=True)
    rgba = rgba[first]
    # bilinear lookups at chart borders read texels outside every chart: grow the paint into those
    # (never into another triangle's texels) by two texels
    idx, rgba = _grow_into_gutter(idx, rgba, texel, h_img, 2, atlas.cell)
    keep = ~np.isin(idx, protected, assume_unique=False)
    idx, rgba = idx[keep], rgba[keep]
    if len(idx) == 0:
        raise PaintMissError("no texel of the paint atlas lies under the paint; paint over the object")
    return idx, rgba, protected, touched


def _write_paint(field, atlas, idx: np.ndarray, rgba: np.ndarray) -> AtlasRecord:
    """Step 5: the paint ``rgba`` composited over the atlas's paint at texels ``idx``; the record."""
    img = atlas.image.view(-1, 4)
    tid = torch.as_tensor(idx)
    old = img[tid].numpy().copy()
    a = rgba[:, 3:4]
    out_a = a + (1 - a) * old[:, 3:4]
    out_rgb = (a * rgba[:, :3] + (1 - a) * old[:, 3:4] * old[:, :3]) / np.maximum(out_a, 1e-12)
    new = np.concatenate([out_rgb, out_a], 1).astype(np.float32)
    rec = AtlasRecord(op="paint_atlas", vertices=np.zeros(0, np.int64), old={}, texels=idx,
                      texels_old=old, texels_new=new, decoders_before=field.num_decoders,
                      decoders_after=field.num_decoders)
    img[tid] = torch.as_tensor(new)
    atlas.changed(idx)
    return rec


def paint_image_record(field, before) -> AtlasRecord:
    """The texels of the field's paint image that differ from ``before`` ((H,W,4) float, the image as
    it was, e.g. when it was last saved) as an :class:`AtlasRecord`: the record of paint made outside
    NeuMesh (Blender's Texture Paint writes the image directly), for saving it as an edit
    (``save_edited``) and undoing it exactly.  Raises :class:`EditError` when the field has no atlas
    or ``before`` is not an image of its size."""
    atlas = getattr(field, "paint_atlas", None)
    if atlas is None:
        raise EditError("the field has no paint atlas; make one first (create_paint_atlas)")
    prev = np.asarray(before, np.float32)
    if prev.shape != tuple(atlas.image.shape):
        raise EditError(f"the earlier paint image is {prev.shape}, the atlas's is {tuple(atlas.image.shape)}; "
                        "they must be the same image")
    now = atlas.image.numpy()
    idx = np.nonzero((np.abs(now - prev) > 0).any(-1).reshape(-1))[0]
    rec = AtlasRecord(op="paint_image", vertices=np.zeros(0, np.int64), old={}, texels=idx,
                      texels_old=prev.reshape(-1, 4)[idx].copy(), texels_new=now.reshape(-1, 4)[idx].copy(),
                      decoders_before=field.num_decoders, decoders_after=field.num_decoders)
    rec.info.update(painted_texels=int(len(idx)), atlas_resolution=int(atlas.size[0]))
    return rec


__all__ = ["AtlasRecord", "create_paint_atlas", "paint_atlas_from_view", "paint_image_record"]
