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
# the last render_items call: seconds in nm.render_camera, in posing the fields, torch's threads
LAST_TIMINGS: dict = {}


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
        _DERIVED.clear()
        _SOURCES.clear()
        _IDENTITY_MEMO.clear()


@dataclass
class Item:
    key: str           # object name (or "object#key" for a field remapped onto the object's mesh)
    path: str          # absolute field path
    vertices: np.ndarray  # (N,3) float32 world space, evaluated
    field: object = None  # a remapped field (None: the object's own cached field)
    mesh_index: np.ndarray | None = None   # the mesh vertices of a remapped field (its vertex order)


@dataclass
class _Derived:
    """A field remapped onto an object's mesh, and what it was made from."""

    source: object
    signature: tuple
    vid: np.ndarray
    rest: np.ndarray
    field: object


_DERIVED: dict[str, _Derived] = {}
_SOURCES: dict[str, _Entry] = {}   # fields loaded for a joined-in key (read-only; shared)
# object name -> ((its field, vid, rest, key as read, mesh counts), plan) of the last frame: plan None
# when the ids were exactly the field's vertices in order, else one entry per remapped field; while
# the ids do not change (the mesh only deforms) the next frame reuses it after one comparison
_IDENTITY_MEMO: dict[str, tuple] = {}


def _source(path: str):
    """A field loaded read-only for remapping (fields joined into an object from elsewhere)."""
    nm = core.get()
    if not os.path.isfile(path):
        raise FileNotFoundError(f"NeuMesh field file not found: {path}")
    stamp = _stamp(path)
    with _LOCK:
        e = _SOURCES.get(path)
        if e is None or e.stamp != stamp:
            e = _SOURCES[path] = _Entry(path, stamp, nm.load_field(path), None)
            STATS["loads"] += 1
        return e.field


def _derived(name: str, source, vid, rest, signature, faces_fn):
    """The cached remapped field for ``name``, rebuilt when its source or vertex identity changed."""
    from .identity import _remap

    with _LOCK:
        d = _DERIVED.get(name)
        if d is not None and d.source is source and d.signature == signature and \
                np.array_equal(d.vid, vid) and np.array_equal(d.rest, rest):
            return d.field
        rm = _remap()
        ids = rm.resolve_ids(source, vid, rest)
        field = rm.remap_field(source, ids, rest, faces_fn())
        STATS["remaps"] = STATS.get("remaps", 0) + 1
        _DERIVED[name] = _Derived(source, signature, vid.copy(), rest.copy(), field)
        _CACHE.pop(name, None)
        return field


def _object_items(ob, orig, path, depsgraph, for_render: bool) -> list:
    """Items for one object: its own field by order (no identity attributes, or an exact identity
    map), else one remapped field per field key in its mesh."""
    from . import identity

    own = get_field(orig.name_full, path)
    mesh = ob.data if hasattr(ob, "data") and hasattr(ob.data, "attributes") else None
    ident = identity.read(mesh, raw=True) if mesh is not None else None
    if ident is None:   # the strict path: the evaluated mesh must be the field's vertices in order
        try:
            verts = sync.evaluated_world_vertices(orig, depsgraph, expected_count=int(own.num_vertices),
                                                  for_render=for_render)
        except sync.TopologyError as exc:
            raise sync.TopologyError(
                f"{exc}. The mesh has no NeuMesh vertex ids (point attributes {', '.join(identity.ATTRS)}), "
                "which let a field follow deleted, separated, joined or subdivided vertices: they were "
                "removed, or the field was attached before they existed. Undo the change, or Load field "
                "on the field's own mesh (New object) to get them back") from exc
        return [Item(orig.name_full, path, verts)]
    verts = sync.to_world(sync.mesh_vertices(mesh), ob.matrix_world)
    signature = (len(mesh.vertices), len(mesh.polygons), len(mesh.loops))
    items = _memo_items(orig.name_full, own, path, ident, signature, verts, depsgraph.scene)
    if items is not None:   # the same ids as the last frame (the mesh only moved)
        return items
    vid, rest, key = ident[0].astype(np.int64), ident[1].astype(np.float64), ident[2].astype(np.int64)
    own_key = identity.key_of(own)
    # keys this scene knows; any other value (interpolated by a modifier between vertices, lost, or the
    # key of this object's field before it was trained further) counts as the object's own field
    known = {own_key: (own, path)}
    for k in np.unique(key):
        if int(k) != own_key:
            spath = identity.lookup(depsgraph.scene, int(k))
            if spath is not None and os.path.isfile(spath):
                known[int(k)] = (_source(spath), spath)
    key = np.where(np.isin(key, list(known)), key, own_key)
    memo_key = (own,) + tuple(ident) + (signature,)   # identity.read returns fresh arrays: no copies
    if len(vid) == own.num_vertices and (key == own_key).all() and np.array_equal(vid, np.arange(len(vid))):
        ok = identity._remap().resolve_ids(own, vid, rest)
        if (ok >= 0).all():   # exactly the field's vertices, in order: the field itself
            _DERIVED.pop(orig.name_full, None)
            _IDENTITY_MEMO[orig.name_full] = (memo_key, None)
            return [Item(orig.name_full, path, verts)]
    items, plan = [], []
    tri = None
    for k in np.unique(key):
        sel = np.nonzero(key == k)[0]
        source, spath = known[int(k)]

        def faces_fn(sel=sel):
            nonlocal tri
            if tri is None:
                tri = sync.mesh_triangles(mesh)
            pos = np.full(len(vid), -1, np.int64)
            pos[sel] = np.arange(len(sel))
            f = pos[tri]
            return f[(f >= 0).all(1)]
        name = f"{orig.name_full}#{int(k)}"
        field = _derived(name, source, vid[sel], rest[sel], signature + (int(k),), faces_fn)
        items.append(Item(name, spath, verts[sel], field, sel))
        plan.append((int(k) if int(k) != own_key else None, name, spath, source, field, sel))
    _IDENTITY_MEMO[orig.name_full] = (memo_key, plan)
    return items


def _memo_items(name: str, own, path: str, ident, signature, verts, scene):
    """The items of the last frame for ``verts`` when the mesh's ids, its counts and every field they
    came from are unchanged (deformation only); None when they must be worked out again."""
    from . import identity

    memo = _IDENTITY_MEMO.get(name)
    if memo is None:
        return None
    (m_own, *m_raw, m_sig), plan = memo
    if m_own is not own or m_sig != signature or not all(np.array_equal(a, b) for a, b in zip(m_raw, ident)):
        _IDENTITY_MEMO.pop(name, None)
        return None
    if plan is None:
        return [Item(name, path, verts)]
    items = []
    for k, dname, spath, source, field, sel in plan:
        if k is not None and (identity.lookup(scene, k) != spath or _source(spath) is not source):
            _IDENTITY_MEMO.pop(name, None)
            return None
        d = _DERIVED.get(dname)
        if d is None or d.field is not field:
            _IDENTITY_MEMO.pop(name, None)
            return None
        items.append(Item(dname, spath, verts[sel], field, sel))
    return items


def object_field(obj, depsgraph):
    """(field, mesh_index) of ``obj`` posed as it renders now: its own field's vertices as the mesh's
    vertices (``mesh_index`` None: vertex i is mesh vertex i), or for a remapped mesh the remapped field
    of the object's own field and the mesh vertex of each of its vertices."""
    from . import props

    path = props.field_abspath(obj)
    ob = obj.evaluated_get(depsgraph)
    items = _object_items(ob, obj, path, depsgraph, True)
    own = [it for it in items if it.field is None or it.path == path]
    it = own[0] if own else items[0]
    with _LOCK:
        if it.field is None:
            get_field(it.key, it.path)
        field = _apply_vertices(it)
    return field, it.mesh_index


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
        if for_render and _is_holdout(orig, depsgraph):   # an occluder (holdout_meshes), not a field
            continue
        path = props.field_abspath(orig)
        if not os.path.isfile(path):
            raise FileNotFoundError(props.missing_field_message(orig))
        items.extend(_object_items(ob, orig, path, depsgraph, for_render))
    return items


def _is_holdout(obj, depsgraph) -> bool:
    try:
        return bool(obj.holdout_get(view_layer=depsgraph.view_layer))
    except (TypeError, RuntimeError, ReferenceError, AttributeError):
        return False


def _apply_vertices(item: Item):
    if item.field is not None:
        e = _CACHE.get(item.key)
        if e is None or e.field is not item.field:
            e = _CACHE[item.key] = _Entry(item.path, None, item.field, None)
    else:
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
    out = _render_out(items, K, c2w, width, height, transparent, progress, supersample)
    if out is None:
        return _empty(width, height, transparent)
    return _rgba(out, width, height, transparent)


def _render_out(items: list[Item], K, c2w, width: int, height: int, transparent: bool, progress,
                supersample: int, far=None):
    """``nm.render_camera`` of the posed fields of ``items`` (None when there is none)."""
    nm = core.get()
    LAST_TIMINGS.clear()
    bg = (0.0, 0.0, 0.0) if transparent else (1.0, 1.0, 1.0)
    if not items:
        return None
    import time

    import torch

    with core.torch_work() as threads, _LOCK:
        t0 = time.perf_counter()
        fields = []
        for it in items:
            if it.field is None:
                get_field(it.key, it.path)
            fields.append(_apply_vertices(it))
        t1 = time.perf_counter()
        out = nm.render_camera(fields if len(fields) > 1 else fields[0], np.asarray(K, np.float32),
                               np.asarray(c2w, np.float32), int(width), int(height), background=bg,
                               settings=nm.RenderSettings(supersample=int(supersample)), progress=progress,
                               far=far)
        t2 = time.perf_counter()
    LAST_TIMINGS.update(pose_s=t1 - t0, core_s=t2 - t1, torch_threads=torch.get_num_threads(),
                        threads_wanted=threads)
    core.guard_torch_namespaces()  # torch may have imported more modules lazily
    return out


@dataclass
class Passes:
    """One frame's render passes for Blender: ``combined`` (H,W,4) scene-linear premultiplied RGBA,
    ``z`` (H,W) distance along the camera axis (the Depth pass of Cycles/EEVEE; inf where empty),
    and ``mod`` (H,W,3) the rendered modification colour (premultiplied by opacity; a data pass)."""

    combined: np.ndarray
    z: np.ndarray
    mod: np.ndarray


def _core_module(name: str):
    import importlib

    return importlib.import_module(core.get().__name__ + "." + name)


def holdout_meshes(depsgraph) -> tuple[np.ndarray, np.ndarray] | None:
    """World-space (V,3) vertices and (F,3) triangles of every object that is a holdout in the
    depsgraph's view layer (Object properties > Visibility > Holdout, or a holdout collection), or
    None when there is none. Those objects occlude the field and leave transparent holes."""
    verts, tris, base = [], [], 0
    for ob in depsgraph.objects:
        if ob.type not in {"MESH", "CURVE", "SURFACE", "META", "FONT"}:
            continue
        if not _is_holdout(ob.original, depsgraph):
            continue
        me = ob.to_mesh()
        try:
            me.calc_loop_triangles()
            n, t = len(me.vertices), len(me.loop_triangles)
            if n == 0 or t == 0:
                continue
            v = np.empty(n * 3, np.float32)
            me.vertices.foreach_get("co", v)
            f = np.empty(t * 3, np.int64)
            me.loop_triangles.foreach_get("vertices", f)
        finally:
            ob.to_mesh_clear()
        verts.append(sync.to_world(v.reshape(-1, 3), ob.matrix_world))
        tris.append(f.reshape(-1, 3) + base)
        base += n
    if not verts:
        return None
    return np.concatenate(verts).astype(np.float64), np.concatenate(tris)


def holdout_z(depsgraph, K, c2w, width: int, height: int) -> np.ndarray | None:
    """(H,W) camera-axis distance of the nearest holdout surface at each pixel (inf: none), or None."""
    meshes = holdout_meshes(depsgraph)
    if meshes is None:
        return None
    return _core_module("render.raster").depth_buffer(meshes[0], meshes[1], K, c2w, width, height)


def render_passes(items: list[Item], K, c2w, width: int, height: int, transparent: bool = False,
                  progress=None, supersample: int = 1, occluder_z: np.ndarray | None = None) -> Passes:
    """The passes of one frame (see :class:`Passes`). ``occluder_z`` (H,W) camera-axis distances of
    holdout surfaces (inf: none): the field behind them is not sampled, and there the background is
    left out (alpha = the field's opacity in front of the holdout, even without Film > Transparent)."""
    cams = _core_module("data.cameras")
    far = None if occluder_z is None else cams.axis_to_ray_depth(occluder_z, K)
    out = _render_out(items, K, c2w, width, height, transparent, progress, supersample, far)
    if out is None:
        rgba = _empty(width, height, transparent)
        z = np.full((height, width), np.inf, np.float32)
        mod = np.zeros((height, width, 3), np.float32)
        a = np.zeros((height, width), np.float32)
    else:
        rgba = _rgba(out, width, height, transparent)
        z = cams.ray_to_axis_depth(out.depth.reshape(height, width), K)
        mod = np.asarray(out.mod_rgb, np.float32).reshape(height, width, 3)
        a = np.asarray(out.opacity, np.float32).reshape(height, width)
    combined = to_scene_linear(rgba, transparent)
    if occluder_z is not None:
        hold = np.isfinite(occluder_z)
        if not transparent and hold.any():   # the white background was added in display space
            premult = rgba[..., :3] - (1.0 - a[..., None])
            cut = to_scene_linear(np.concatenate([premult, a[..., None]], -1), True)
            combined[hold] = cut[hold]
        z = np.minimum(z, occluder_z.astype(np.float32))
    return Passes(combined.astype(np.float32), z.astype(np.float32), mod)


def _empty(width: int, height: int, transparent: bool) -> np.ndarray:
    img = np.zeros((height, width, 4), np.float32)
    if not transparent:
        img[:] = 1.0
    return img


def _rgba(out, width: int, height: int, transparent: bool) -> np.ndarray:
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
