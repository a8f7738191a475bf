"""The fields a render shows: collect the field-carrying objects (with their evaluated world-space
vertices, mapped to field vertices through their identity attributes), keep loaded fields cached and
posed. :mod:`frame` renders them.

Colour: a field reproduces the training images' pixel values, i.e. display-referred sRGB. Blender's
render result is scene-linear, so pixels are decoded with the sRGB transfer function before they are
handed to Blender; with the view transform 'Standard' (display sRGB, look None, exposure 0, gamma 1)
and dither 0 the saved PNG equals the core's own output (up to 8/16-bit quantisation).
"""
from __future__ import annotations

import os
import threading
from dataclasses import dataclass

from ..runtime._np import np
from ..runtime import core
from ..runtime.errors import UserError
from ..scene import camera, identity, props, sync

LOCK = threading.RLock()  # guards every field in the cache (set_vertices + render are not re-entrant)
_LOAD_LOCK = threading.Lock()  # one load per file at a time (get_field); taken after LOCK, never before


def user_message(exc) -> str:
    """The message an artist sees for ``exc``: the text of the errors that say what to do, else with the
    exception type."""
    if isinstance(exc, (sync.TopologyError, camera.CameraError, FileNotFoundError, core.CoreUnavailable, UserError)):
        return str(exc)
    types = core.error_types()
    if types and isinstance(exc, types):
        return str(exc)
    return f"{type(exc).__name__}: {exc}"


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
    # Not under LOCK: a render in another thread (the viewport's preview) holds it for a whole level,
    # seconds on a big field, and the main thread asks here on every depsgraph update and after every
    # undo. Waiting there would freeze Blender until the level ended before the viewport could even ask
    # for the new image, which cancels that render.
    # A hit is one dict read; a load makes a new field object, never touching the one a render uses.
    e = _CACHE.get(key)
    if e is not None and e.path == path and e.stamp == stamp:
        return e.field
    with _LOAD_LOCK:
        e = _CACHE.get(key)
        if e is not None and e.path == path and e.stamp == stamp:
            return e.field
        field = nm.load_field(path)
        STATS["loads"] += 1
        _CACHE[key] = _Entry(path, stamp, field, None)
        return field


def cached_field(key: str, path: str):
    """The field the viewport shows for object ``key`` from ``path`` without waiting for the cache's
    lock (a render may hold it for seconds): the cached field when it is from ``path``, else
    :func:`get_field` (which loads it).  For writes that a render may see half-done (paint pixels)."""
    e = _CACHE.get(key)
    if e is not None and e.path == path:
        return e.field
    return get_field(key, path)


def adopt(key: str, path: str, field):
    """Make the cache hold ``field`` (already in memory, just saved to ``path``) for object ``key``, so
    an edit shows at once without reloading the file it wrote."""
    with LOCK:
        e = _CACHE.get(key)
        last = e.last_vertices if e is not None and e.field is field else None
        _CACHE[key] = _Entry(path, _stamp(path), field, last)


def clear_cache():
    with LOCK:
        _CACHE.clear()
        _MIRRORS.clear()
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
    with LOCK:
        e = _SOURCES.get(path)
        if e is None or e.stamp != stamp:
            e = _SOURCES[path] = _Entry(path, stamp, nm.load_field(path), None)
            STATS["loads"] += 1
        return e.field


def _derived(name: str, source, vid, rest, signature, faces_fn):
    """The cached remapped field for ``name``, rebuilt when its source or vertex identity changed."""
    nm = core.get()
    with LOCK:
        d = _DERIVED.get(name)
        if d is not None and d.source is source and d.signature == signature and \
                np.array_equal(d.vid, vid) and np.array_equal(d.rest, rest):
            return d.field
        ids = nm.resolve_ids(source, vid, rest)
        field = nm.remap_field(source, ids, rest, faces_fn())
        STATS["remaps"] = STATS.get("remaps", 0) + 1
        _DERIVED[name] = _Derived(source, signature, vid.copy(), rest.copy(), field)
        _CACHE.pop(name, None)
        return field


def _object_items(ob, orig, path, depsgraph, for_render: bool) -> list:
    """Items for one object: its own field by order (no identity attributes, or an exact identity
    map), else one remapped field per field key in its mesh."""
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
    nm = core.get()
    groups = nm.split_by_key(key, known, own_key)
    memo_key = (own,) + tuple(ident) + (signature,)   # identity.read returns fresh arrays: no copies
    if len(vid) == own.num_vertices and [k for k, _ in groups] == [own_key] and \
            np.array_equal(vid, np.arange(len(vid))):
        ok = nm.resolve_ids(own, vid, rest)
        if (ok >= 0).all():   # exactly the field's vertices, in order: the field itself
            _DERIVED.pop(orig.name_full, None)
            _IDENTITY_MEMO[orig.name_full] = (memo_key, None)
            return [Item(orig.name_full, path, verts)]
    items, plan = [], []
    tri = None
    for k, sel in groups:
        source, spath = known[k]

        def faces_fn(sel=sel):
            nonlocal tri
            if tri is None:
                tri = sync.mesh_triangles(mesh)
            return nm.sub_triangles(tri, sel, len(vid))
        name = f"{orig.name_full}#{int(k)}"
        field = _derived(name, source, vid[sel], rest[sel], signature + (int(k),), faces_fn)
        items.append(Item(name, spath, verts[sel], field, sel))
        plan.append((int(k) if int(k) != own_key else None, name, spath, source, field, sel))
    _IDENTITY_MEMO[orig.name_full] = (memo_key, plan)
    return items


def source_ids(key: str, source):
    """For the remapped field of item ``key`` (an ``"object#key"`` item), the vertex of ``source`` each
    of its vertices came from (-1 for a new vertex), as ``nm.resolve_ids`` gives."""
    with LOCK:
        d = _DERIVED[key]
        vid, rest = d.vid, d.rest
    return core.get().resolve_ids(source, vid, rest)


def _memo_items(name: str, own, path: str, ident, signature, verts, scene):
    """The items of the last frame for ``verts`` when the mesh's ids, its counts and every field they
    came from are unchanged (deformation only); None when they must be worked out again."""
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
    path = props.field_abspath(obj)
    ob = obj.evaluated_get(depsgraph)
    items = _object_items(ob, obj, path, depsgraph, True)
    own = [it for it in items if it.field is None or it.path == path]
    it = own[0] if own else items[0]
    with LOCK:
        if it.field is None:
            get_field(it.key, it.path)
        field = posed_field(it)
    return field, it.mesh_index


def collect(depsgraph, for_render: bool = True) -> list[Item]:
    """Every visible mesh object with a field, with its evaluated world-space vertices.

    Raises sync.TopologyError (naming the modifier) or FileNotFoundError / core errors.
    """
    items = []
    for ob in depsgraph.objects:
        if ob.type != "MESH":
            continue
        orig = ob.original
        if not props.has_field(orig):
            continue
        if for_render and is_holdout(orig, depsgraph):   # an occluder (holdout_meshes), not a field
            continue
        path = props.field_abspath(orig)
        if not os.path.isfile(path):
            raise FileNotFoundError(props.missing_field_message(orig))
        items.extend(_object_items(ob, orig, path, depsgraph, for_render))
    return items


def is_holdout(obj, depsgraph) -> bool:
    """Is ``obj`` a holdout in the depsgraph's view layer (an occluder, not a field)?"""
    try:
        return bool(obj.holdout_get(view_layer=depsgraph.view_layer))
    except (TypeError, RuntimeError, ReferenceError, AttributeError):
        return False


def posed_field(item: Item):
    """The cached field of ``item`` posed at ``item.vertices`` (set only when they moved); call it under
    :data:`LOCK`, with the object's own field loaded (:func:`get_field`)."""
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


@dataclass
class _Mirror:
    """A copy of a cached field on the render device (a CUDA GPU), kept posed like the cached field."""

    entry: _Entry            # the cache entry it copies: a new entry (edit adopted, file reloaded) -> new copy
    device: object
    field: object
    vertices: np.ndarray | None


_MIRRORS: dict[str, _Mirror] = {}
STATS["mirrors"] = 0


def on_device(item: Item, field, device):
    """``field`` (the posed cached field of ``item``) as rendered on ``device``: itself on the CPU, else a
    copy there, made once per cache entry and re-posed when the cached field was deformed. The cached
    field stays on the CPU: edits, selection and bake work on it, and an edit shows on the device when
    it is adopted (:func:`adopt` makes a new entry). Call under the cache's lock, after posing."""
    if getattr(device, "type", str(device)) == "cpu":
        _MIRRORS.pop(item.key, None)
        return field
    e = _CACHE.get(item.key)
    if e is None or e.field is not field:   # not posed through the cache (posed_field always is)
        raise RuntimeError(f"on_device: {item.key} is not the cached field; pose it with posed_field first")
    m = _MIRRORS.get(item.key)
    if m is None or m.entry is not e or m.device != device:
        return _fresh_mirror(item.key, e, device)
    if e.last_vertices is not None and (m.vertices is None or m.vertices.shape != e.last_vertices.shape
                                        or not np.array_equal(m.vertices, e.last_vertices)):
        m.field.set_vertices(e.last_vertices)
        m.vertices = e.last_vertices.copy()
    _share_paint(e.field, m.field)
    return m.field


def _share_paint(cpu, dev) -> None:
    """The device copy shows the cached field's paint layer itself (Texture Paint writes its texels in
    place; the paint is composited from the CPU side, see field/paint_atlas.composite)."""
    atlas = getattr(cpu, "paint_atlas", None)
    if getattr(dev, "paint_atlas", None) is not atlas:
        dev.paint_atlas = atlas


def _fresh_mirror(key: str, e: _Entry, device):
    import copy

    _MIRRORS.pop(key, None)   # free the old copy's device memory before making the new one
    memo = {id(getattr(e.field, "paint_atlas", None)): None}   # not copied: shared (_share_paint)
    dev = copy.deepcopy(e.field, memo).to(device)
    _share_paint(e.field, dev)
    STATS["mirrors"] += 1
    _MIRRORS[key] = _Mirror(e, device, dev, None if e.last_vertices is None else e.last_vertices.copy())
    return dev


def private_copy(field):
    """A private copy of a cached field for work in another thread (taken under the cache's lock, so
    no render or deformation is half-way through it)."""
    import copy

    with LOCK:
        return copy.deepcopy(field)


def posed_copy(item: Item):
    """A private copy of ``item``'s field posed at ``item.vertices``: posed in the cache under its lock,
    as a render poses it (nothing is recomputed when the render already posed it there), then copied."""
    import copy

    with LOCK:
        if item.field is None:
            get_field(item.key, item.path)
        return copy.deepcopy(posed_field(item))
