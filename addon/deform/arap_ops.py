"""ARAP deform, the Blender side of it: the settings, the operators (Add ARAP deform, Refresh,
Apply as shape key, Remove) and the panel under *Edit field*; the solving and the handlers are in
:mod:`.arap`."""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty, IntProperty, PointerProperty, StringProperty

from ..runtime._np import np
from ..runtime import classes_factory
from ..runtime.errors import UserError
from ..runtime.text import labelled, labelled_search
from .arap import (APPLIED_KEY, LIVE_KEY, TIMINGS, _DRAGS, _HELD, _SHAPES, _SOLVERS, _after_stroke, _apply_drags,
                   _list, _rest, on_depsgraph_update, on_frame_change, prepare_preview, read_groups, start,
                   wait_for_drags)
from .arap_undo import on_undo_post, on_undo_pre
from ..edit.base import EditSubPanel, shown_object


class NeuMeshArapSettings(bpy.types.PropertyGroup):
    enabled: BoolProperty(name="ARAP deform", default=False)
    anchor_group: StringProperty(name="Anchor group", default="Anchor")
    handle_prefix: StringProperty(name="Handle groups", default="Handle",
                                  description="Every vertex group whose name starts with this is a handle")
    handle_groups: StringProperty(default="", options={"HIDDEN"})   # "\n"-joined, in the Empties' order
    handle_empties: StringProperty(default="", options={"HIDDEN"})  # "\n"-joined Empty names
    centroids: StringProperty(default="", options={"HIDDEN"})       # flat floats, local rest centroids
    preview_vertices: IntProperty(
        name="Preview", default=30000, min=0, soft_max=200000,
        description="Solve on a cage of about this many vertices while dragging and carry the result to "
                    "every vertex (0: the full mesh). Smaller is faster")
    iterations: IntProperty(name="Iterations", default=2, min=1, max=100,
                            description="Local-global iterations per move while dragging (each move "
                                        "starts from the last one's result; more: closer to the "
                                        "converged shape, fewer previews a second)")
    frame_iterations: IntProperty(name="Frame iterations", default=30, min=1, max=500,
                                  description="Iterations of a solve from rest on a frame change or render")
    cage_in_renders: BoolProperty(name="Cage in renders", default=False,
                                  description="Solve frame changes and renders on the preview cage too")
    generation: IntProperty(default=0, options={"HIDDEN"})   # bumped by Refresh: rebuild the solver


# -------------------------------------------------------------------------------------- operators
def _active_mesh(context):
    obj = shown_object(context.active_object)   # the handle Empty selected: the object it deforms
    if obj is None or obj.type != "MESH":
        raise UserError("select the mesh object to deform (the one with the Anchor and Handle groups)")
    return obj


def _make_empties(context, obj, s, handles, names) -> None:
    rest = _rest(obj)
    old = _list(s.handle_empties)
    empties, cents = [], []
    for n, h in zip(names, handles):
        c = rest[h].mean(0)
        ename = f"{obj.name} {n}"
        e = bpy.data.objects.get(ename) if ename in old else None
        if e is None:
            e = bpy.data.objects.new(ename, None)
            e.empty_display_type = "SPHERE"
            e.empty_display_size = max(float(np.ptp(rest, 0).max()) * 0.05, 1e-3)
            (obj.users_collection[0] if obj.users_collection else context.scene.collection).objects.link(e)
            e.parent = obj
            e.matrix_parent_inverse.identity()
            e.location = c
        empties.append(e.name)
        cents.extend(float(x) for x in c)
    for en in old:
        if en not in empties and bpy.data.objects.get(en) is not None:
            bpy.data.objects.remove(bpy.data.objects[en])
    s.handle_groups, s.handle_empties = "\n".join(names), "\n".join(empties)
    s.centroids = " ".join(f"{x:.9g}" for x in cents)


class _ArapOperator:
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        try:
            return self.run(context)
        except UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}


class NEUMESH_OT_arap_add(_ArapOperator, bpy.types.Operator):
    """Deform the active object as rigidly as possible: the 'Anchor' group stays, each 'Handle' group
    follows its Empty (move, rotate, scale or keyframe it)"""

    bl_idname, bl_label = "neumesh.arap_add", "Add ARAP deform"

    def run(self, context):
        obj = _active_mesh(context)
        if obj.mode != "OBJECT":
            bpy.ops.object.mode_set(mode="OBJECT")
        s = obj.neumesh_arap
        _anchors, handles, names = read_groups(obj, s)
        if obj.data.shape_keys is None:
            obj.shape_key_add(name="Basis", from_mix=False)
        s.enabled = False   # no handler runs while the Empties are made
        _make_empties(context, obj, s, handles, names)
        context.view_layer.update()   # the new Empties' matrix_world
        s.enabled = True
        s.generation += 1
        wait_for_drags()
        _SOLVERS.pop(obj.name_full, None)
        _DRAGS.pop(obj.name_full, None)
        start(obj, context.evaluated_depsgraph_get())
        prepare_preview(obj)   # the drag's cage, factorised beside the interface
        self.report({"INFO"}, f"ARAP deform: {len(names)} handle Empt{'y' if len(names) == 1 else 'ies'} "
                              f"({', '.join(names)}); move them with G/R/S")
        return {"FINISHED"}


class NEUMESH_OT_arap_refresh(_ArapOperator, bpy.types.Operator):
    """Read the Anchor and Handle groups again (after editing them) and re-solve"""

    bl_idname, bl_label = "neumesh.arap_refresh", "Refresh"

    def run(self, context):
        return NEUMESH_OT_arap_add.run(self, context)


def _remove_setup(obj) -> None:
    wait_for_drags()
    s = obj.neumesh_arap
    for en in _list(s.handle_empties):
        if bpy.data.objects.get(en) is not None:
            bpy.data.objects.remove(bpy.data.objects[en])
    keys = obj.data.shape_keys
    if keys and keys.key_blocks.get(LIVE_KEY) is not None:
        obj.shape_key_remove(keys.key_blocks[LIVE_KEY])
    s.enabled = False
    s.handle_groups = s.handle_empties = s.centroids = ""
    _SOLVERS.pop(obj.name_full, None)
    _SHAPES.pop(obj.name_full, None)


class NEUMESH_OT_arap_apply(_ArapOperator, bpy.types.Operator):
    """Bake the current ARAP pose into a shape key ('ARAP pose') and remove the live deform and its
    Empties"""

    bl_idname, bl_label = "neumesh.arap_apply", "Apply as shape key"

    def run(self, context):
        obj = _active_mesh(context)
        keys = obj.data.shape_keys
        kb = keys.key_blocks.get(LIVE_KEY) if keys else None
        if not obj.neumesh_arap.enabled or kb is None:
            raise UserError(f"'{obj.name}' has no ARAP deform to apply: press Add ARAP deform first")
        arr = np.empty(len(kb.data) * 3, np.float32)
        kb.data.foreach_get("co", arr)
        new = obj.shape_key_add(name=APPLIED_KEY, from_mix=False)
        new.data.foreach_set("co", arr)
        new.value = 1.0
        _remove_setup(obj)
        obj.data.update()
        self.report({"INFO"}, f"ARAP pose applied as shape key '{new.name}'")
        return {"FINISHED"}


class NEUMESH_OT_arap_remove(_ArapOperator, bpy.types.Operator):
    """Remove the ARAP deform (its shape key and Empties): the object goes back to its rest shape"""

    bl_idname, bl_label = "neumesh.arap_remove", "Remove"

    def run(self, context):
        obj = _active_mesh(context)
        _remove_setup(obj)
        obj.data.update()
        return {"FINISHED"}


class NEUMESH_PT_arap(EditSubPanel, bpy.types.Panel):
    bl_label = "ARAP deform"

    def draw_edit(self, context, col, obj):
        s = obj.neumesh_arap
        # the sidebar is narrow: names above their fields, one number a row
        labelled_search(col, s, "anchor_group", obj, "vertex_groups", "Anchor group")
        labelled(col, s, "handle_prefix", "Handle groups start with")
        col.prop(s, "preview_vertices", text="Preview vertices")
        col.prop(s, "iterations", text="Drag iterations")
        col.prop(s, "frame_iterations")
        col.prop(s, "cage_in_renders")
        if not s.enabled:
            col.operator("neumesh.arap_add", icon="MOD_MESHDEFORM")
            return
        t = TIMINGS.get(obj.name_full, {})
        if "solve_s" in t:
            col.label(text=f"Last solve {t['solve_s']:.2f} s ({'cage' if t.get('cage') else 'full'})")
        row = col.row(align=True)
        row.operator("neumesh.arap_refresh", icon="FILE_REFRESH")
        row.operator("neumesh.arap_remove", icon="X")
        col.operator("neumesh.arap_apply", icon="SHAPEKEY_DATA")


classes = (NeuMeshArapSettings, NEUMESH_OT_arap_add, NEUMESH_OT_arap_refresh, NEUMESH_OT_arap_apply,
           NEUMESH_OT_arap_remove, NEUMESH_PT_arap)
_register, _unregister = classes_factory(
    classes, ((bpy.types.Object, "neumesh_arap", lambda: PointerProperty(type=NeuMeshArapSettings)),))
_HANDLERS = ((bpy.app.handlers.frame_change_post, on_frame_change),
             (bpy.app.handlers.depsgraph_update_post, on_depsgraph_update),
             (bpy.app.handlers.undo_pre, on_undo_pre), (bpy.app.handlers.redo_pre, on_undo_pre),
             (bpy.app.handlers.undo_post, on_undo_post), (bpy.app.handlers.redo_post, on_undo_post))


def register():
    _register()
    for lst, fn in _HANDLERS:
        if fn not in lst:
            lst.append(fn)


def unregister():
    for lst, fn in _HANDLERS:
        if fn in lst:
            lst.remove(fn)
    _SOLVERS.clear()
    _DRAGS.clear()
    _SHAPES.clear()
    _HELD.clear()
    for fn in (_apply_drags, _after_stroke):
        if bpy.app.timers.is_registered(fn):
            bpy.app.timers.unregister(fn)
    _unregister()
