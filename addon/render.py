"""Rendering shared by the F12 engine, the viewport preview, the render-to-image operator and the
benchmark: collect field-carrying objects (with their evaluated world-space vertices), keep loaded
fields cached, call ``nm.render_camera``.

Colour: a field reproduces the training images' pixel values, i.e. display-referred sRGB. Blender's
render result is scene-linear, so pixels are decoded with the sRGB transfer function before they are
handed to Blender; with the view transform 'Standard' (display sRGB, look None, exposure 0, gamma 1)
and dither 0 the saved PNG equals the core's own output (up to 8/16-bit quantisation).
"""
from __future__ import annotations

import os
import threading
from dataclasses import dataclass

from ._np import np

from . import core, sync

_LOCK = threading.RLock()  # guards every field in the cache (set_vertices + render are not re-entrant)


@dataclass
class _Entry:
    path: str
    stamp: tuple
    field: object
    last_vertices: np.ndarray | None = None


_CACHE: dict[str, _Entry] = {}
STATS = {"loads": 0, "set_vertices": 0}


def _stamp(path):
    st = os.stat(path)
    return (st.st_mtime_ns, st.st_size)


def get_field(key: str, path: str):
    """Cached ``nm.load_field(path)``; reloaded when the file's mtime/size changes."""
    nm = core.get()
    if not path:
        raise FileNotFoundError(f"object '{key}' has no NeuMesh field file set")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"object '{key}': NeuMesh field file not found: {path}")
    stamp = _stamp(path)
    with _LOCK:
        e = _CACHE.get(key)
        if e is not None and e.path == path and e.stamp == stamp:
            return e.field
        field = nm.load_field(path)
        STATS["loads"] += 1
        _CACHE[key] = _Entry(path, stamp, field, None)
        return field


def adopt(key: str, path: str, field):
    """Make the cache hold ``field`` (already in memory, just saved to ``path``) for object ``key``, so
    an edit shows at once without reloading the file it wrote."""
    with _LOCK:
        e = _CACHE.get(key)
        last = e.last_vertices if e is not None and e.field is field else None
        _CACHE[key] = _Entry(path, _stamp(path), field, last)


def clear_cache():
    with _LOCK:
        _CACHE.clear()


@dataclass
class Item:
    key: str           # object name
    path: str          # absolute field path
    vertices: np.ndarray  # (N,3) float32 world space, evaluated


def collect(depsgraph, for_render: bool = True) -> list[Item]:
    """Every visible mesh object with a field, with its evaluated world-space vertices.

    Raises sync.TopologyError (naming the modifier) or FileNotFoundError / core errors.
    """
    from . import props

    items = []
    for ob in depsgraph.objects:
        if ob.type != "MESH":
            continue
        orig = ob.original
        if not props.has_field(orig):
            continue
        path = props.field_abspath(orig)
        if not os.path.isfile(path):
            raise FileNotFoundError(props.missing_field_message(orig))
        field = get_field(orig.name_full, path)
        verts = sync.evaluated_world_vertices(orig, depsgraph, expected_count=int(field.num_vertices),
                                              for_render=for_render)
        items.append(Item(orig.name_full, path, verts))
    return items


def _apply_vertices(item: Item):
    e = _CACHE[item.key]
    if e.last_vertices is not None and e.last_vertices.shape == item.vertices.shape and \
            np.array_equal(e.last_vertices, item.vertices):
        return e.field
    e.field.set_vertices(item.vertices)
    STATS["set_vertices"] += 1
    e.last_vertices = item.vertices.copy()
    return e.field


def render_items(items: list[Item], K, c2w, width: int, height: int, transparent: bool = False,
                 progress=None, supersample: int = 1) -> np.ndarray:
    """Render (H,W,4) float32 display-referred RGBA (sRGB-encoded like the field's training images).

    ``supersample``: S x S rays per pixel, averaged (anti-aliasing).
    Transparent: straight alpha = opacity, rgb composited on black (premultiplied).
    Otherwise: composited on white, alpha = 1.
    """
    nm = core.get()
    bg = (0.0, 0.0, 0.0) if transparent else (1.0, 1.0, 1.0)
    if not items:
        img = np.zeros((height, width, 4), np.float32)
        if not transparent:
            img[:] = 1.0
        return img
    with _LOCK:
        fields = []
        for it in items:
            get_field(it.key, it.path)
            fields.append(_apply_vertices(it))
        out = nm.render_camera(fields if len(fields) > 1 else fields[0], np.asarray(K, np.float32),
                               np.asarray(c2w, np.float32), int(width), int(height), background=bg,
                               settings=nm.RenderSettings(supersample=int(supersample)), progress=progress)
    core.guard_torch_namespaces()  # torch may have imported more modules lazily
    rgb = np.asarray(out.rgb, dtype=np.float32).reshape(height, width, 3)
    alpha = np.asarray(out.opacity, dtype=np.float32).reshape(height, width, 1) if transparent else \
        np.ones((height, width, 1), np.float32)
    return np.concatenate([rgb, alpha], axis=-1)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, None)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, None)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def to_scene_linear(rgba: np.ndarray, transparent: bool) -> np.ndarray:
    """Display-referred RGBA from :func:`render_items` -> Blender scene-linear premultiplied RGBA."""
    rgb, a = rgba[..., :3], rgba[..., 3:4]
    if transparent:
        straight = np.where(a > 1e-6, rgb / np.maximum(a, 1e-6), 0.0)
        lin = srgb_to_linear(np.clip(straight, 0.0, 1.0)) * a
    else:
        lin = srgb_to_linear(rgb)
    return np.concatenate([lin, a], axis=-1).astype(np.float32)


def scale_K(K, width, height, new_w, new_h):
    K = np.array(K, dtype=np.float32)
    K[0, :] *= new_w / float(width)
    K[1, :] *= new_h / float(height)
    return K
