"""Edits in Blender: the shared plumbing of every edit operator, and Undo edit / Revert.

An edit operator gets the object's field (:func:`field_for_edit`), calls a core edit function, and hands
the result to :func:`commit_edit`, which saves the edited field in the scene's *Edits folder*
(``<name>.edit-NNN.neumesh``; by default beside the .blend in ``<blend name>_neumesh/``, see
:func:`props.edits_folder`: never the folder the field was read from unless the artist chose it; the
file training produced is never overwritten) and points the object at it. The object's field path is an
ordinary undoable property, so Blender's Ctrl+Z / Ctrl+Shift+Z step between the files, and the render
cache reloads whichever file the object points to. "Undo edit" steps to the file an edited field was
made from; "Revert to trained field" to the root of the chain. Edit operators declare ``bl_options =
{"REGISTER", "UNDO"}`` and add their panel as a child of :class:`NEUMESH_PT_edit` (``bl_parent_id =
"NEUMESH_PT_edit"``).

Long edits run in a background thread (:class:`EditOperator`): invoked from the UI the operator is
modal, shows progress in the status bar and the cursor, and Esc cancels (nothing changes); run from a
script (``bpy.ops.neumesh.<edit>()``, EXEC) it blocks.  The thread edits a *copy* of the object's
field, so the viewport can keep rendering the current one; the copy replaces it when the edit is
committed.
"""
from __future__ import annotations

import os

import bpy

from ..runtime import core, jobs, quiet
from ..runtime.errors import UserError
from ..runtime.jobs import Job, JobModal, redraw
from ..runtime.text import file_size, labelled, text_width, wrapped_label
from ..scene import identity, props, sync
from ..scene.props import field_path_of
from ..render import field_cache
from ..render.engine import refresh_viewports


def field_for_edit(obj):
    """(field, path): the object's field as the renderer holds it (edits write into this instance, so
    the next render shows them without reloading)."""
    path = field_path_of(obj)
    return field_cache.get_field(obj.name_full, path), path


def edit_out_path(parent_path: str, folder: str) -> str:
    """The file an edit of ``parent_path`` is written to: the next free ``<name>.edit-NNN.neumesh`` in
    ``folder`` (the edits folder, :func:`props.edits_folder`)."""
    return core.get().edit.next_edit_path(os.path.join(folder, os.path.basename(parent_path)))


def edits_folder_ready(folder: str) -> str:
    """Create the edits folder if needed; :class:`UserError` saying what to do when it cannot be
    written."""
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create the Edits folder {folder}: {exc.strerror}; choose another one "
                        "(Edit field panel)") from exc
    if not os.access(folder, os.W_OK):
        raise UserError(f"the Edits folder {folder} cannot be written; choose another one (Edit field panel)")
    return folder


def commit_edit(obj, field, record, parent_path: str, folder: str | None = None) -> str:
    """Save ``field`` (edited in memory by ``record``) in ``folder`` (default: the current scene's edits
    folder) and point ``obj`` at the new file; returns its path.  On failure the edit is undone in
    memory and the object is left as it was."""
    try:
        folder = edits_folder_ready(folder or props.scene_edits_folder())
        out = core.get().edit.save_edited(field, parent_path, record, out_path=edit_out_path(parent_path, folder))
    except BaseException:
        record.undo(field)
        raise
    props.set_field_path(obj, out)
    field_cache.adopt(obj.name_full, out, field)
    _register(obj, field, out)
    return out


def _register(obj, field, path):
    """The scene's record of which file holds this field's key (joined objects find it there)."""
    try:
        for scene in obj.users_scene or (bpy.context.scene,):
            identity.register_field(scene, field, path)
    except Exception as exc:  # noqa: BLE001 - only joins of this object later would miss it
        print(f"NeuMesh: could not record the field of '{obj.name}': {exc}")


_CHAIN_CACHE: dict = {}


def edit_chain(obj):
    """[(op, path), ...] from the trained file to the object's current file (empty without a field).
    Cached per file (panels draw often; headers change only when a file is rewritten)."""
    try:
        path = field_path_of(obj)
        edit = core.get().edit
    except (UserError, core.CoreUnavailable):
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


edit_copy = field_cache.private_copy   # a private copy of a cached field for a background edit


def region_of(obj, group: str, field, what: str):
    """Field vertex indices of vertex group ``group`` of ``obj`` (mesh vertices mapped to field vertices
    through their identity attributes, see identity.py); :class:`UserError` when the group is missing
    or empty, or its vertices cannot be mapped."""
    if not group:
        raise UserError(f"{what}: choose a vertex group of '{obj.name}'")
    if obj.vertex_groups.get(group) is None:
        raise UserError(f"{what}: '{obj.name}' has no vertex group '{group}'")
    idx = sync.vertex_group_indices(obj, group)
    if len(idx) == 0:
        raise UserError(f"{what}: vertex group '{group}' of '{obj.name}' is empty; assign vertices to it")
    return identity.field_rows(obj, field, idx, what)


class EditOperator(JobModal):
    """Mixin of the edit operators.  A subclass implements :meth:`prepare` (main thread: read Blender
    state, raise :class:`UserError` for bad input) returning ``(targets, fn)``: ``targets`` a list of
    ``(obj, field, parent_path)`` with ``field`` a copy from :func:`edit_copy`, and ``fn(progress)``
    running the core edit on those fields and returning one record per target (None: unchanged).
    Invoked from the UI the edit runs in a thread with progress and Esc; EXEC blocks."""

    bl_options = {"REGISTER", "UNDO"}
    edit_label = "edit"
    writes_files = True   # False: the operator only reads fields (no edits folder needed)

    def prepare(self, context):  # pragma: no cover - abstract
        raise NotImplementedError

    def invoke(self, context, event):
        """Invoked from the interface: an undo step of the state the edit starts from is pushed first, so
        the redo panel (which undoes to the step before this operator's and calls :meth:`execute` with
        the new options) starts from exactly that state, also when the scene was changed without an undo
        step (a script, a timer): without that step the redo would undo those changes too (the object
        deselected, its vertex groups gone) and the re-run would fail without a word."""
        if "UNDO" in self.bl_options:
            push_undo_step(context, f"Before {self.bl_label}")
        return JobModal.invoke(self, context, event)

    def _start(self, context):
        try:
            targets, fn = self._prepare(context)
        except (UserError, core.CoreUnavailable, ValueError) as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return None
        except core.error_types() as exc:   # the core's own input errors (nm.EditError...): the message says it
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return None
        except Exception as exc:  # noqa: BLE001
            self.report({"ERROR"}, f"NeuMesh: {self.edit_label} failed: {exc}")
            return None
        self._targets = [(obj.name_full, field, parent) for obj, field, parent in targets]
        return Job(self.edit_label, fn)

    def _prepare(self, context):
        """The edits folder first (an unsaved .blend says so before any work), then :meth:`prepare`."""
        if self.writes_files:
            self._folder = edits_folder_ready(props.scene_edits_folder(context.scene))
        return self.prepare(context)

    def _finish(self, context, job):
        if job.cancelled:
            self.report({"WARNING"}, f"NeuMesh: {self.edit_label} cancelled; nothing changed")
            return {"CANCELLED"}
        if job.error is not None:
            self.report({"ERROR"}, f"NeuMesh: {self.edit_label}: {job.error}")
            return {"CANCELLED"}
        saved, changed, unchanged = [], 0, []
        for (name, field, parent), record in zip(self._targets, job.result):
            if record is None:
                continue
            n = record.count_changed()
            if n == 0:   # nothing to save: the object keeps its file (the edit ran on a copy)
                unchanged.append(name)
                continue
            obj = bpy.data.objects.get(name)
            try:
                out = commit_edit(obj, field, record, parent, self._folder)
                saved.append(f"{os.path.basename(out)} ({file_size(out)})")
            except Exception as exc:  # noqa: BLE001
                self.report({"ERROR"}, f"NeuMesh: could not save the edited field of '{name}': {exc}")
                return {"CANCELLED"} if not saved else {"FINISHED"}
            changed += n
        refresh_viewports(context)
        redraw(context, whole=True)
        done = [r for r in job.result if r is not None]
        if not saved:
            why = f" ('{', '.join(unchanged)}' already looked like that)" if unchanged else ""
            self.report({"INFO"}, f"NeuMesh: {self.edit_label}: nothing changed{why}; no file written")
            return {"FINISHED"}
        self.report({"INFO"}, f"NeuMesh: {self.edit_label}: {changed} vertices changed; saved "
                              f"{', '.join(saved)} in {self._folder} ({self.summary(done[0]) if done else ''})")
        return {"FINISHED"}

    def summary(self, record) -> str:
        return f"{record.info.get('seconds', 0.0):.1f} s"

def push_undo_step(context, message: str) -> bool:
    """Push an undo step of the current state (main thread, interface only); False where there is no
    undo stack (background mode, a script run without a window)."""
    if bpy.app.background or context.window is None:
        return False
    try:
        if bpy.context.window is not None:   # no override where none is needed (runtime/quiet.py)
            return "FINISHED" in bpy.ops.ed.undo_push(message=message)
        with quiet.override(context, window=context.window):
            return "FINISHED" in bpy.ops.ed.undo_push(message=message)
    except (RuntimeError, AttributeError, TypeError):   # poll failed / no temp_override before 3.2
        return False


def _point_back(op, context, which: str):
    """Point the active object at the file its field was edited from (``which="parent"``) or at the
    trained root of the chain (``"root"``); reports and returns the operator result."""
    obj = context.active_object
    path = None
    try:
        path = field_path_of(obj)
        edit = core.get().edit
        target = edit.parent_of(path) if which == "parent" else edit.root_of(path)
    except (UserError, core.CoreUnavailable) as exc:
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
    _register(obj, field_cache.get_field(obj.name_full, target), target)
    refresh_viewports(context)
    shown = "the trained field " if which == "root" else ""
    op.report({"INFO"}, f"NeuMesh: '{obj.name}' shows {shown}{os.path.basename(target)}")
    return {"FINISHED"}


class _PointBack:
    bl_options = {"REGISTER", "UNDO"}
    which = "parent"

    def execute(self, context):
        return _point_back(self, context, self.which)


class NEUMESH_OT_undo_edit(_PointBack, bpy.types.Operator):
    """Point the object back at the field file this edit was made from (the edited file stays on disk;
    Ctrl+Z does the same within this session)"""

    bl_idname, bl_label = "neumesh.undo_edit", "Undo edit"


class NEUMESH_OT_revert_field(_PointBack, bpy.types.Operator):
    """Point the object back at the trained field, before all edits (edited files stay on disk)"""

    bl_idname, bl_label, which = "neumesh.revert_field", "Revert to trained field", "root"


def shown_object(obj):
    """The object whose field the Edit field panels show and their buttons act on, for the active
    object ``obj``: itself, or for an ARAP handle Empty (what the artist selects to drag it) the object
    the Empty deforms."""
    parent = getattr(obj, "parent", None)
    if obj is not None and obj.type == "EMPTY" and parent is not None and parent.type == "MESH":
        s = getattr(parent, "neumesh_arap", None)
        if s is not None and s.enabled and obj.name in s.handle_empties.split("\n"):
            return parent
    return obj


class _FieldPanel:
    """A sidebar panel about the active object's field: ``draw_edit(context, layout, obj)`` runs when the
    active object carries one (an ARAP handle Empty: the object it deforms, see :func:`shown_object`),
    else the panel says to select one."""

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NeuMesh"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        active = context.active_object
        obj = shown_object(active)
        col = self.layout.column()
        if obj is not None and obj != active:   # a handle Empty: the buttons act on its object
            col.context_pointer_set("active_object", obj)
            if not getattr(self, "bl_parent_id", ""):
                wrapped_label(col, f"'{obj.name}', which the selected handle deforms", text_width(context),
                              icon="OBJECT_DATA", context=context)
        job = jobs.active(self.bl_label)   # the running job of the operator with the panel's label
        if job is not None:   # the modal operator redraws the sidebar on every progress step
            text = f"{self.bl_label} {100 * job.fraction:.0f}% (Esc cancels)"
            if hasattr(col, "progress"):
                col.progress(factor=job.fraction, text=text)
            else:
                col.label(text=text, icon="SORTTIME")
        if obj is None or obj.type != "MESH" or not props.field_abspath(obj):
            wrapped_label(col, "Select an object with a field", text_width(context), icon="INFO",
                          context=context)
            return
        self.draw_edit(context, col, obj)


class NEUMESH_PT_edit(_FieldPanel, bpy.types.Panel):
    """Parent panel of the edit tools; shows the active object's edit history."""

    bl_label = "Edit field"

    def draw_edit(self, context, col, obj):
        chain = edit_chain(obj)
        width = text_width(context)
        if chain:
            wrapped_label(col, f"Shows: {os.path.basename(chain[-1][1])}", width, context=context)
            if len(chain) > 1:
                wrapped_label(col, "Edits: " + ", ".join(op for op, _ in chain[1:]), width, context=context)
        row = col.row(align=True)
        row.operator("neumesh.undo_edit", icon="LOOP_BACK")
        row.operator("neumesh.revert_field", text="Revert", icon="FILE_REFRESH")
        draw_edits_folder(context, col, width)


def draw_edits_folder(context, col, width):
    """The scene's *Edits folder*, and where edits go while it is empty (or why they cannot go)."""
    s = context.scene.neumesh
    labelled(col, s, "edits_dir", "Edits folder")
    try:
        folder = props.scene_edits_folder(context.scene)
    except UserError:
        wrapped_label(col, "Save the .blend first (edits go beside it), or choose a folder", width, icon="ERROR",
                      context=context)
        return
    if not s.edits_dir.strip():
        wrapped_label(col, f"Empty: the folder {os.path.basename(folder)} beside the .blend", width, context=context)


class EditSubPanel(_FieldPanel):
    """Base of the panels under *Edit field*; subclasses implement ``draw_edit(context, layout, obj)``."""

    bl_parent_id = "NEUMESH_PT_edit"


classes = (NEUMESH_OT_undo_edit, NEUMESH_OT_revert_field, NEUMESH_PT_edit)


@bpy.app.handlers.persistent
def _after_undo(*_args):
    """Ctrl+Z / Ctrl+Shift+Z (and undo history jumps) change which file an object shows: the Rendered
    viewport and the panels follow at once."""
    refresh_viewports()


_HANDLERS = ("undo_post", "redo_post")
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()
    for name in _HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        if _after_undo not in lst:
            lst.append(_after_undo)


def unregister():
    for name in _HANDLERS:
        lst = getattr(bpy.app.handlers, name)
        while _after_undo in lst:
            lst.remove(_after_undo)
    _unregister_classes()
