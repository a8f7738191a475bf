"""Semantics in Blender: distil semantic codes (background thread), select a part by one click, show
the semantic features as vertex colours.

* **Distil semantics** runs ``nm.semantics.distill_semantics`` on a copy of the active object's field in
  a background thread (progress in the panel and the status bar, Cancel writes nothing) and saves the
  result beside the field as an edit (``<name>.edit-NNN.neumesh``); the object then points at it, so
  "Undo edit" / Ctrl+Z go back to the field without semantics.
* **Select by click** (modal, 3D viewport): click on the rendered object; the part under the cursor
  becomes a vertex group (default "NeuMesh selection", or the name given) and the edit-mode selection.
  The redo panel's *Similarity* slider re-runs the region growing (the vertex features and neighbour
  graph are cached).  Esc / right click cancels.  Scripts drive it with ``camera=`` (a camera object's
  view at the scene's render size) and ``pixel=(x, y)`` (pixels from the top-left corner).
  The group feeds every other tool: swap, fill, paint, and Blender's own hook, armature weights,
  proportional editing or Separate.
* **Show semantic colours** writes the vertex features' first three principal components as a colour
  attribute, so the artist sees what will group together (Solid shading > Attribute).
"""
from __future__ import annotations

import os
import threading
import time
import traceback

import bpy
from bpy.props import (BoolProperty, EnumProperty, FloatProperty, FloatVectorProperty, IntProperty,
                       IntVectorProperty, PointerProperty, StringProperty)

from ._np import np
from . import camera, core, props, render, sync
from .text import labelled

DEFAULT_GROUP = "NeuMesh selection"
COLOUR_ATTRIBUTE = "NeuMesh semantics"
_EXTRACTORS = [("colour-texture", "Colour & texture", "Weight-free: colour and texture statistics over "
                                                      "superpixels (needs nothing downloaded)"),
               ("dino-vits8", "DINO ViT-S/8", "Self-supervised ViT features; weights from $NEUMESH_WEIGHTS "
                                              "(dino-vits8.safetensors) or the Hugging Face cache"),
               ("dino-vitb8", "DINO ViT-B/8", "Larger DINO ViT; local weights as above"),
               ("dinov2-small", "DINOv2 ViT-S/14", "DINOv2 features; local weights as above")]


class SemanticsError(RuntimeError):
    """Selection or distillation cannot start; the message says what to do."""


def _field_path(obj) -> str:
    if obj is None or obj.type != "MESH":
        raise SemanticsError("select a mesh object that carries a NeuMesh field")
    path = props.field_abspath(obj)
    if not path:
        raise SemanticsError(f"object '{obj.name}' has no NeuMesh field; load or train one first")
    if not os.path.isfile(path):
        raise SemanticsError(f"object '{obj.name}': its field file is missing: {path}")
    return path


# ------------------------------------------------------------------------------------------ distil job
class DistilJob:
    """Distillation in a thread; never touches bpy (the operator reads Blender state beforehand)."""

    def __init__(self, *, object_name: str, field_path: str, dataset_path: str, downscale: int = 1,
                 background: str = "white", extractor: str = "colour-texture", steps: int = 1500,
                 config=None):
        self.object_name = object_name
        self.field_path = field_path
        self.dataset_path = dataset_path
        self.downscale = int(downscale)
        self.background = background
        self.extractor = extractor
        self.steps = int(steps)
        self.config = dict(config or {})
        self.threads = core.wanted_threads()   # read here, on the main thread
        self.state = "PENDING"   # RUNNING, DONE, CANCELLED, ERROR
        self.stage = ""
        self.step = 0
        self.total = 1
        self.loss = float("nan")
        self.message = ""
        self.out_path = None
        self.handled = False
        self._cancel = threading.Event()
        self._thread = threading.Thread(target=self._run_in_torch_work, name="neumesh-semantics", daemon=True)

    def start(self):
        self.state = "RUNNING"
        self._thread.start()
        return self

    def cancel(self):
        self._cancel.set()

    def join(self, timeout=None):
        self._thread.join(timeout)
        return not self._thread.is_alive()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    @property
    def fraction(self) -> float:
        # features and rays take the first 20%, training the rest
        base = {"features": 0.0, "rays": 0.1, "train": 0.2}.get(self.stage, 0.0)
        span = 0.1 if self.stage in ("features", "rays") else 0.8
        return min(1.0, base + span * self.step / max(1, self.total))

    def status_text(self) -> str:
        if self.state == "RUNNING":
            what = {"features": "2D features", "rays": "marching rays", "train": "training"}.get(self.stage, "loading")
            loss = f", loss {self.loss:.4f}" if self.stage == "train" and np.isfinite(self.loss) else ""
            return f"NeuMesh semantics: {what} {self.step}/{self.total}{loss}"
        return f"NeuMesh semantics: {self.state.lower()} {self.message}".strip()

    def _callback(self, p):
        self.stage, self.step, self.total, self.loss = p.stage, int(p.step), int(p.total), float(p.loss)
        return not self._cancel.is_set()

    def _run_in_torch_work(self):
        with core.torch_work(self.threads):   # the preference's threads; jemalloc keeps freed memory
            self._run()

    def _run(self):
        try:
            nm = core.get()
            sem = nm.semantics
            field = nm.load_field(self.field_path)   # a copy: the render cache's field is not touched
            scene = nm.load_scene(self.dataset_path, downscale=self.downscale, background=self.background)
            extractor = sem.make_extractor(self.extractor)
            cfg = sem.DistillConfig(steps=self.steps, **self.config)
            res = sem.distill_semantics(field, scene, extractor, cfg, callback=self._callback)
            if res.cancelled or self._cancel.is_set():
                self.state, self.message = "CANCELLED", "nothing was written"
                return
            self.out_path = nm.edit.save_edited(field, self.field_path, sem.semantics_record(field, res))
            self.state = "DONE"
            self.message = (f"{res.steps_done} steps in {res.seconds:.0f}s, loss {res.final_loss:.3f}; "
                            f"saved {os.path.basename(self.out_path)}")
        except Exception as exc:  # noqa: BLE001 - shown in the UI
            self.state, self.message = "ERROR", f"{type(exc).__name__}: {exc}"
            traceback.print_exc()
        finally:
            try:
                core.guard_torch_namespaces()
            except Exception:  # noqa: BLE001
                pass


_job: DistilJob | None = None


def current_job() -> DistilJob | None:
    return _job


def finish_job():
    """Main thread: point the object at the file the finished job wrote."""
    job = _job
    if job is None or job.running or job.handled:
        return
    job.handled = True
    if job.state == "DONE" and job.out_path and os.path.isfile(job.out_path):
        obj = bpy.data.objects.get(job.object_name)
        if obj is not None:
            props.set_field_path(obj, job.out_path)
    _status(None)
    _redraw()


def _timer():
    job = _job
    if job is None:
        return None
    _status(job.status_text() if job.running else None)
    _redraw()
    if job.running:
        return 0.25
    finish_job()
    return None


def _status(text):
    try:
        ws = bpy.context.workspace
        if ws is not None:
            ws.status_text_set(text)
    except Exception:  # noqa: BLE001
        pass


def _redraw():
    try:
        for win in bpy.context.window_manager.windows:
            for area in win.screen.areas:
                if area.type in ("VIEW_3D", "PROPERTIES"):
                    area.tag_redraw()
    except Exception:  # noqa: BLE001
        pass


class NEUMESH_OT_distil_semantics(bpy.types.Operator):
    """Distil semantic codes into the active object's field from 2D features of the dataset's training
    images (background thread; the result is saved beside the field as an edit)"""

    bl_idname = "neumesh.distil_semantics"
    bl_label = "Distil semantics"

    steps: IntProperty(name="Steps", default=0, min=0, options={"SKIP_SAVE"}, description="0 = panel setting")
    max_views: IntProperty(default=0, min=0, options={"HIDDEN", "SKIP_SAVE"}, description="0 = all views")
    rays_per_view: IntProperty(default=0, min=0, options={"HIDDEN", "SKIP_SAVE"}, description="0 = default")
    wait: BoolProperty(default=False, options={"HIDDEN", "SKIP_SAVE"},
                       description="Block until distillation ends (scripts, background mode)")

    def execute(self, context):
        global _job
        s = context.scene.neumesh_semantics
        obj = context.active_object
        try:
            path = _field_path(obj)
        except SemanticsError as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        dataset = bpy.path.abspath(context.scene.neumesh.dataset_path)
        if not dataset or not os.path.isdir(dataset):
            self.report({"ERROR"}, "NeuMesh: set the dataset folder the field was trained on (NeuMesh data panel)")
            return {"CANCELLED"}
        if _job is not None and _job.running:
            self.report({"ERROR"}, "NeuMesh: a semantic distillation is already running; cancel it first")
            return {"CANCELLED"}
        cfg = {k: v for k, v in (("max_views", self.max_views), ("rays_per_view", self.rays_per_view)) if v}
        _job = DistilJob(object_name=obj.name, field_path=path, dataset_path=dataset,
                         downscale=context.scene.neumesh.downscale, extractor=s.extractor,
                         steps=self.steps or s.steps, config=cfg).start()
        if self.wait:
            _job.join()
            finish_job()
            level = "INFO" if _job.state in ("DONE", "CANCELLED") else "ERROR"
            self.report({level}, _job.status_text())
            return {"FINISHED"} if _job.state == "DONE" else {"CANCELLED"}
        if not bpy.app.timers.is_registered(_timer):
            bpy.app.timers.register(_timer, first_interval=0.25)
        self.report({"INFO"}, f"NeuMesh: distilling semantics of '{obj.name}'")
        return {"FINISHED"}


class NEUMESH_OT_distil_cancel(bpy.types.Operator):
    """Stop the semantic distillation (nothing is written)"""

    bl_idname = "neumesh.distil_cancel"
    bl_label = "Cancel distillation"

    def execute(self, context):
        if _job is None or not _job.running:
            self.report({"WARNING"}, "NeuMesh: no distillation is running")
            return {"CANCELLED"}
        _job.cancel()
        return {"FINISHED"}


# ------------------------------------------------------------------------------------------ selection
_CONTEXTS: dict = {}   # object name -> SelectionContext (vertex features + graph of one pose)


def _posed_field(obj, context):
    """(field, mesh_index): the object's field posed at its evaluated vertices (the render cache's
    instance; for a mesh changed by topology edits, the field remapped onto it) and the mesh vertex of
    each field vertex (None: the same order)."""
    _field_path(obj)
    depsgraph = context.evaluated_depsgraph_get()
    n_eval = len(obj.evaluated_get(depsgraph).data.vertices)
    if n_eval != len(obj.data.vertices):
        raise SemanticsError(f"'{obj.name}' has modifiers that add or remove vertices ({n_eval} evaluated, "
                             f"{len(obj.data.vertices)} in the mesh); disable them (e.g. Subdivision Surface) "
                             "while selecting, so the selection lands on the mesh's own vertices")
    return render.object_field(obj, depsgraph)


_PREPARING: dict = {}   # object name -> thread building its SelectionContext (see prepare_selection)


def _context_for(obj, field, nm):
    job = _PREPARING.pop(obj.name_full, None)
    if job is not None:
        job.join()   # the context started when the operator was invoked (usually done by the click)
    ctx = _CONTEXTS.get(obj.name_full)
    if ctx is None or not ctx.matches(field):
        ctx = nm.semantics.SelectionContext(field)
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
    ctx = _CONTEXTS.get(name)
    if (ctx is not None and ctx.matches(field)) or name in _PREPARING:
        return None

    def build():
        try:
            c = nm.semantics.SelectionContext(field).prepare()
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
                             description="Cosine similarity to the clicked part's mean feature for a vertex to "
                                         "join; lower grows further")
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
                raise SemanticsError(f"no camera object named '{self.camera}'")
            return camera.camera_K_c2w(cam, context.scene, context.evaluated_depsgraph_get())
        w, h = self.view_size
        if w <= 0 or h <= 0:
            raise SemanticsError("no view: click in a 3D viewport, or give camera= and pixel= from a script")
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
            K, c2w, w, h = self._view(context)
            field, mesh_index = _posed_field(obj, context)
            ctx = _context_for(obj, field, nm)
            cfg = nm.semantics.SelectConfig(threshold=self.threshold,
                                            segmenter="features" if self.use_segmenter else None)
            sel = nm.semantics.select_region(field, (K, c2w, w, h), tuple(self.pixel), cfg, context=ctx)
        except (SemanticsError, core.CoreUnavailable, camera.CameraError, sync.TopologyError, ImportError) as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        except core.error_types() as exc:   # NoSemanticsError, SelectionError, ... (messages say what to do)
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        name = self.group_name.strip() or DEFAULT_GROUP
        picked = np.asarray(sel.vertices) if mesh_index is None else mesh_index[np.asarray(sel.vertices)]
        write_selection(obj, picked, name, replace=self.mode == "REPLACE")
        self.report({"INFO"}, f"NeuMesh: {len(sel.vertices)} vertices in group '{name}' "
                              f"({time.perf_counter() - t0:.2f}s)")
        return {"FINISHED"}


class NEUMESH_OT_semantic_colours(bpy.types.Operator):
    """Colour the mesh by its semantic features (first three principal components) in a colour
    attribute, to see what will group together (Solid shading > Color: Attribute)"""

    bl_idname = "neumesh.semantic_colours"
    bl_label = "Show semantic colours"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        obj = context.active_object
        try:
            nm = core.get()
            _field_path(obj)
            field, mesh_index = render.object_field(obj, context.evaluated_depsgraph_get())
            feats = field.vertex_semantics().cpu().numpy().astype(np.float64)
            if mesh_index is not None:   # a remapped mesh: features onto its vertices (others stay 0)
                full = np.zeros((len(obj.data.vertices), feats.shape[1]))
                full[mesh_index] = feats
                feats = full
        except (SemanticsError, core.CoreUnavailable) as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        except core.error_types() as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        if len(obj.data.vertices) != len(feats):
            self.report({"ERROR"}, f"NeuMesh: '{obj.name}' does not have its field's {len(feats)} vertices")
            return {"CANCELLED"}
        rgb = pca_colours(feats)
        me = obj.data
        attr = me.color_attributes.get(COLOUR_ATTRIBUTE)
        if attr is None or attr.domain != "POINT" or attr.data_type != "FLOAT_COLOR":
            if attr is not None:
                me.color_attributes.remove(attr)
            attr = me.color_attributes.new(COLOUR_ATTRIBUTE, "FLOAT_COLOR", "POINT")
        rgba = np.concatenate([rgb, np.ones((len(rgb), 1))], 1).astype(np.float32)
        attr.data.foreach_set("color", rgba.ravel())
        me.color_attributes.active_color = attr
        me.update()
        try:
            for area in context.screen.areas:
                if area.type == "VIEW_3D":
                    area.spaces.active.shading.color_type = "VERTEX"
        except Exception:  # noqa: BLE001 - no screen in background mode
            pass
        self.report({"INFO"}, f"NeuMesh: semantic colours in attribute '{COLOUR_ATTRIBUTE}'")
        return {"FINISHED"}


def pca_colours(feats: np.ndarray) -> np.ndarray:
    """(N,C) features -> (N,3) colours in [0,1]: the first three principal components, each stretched
    between its 1st and 99th percentile."""
    x = feats - feats.mean(0)
    _, _, vt = np.linalg.svd(x[:: max(1, len(x) // 20000)], full_matrices=False)
    y = x @ vt[:3].T
    if y.shape[1] < 3:
        y = np.concatenate([y, np.zeros((len(y), 3 - y.shape[1]))], 1)
    lo, hi = np.percentile(y, 1, axis=0), np.percentile(y, 99, axis=0)
    return np.clip((y - lo) / np.maximum(hi - lo, 1e-9), 0.0, 1.0)


# ------------------------------------------------------------------------------------------ settings + panel
class NeuMeshSemanticSettings(bpy.types.PropertyGroup):
    extractor: EnumProperty(name="Features", items=_EXTRACTORS, default="colour-texture",
                            description="2D feature extractor the semantic codes are distilled from")
    steps: IntProperty(name="Steps", default=1500, min=1, max=1_000_000)
    group_name: StringProperty(name="Group", default=DEFAULT_GROUP,
                               description="Vertex group that Select by click writes")


class NEUMESH_PT_semantics(bpy.types.Panel):
    bl_label = "Semantics"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NeuMesh"
    bl_parent_id = "NEUMESH_PT_edit"

    def draw(self, context):
        s = context.scene.neumesh_semantics
        col = self.layout.column()
        job = _job
        if job is not None and job.running:
            col.label(text=job.status_text(), icon="SORTTIME")
            if hasattr(col, "progress"):
                col.progress(factor=job.fraction, text=f"{job.stage} {job.step}/{job.total}")
            col.operator("neumesh.distil_cancel", icon="CANCEL")
        else:
            labelled(col, s, "extractor", "2D features")
            col.prop(s, "steps")
            col.operator("neumesh.distil_semantics", icon="SHADERFX")
            if job is not None:
                col.label(text=job.status_text(), icon={"DONE": "CHECKMARK", "ERROR": "ERROR"}.get(job.state, "INFO"))
        col.separator()
        labelled(col, s, "group_name", "Vertex group for the clicked part")
        op = col.operator("neumesh.select_by_click", icon="EYEDROPPER")
        op.group_name = s.group_name
        col.operator("neumesh.semantic_colours", icon="COLOR")


classes = (NeuMeshSemanticSettings, NEUMESH_OT_distil_semantics, NEUMESH_OT_distil_cancel,
           NEUMESH_OT_select_by_click, NEUMESH_OT_semantic_colours, NEUMESH_PT_semantics)


def register():
    for c in classes:
        bpy.utils.register_class(c)
    bpy.types.Scene.neumesh_semantics = PointerProperty(type=NeuMeshSemanticSettings)


def unregister():
    if bpy.app.timers.is_registered(_timer):
        bpy.app.timers.unregister(_timer)
    if _job is not None and _job.running:
        _job.cancel()
    _CONTEXTS.clear()
    del bpy.types.Scene.neumesh_semantics
    for c in reversed(classes):
        bpy.utils.unregister_class(c)
