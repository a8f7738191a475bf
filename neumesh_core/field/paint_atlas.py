"""The paint atlas: paint at texel resolution, bound to the scaffold's faces.

A field's per-vertex modification colours carry paint at the resolution of the vertex spacing (the
field radius): a thin line or lettering painted with them comes out as a soft blob.  The paint atlas
holds paint in an image instead:

* a UV atlas of the scaffold: (F,3,2) UVs per face corner (the user's UV map, or an xatlas unwrap),
  v up as in Blender and OBJ (v = 1 is the image's first row);
* an RGBA paint image (H,W,4), straight alpha, in that atlas.

At render time every ray's expected surface point (its origin + direction x its expected depth) is
projected onto the nearest scaffold face in the field's *current* pose; the face and barycentric
coordinates give a UV, the UV a paint colour (bilinear, premultiplied), and the paint is composited
over the field's colour there (:meth:`PaintAtlas.composite`).  Because the binding is to the scaffold's
faces, the paint follows every deformation of the scaffold; because it is looked up by surface point,
not by view, it is view independent like the paper's modification colours.

Files: the atlas is saved with the field as ``paint/uv`` (F,3,2) float32 and ``paint/image`` (H,W,4)
uint8 tensors and a ``paint_atlas`` header entry {version, resolution, source}; a file without them
(every file written before the atlas existed) loads as a field without paint atlas.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np
import torch

from ..errors import CheckpointError, NeuMeshError
from .paint_copy import PremultipliedCopy
from .triangles import closest_faces_reference, closest_points_on_triangles  # noqa: F401  (re-exported)

ATLAS_VERSION = 1


def grid_atlas(faces: np.ndarray, resolution: int, gutter: float = 1.0) -> tuple:
    """A UV atlas for any triangle mesh in a fraction of a second: faces paired across shared edges
    (greedy matching), each pair in its own square cell of a regular grid (the shared edge on the
    cell's diagonal, so paint is continuous across it), a face without a partner alone in a cell;
    ``gutter`` texels kept free along every cell border (1: a bilinear lookup inside a face reads only
    its own cell's texels).  Texel density is per face, not per area (scaffold faces are of similar
    size); xatlas gives fewer seams but takes minutes for a few hundred thousand faces.
    Returns (UVs per face corner (F,3,2) v up, the cell size in texels)."""
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    nf = len(F)
    if nf == 0:
        raise NeuMeshError("the mesh has no faces to lay out")
    # interior edges: (face, corner) of both sides
    e = np.stack([F, np.roll(F, -1, 1)], 2).reshape(-1, 2)            # edge k of face f: corners k, k+1
    key = np.sort(e, 1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    ks = key[order]
    same = (ks[1:] == ks[:-1]).all(1)
    first, second = order[:-1][same], order[1:][same]                   # half-edge ids (3 f + k)
    partner = np.full(nf, -1, np.int64)
    corner = np.zeros(nf, np.int64)
    taken = np.zeros(nf, bool)
    for h1, h2 in zip(first.tolist(), second.tolist()):
        f1, f2 = h1 // 3, h2 // 3
        if f1 != f2 and not taken[f1] and not taken[f2]:
            taken[f1] = taken[f2] = True
            partner[f1], partner[f2] = f2, -2                                # f2 is laid out with f1
            corner[f1], corner[f2] = h1 % 3, h2 % 3
    leads = np.nonzero(partner != -2)[0]                                # one cell each
    cells = len(leads)
    per_row = int(math.ceil(math.sqrt(cells)))
    size = float(resolution) / per_row
    if size - 2 * gutter < 1.0:
        raise NeuMeshError(f"{nf} faces do not fit a {resolution}^2 paint atlas (cells of {size:.2f} texels); "
                           "use a larger resolution")
    x0 = (np.arange(cells) % per_row) * size
    y0 = (np.arange(cells) // per_row) * size
    lo, hi = gutter, size - gutter
    uv = np.zeros((nf, 3, 2))
    # lead face corners a (at corner k), b (k+1), c (k+2): a -> (lo, lo), b -> (hi, hi), c -> (hi, lo)
    k = corner[leads]
    for off, (px, py) in enumerate(((lo, lo), (hi, hi), (hi, lo))):
        uv[leads, (k + off) % 3, 0] = x0 + px
        uv[leads, (k + off) % 3, 1] = y0 + py
    paired = partner[leads] >= 0
    f2 = partner[leads][paired]
    k2 = corner[f2]
    # partner corners: b (at its corner k2), a (k2+1), d (k2+2) -> (hi, hi), (lo, lo), (lo, hi)
    for off, (px, py) in enumerate(((hi, hi), (lo, lo), (lo, hi))):
        uv[f2, (k2 + off) % 3, 0] = x0[paired] + px
        uv[f2, (k2 + off) % 3, 1] = y0[paired] + py
    out = np.empty_like(uv)
    out[..., 0] = uv[..., 0] / resolution
    out[..., 1] = 1.0 - uv[..., 1] / resolution
    return out.astype(np.float32), float(size)


class PaintAtlas:
    """UVs per scaffold face corner and an RGBA paint image in that atlas (see the module's doc)."""

    def __init__(self, uv, image, source: str = "xatlas", cell: Optional[float] = None, offsets=None):
        uv = torch.as_tensor(np.asarray(uv, np.float32))
        image = torch.as_tensor(np.asarray(image, np.float32))
        if uv.ndim != 3 or uv.shape[1:] != (3, 2):
            raise NeuMeshError(f"paint atlas UVs must be (faces, 3, 2), got {tuple(uv.shape)}")
        if image.ndim != 3 or image.shape[2] != 4 or image.shape[0] < 1 or image.shape[1] < 1:
            raise NeuMeshError(f"the paint image must be (height, width, 4) RGBA, got {tuple(image.shape)}")
        if not torch.isfinite(uv).all() or not torch.isfinite(image).all():
            raise NeuMeshError("the paint atlas holds NaN/inf values")
        self.uv = uv.contiguous()
        self.image = image.clamp(0, 1).contiguous()
        self.source = str(source)
        self.cell = None if cell is None else float(cell)   # grid atlases: the cell size in texels
        # (N,) per scaffold vertex: how far along its normal the field's surface lies (world units);
        # lookups use the scaffold moved by them (the surface the field renders), None: the scaffold
        self.offsets = None if offsets is None else torch.as_tensor(np.asarray(offsets, np.float32)).reshape(-1)
        if self.offsets is not None and not torch.isfinite(self.offsets).all():
            raise NeuMeshError("the paint atlas's surface offsets hold NaN/inf values")
        self._cache = None
        self._premultiplied = PremultipliedCopy()   # what sample() reads; safe across threads

    def changed(self, texels=None) -> None:
        """Call after writing :attr:`image` in place: the premultiplied copy used for sampling is
        rebuilt, or with ``texels`` (flat indices of the texels written) updated at those texels only
        (also while another thread renders: field/paint_copy.py)."""
        if texels is None:
            self._premultiplied.invalidate()
        else:
            self._premultiplied.update(self.image.numpy(), texels)

    def set_image(self, rgba, region=None) -> np.ndarray:
        """Replace the paint image, or the part of it in ``region`` (y0, y1, x0, x1 in image rows/columns,
        top row first), with ``rgba`` (straight alpha, float in [0, 1]; a paint program's pixels).  The
        field is not rebuilt: the next render shows the new paint.  Returns the flat indices of the
        texels that changed."""
        h, w = self.size
        y0, y1, x0, x1 = (0, h, 0, w) if region is None else (int(v) for v in region)
        if not (0 <= y0 < y1 <= h and 0 <= x0 < x1 <= w):
            raise NeuMeshError(f"region {region} lies outside the {w}x{h} paint image")
        px = np.asarray(rgba, np.float32)
        if px.shape != (y1 - y0, x1 - x0, 4):
            raise NeuMeshError(f"the paint pixels are {px.shape}, expected ({y1 - y0}, {x1 - x0}, 4) RGBA for "
                               f"this part of the {w}x{h} paint image; was the image resized?")
        if not np.isfinite(px).all():
            raise NeuMeshError("the paint pixels hold NaN/inf values")
        cur = self.image.numpy()[y0:y1, x0:x1]
        yy, xx = np.nonzero((cur != np.clip(px, 0.0, 1.0)).any(-1))
        return self.set_texels((yy + y0) * w + (xx + x0), px[yy, xx])

    def set_texels(self, texels, rgba) -> np.ndarray:
        """Write RGBA (n,4) (straight alpha, clamped to [0, 1]) at flat texel indices (n,) of the paint
        image (row-major, top row first): :meth:`set_image` for paint whose changed texels are known.
        Returns the indices of the texels whose value changed."""
        t = np.asarray(texels, np.int64).reshape(-1)
        v = np.asarray(rgba, np.float32).reshape(-1, 4)
        h, w = self.size
        if len(t) != len(v):
            raise NeuMeshError(f"{len(t)} texels but {len(v)} RGBA values")
        if len(t) and (t.min() < 0 or t.max() >= h * w):
            raise NeuMeshError(f"texel indices outside the {w}x{h} paint image")
        if not np.isfinite(v).all():
            raise NeuMeshError("the paint pixels hold NaN/inf values")
        v = np.clip(v, 0.0, 1.0)
        flat = self.image.view(-1, 4).numpy()
        diff = (flat[t] != v).any(1)
        t, v = t[diff], v[diff]
        if len(t) == 0:
            return np.zeros(0, np.int64)
        flat[t] = v
        self.changed(t)
        return t

    def _pm(self) -> np.ndarray:
        return self._premultiplied.get(self.image.numpy())[0]

    # -- basics ---------------------------------------------------------------------------------------
    @property
    def num_faces(self) -> int:
        return int(self.uv.shape[0])

    @property
    def size(self) -> tuple:
        """(height, width) of the paint image."""
        return int(self.image.shape[0]), int(self.image.shape[1])

    @property
    def is_empty(self) -> bool:
        return not self._premultiplied.get(self.image.numpy())[1]

    def copy(self) -> "PaintAtlas":
        return PaintAtlas(self.uv.clone(), self.image.clone(), self.source, self.cell,
                          None if self.offsets is None else self.offsets.clone())

    def check(self, field) -> None:
        if self.num_faces != len(field.faces):
            raise NeuMeshError(f"the paint atlas has UVs for {self.num_faces} faces but the field's scaffold has "
                               f"{len(field.faces)}; the scaffold's topology changed since the atlas was made: "
                               "make a new paint atlas")

    # -- surface points -> faces -> UVs -> paint ------------------------------------------------------
    def lookup_vertices(self, field) -> np.ndarray:
        """(N,3) the surface lookups are made on: the scaffold in its current pose, each vertex moved
        by its offset along its current normal (the field's surface) when the atlas has offsets."""
        v = field.scaffold.vertices_.detach().cpu().numpy().astype(np.float64)
        if self.offsets is None:
            return v
        if len(self.offsets) != len(v):
            raise NeuMeshError(f"the paint atlas has surface offsets for {len(self.offsets)} vertices but the "
                               f"scaffold has {len(v)}; make a new paint atlas")
        n = field.scaffold.normals.detach().cpu().numpy().astype(np.float64)
        return v + self.offsets.numpy().astype(np.float64)[:, None] * n

    def _tree(self, field):
        """KD-tree of the face centroids in the current pose, rebuilt when the scaffold's vertex buffer
        was written (its version counter) or is another tensor."""
        v = field.scaffold.vertices_
        f = field.faces
        key = (id(field), v.data_ptr(), v._version, f.data_ptr(), f._version)
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1:]
        from .knn import kd_tree

        Vn = self.lookup_vertices(field)
        F = f.cpu().numpy().astype(np.int64)
        cen = Vn[F].mean(1)
        tree = kd_tree(cen)
        self._cache = (key, tree, Vn, F)
        return tree, Vn, F

    def closest_faces(self, field, points, candidates: int = 8):
        """The nearest point of the scaffold (current pose) to each point: (face (n,), bary (n,3),
        distance (n,)).  Candidate faces: the ``candidates`` faces with the nearest centroids."""
        self.check(field)
        p = np.asarray(points, np.float64).reshape(-1, 3)
        if len(p) == 0:
            return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0)
        tree, V, F = self._tree(field)
        k = int(min(candidates, len(F)))
        _, cand = tree.query(p, k=k)
        cand = np.asarray(cand, np.int64).reshape(len(p), k)
        tri = V[F[cand]]                                              # (n,k,3,3)
        q = np.repeat(p[:, None], k, 1).reshape(-1, 3)
        b = closest_points_on_triangles(q, tri[:, :, 0].reshape(-1, 3), tri[:, :, 1].reshape(-1, 3),
                                        tri[:, :, 2].reshape(-1, 3)).reshape(len(p), k, 3)
        x = (b[..., None] * tri).sum(2)
        d = np.linalg.norm(x - p[:, None], axis=2)
        j = np.argmin(d, 1)
        rows = np.arange(len(p))
        return cand[rows, j], b[rows, j], d[rows, j]

    def uv_at(self, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """(n,2) UVs of barycentric points of faces."""
        uv = self.uv.numpy()[np.asarray(face, np.int64)]
        return (np.asarray(bary)[..., None] * uv).sum(1)

    def texel_coords(self, uv: np.ndarray) -> np.ndarray:
        """UVs (v up) -> continuous image coordinates (x right, y down; texel centres at +0.5)."""
        h, w = self.size
        uv = np.asarray(uv, np.float64)
        return np.stack([uv[:, 0] * w, (1.0 - uv[:, 1]) * h], 1)

    def sample(self, uv: np.ndarray) -> np.ndarray:
        """(n,4) premultiplied RGBA paint at UVs (bilinear between texel centres, clamped at the border)."""
        h, w = self.size
        xy = self.texel_coords(uv) - 0.5
        x0 = np.floor(xy[:, 0]).astype(np.int64)
        y0 = np.floor(xy[:, 1]).astype(np.int64)
        fx, fy = (xy[:, 0] - x0)[:, None], (xy[:, 1] - y0)[:, None]
        pm = self._pm()

        def at(yy, xx):
            return pm[np.clip(yy, 0, h - 1), np.clip(xx, 0, w - 1)].astype(np.float32)

        return ((1 - fx) * (1 - fy) * at(y0, x0) + fx * (1 - fy) * at(y0, x0 + 1) +
                (1 - fx) * fy * at(y0 + 1, x0) + fx * fy * at(y0 + 1, x0 + 1))

    def paint_at(self, field, points, max_distance: Optional[float] = None):
        """(n,4) premultiplied paint at surface points: zero where the nearest scaffold face is farther
        than ``max_distance`` (default 2.5 field radii: the point belongs to another object)."""
        face, bary, dist = self.closest_faces(field, points)
        lim = 2.5 * float(field.radius) if max_distance is None else float(max_distance)
        out = self.sample(self.uv_at(face, bary))
        out[dist > lim] = 0.0
        return out

    @torch.no_grad()
    def composite(self, field, origins: torch.Tensor, dirs: torch.Tensor, rgb: torch.Tensor,
                  opacity: torch.Tensor, depth: torch.Tensor, min_opacity: float = 1e-3) -> torch.Tensor:
        """Premultiplied colours (R,3) of rays with the paint composited over the field's colour at each
        ray's expected surface point: rgb (1 - a) + opacity x paint (paint premultiplied by its a)."""
        if self.is_empty:
            return rgb
        live = (opacity > min_opacity) & torch.isfinite(depth)
        if not bool(live.any()):
            return rgb
        idx = live.nonzero().squeeze(1)
        x = (origins[idx] + dirs[idx] * depth[idx, None]).detach().cpu().numpy()
        paint = torch.as_tensor(self.paint_at(field, x), dtype=rgb.dtype, device=rgb.device)
        a = paint[:, 3:]
        out = rgb.clone()
        out[idx] = rgb[idx] * (1 - a) + opacity[idx, None] * paint[:, :3]
        return out

    # -- files ----------------------------------------------------------------------------------------
    def to_tensors(self) -> tuple:
        """(tensors, header entry) for a field file."""
        img = (self.image.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8)
        meta = {"version": ATLAS_VERSION, "resolution": list(self.size), "source": self.source}
        if self.cell is not None:
            meta["cell"] = self.cell
        if self.offsets is not None:
            return ({"paint/uv": self.uv.contiguous(), "paint/image": img.contiguous(),
                     "paint/offsets": self.offsets.contiguous()}, meta)
        return {"paint/uv": self.uv.contiguous(), "paint/image": img.contiguous()}, meta

    @classmethod
    def from_tensors(cls, meta: dict, tensors: dict, num_faces: int, path: str = "") -> "PaintAtlas":
        version = int(meta.get("version", 0))
        if version > ATLAS_VERSION:
            raise CheckpointError(f"{path}: its paint atlas has format version {version}, newer than this "
                                  f"NeuMesh reads ({ATLAS_VERSION}); update NeuMesh to open it")
        try:
            uv, img = tensors["paint/uv"].float(), tensors["paint/image"]
        except KeyError as exc:
            raise CheckpointError(f"{path}: the header names a paint atlas but {exc} is missing; the file is "
                                  "incomplete") from exc
        if tuple(uv.shape) != (num_faces, 3, 2) or img.ndim != 3 or img.shape[2] != 4:
            raise CheckpointError(f"{path}: paint atlas tensors have shapes {tuple(uv.shape)} and "
                                  f"{tuple(img.shape)}, expected ({num_faces}, 3, 2) and (H, W, 4); the file is "
                                  "corrupt")
        image = img.float() / 255.0 if img.dtype == torch.uint8 else img.float()
        try:
            off = tensors.get("paint/offsets")
            return cls(uv, image, meta.get("source", "xatlas"), meta.get("cell"),
                       None if off is None else off.float())
        except NeuMeshError as exc:
            raise CheckpointError(f"{path}: {exc}") from exc


def field_atlas(field) -> Optional[PaintAtlas]:
    """The field's paint atlas, or None."""
    return getattr(field, "paint_atlas", None)


@torch.no_grad()
def composite_paint(fields, origins: torch.Tensor, dirs: torch.Tensor, out: dict) -> dict:
    """Render hook: composite every field's paint atlas over ``out`` (render_rays' premultiplied
    output: rgb, opacity, depth) at each ray's expected surface point.  Fields without paint: no-op."""
    for f in fields:
        atlas = field_atlas(f)
        if atlas is not None and not atlas.is_empty:
            out["rgb"] = atlas.composite(f, origins, dirs, out["rgb"], out["opacity"], out["depth"])
    return out
