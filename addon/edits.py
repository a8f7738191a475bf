"""Edits in Blender: the shared plumbing of every edit operator, and Undo edit / Revert.

An edit operator gets the object's field (:func:`field_for_edit`), calls a core edit function, and
hands the result to :func:`commit_edit`, which saves the edited field *beside* the file it came from
(``<name>.edit-NNN.neumesh``; the file training produced is never overwritten) and points the object
at it.  The object's field path is an ordinary undoable property, so Blender's Ctrl+Z / Ctrl+Shift+Z
step between the files, and the render cache reloads whichever file the object points to.  "Undo
edit" steps to the file an edited field was made from; "Revert to trained field" to the root of the
chain.  Edit operators declare ``bl_options = {"REGISTER", "UNDO"}`` and add their panel as a child of
:class:`NEUMESH_PT_edit` (``bl_parent_id = "NEUMESH_PT_edit"``).
"""
from __future__ import annotations

import os

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
    return out


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


class NEUMESH_OT_undo_edit(bpy.types.Operator):
    """Point the object back at the field file this edit was made from (the edited file stays on disk;
    Ctrl+Z does the same within this session)"""

    bl_idname = "neumesh.undo_edit"
    bl_label = "Undo edit"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        obj = context.active_object
        try:
            path = field_path_of(obj)
            parent = _edit_module(core.get()).parent_of(path)
        except (EditError, core.CoreUnavailable) as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        except Exception as exc:  # noqa: BLE001 - e.g. a corrupt header
            self.report({"ERROR"}, f"NeuMesh: cannot read {path}: {exc}")
            return {"CANCELLED"}
        if parent is None:
            self.report({"WARNING"}, f"NeuMesh: '{obj.name}' shows the trained field; there is no edit to undo")
            return {"CANCELLED"}
        if not os.path.isfile(parent):
            self.report({"ERROR"}, f"NeuMesh: the field this edit was made from is missing: {parent}")
            return {"CANCELLED"}
        props.set_field_path(obj, parent)
        self.report({"INFO"}, f"NeuMesh: '{obj.name}' shows {os.path.basename(parent)}")
        return {"FINISHED"}


class NEUMESH_OT_revert_field(bpy.types.Operator):
    """Point the object back at the trained field, before all edits (edited files stay on disk)"""

    bl_idname = "neumesh.revert_field"
    bl_label = "Revert to trained field"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        obj = context.active_object
        try:
            path = field_path_of(obj)
            root = _edit_module(core.get()).root_of(path)
        except (EditError, core.CoreUnavailable) as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        except Exception as exc:  # noqa: BLE001
            self.report({"ERROR"}, f"NeuMesh: cannot read {path}: {exc}")
            return {"CANCELLED"}
        if not os.path.isfile(root):
            self.report({"ERROR"}, f"NeuMesh: the trained field is missing: {root}")
            return {"CANCELLED"}
        props.set_field_path(obj, root)
        self.report({"INFO"}, f"NeuMesh: '{obj.name}' shows the trained field {os.path.basename(root)}")
        return {"FINISHED"}


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


classes = (NEUMESH_OT_undo_edit, NEUMESH_OT_revert_field, NEUMESH_PT_edit)


def register():
    for c in classes:
        bpy.utils.register_class(c)


def unregister():
    for c in reversed(classes):
        bpy.utils.unregister_class(c)
