"""Edits in Blender: the shared plumbing of every edit operator, and Undo edit / Revert.

An edit operator gets the object's field (:func:`field_for_edit`), calls a core edit function, and
hands the result to :func:`commit_edit`, which saves the edited field *beside* the file it came from
(``<name>.edit-NNN.neumesh``; the file training produced is never overwritten) and points the object
at it.  The object's field path is an ordinary undoable property, so Blender's Ctrl+Z / Ctrl+Shift+Z
step between the files, and the render cache reloads whichever file the object points to.  "Undo
edit" steps to the file an edited field was made from; "Revert to trained field" to the root of the
chain.  Edit operators declare ``bl_options = {"REGISTER", "UNDO"}`` and add their panel as a child of
:class:`NEUMESH_PT_edit` (``bl_parent_id = "NEUMESH_PT_edit"``).

Long edits run in a background thread (:class:`EditOperator`): invoked from the UI the operator is
modal, shows progress in the status bar and the cursor, and Esc cancels (nothing changes); run from a
script (``bpy.ops.neumesh.<edit>()``, EXEC) it blocks.  The thread edits a *copy* of the object's
field, so the viewport can keep rendering the current one; the copy replaces it when the edit is
committed.
"""
from __future__ import annotations

import copy
import os
import threading
import time
import traceback

import bpy

from . import core, props, render


class EditError(RuntimeError):
    """An edit cannot start; the message says what to do. Nothing was changed."""


def field_path_of(obj) -> str:
    """The object's field file (absolute); :class:`EditError` when it has none or it is missing."""
    if obj is None or obj.type != "MESH":
        raise EditError("select a mesh object that carries a NeuMesh field")
    path = props.field_abspath(obj)
    if not path:
        raise EditError(f"object '{obj.name}' has no NeuMesh field; load or train one first")
    if not os.path.isfile(path):
        raise EditError(f"object '{obj.name}': its field file is missing: {obj.neumesh.field_path}")
    return path


def field_for_edit(obj):
    """(field, path): the object's field as the renderer holds it (edits write into this instance, so
    the next render shows them without reloading)."""
    path = field_path_of(obj)
    return render.get_field(obj.name_full, path), path


def commit_edit(obj, field, record, parent_path: str) -> str:
    """Save ``field`` (edited in memory by ``record``) beside ``parent_path`` and point ``obj`` at the
    new file; returns its path.  On failure the edit is undone in memory and the object is left as
    it was."""
    nm = core.get()
    edit = _edit_module(nm)
    try:
        out = edit.save_edited(field, parent_path, record)
    except BaseException:
        record.undo(field)
        raise
    props.set_field_path(obj, out)
    render.adopt(obj.name_full, out, field)
    _register(obj, field, out)
    return out


def _register(obj, field, path):
    """The scene's record of which file holds this field's key (joined objects find it there)."""
    from . import identity

    try:
        for scene in obj.users_scene or (bpy.context.scene,):
            identity.register_field(scene, field, path)
    except Exception as exc:  # noqa: BLE001 - only joins of this object later would miss it
        print(f"NeuMesh: could not record the field of '{obj.name}': {exc}")


def _edit_module(nm):
    import importlib

    return importlib.import_module(nm.__name__ + ".edit")


_CHAIN_CACHE: dict = {}


def edit_chain(obj):
    """[(op, path), ...] from the trained file to the object's current file (empty without a field).
    Cached per file (panels draw often; headers change only when a file is rewritten)."""
    try:
        path = field_path_of(obj)
        edit = _edit_module(core.get())
    except (EditError, core.CoreUnavailable):
        return []
    st = os.stat(path)
    key = (path, st.st_mtime_ns, st.st_size)
    if key in _CHAIN_CACHE:
        return _CHAIN_CACHE[key]
    try:
        chain = _read_chain(edit, path)
    except Exception:  # noqa: BLE001 - a panel must draw even if a header is unreadable
        chain = [("unreadable", path)]
    if len(_CHAIN_CACHE) > 64:
        _CHAIN_CACHE.clear()
    _CHAIN_CACHE[key] = chain
    return chain


def _read_chain(edit, path):
    chain = []
    p = path
    while p is not None and len(chain) < 1000:
        info = edit.edit_info(p) if os.path.isfile(p) else None
        chain.append(((info or {}).get("op", "trained"), p))
        p = edit.parent_of(p) if info else None
    return chain[::-1]


def edit_copy(field):
    """A private copy of a cached field for a background edit (taken under the render lock, so no
    render or deformation is half-way through it)."""
    with render._LOCK:
        return copy.deepcopy(field)


def region_of(obj, group: str, field, what: str):
    """Field vertex indices of vertex group ``group`` of ``obj`` (mesh vertices mapped to field vertices
    through their identity attributes, see identity.py); :class:`EditError` when the group is missing
    or empty, or its vertices cannot be mapped."""
    from . import identity, sync

    if not group:
        raise EditError(f"{what}: choose a vertex group of '{obj.name}'")
    if obj.vertex_groups.get(group) is None:
        raise EditError(f"{what}: '{obj.name}' has no vertex group '{group}'")
    idx = sync.vertex_group_indices(obj, group)
    if len(idx) == 0:
        raise EditError(f"{what}: vertex group '{group}' of '{obj.name}' is empty; assign vertices to it")
    try:
        return identity.field_rows(obj, field, idx, what)
    except identity.IdentityError as exc:
        raise EditError(str(exc)) from exc


class EditJob:
    """One core edit in a background thread: ``fn(progress) -> [EditRecord | None, ...]``; ``progress(fraction)``
    returns False once :meth:`cancel` was called (the core then raises ``Cancelled``)."""

    def __init__(self, label: str, fn):
        self.label = label
        self.fn = fn
        self.fraction = 0.0
        self.record = None
        self.error = None
        self.cancelled = False
        self.started = time.time()
        self.threads = core.wanted_threads()   # read here, on the main thread
        self._cancel = threading.Event()
        self._thread = threading.Thread(target=self._run_in_torch_work, name=f"neumesh-{label}", daemon=True)

    def start(self):
        self._thread.start()
        return self

    def cancel(self):
        self._cancel.set()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def join(self):
        self._thread.join()

    def _progress(self, fraction):
        self.fraction = float(fraction)
        return not self._cancel.is_set()

    def _run_in_torch_work(self):
        with core.torch_work(self.threads):   # the preference's threads; jemalloc keeps freed memory
            self._run()

    def _run(self):
        try:
            self.record = self.fn(self._progress)
        except Exception as exc:  # noqa: BLE001 - reported by the operator
            if type(exc).__name__ == "Cancelled":
                self.cancelled = True
            else:
                self.error = exc
                if not isinstance(exc, (EditError, ValueError)):
                    traceback.print_exc()
        finally:
            try:
                core.guard_torch_namespaces()
            except Exception:  # noqa: BLE001
                pass


class JobModal:
    """Mixin: an operator whose work runs in a background job (``_start(context)`` -> a job with
    ``start()``, ``join()``, ``running``, ``fraction``, ``cancel()``; ``_finish(context, job)``).
    From a script (EXEC) it blocks; invoked from the UI it is modal with progress in the status bar and
    Esc to cancel, and the viewport stays usable meanwhile.  ``edit_label`` names the work."""

    edit_label = "working"

    def execute(self, context):
        job = self._start(context)
        if job is None:
            return {"CANCELLED"}
        job.start().join()
        return self._finish(context, job)

    def invoke(self, context, event):
        job = self._start(context)
        if job is None:
            return {"CANCELLED"}
        self._job = job.start()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        _status(context, f"NeuMesh: {self.edit_label}... (Esc cancels)")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC" and job.running:
            job.cancel()
        if event.type == "TIMER":
            context.window_manager.progress_update(int(100 * job.fraction))
            _status(context, f"NeuMesh: {self.edit_label} {100 * job.fraction:.0f}% (Esc cancels)")
        if job.running:   # the viewport stays usable while the edit runs; Esc is ours
            return {"RUNNING_MODAL"} if event.type == "ESC" else {"PASS_THROUGH"}
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        _status(context, None)
        return self._finish(context, job)


class EditOperator(JobModal):
    """Mixin of the edit operators.  A subclass implements :meth:`prepare` (main thread: read Blender
    state, raise :class:`EditError` for bad input) returning ``(targets, fn)``: ``targets`` a list of
    ``(obj, field, parent_path)`` with ``field`` a copy from :func:`edit_copy`, and ``fn(progress)``
    running the core edit on those fields and returning one record per target (None: unchanged).
    Invoked from the UI the edit runs in a thread with progress and Esc; EXEC blocks."""

    bl_options = {"REGISTER", "UNDO"}
    edit_label = "edit"

    def prepare(self, context):  # pragma: no cover - abstract
        raise NotImplementedError

    def _start(self, context):
        try:
            targets, fn = self.prepare(context)
        except (EditError, core.CoreUnavailable, ValueError) as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return None
        except Exception as exc:  # noqa: BLE001
            self.report({"ERROR"}, f"NeuMesh: {self.edit_label} failed: {exc}")
            return None
        self._targets = [(obj.name_full, field, parent) for obj, field, parent in targets]
        return EditJob(self.edit_label, fn)

    def _finish(self, context, job):
        if job.cancelled:
            self.report({"WARNING"}, f"NeuMesh: {self.edit_label} cancelled; nothing changed")
            return {"CANCELLED"}
        if job.error is not None:
            self.report({"ERROR"}, f"NeuMesh: {self.edit_label}: {job.error}")
            return {"CANCELLED"}
        saved, changed = [], 0
        for (name, field, parent), record in zip(self._targets, job.record):
            if record is None:
                continue
            obj = bpy.data.objects.get(name)
            try:
                saved.append(os.path.basename(commit_edit(obj, field, record, parent)))
            except Exception as exc:  # noqa: BLE001
                self.report({"ERROR"}, f"NeuMesh: could not save the edited field of '{name}': {exc}")
                return {"CANCELLED"} if not saved else {"FINISHED"}
            changed += record.num_changed
        for area in getattr(context.screen, "areas", []) or []:
            area.tag_redraw()
        done = [r for r in job.record if r is not None]
        self.report({"INFO"}, f"NeuMesh: {self.edit_label}: {changed} vertices changed; saved "
                              f"{', '.join(saved)} ({self.summary(done[0]) if done else ''})")
        return {"FINISHED"}

    def summary(self, record) -> str:
        return f"{record.info.get('seconds', 0.0):.1f} s"

def _status(context, text):
    try:
        context.workspace.status_text_set(text)
    except Exception:  # noqa: BLE001 - no workspace in background mode
        pass


def _point_back(op, context, which: str):
    """Point the active object at the file its field was edited from (``which="parent"``) or at the
    trained root of the chain (``"root"``); reports and returns the operator result."""
    obj = context.active_object
    path = None
    try:
        path = field_path_of(obj)
        edit = _edit_module(core.get())
        target = edit.parent_of(path) if which == "parent" else edit.root_of(path)
    except (EditError, core.CoreUnavailable) as exc:
        op.report({"ERROR"}, f"NeuMesh: {exc}")
        return {"CANCELLED"}
    except Exception as exc:  # noqa: BLE001 - e.g. a corrupt header
        op.report({"ERROR"}, f"NeuMesh: cannot read {path}: {exc}")
        return {"CANCELLED"}
    if target is None:
        op.report({"WARNING"}, f"NeuMesh: '{obj.name}' shows the trained field; there is no edit to undo")
        return {"CANCELLED"}
    if not os.path.isfile(target):
        what = "the field this edit was made from" if which == "parent" else "the trained field"
        op.report({"ERROR"}, f"NeuMesh: {what} is missing: {target}")
        return {"CANCELLED"}
    props.set_field_path(obj, target)
    _register(obj, render.get_field(obj.name_full, target), target)
    shown = "the trained field " if which == "root" else ""
    op.report({"INFO"}, f"NeuMesh: '{obj.name}' shows {shown}{os.path.basename(target)}")
    return {"FINISHED"}


class NEUMESH_OT_undo_edit(bpy.types.Operator):
    """Point the object back at the field file this edit was made from (the edited file stays on disk;
    Ctrl+Z does the same within this session)"""

    bl_idname = "neumesh.undo_edit"
    bl_label = "Undo edit"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        return _point_back(self, context, "parent")


class NEUMESH_OT_revert_field(bpy.types.Operator):
    """Point the object back at the trained field, before all edits (edited files stay on disk)"""

    bl_idname = "neumesh.revert_field"
    bl_label = "Revert to trained field"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        return _point_back(self, context, "root")


class NEUMESH_PT_edit(bpy.types.Panel):
    """Parent panel of the edit tools; shows the active object's edit history."""

    bl_label = "Edit field"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NeuMesh"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        col = self.layout.column()
        obj = context.active_object
        if obj is None or obj.type != "MESH" or not props.field_abspath(obj):
            col.label(text="Select an object with a field", icon="INFO")
            return
        chain = edit_chain(obj)
        if chain:
            col.label(text=f"Shows: {os.path.basename(chain[-1][1])}")
            if len(chain) > 1:
                col.label(text="Edits: " + ", ".join(op for op, _ in chain[1:]))
        row = col.row(align=True)
        row.operator("neumesh.undo_edit", icon="LOOP_BACK")
        row.operator("neumesh.revert_field", text="Revert", icon="FILE_REFRESH")


class EditSubPanel:
    """Base of the panels under *Edit field*: the active object must carry a field;
    subclasses implement ``draw_edit(context, layout, obj)``."""

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NeuMesh"
    bl_parent_id = "NEUMESH_PT_edit"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        obj = context.active_object
        col = self.layout.column()
        if obj is None or obj.type != "MESH" or not props.field_abspath(obj):
            col.label(text="Select an object with a field", icon="INFO")
            return
        self.draw_edit(context, col, obj)


classes = (NEUMESH_OT_undo_edit, NEUMESH_OT_revert_field, NEUMESH_PT_edit)


register, unregister = bpy.utils.register_classes_factory(classes)
