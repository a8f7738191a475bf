"""Import Mesh and Load Field: a file read in a background job, then one Blender object.

Both open their file browser in the folder the artist works in (:func:`start_folder`: the field's or
the dataset's folder, else the .blend's) and list only their own files (``filter_glob``: ``.ply``/``.obj``,
``.neumesh``).  The file is read by the core in a :class:`jobs.Job` (the first read also imports torch,
seconds on a busy machine): from the interface the window stays responsive, the status bar shows the
stage and the percentage, and Esc cancels (nothing is made); from a script the operator blocks.  The
object is made on the main thread at the end (``sync.new_mesh_object``: ``vertices.add`` +
``foreach_set``), and an Info report says what was loaded: vertices, faces, the file's size and, for a
field put on an existing mesh, how well the mesh's vertices match the field's scaffold.
"""
from __future__ import annotations

import os

import bpy
from bpy.props import BoolProperty, StringProperty

from ..runtime._np import np
from ..runtime import core, jobs
from ..runtime.text import file_size
from ..scene import identity, props, sync
from ..render import field_cache

MESH_GLOB = "*.ply;*.obj"
FIELD_GLOB = "*.neumesh"
# a mesh whose vertices lie further than this share of the field's size from its scaffold is reported
MATCH_TOLERANCE = 1e-3


def start_folder(*candidates: str) -> str:
    """The folder a file browser opens in: the first candidate (a folder or a file, '' skipped) that
    exists, as a folder path ending in a separator; '' when none does (Blender's own default)."""
    for c in candidates:
        if not c:
            continue
        d = c if os.path.isdir(c) else os.path.dirname(c) if os.path.isfile(c) else ""
        if d:
            return os.path.join(os.path.abspath(d), "")
    return ""


def _blend_folder() -> str:
    return os.path.dirname(bpy.data.filepath) if bpy.data.filepath else ""


def _dataset_folder(context) -> str:
    p = context.scene.neumesh.dataset_path
    return bpy.path.abspath(p) if p.strip() else ""


def make_active(context, obj):
    for o in context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    context.view_layer.objects.active = obj


class ReadJob(jobs.Job):
    """``read(job)`` in the thread (it sets ``job.message`` to its stage and calls ``job.progress``). Any
    error is the whole story for the report (no traceback)."""

    quiet_errors = (Exception,)

    def __init__(self, label: str, read):
        super().__init__(label)
        self._read = read

    def run(self):
        return self._read(self)


def _stage(job, fraction: float, message: str) -> None:
    job.message = message
    if not job.progress(fraction):
        raise core.get().Cancelled(f"{job.label} cancelled")


class _BrowseThenRead(jobs.JobModal):
    """From the interface: the file browser first (in :meth:`start_in`, with ``filter_glob``); its button
    runs the operator again as a modal job (``run``), with progress in the status bar and Esc. From a
    script (EXEC): the read blocks."""

    run: BoolProperty(default=False, options={"HIDDEN", "SKIP_SAVE"})
    op_name = ""   # bpy.ops.neumesh.<op_name> (a registered operator's bl_idname reads NEUMESH_OT_...)

    def start_in(self, context) -> str:  # pragma: no cover - each operator says
        raise NotImplementedError

    def invoke(self, context, event):
        if self.run:
            return jobs.JobModal.invoke(self, context, event)
        if not self.filepath:
            self.filepath = self.start_in(context)
        self._browsed = True
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        if getattr(self, "_browsed", False):
            # the file browser's button: the same operator again, modal (an operator the file browser
            # runs cannot itself stay modal)
            op = getattr(bpy.ops.neumesh, self.op_name)
            res = op("INVOKE_DEFAULT", run=True, **self.rerun_props())
            return {"FINISHED"} if res & {"RUNNING_MODAL", "FINISHED"} else {"CANCELLED"}
        return jobs.JobModal.execute(self, context)

    def rerun_props(self) -> dict:
        return {"filepath": self.filepath}

    def _failed(self, job, what: str):
        if job.state == "CANCELLED":
            self.report({"WARNING"}, f"NeuMesh: {self.edit_label} cancelled; nothing was made")
        elif isinstance(job.error, core.CoreUnavailable):
            self.report({"ERROR"}, f"NeuMesh: {job.error}")
        else:
            self.report({"ERROR"}, f"NeuMesh: {what}: {job.message}")
        return {"CANCELLED"}


class NEUMESH_OT_import_mesh(_BrowseThenRead, bpy.types.Operator):
    """Import a mesh (.ply/.obj) as the scaffold, the mesh the field is stored on (read by the core's
    loader, so the vertex order is exactly the file's)"""

    bl_idname, op_name = "neumesh.import_mesh", "import_mesh"
    bl_label = "Import scaffold mesh"
    bl_options = {"REGISTER", "UNDO"}
    edit_label = "importing the mesh"

    filepath: StringProperty(subtype="FILE_PATH")
    filter_glob: StringProperty(default=MESH_GLOB, options={"HIDDEN"})

    def start_in(self, context) -> str:
        return start_folder(_dataset_folder(context), _blend_folder())

    def _start(self, context):
        path = os.path.abspath(bpy.path.abspath(self.filepath))

        def read(job):
            _stage(job, 0.02, "loading NeuMesh")
            nm = core.get()
            _stage(job, 0.1, f"reading {os.path.basename(path)}")
            mesh = nm.load_mesh(path)
            V = np.ascontiguousarray(mesh.vertices, np.float32).reshape(-1, 3)
            F = np.ascontiguousarray(mesh.faces, np.int64).reshape(-1, 3)
            _stage(job, 0.9, "making the object")
            return V, F

        self._path = path
        return ReadJob("import mesh", read)

    def _finish(self, context, job):
        path = self._path
        if job.state != "DONE":
            return self._failed(job, f"cannot load mesh {path}")
        V, F = job.result
        name = os.path.splitext(os.path.basename(path))[0] or "scaffold"
        obj = sync.new_mesh_object(name, V, F)
        make_active(context, obj)
        context.scene.neumesh.train_object = obj
        self.report({"INFO"}, f"NeuMesh: imported {os.path.basename(path)} ({file_size(path)}): {len(V):,} "
                              f"vertices, {len(F):,} faces as '{obj.name}', the Training mesh")
        return {"FINISHED"}


def scaffold_offset(obj, field) -> tuple:
    """(largest distance, the field's size): how far the mesh's own vertices (world space, undeformed)
    lie from the field's scaffold vertices, vertex by vertex, and the diagonal of the scaffold's box."""
    rest = np.asarray(field.rest_vertices.detach().cpu().numpy() if hasattr(field.rest_vertices, "detach")
                      else field.rest_vertices, np.float64)
    mesh = sync.rest_world_vertices(obj).astype(np.float64)
    size = float(np.linalg.norm(rest.max(0) - rest.min(0))) if len(rest) else 0.0
    return float(np.linalg.norm(mesh - rest, axis=1).max()) if len(rest) else 0.0, size


class NEUMESH_OT_load_field(_BrowseThenRead, bpy.types.Operator):
    """Attach a trained field file to the active mesh (same vertex count), or create its scaffold mesh"""

    bl_idname, op_name = "neumesh.load_field", "load_field"
    bl_label = "Load field"
    bl_options = {"REGISTER", "UNDO"}
    edit_label = "loading the field"

    filepath: StringProperty(subtype="FILE_PATH")
    filter_glob: StringProperty(default=FIELD_GLOB, options={"HIDDEN"})
    new_object: BoolProperty(name="New object", default=False,
                             description="Create a mesh object from the field's scaffold")

    def start_in(self, context) -> str:
        obj = context.active_object
        own = props.field_abspath(obj) if obj is not None and obj.type == "MESH" else ""
        return start_folder(own, _dataset_folder(context), _blend_folder())

    def rerun_props(self) -> dict:
        return {"filepath": self.filepath, "new_object": self.new_object}

    def _start(self, context):
        path = os.path.abspath(bpy.path.abspath(self.filepath))

        def read(job):
            _stage(job, 0.02, "loading NeuMesh")
            nm = core.get()
            size = f" ({file_size(path)})" if os.path.isfile(path) else ""
            _stage(job, 0.1, f"reading {os.path.basename(path)}{size}")
            field = nm.load_field(path)
            _stage(job, 0.9, "putting it on the object")
            return field

        self._path = path
        return ReadJob("load field", read)

    def _finish(self, context, job):
        path = self._path
        if job.state != "DONE":
            return self._failed(job, f"cannot load field {path}")
        field = job.result
        nv, nf = int(field.num_vertices), int(len(field.faces))
        obj = context.active_object
        made = self.new_object or obj is None or obj.type != "MESH"
        if made:
            V = np.asarray(field.rest_vertices, np.float32)
            F = np.asarray(field.faces, np.int64)
            obj = sync.new_mesh_object(os.path.splitext(os.path.basename(path))[0], V, F)
            make_active(context, obj)
        elif len(obj.data.vertices) != nv:
            self.report({"ERROR"}, f"NeuMesh: '{obj.name}' has {len(obj.data.vertices)} vertices but the field "
                                   f"has {nv}; enable 'New object' to create its mesh")
            return {"CANCELLED"}
        identity.attach(context, obj, field, path)   # path, vertex ids (topology edits keep the field)
        field_cache.adopt(obj.name_full, path, field)     # the render uses this copy: no second read of the file
        obj.neumesh.enabled = True
        context.scene.neumesh.train_object = obj   # Training > Scaffold mesh: the mesh this field is on
        what = f"NeuMesh: loaded {os.path.basename(path)} ({file_size(path)}): {nv:,} vertices, {nf:,} faces"
        if made:
            self.report({"INFO"}, f"{what}, as the new object '{obj.name}' (the field's own scaffold)")
            return {"FINISHED"}
        offset, size = scaffold_offset(obj, field)
        if offset <= MATCH_TOLERANCE * max(size, 1e-12):
            self.report({"INFO"}, f"{what}, on '{obj.name}': its {nv:,} vertices match the field's scaffold")
        else:
            self.report({"WARNING"}, f"{what}, on '{obj.name}': its vertices lie up to {offset:.3g} "
                                     f"({offset / max(size, 1e-12):.1%} of the field's size) from the field's "
                                     "scaffold; the field follows the mesh as it is now (a different mesh with "
                                     "the same vertex count renders wrong: use 'New object')")
        return {"FINISHED"}


classes = (NEUMESH_OT_import_mesh, NEUMESH_OT_load_field)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()


def unregister():
    _unregister_classes()
