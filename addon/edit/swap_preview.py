"""The swap's alignment shown before it is applied: *Preview alignment* runs
``nm.edit.swap_alignment`` (nothing written) and draws the aligned source region as a temporary
wireframe object, a child of the target drawn in the target's frame (the field's rest frame, which
is the object's local frame of a loaded field); the Swap panel shows the overlap, the residual and
the core's message. *Accept* applies exactly that alignment (``nm.swap_texture(..., alignment=)``) and
removes the wireframe; *Discard* removes it. A failed fit is refused with the core's message (what to
do: pick 3 or more vertex pairs...) unless *Skip fit check* is on.
"""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty, StringProperty

from ..runtime import classes_factory, core
from ..runtime.errors import UserError
from ..runtime.text import text_width, ui_scale, wrapped_label
from ..scene import props
from ..render.engine import refresh_viewports
from .base import edit_copy
from .swap_fill import NEUMESH_OT_swap_texture, NEUMESH_PT_swap, SwapResult, _FromPanel, selected_pairs

WIRE_NAME = "NeuMesh swap preview"
WIRE_TAG = "neumesh_swap_preview"   # custom property on the wireframe object: the target's name
_PREVIEWS: dict = {}   # target object name -> {"alignment", "wire", "path", "target_group", ...}


def preview_of(obj):
    """The pending preview of ``obj`` (a dict) or None; a preview whose wireframe was deleted, or whose
    object shows another file since, is dropped."""
    if obj is None:
        return None
    p = _PREVIEWS.get(obj.name_full)
    if p is None:
        return None
    if bpy.data.objects.get(p["wire"]) is None or props.field_abspath(obj) != p["path"]:
        discard(obj.name_full)
        return None
    return p


def discard(target_name: str) -> bool:
    """Remove the preview of the object named ``target_name`` (its wireframe too); True if one was there."""
    p = _PREVIEWS.pop(target_name, None)
    removed = False
    for ob in list(bpy.data.objects):   # also wireframes left over (an undo brought one back)
        if ob.get(WIRE_TAG) == target_name or (p is not None and ob.name_full == p["wire"]):
            me = ob.data
            bpy.data.objects.remove(ob, do_unlink=True)
            if me is not None and me.users == 0:
                bpy.data.meshes.remove(me)
            removed = True
    return removed or p is not None


def make_wire(target, alignment):
    """A wireframe object of the aligned source region (``alignment.points``/``faces``), parented to
    ``target`` with no parent inverse (so it moves with the target, in the target's frame)."""
    me = bpy.data.meshes.new(WIRE_NAME)
    pts = alignment.points.astype(float).tolist()
    faces = alignment.faces.astype(int).tolist()
    me.from_pydata(pts, [], faces)
    me.update()
    ob = bpy.data.objects.new(WIRE_NAME, me)
    coll = target.users_collection[0] if target.users_collection else bpy.context.scene.collection
    coll.objects.link(ob)
    ob.parent = target
    ob.matrix_parent_inverse.identity()
    ob.display_type = "WIRE"
    ob.show_in_front = True
    ob.hide_render = True
    ob.hide_select = True
    ob[WIRE_TAG] = target.name_full
    return ob


class NEUMESH_OT_swap_preview(_FromPanel, bpy.types.Operator):
    """Align the source region onto the target without changing anything: the aligned source is drawn
    as a wireframe and the panel shows how well it fits (Accept swaps, Discard removes it)"""

    bl_idname = "neumesh.swap_preview"
    bl_label = "Preview alignment"
    bl_options = {"REGISTER"}   # writes no field: nothing to undo; no redo panel (the Swap panel shows it)
    edit_label = "swap alignment"
    writes_files = False

    target_group: StringProperty(name="Target group", default="")
    source_object: StringProperty(name="Source object", default="", description="Empty: the active object")
    source_group: StringProperty(name="Source group", default="")
    use_pairs: BoolProperty(name="Use selected pairs", default=False)
    nonrigid: BoolProperty(name="Non-rigid fit", default=True)
    from_panel = NEUMESH_OT_swap_texture.from_panel

    def prepare(self, context):
        nm = core.get()
        target, field, path, src_obj, src_field, t_idx, s_idx = self._regions(
            context, self.source_object, self.source_group, "source")
        pairs = selected_pairs(target, src_obj, field, src_field or field) if self.use_pairs else None
        source = src_field if src_field is not None else field
        cfg = nm.edit.SwapConfig(nonrigid=self.nonrigid)
        self._params = dict(path=path, target_group=self.target_group, source_object=src_obj.name_full
                            if src_obj != target else "", source_group=self.source_group,
                            nonrigid=self.nonrigid, use_pairs=self.use_pairs)

        def run(progress):   # reads the fields only (swap_alignment writes nothing)
            return nm.edit.swap_alignment(field, t_idx, source, s_idx, pairs=pairs, config=cfg, progress=progress)
        return [(target, field, path)], run

    def _finish(self, context, job):
        if job.cancelled:
            self.report({"WARNING"}, "NeuMesh: alignment preview cancelled")
            return {"CANCELLED"}
        if job.error is not None:
            self.report({"ERROR"}, f"NeuMesh: {self.edit_label}: {job.error}")
            return {"CANCELLED"}
        al = job.result
        target = bpy.data.objects.get(self._targets[0][0])
        discard(target.name_full)
        wire = make_wire(target, al)
        _PREVIEWS[target.name_full] = dict(alignment=al, wire=wire.name_full, **self._params)
        refresh_viewports(context)
        f = al.figures
        text = (f"overlap {100 * f.overlap:.0f}%, target residual {f.target_residual:.2f} edge lengths")
        if al.ok:
            self.report({"INFO"}, f"NeuMesh: alignment preview: {text}; Accept swaps, Discard removes the wireframe")
        else:
            self.report({"WARNING"}, f"NeuMesh: {al.message}")
        return {"FINISHED"}


class NEUMESH_OT_swap_accept(SwapResult, _FromPanel, bpy.types.Operator):
    """Swap the texture with the previewed alignment, exactly as shown, and remove the wireframe"""

    bl_idname = "neumesh.swap_accept"
    bl_label = "Accept"
    bl_options = {"UNDO"}   # no redo panel: the preview it applies is gone once it has run
    edit_label = "texture swap"

    check_fit: BoolProperty(name="Check the fit", default=True,
                            description="Refuse an alignment that fails the fit check (off: apply it anyway)")

    @classmethod
    def poll(cls, context):
        return preview_of(context.active_object) is not None

    def prepare(self, context):
        nm = core.get()
        target = context.active_object
        p = preview_of(target)
        if p is None:
            raise UserError("no alignment preview of this object: press Preview alignment first")
        self.target_group, self.source_group = p["target_group"], p["source_group"]
        target, field, path, src_obj, src_field, t_idx, s_idx = self._regions(
            context, p["source_object"], p["source_group"], "source")
        work = edit_copy(field)
        source = edit_copy(src_field) if src_field is not None else None
        cfg = nm.edit.SwapConfig(nonrigid=p["nonrigid"], check_fit=bool(self.check_fit))
        al = p["alignment"]

        def run(progress):
            return [nm.swap_texture(work, t_idx, work if source is None else source, s_idx, config=cfg,
                                    progress=progress, alignment=al)]
        return [(target, work, path)], run

    def _finish(self, context, job):
        name = self._targets[0][0]
        result = super()._finish(context, job)
        if "FINISHED" in result:
            discard(name)
            refresh_viewports(context)
        return result


class NEUMESH_OT_swap_discard(bpy.types.Operator):
    """Remove the alignment preview (the wireframe); nothing else changes"""

    bl_idname = "neumesh.swap_discard"
    bl_label = "Discard"
    bl_options = {"INTERNAL"}

    @classmethod
    def poll(cls, context):
        return context.active_object is not None

    def execute(self, context):
        if not discard(context.active_object.name_full):
            self.report({"INFO"}, "NeuMesh: no alignment preview to discard")
            return {"CANCELLED"}
        refresh_viewports(context)
        return {"FINISHED"}


def draw_preview(context, col, obj):
    """The Swap panel's preview part: the button, and for a pending preview its figures, the core's
    message in full, Skip fit check (when it failed), Accept and Discard."""
    s = context.scene.neumesh_edit
    col.operator("neumesh.swap_preview", icon="HIDE_OFF")
    p = preview_of(obj)
    if p is None:
        return
    al = p["alignment"]
    f = al.figures
    box = col.box()
    # a box in a sub-panel: its margins and the labels' padding leave ~40 px less than the region's text
    # width (at -10 the refusal's lines were cut with '…' in Blender 3.4's 229 px sidebar)
    width = max(40.0, text_width(context) - 40 * ui_scale(context))
    box.label(text=f"Overlap {100 * f.overlap:.0f}%", icon="CHECKMARK" if al.ok else "ERROR")
    box.label(text=f"Residual {f.target_residual:.2f} edge lengths")
    if not al.ok:
        wrapped_label(box, al.message, width, context=context)
        box.prop(s, "swap_skip_fit_check")
    row = box.row(align=True)
    sub = row.row(align=True)
    sub.enabled = al.ok or s.swap_skip_fit_check
    op = sub.operator("neumesh.swap_accept", icon="CHECKMARK")
    op.check_fit = not s.swap_skip_fit_check
    row.operator("neumesh.swap_discard", icon="X")


classes = (NEUMESH_OT_swap_preview, NEUMESH_OT_swap_accept, NEUMESH_OT_swap_discard)

_register_classes, _unregister_classes = classes_factory(classes)


def register():
    _register_classes()
    NEUMESH_PT_swap.extra_draw.append(draw_preview)


def unregister():
    for name in list(_PREVIEWS):
        try:
            discard(name)
        except Exception:  # noqa: BLE001 - Blender is closing
            pass
    while draw_preview in NEUMESH_PT_swap.extra_draw:
        NEUMESH_PT_swap.extra_draw.remove(draw_preview)
    _unregister_classes()
