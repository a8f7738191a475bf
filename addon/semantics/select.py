"""Select by click (modal, 3D viewport): click on the rendered object; the part under the cursor
becomes a vertex group (default "NeuMesh selection", or the name given) and the edit-mode selection.
The redo panel's *Similarity* slider re-runs the region growing (the vertex features and neighbour
graph are cached).  Esc / right click cancels.  Scripts drive it with ``camera=`` (a camera object's
view at the scene's render size) and ``pixel=(x, y)`` (pixels from the top-left corner).  The group
feeds every other tool: swap, fill, paint, and Blender's own hook, armature weights, proportional
editing or Separate.
"""
from __future__ import annotations

import threading
import time

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, FloatVectorProperty, IntVectorProperty, StringProperty

from ..runtime._np import np
from ..runtime import core
from ..runtime.errors import UserError
from ..scene import camera, props, sync
from ..render import field_cache

DEFAULT_GROUP = "NeuMesh selection"

_CONTEXTS: dict = {}   # object name -> SelectionContext (vertex features + graph of one pose)


def _posed_field(obj, context):
    """(field, mesh_index): the object's field posed at its evaluated vertices (the render cache's
    instance; for a mesh changed by topology edits, the field remapped onto it) and the mesh vertex of
    each field vertex (None: the same order)."""
    props.field_path_of(obj)
    depsgraph = context.evaluated_depsgraph_get()
    n_eval = len(obj.evaluated_get(depsgraph).data.vertices)
    if n_eval != len(obj.data.vertices):
        raise UserError(f"'{obj.name}' has modifiers that add or remove vertices ({n_eval} evaluated, "
                             f"{len(obj.data.vertices)} in the mesh); disable them (e.g. Subdivision Surface) "
                             "while selecting, so the selection lands on the mesh's own vertices")
    return field_cache.object_field(obj, depsgraph)


_PREPARING: dict = {}   # object name -> thread building its SelectionContext (see prepare_selection)


def geometry_cache(obj):
    """The edits folder (``props.edits_folder``): the core caches the scaffold's shape features there
    (one file per scaffold, reused by every edited file of it); None when the object has no field file
    or there is no edits folder yet (an unsaved .blend): the features are then kept in memory only."""
    if not props.field_abspath(obj):
        return None
    try:
        return props.scene_edits_folder()
    except UserError:
        return None


def shape_note(info: dict) -> str:
    """'' when the selection used the shape; otherwise why it used colour alone (for the report)."""
    return "colour only: the shape features need robust-laplacian (Install in the Semantics panel)" \
        if info.get("geometry") else ""


def core_message(exc, obj) -> str:
    """A core error as the artist reads it here: a field without semantic codes names the panel button
    that makes them (the core's own message names the command line)."""
    if type(exc).__name__ == "NoSemanticsError":
        return (f"'{obj.name}' has no semantic codes yet: press Distill semantics (Edit field > Semantics) "
                "first; it learns them from the dataset's photos")
    return str(exc)


def _context_for(obj, field, nm):
    job = _PREPARING.pop(obj.name_full, None)
    if job is not None:
        job.join()   # the context started when the operator was invoked (usually done by the click)
    ctx = _CONTEXTS.get(obj.name_full)
    if ctx is None or not ctx.matches(field):
        ctx = nm.semantics.SelectionContext(field, geometry_cache=geometry_cache(obj))
        _CONTEXTS.clear()   # one object's features at a time (they can be large)
        _CONTEXTS[obj.name_full] = ctx
    return ctx


def prepare_selection(obj, context):
    """Start building ``obj``'s selection context (vertex features, KD-tree, neighbour graph) in a
    background thread, so that the click itself only pays for the pick and the region growing.  Called
    when Select by click starts waiting for the click; returns the thread (None when the context is
    already current or the object cannot be selected on: the click then reports the error)."""
    try:
        nm = core.get()
        field, _ = _posed_field(obj, context)
        field._require_semantics()
    except Exception:  # noqa: BLE001  (errors are reported by the click, with their message)
        return None
    name = obj.name_full
    cache = geometry_cache(obj)
    ctx = _CONTEXTS.get(name)
    if (ctx is not None and ctx.matches(field)) or name in _PREPARING:
        return None

    def build():
        try:
            c = nm.semantics.SelectionContext(field, geometry_cache=cache).prepare()
        except Exception:  # noqa: BLE001  (rebuilt, with its error, on the click)
            return
        _CONTEXTS.clear()
        _CONTEXTS[name] = c

    job = threading.Thread(target=build, name="neumesh-select-context", daemon=True)
    _PREPARING[name] = job
    job.start()
    return job


def write_selection(obj, vertices, group_name: str, replace: bool = True):
    """Vertex group ``group_name`` := ``vertices`` (weight 1; added to it when not ``replace``) and the
    mesh's vertex/edge/face selection := the group.  Works in object and edit mode."""
    me = obj.data
    n = len(me.vertices)
    was_edit = obj.mode == "EDIT"
    if was_edit:
        bpy.ops.object.mode_set(mode="OBJECT")
    try:
        vg = obj.vertex_groups.get(group_name) or obj.vertex_groups.new(name=group_name)
        mask = np.zeros(n, bool)
        if not replace:
            mask[sync.vertex_group_indices(obj, vg.name)] = True
        mask[np.asarray(vertices, np.int64)] = True
        vg.remove(list(range(n)))
        idx = np.nonzero(mask)[0]
        if len(idx):
            vg.add(idx.tolist(), 1.0, "REPLACE")
        obj.vertex_groups.active_index = vg.index
        _select_vertices(me, mask)
        me.update()
        return vg
    finally:
        if was_edit:
            bpy.ops.object.mode_set(mode="EDIT")


def _select_vertices(me, mask) -> None:
    """Vertex selection := ``mask``; edges and faces follow (selected when all their vertices are).
    Through bmesh: Blender 5.0's ``edges.foreach_set("select")`` crashes on meshes built from arrays."""
    import bmesh

    bm = bmesh.new()
    try:
        bm.from_mesh(me)
        bm.select_mode = {"VERT"}
        for v, sel in zip(bm.verts, mask.tolist()):
            v.select = sel
        bm.select_flush_mode()
        bm.to_mesh(me)
    finally:
        bm.free()


def viewport_region_at(area, x: int, y: int):
    """The 3D view's main ('WINDOW') region of ``area`` under window coordinates (x, y), or None."""
    if area is None or area.type != "VIEW_3D":
        return None
    for r in area.regions:
        if r.type == "WINDOW" and r.x <= x < r.x + r.width and r.y <= y < r.y + r.height and r.data is not None:
            return r
    return None


class NEUMESH_OT_select_by_click(bpy.types.Operator):
    """Click on the rendered object: the part under the cursor becomes a vertex group and the edit-mode
    selection (Esc cancels)"""

    bl_idname = "neumesh.select_by_click"
    bl_label = "Select by click"
    bl_options = {"REGISTER", "UNDO"}

    threshold: FloatProperty(name="Similarity", default=0.75, min=0.0, max=1.0, subtype="FACTOR",
                             description="Combined colour + shape similarity to the clicked part for a vertex "
                                         "to join; lower grows further")
    geometry: FloatProperty(name="Shape weight", default=0.5, min=0.0, max=1.0, subtype="FACTOR",
                            description="How much the shape counts in the similarity (0: colour only); needs "
                                        "robust-laplacian, else the selection uses colour alone")
    creases: BoolProperty(name="Stop at creases", default=True,
                          description="Never grow across a concave crease (a sharp inward bend of the surface)")
    group_name: StringProperty(name="Vertex group", default=DEFAULT_GROUP)
    mode: EnumProperty(name="Mode", items=[("REPLACE", "Replace", "The group becomes the clicked part"),
                                           ("ADD", "Add", "Add the clicked part to the group")], default="REPLACE")
    use_segmenter: BoolProperty(name="2D region seeds", default=True,
                                description="Seed the part from the connected 2D region of similar rendered "
                                            "features around the click (steadier on large parts)")
    pixel: FloatVectorProperty(name="Pixel", size=2, default=(-1.0, -1.0),
                               description="Click position in pixels from the view's top-left corner")
    camera: StringProperty(name="Camera", default="",
                           description="Camera object whose view (at the scene's render size) was clicked; "
                                       "empty: the 3D viewport the click came from")
    view_matrix: FloatVectorProperty(size=16, options={"HIDDEN"})
    window_matrix: FloatVectorProperty(size=16, options={"HIDDEN"})
    view_size: IntVectorProperty(size=2, default=(0, 0), options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and obj.type == "MESH"

    def invoke(self, context, event):
        if context.area is None or context.area.type != "VIEW_3D":
            self.report({"ERROR"}, "NeuMesh: Select by click runs in a 3D viewport")
            return {"CANCELLED"}
        context.window_manager.modal_handler_add(self)
        if context.active_object is not None:
            prepare_selection(context.active_object, context)   # features + graph while the artist aims
        context.area.header_text_set("NeuMesh: click a part of the object (Esc / right click cancels)")
        context.window.cursor_modal_set("EYEDROPPER")
        return {"RUNNING_MODAL"}

    def _end(self, context):
        try:
            context.area.header_text_set(None)
            context.window.cursor_modal_restore()
        except Exception:  # noqa: BLE001
            pass

    def modal(self, context, event):
        if event.type in {"ESC", "RIGHTMOUSE"} and event.value == "PRESS":
            self._end(context)
            return {"CANCELLED"}
        if event.type == "LEFTMOUSE" and event.value == "PRESS":
            # the operator may have been started from the sidebar: find the 3D view region under the
            # mouse (window coordinates), not the region it was invoked from
            region = viewport_region_at(context.area, event.mouse_x, event.mouse_y)
            if region is None:
                return {"PASS_THROUGH"}   # a click on the sidebar/header: not a pick
            self._end(context)
            self.store_view(region, region.data, event.mouse_x - region.x, event.mouse_y - region.y)
            return self.execute(context)
        return {"PASS_THROUGH"}   # navigation keeps working while waiting for the click

    def store_view(self, region, rv3d, mouse_x: int, mouse_y: int) -> None:
        """Keep the viewport's view and the click (region coordinates, origin bottom-left) on the operator,
        so that redo re-runs the same click."""
        self.view_matrix = [v for row in rv3d.view_matrix for v in row]
        self.window_matrix = [v for row in rv3d.window_matrix for v in row]
        self.view_size = (int(region.width), int(region.height))
        self.pixel = (mouse_x + 0.5, region.height - mouse_y - 0.5)
        self.camera = ""

    def _view(self, context):
        if self.camera:
            cam = bpy.data.objects.get(self.camera)
            if cam is None or cam.type != "CAMERA":
                raise UserError(f"no camera object named '{self.camera}'")
            return camera.camera_K_c2w(cam, context.scene, context.evaluated_depsgraph_get())
        w, h = self.view_size
        if w <= 0 or h <= 0:
            raise UserError("no view: click in a 3D viewport, or give camera= and pixel= from a script")
        P = np.asarray(self.window_matrix, np.float64).reshape(4, 4)
        V = np.asarray(self.view_matrix, np.float64).reshape(4, 4)
        K = camera.k_from_projection(P, w, h)
        return K, camera.c2w_from_matrix_world(np.linalg.inv(V)), w, h

    def execute(self, context):
        obj = context.active_object
        if obj.mode == "EDIT":   # the evaluated mesh (and the vertex groups) are current in object mode
            bpy.ops.object.mode_set(mode="OBJECT")
            try:
                return self._execute(context, obj)
            finally:
                bpy.ops.object.mode_set(mode="EDIT")
        return self._execute(context, obj)

    def _execute(self, context, obj):
        t0 = time.perf_counter()
        try:
            nm = core.get()
            core.require("select")
            K, c2w, w, h = self._view(context)
            field, mesh_index = _posed_field(obj, context)
            ctx = _context_for(obj, field, nm)
            cfg = nm.semantics.SelectConfig(threshold=self.threshold, geometry=self.geometry, creases=self.creases,
                                            segmenter="features" if self.use_segmenter else None)
            sel = nm.semantics.select_region(field, (K, c2w, w, h), tuple(self.pixel), cfg, context=ctx)
        except (UserError, core.CoreUnavailable, camera.CameraError, sync.TopologyError) as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        except core.error_types() as exc:   # NoSemanticsError, SelectionError, ... (messages say what to do)
            self.report({"ERROR"}, f"NeuMesh: {core_message(exc, obj)}")
            return {"CANCELLED"}
        name = self.group_name.strip() or DEFAULT_GROUP
        picked = np.asarray(sel.vertices) if mesh_index is None else mesh_index[np.asarray(sel.vertices)]
        write_selection(obj, picked, name, replace=self.mode == "REPLACE")
        note = shape_note(sel.info)
        self.report({"WARNING"} if note else {"INFO"},
                    f"NeuMesh: {len(sel.vertices)} vertices in group '{name}' "
                    f"({time.perf_counter() - t0:.2f}s){'; ' + note if note else ''}")
        return {"FINISHED"}


classes = (NEUMESH_OT_select_by_click,)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()


def unregister():
    _CONTEXTS.clear()
    _unregister_classes()
