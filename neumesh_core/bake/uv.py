"""The UV atlas a bake (and the paint atlas) writes into: xatlas's unwrap packed into a square image,
UVs to texel coordinates, the texels each atlas triangle covers, and dilation of the charts' borders.
"""
from __future__ import annotations

import numpy as np

from ..errors import NeuMeshError
from ..render.raster import raster_triangles


def unwrap(vertices: np.ndarray, faces: np.ndarray, resolution: int, padding: int = 4):
    """xatlas UV atlas of a triangle mesh packed into a ``resolution`` square.

    Returns (vertex_index (M,), faces (F,3) into the atlas vertices, uvs (M,2) with v up, info)."""
    try:
        import xatlas
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise NeuMeshError("baking needs the 'xatlas' package: pip install xatlas (or the add-on's "
                           "Install dependencies)") from exc
    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces, np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = int(resolution)
    pack.padding = int(padding)
    pack.bilinear = True
    pack.blockAlign = True
    atlas.generate(pack_options=pack)
    vmap, idx, uv = atlas[0]
    # xatlas treats the resolution as a target, not a cap (the atlas can come out a little larger and
    # not square): scale the atlas uniformly into the resolution square (padding shrinks by that factor)
    scale = max(atlas.width, atlas.height) / float(resolution)
    uv = np.asarray(uv, np.float64)
    uv[:, 0] *= atlas.width / (scale * resolution)
    uv[:, 1] *= atlas.height / (scale * resolution)
    uv[:, 1] = 1.0 - uv[:, 1]   # xatlas: v down from the image's first row; OBJ/Blender: v up
    info = {"charts": int(atlas.chart_count), "atlas_width": int(atlas.width),
            "atlas_height": int(atlas.height), "utilization": float(np.mean(atlas.utilization)),
            "padding_texels": float(padding) / max(scale, 1.0)}
    if atlas.atlas_count != 1:
        raise NeuMeshError(f"xatlas made {atlas.atlas_count} atlases; expected one (report this mesh)")
    return np.asarray(vmap, np.int64), np.asarray(idx, np.int32), uv.astype(np.float32), info


def uv_pixels(uvs: np.ndarray, resolution: int) -> np.ndarray:
    """UVs (n,2) (v up) -> texel-space coordinates (x right, y down) of a resolution x resolution image."""
    return np.stack([uvs[:, 0] * resolution, (1.0 - uvs[:, 1]) * resolution], 1)


def texel_coverage(uvs: np.ndarray, faces: np.ndarray, resolution: int, eps: float = 1e-7):
    """Texels whose centre lies in a triangle of the atlas: (texel (n,), face (n,), bary (n,3)), the
    first triangle winning where two touch (shared edges)."""
    tri = uv_pixels(uvs, resolution)[faces]
    ids, px, bary = [], [], []
    for i, p, b in raster_triangles(tri, resolution, resolution, eps=eps):
        ids.append(i)
        px.append(p)
        bary.append(b)
    if not ids:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))
    ids, px, bary = np.concatenate(ids), np.concatenate(px), np.concatenate(bary)
    _, first = np.unique(px, return_index=True)
    return px[first], ids[first], bary[first]


def dilate(image: np.ndarray, mask: np.ndarray, iterations: int) -> tuple:
    """Grow ``image``'s valid texels (``mask``) outwards by ``iterations`` texels: each new texel is the
    mean of its valid 8-neighbours.  Returns (image, grown mask)."""
    img = image.astype(np.float32).copy()
    m = mask.astype(bool).copy()
    h, w = m.shape
    for _ in range(int(iterations)):
        if m.all():
            break
        acc = np.zeros_like(img)
        cnt = np.zeros((h, w), np.float32)
        pi = np.pad(img * m[..., None], ((1, 1), (1, 1), (0, 0)))
        pm = np.pad(m.astype(np.float32), 1)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy == 0 and dx == 0:
                    continue
                acc += pi[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
                cnt += pm[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
        new = (~m) & (cnt > 0)
        img[new] = acc[new] / cnt[new][:, None]
        m |= new
    return img, m
