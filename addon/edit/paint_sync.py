"""Texture Paint's image -> the field's paint atlas (``addon/edit/texture_paint.py`` has the operators).

The image ("NeuMesh Paint <object>") is the truth while painting: whenever its pixels change (a stroke,
Blender's undo or redo of one, a script writing ``image.pixels``) the changed texels are pushed into
the cached field's paint atlas (``PaintAtlas.set_texels``; the field is not rebuilt) and the Rendered
viewports render again.  Changes are noticed by a stroke watcher (a modal handler that passes every
event on: after a mouse press it pushes the image every 0.1 s, or twice as long as a push takes, until
the stroke has ended and the image settles), by undo/redo handlers, and by a timer that compares the
pixels itself where there is no window (scripts) and, rarely, as a fallback beside the watcher.  A
push reads the whole image (~0.4 s at 4096^2 on an idle core).
"""
from __future__ import annotations

import time

import bpy

from ..runtime._np import np
from ..runtime import core, quiet
from ..runtime.errors import UserError
from ..scene import props
from ..render import engine, field_cache

UV_NAME = "NeuMesh Paint"
IMAGE_PREFIX = "NeuMesh Paint "
OBJECT_KEY = "neumesh_paint_object"     # on the image: the object whose field it paints
POLL_S = 0.5
# figures of the last pushes (tests and benchmarks read them)
STATS = {"pushes": 0, "texels": 0, "last_push_s": 0.0, "last_push_at": 0.0, "polls": 0}
STATE: dict = {}   # object name -> {"image": name, "last": flat pixels pushed, "atlas": id, "saved": (H,W,4)}


def image_name(obj) -> str:
    return IMAGE_PREFIX + obj.name


def paint_image(obj):
    """The object's Texture Paint image, or None."""
    img = bpy.data.images.get(image_name(obj))
    return img if img is not None and img.get(OBJECT_KEY) == obj.name else None


def triangles(mesh):
    """(vertices (F,3), loops (F,3)) of the mesh's loop triangles."""
    mesh.calc_loop_triangles()
    n = len(mesh.loop_triangles)
    tri = np.empty(n * 3, np.int32)
    loops = np.empty(n * 3, np.int32)
    mesh.loop_triangles.foreach_get("vertices", tri)
    mesh.loop_triangles.foreach_get("loops", loops)
    return tri.reshape(n, 3).astype(np.int64), loops.reshape(n, 3).astype(np.int64)


def own_field(obj, depsgraph=None):
    """The cached field the viewport renders for ``obj`` (the object's own file on its own mesh) and
    the mesh's loop of each field face corner (F,3); :class:`UserError` when the object's mesh is not
    the field's scaffold face for face."""
    if obj is None or obj.type != "MESH" or not props.has_field(obj):
        raise UserError("select an object with a NeuMesh field (Load field) to texture paint it")
    depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
    field, mesh_index = field_cache.object_field(obj, depsgraph)
    if mesh_index is not None:
        raise UserError(f"'{obj.name}' shows a field remapped onto an edited mesh; Texture Paint needs the "
                        "field's own scaffold mesh (Load field > New object)")
    tri, loops = triangles(obj.data)
    faces = np.asarray(field.faces.cpu().numpy(), np.int64)
    if tri.shape != faces.shape or not np.array_equal(tri, faces):
        raise UserError(f"'{obj.name}' has {len(tri)} triangles but its field's scaffold has {len(faces)} faces "
                        "in another order; Texture Paint needs the scaffold mesh as loaded (Load field > New "
                        "object)")
    return field, loops


def write_uv_layer(mesh, loops, uv) -> None:
    """The atlas's UVs (F,3,2) as the mesh's UV map "NeuMesh Paint" (made active)."""
    per_loop = np.zeros((len(mesh.loops), 2), np.float32)
    per_loop[loops.reshape(-1)] = np.asarray(uv, np.float32).reshape(-1, 2)
    if not np.allclose(per_loop[loops.reshape(-1)], np.asarray(uv, np.float32).reshape(-1, 2), atol=1e-6):
        raise UserError("the mesh's faces are not triangles, so one corner would need two UVs; triangulate "
                        "the field's scaffold before training, or Load field > New object")
    layer = mesh.uv_layers.get(UV_NAME) or mesh.uv_layers.new(name=UV_NAME)
    layer.data.foreach_set("uv", per_loop.ravel())
    mesh.uv_layers.active = layer
    mesh.update()


def mesh_uvs(mesh, loops):
    """The artist's own UV map per field face corner (F,3,2), or None (no UV map but ours)."""
    layer = next((u for u in mesh.uv_layers if u.active and u.name != UV_NAME), None) or \
        next((u for u in mesh.uv_layers if u.name != UV_NAME), None)
    if layer is None:
        return None
    uv = np.empty(len(mesh.loops) * 2, np.float32)
    layer.data.foreach_get("uv", uv)
    return uv.reshape(-1, 2)[loops]


def _differ(a, b) -> np.ndarray:
    """(H,W) where two (H,W,4) float32 images differ (each pixel compared as two 64-bit words)."""
    if a.flags.c_contiguous and b.flags.c_contiguous:
        a2, b2 = a.view(np.uint64), b.view(np.uint64)
        return (a2[..., 0] != b2[..., 0]) | (a2[..., 1] != b2[..., 1])
    return (a != b).any(-1)


def _read_pixels(img) -> np.ndarray:
    w, h = img.size
    out = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(out)
    return out


def new_image(obj, atlas):
    h, w = atlas.size
    name = image_name(obj)
    old = bpy.data.images.get(name)
    if old is not None:
        bpy.data.images.remove(old)
    img = bpy.data.images.new(name, w, h, alpha=True, float_buffer=False)
    img.colorspace_settings.name = "sRGB"     # the field's colours are display-referred sRGB
    img.alpha_mode = "STRAIGHT"
    img.pixels.foreach_set(np.ascontiguousarray(atlas.image.numpy()[::-1], np.float32).ravel())
    img.update()
    img.pack()
    img[OBJECT_KEY] = obj.name
    return img


def sync_object(obj, depsgraph=None, force: bool = False) -> int:
    """Push the object's paint image into its field's paint atlas where its pixels changed since the
    last push (all of it with ``force`` or when the field was reloaded); returns the texels changed.
    Rendered viewports render again when any did."""
    img = paint_image(obj)
    if img is None or not props.has_field(obj):
        return 0
    t0 = time.perf_counter()
    # the field the viewport shows (not waiting for a render that holds the cache's lock)
    field = field_cache.cached_field(obj.name_full, props.field_abspath(obj))
    st = STATE.setdefault(obj.name, {})
    w, h = img.size
    if getattr(field, "paint_atlas", None) is None or field.paint_atlas.size != (h, w):
        # the field was loaded again (Ctrl+Z to a file without this paint, a reload): the image and the
        # mesh's UV map still hold the paint, so the atlas is made from them
        field, loops = own_field(obj, depsgraph)
        layer = obj.data.uv_layers.get(UV_NAME)
        if layer is None or w != h:
            raise UserError(f"'{obj.name}' lost its UV map '{UV_NAME}' or its square paint image; press "
                            "Texture Paint again")
        uv = np.empty(len(obj.data.loops) * 2, np.float32)
        layer.data.foreach_get("uv", uv)
        field.paint_atlas = None
        core.get().edit.create_paint_atlas(field, resolution=w, uvs=uv.reshape(-1, 2)[loops])
        force = True
    atlas = field.paint_atlas
    t1 = time.perf_counter()
    px = _read_pixels(img)
    t2 = time.perf_counter()
    last = st.get("last")
    img3 = px.reshape(h, w, 4)
    if force or last is None or last.size != px.size or st.get("atlas") is not atlas:
        # against the atlas itself (Blender's rows run bottom to top)
        yy, xx = np.nonzero(_differ(img3[::-1], atlas.image.numpy()))
    else:
        yb, xx = np.nonzero(_differ(img3, last.reshape(h, w, 4)))
        yy = h - 1 - yb
    t3 = time.perf_counter()
    changed = len(atlas.set_texels(yy * w + xx, img3[h - 1 - yy, xx])) if len(yy) else 0
    st.update(last=px, atlas=atlas, image=img.name)
    STATS["polls"] += 1
    STATS["last_split_s"] = {"field": t1 - t0, "read": t2 - t1, "diff": t3 - t2, "push": time.perf_counter() - t3}
    if changed:
        STATS["pushes"] += 1
        STATS["texels"] = changed
        STATS["last_push_s"] = time.perf_counter() - t0
        STATS["last_push_at"] = time.perf_counter()
        engine.refresh_viewports()
    return changed


def sync_all(depsgraph=None, only_painting: bool = False) -> int:
    n = 0
    for img in list(bpy.data.images):
        name = img.get(OBJECT_KEY)
        obj = bpy.data.objects.get(name) if name else None
        if obj is None or (only_painting and obj.mode != "TEXTURE_PAINT"):
            continue
        try:
            n += sync_object(obj, depsgraph)
        except Exception as exc:  # noqa: BLE001 - a handler must not raise into Blender
            print(f"NeuMesh: Texture Paint of '{obj.name}' not shown: {exc}")
    return n


WATCH = {"running": False, "pending": False, "last": 0.0, "cost": 0.0}


def _painting() -> bool:
    """Is an object whose field has a paint image in Texture Paint mode?"""
    for img in bpy.data.images:
        name = img.get(OBJECT_KEY)
        obj = bpy.data.objects.get(name) if name else None
        if obj is not None and obj.mode == "TEXTURE_PAINT":
            return True
    return False


def stroke_running(obj=None) -> bool:
    """May a Texture Paint stroke be running now (on ``obj``, when given)?  The stroke watcher saw a
    mouse press in Texture Paint mode and no event since: the stroke's own handler takes every event
    until it ends.  Blender's projection paint reads the painted object's evaluated mesh through
    pointers it took when the stroke began, so nothing may make that mesh evaluate anew until the
    stroke ends (a shape key written meanwhile: Blender 3.4 segfaults at the stroke's next dab)."""
    if not (WATCH["running"] and WATCH.get("stroke")):
        return False
    return obj is None or obj.mode == "TEXTURE_PAINT"


def tick():
    """Timer.  With a window, it starts the stroke watcher (:class:`NEUMESH_OT_texture_paint_watch`)
    while an object is in Texture Paint mode; without one (scripts), or as a slow fallback beside
    the watcher, it compares the pixels itself, only once the image was painted (``is_dirty``).  A
    4096^2 image takes ~0.5 s to read, so the next poll waits 3 (no watcher) or 10 (watcher) times as
    long as this one took."""
    if not _painting():
        return POLL_S
    if not WATCH["running"]:
        _start_watch()
    if not any(img.get(OBJECT_KEY) and img.is_dirty for img in bpy.data.images):
        return POLL_S
    t = time.perf_counter()
    sync_all(only_painting=True)
    cost = time.perf_counter() - t
    return max(5.0, 10.0 * cost) if WATCH["running"] else max(POLL_S, 3.0 * cost)


def _start_watch():
    try:
        wm = bpy.context.window_manager
        win = wm.windows[0] if wm is not None and len(wm.windows) else None
    except Exception:  # noqa: BLE001
        win = None
    if win is None or bpy.app.background:
        return
    try:
        with quiet.override(bpy.context, window=win):
            bpy.ops.neumesh.texture_paint_watch("INVOKE_DEFAULT")
    except Exception as exc:  # noqa: BLE001 - the timer's poll still follows the image
        print(f"NeuMesh: cannot follow Texture Paint strokes: {exc}")


class NEUMESH_OT_texture_paint_watch(bpy.types.Operator):
    """Follow Texture Paint strokes on a NeuMesh field: after a mouse press (a stroke) the paint image
    is pushed into the field every timer tick until nothing changes any more (runs while an object
    with a NeuMesh paint image is in Texture Paint mode; passes every event on)"""

    bl_idname = "neumesh.texture_paint_watch"
    bl_label = "Follow Texture Paint"
    bl_options = {"INTERNAL"}

    def invoke(self, context, event):
        if WATCH["running"]:
            return {"CANCELLED"}
        self._timer = context.window_manager.event_timer_add(0.1, window=context.window)
        context.window_manager.modal_handler_add(self)
        WATCH.update(running=True, pending=False)
        return {"RUNNING_MODAL"}

    def _end(self, context):
        WATCH.update(running=False, pending=False, stroke=False)
        try:
            context.window_manager.event_timer_remove(self._timer)
        except Exception:  # noqa: BLE001
            pass

    def modal(self, context, event):
        if not _painting():
            self._end(context)
            return {"FINISHED"}
        now = time.perf_counter()
        if event.type == "LEFTMOUSE" and event.value == "PRESS":
            # a stroke starts (its own modal handler takes the events until it ends)
            WATCH.update(pending=True, stroke=True, event_t=now)
        elif event.type != "TIMER":
            if WATCH.get("stroke"):           # the first event after a stroke: it has ended
                WATCH.update(pending=True, stroke=False, event_t=now)
        elif WATCH["pending"] and now - WATCH["last"] >= max(0.1, 2.0 * WATCH["cost"]):
            n = sync_all(only_painting=True)
            WATCH.update(last=time.perf_counter(), cost=time.perf_counter() - now)
            if n:
                WATCH["event_t"] = now
            elif now - WATCH.get("event_t", 0.0) > 0.5 and not WATCH.get("stroke"):
                WATCH["pending"] = False      # the image has settled
        return {"PASS_THROUGH"}

    def cancel(self, context):
        self._end(context)


def on_undo(*_args):
    sync_all()


def ensure_timer():
    if not bpy.app.timers.is_registered(tick):
        bpy.app.timers.register(tick, first_interval=POLL_S, persistent=True)


classes = (NEUMESH_OT_texture_paint_watch,)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()
    bpy.app.handlers.undo_post.append(on_undo)
    bpy.app.handlers.redo_post.append(on_undo)
    ensure_timer()


def unregister():
    for hs, fn in ((bpy.app.handlers.undo_post, on_undo), (bpy.app.handlers.redo_post, on_undo)):
        if fn in hs:
            hs.remove(fn)
    if bpy.app.timers.is_registered(tick):
        bpy.app.timers.unregister(tick)
    STATE.clear()
    _unregister_classes()
