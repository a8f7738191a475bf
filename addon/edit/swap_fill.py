"""Texture swap and texture fill in Blender: vertex groups and UV maps -> numpy -> ``nm.swap_texture`` /
``nm.fill_texture`` (see ``neumesh_core/edit``), committed as an edited field beside the trained one.

Swap: target = the active object and a vertex group; source = another field-carrying object (or the
same one) and a vertex group; optional correspondences from the vertices selected in Edit Mode, in
selection order (the same count on both objects; within one object, alternate source and target).
Fill: target vertex group and UV map; template object, vertex group and UV map; a tile scale.
"""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty, FloatProperty, PointerProperty, StringProperty

from ..runtime._np import np
from ..runtime import classes_factory, core
from ..scene import identity, props, sync
from ..runtime.errors import UserError
from .base import EditOperator, EditSubPanel, edit_copy, field_for_edit, region_of
from ..runtime.text import labelled, labelled_search


def _mesh_with_field(obj):
    return obj is not None and obj.type == "MESH" and bool(props.field_abspath(obj))


def selection_history(obj) -> np.ndarray:
    """Vertex indices of ``obj`` in the order they were selected (Edit Mode's select history)."""
    import bmesh

    if obj.mode == "EDIT":
        bm = bmesh.from_edit_mesh(obj.data)
        hist = [e.index for e in bm.select_history if isinstance(e, bmesh.types.BMVert)]
    else:
        bm = bmesh.new()
        try:
            bm.from_mesh(obj.data)
            hist = [e.index for e in bm.select_history if isinstance(e, bmesh.types.BMVert)]
        finally:
            bm.free()
    return np.asarray(hist, np.int64)


def selected_pairs(target, source, target_field=None, source_field=None) -> np.ndarray:
    """(P,2) (source vertex, target vertex) pairs from the selection order in Edit Mode, as field
    vertex ids when the fields are given (else mesh vertex indices)."""
    if source == target:
        h = selection_history(target)
        if len(h) % 2:
            raise UserError(f"correspondences: {len(h)} vertices are selected on '{target.name}'; select "
                            "pairs in order (a source vertex, then its target vertex), at least 3 pairs")
        pairs = np.stack([h[0::2], h[1::2]], 1)
    else:
        hs, ht = selection_history(source), selection_history(target)
        if len(hs) != len(ht):
            raise UserError(f"correspondences: {len(hs)} vertices selected on '{source.name}' but {len(ht)} on "
                            f"'{target.name}'; select the same number, in matching order, on both (Edit Mode)")
        pairs = np.stack([hs, ht], 1) if len(hs) else np.zeros((0, 2), np.int64)
    if len(pairs) < 3:
        raise UserError(f"correspondences: {len(pairs)} pairs selected; select at least 3 (or turn off "
                        "'Use selected pairs' for the automatic alignment)")
    if target_field is not None and source_field is not None:
        pairs = np.stack([identity.vertex_ids(source, source_field, pairs[:, 0]),
                          identity.vertex_ids(target, target_field, pairs[:, 1])], 1)
        if (pairs < 0).any():
            raise UserError("correspondences: some selected vertices are new (made by subdivision or extrusion) "
                            "and belong to no field vertex; pick vertices of the original mesh")
    return pairs


def corner_uvs(obj, uv_map: str, field=None):
    """The mesh's UV map as per-corner (vertex, uv) pairs (seams keep each side's UV); with ``field``
    the corners' vertices are field vertex ids (corners of new vertices are left out)."""
    nm = core.get()
    me = obj.data
    if not uv_map:
        raise UserError(f"choose a UV map of '{obj.name}'")
    if me.uv_layers.get(uv_map) is None:
        raise UserError(f"'{obj.name}' has no UV map '{uv_map}'; unwrap it (U) or choose another")
    uv = sync.uv_loops(me, uv_map)
    n = len(me.loops)
    vi = np.empty(n, dtype=np.int32)
    me.loops.foreach_get("vertex_index", vi)
    vi = vi.astype(np.int64)
    if field is not None:
        keep, vi = identity.corner_rows(obj, field, vi)
        uv = uv[keep]
    return nm.CornerUVs(vi, uv)


def _source_field(obj, target_obj, target_field):
    if obj is None or obj == target_obj:
        return target_obj, None
    if not _mesh_with_field(obj):
        raise UserError(f"'{obj.name}' has no NeuMesh field; choose an object that carries one")
    field, _ = field_for_edit(obj)
    return obj, field


class NeuMeshEditSettings(bpy.types.PropertyGroup):
    """What the swap and fill panels show (operators read them when invoked from the panel)."""

    swap_target_group: StringProperty(name="Target group", description="Vertex group of the active "
                                      "object that receives the texture")
    swap_source: PointerProperty(name="Source", type=bpy.types.Object, poll=lambda s, o: o.type == "MESH",
                                 description="Object whose texture is copied (empty: the active object)")
    swap_source_group: StringProperty(name="Source group", description="Vertex group of the source object")
    swap_use_pairs: BoolProperty(name="Use selected pairs", default=False,
                                 description="Align by 3+ vertex pairs selected in Edit Mode, in order (same "
                                             "count on both objects; one object: source, target, source...)")
    swap_skip_fit_check: BoolProperty(name="Skip fit check", default=False,
                                      description="Apply the previewed alignment although it fails the fit check")
    fill_target_group: StringProperty(name="Target group", description="Vertex group to fill")
    fill_target_uv: StringProperty(name="Target UV", description="UV map of the active object")
    fill_template: PointerProperty(name="Template", type=bpy.types.Object, poll=lambda s, o: o.type == "MESH",
                                   description="Object whose texture is tiled (empty: the active object)")
    fill_template_group: StringProperty(name="Template group", description="Vertex group of the template")
    fill_template_uv: StringProperty(name="Template UV", description="UV map of the template")
    fill_scale: FloatProperty(name="Scale", default=1.0, min=0.01, soft_max=16.0,
                              description="How many times the template repeats across the target's UV square")


class _FromPanel(EditOperator):
    """Invoked from its panel, an operator takes what the panel shows (``Scene.neumesh_edit``) for the
    properties a script left empty: ``from_panel`` = ``((operator property, panel property), ...)``;
    an object property gives its name."""

    from_panel: tuple = ()

    @classmethod
    def poll(cls, context):
        return _mesh_with_field(context.active_object)

    def invoke(self, context, event):
        s = context.scene.neumesh_edit
        for mine, theirs in self.from_panel:
            value = getattr(s, theirs)
            if isinstance(value, bpy.types.ID) or value is None:
                value = value.name if value is not None else ""
            if not getattr(self, mine) or isinstance(value, float):
                setattr(self, mine, value)
        return EditOperator.invoke(self, context, event)

    def _regions(self, context, other: str, other_group: str, what: str):
        """(target, its field, its file, the other object (source or template), that object's field or
        None when it is the target, the target group's field rows, the other group's field rows)."""
        target = context.active_object
        if target is not None and target.mode == "EDIT":
            bpy.ops.object.mode_set(mode="OBJECT")   # vertex groups and selection as the user left them
        field, path = field_for_edit(target)
        obj = bpy.data.objects.get(other) if other else None
        if other and obj is None:
            raise UserError(f"{what} object '{other}' does not exist")
        obj, other_field = _source_field(obj, target, field)
        t_idx = region_of(target, self.target_group, field, "target")
        s_idx = region_of(obj, other_group, other_field or field, what)
        return target, field, path, obj, other_field, t_idx, s_idx


class SwapResult:
    """Mixin of the operators that swap: the refusal of a failed fit says the Blender way out, and the
    report gives the residual."""

    def _finish(self, context, job):
        if job.error is not None and "check_fit=False" in str(job.error):   # a failed fit: the Blender way out
            job.error = type(job.error)(f"{job.error} In Blender: Preview alignment draws the aligned source; "
                                        "Skip fit check there applies it anyway.")
        return super()._finish(context, job)

    def summary(self, record):
        i = record.info
        return f"residual {i.get('residual', 0):.2f} edge lengths, {i.get('seconds', 0):.1f} s"


class NEUMESH_OT_swap_texture(SwapResult, _FromPanel, bpy.types.Operator):
    """Give a vertex group the texture of another object's (or this object's) vertex group: aligned
    automatically or by selected vertex pairs; the source's decoder comes along. Saved as a new field
    file beside the current one (Undo edit / Ctrl+Z go back)"""

    bl_idname = "neumesh.swap_texture"
    bl_label = "Swap texture"
    bl_options = {"REGISTER", "UNDO"}
    edit_label = "texture swap"

    target_group: StringProperty(name="Target group", default="")
    source_object: StringProperty(name="Source object", default="", description="Empty: the active object")
    source_group: StringProperty(name="Source group", default="")
    use_pairs: BoolProperty(name="Use selected pairs", default=False)
    nonrigid: BoolProperty(name="Non-rigid fit", default=True,
                           description="Bend the source region onto the target's shape (ARAP ICP)")
    from_panel = (("target_group", "swap_target_group"), ("source_object", "swap_source"),
                  ("source_group", "swap_source_group"), ("use_pairs", "swap_use_pairs"))

    def prepare(self, context):
        nm = core.get()
        target, field, path, src_obj, src_field, t_idx, s_idx = self._regions(
            context, self.source_object, self.source_group, "source")
        pairs = selected_pairs(target, src_obj, field, src_field or field) if self.use_pairs else None
        work = edit_copy(field)
        source = edit_copy(src_field) if src_field is not None else None
        cfg = nm.edit.SwapConfig(nonrigid=self.nonrigid)

        def run(progress):
            return [nm.swap_texture(work, t_idx, work if source is None else source, s_idx, pairs=pairs,
                                    config=cfg, progress=progress)]
        return [(target, work, path)], run

class NEUMESH_OT_fill_texture(_FromPanel, bpy.types.Operator):
    """Tile the texture of a template vertex group over a target vertex group through their UV maps.
    Saved as a new field file beside the current one (Undo edit / Ctrl+Z go back)"""

    bl_idname = "neumesh.fill_texture"
    bl_label = "Fill texture"
    bl_options = {"REGISTER", "UNDO"}
    edit_label = "texture fill"

    target_group: StringProperty(name="Target group", default="")
    target_uv: StringProperty(name="Target UV map", default="")
    template_object: StringProperty(name="Template object", default="", description="Empty: the active object")
    template_group: StringProperty(name="Template group", default="")
    template_uv: StringProperty(name="Template UV map", default="")
    scale: FloatProperty(name="Scale", default=1.0, min=0.01, soft_max=16.0)
    from_panel = (("target_group", "fill_target_group"), ("target_uv", "fill_target_uv"),
                  ("template_object", "fill_template"), ("template_group", "fill_template_group"),
                  ("template_uv", "fill_template_uv"), ("scale", "fill_scale"))

    def prepare(self, context):
        nm = core.get()
        target, field, path, tmpl_obj, tmpl_field, t_idx, s_idx = self._regions(
            context, self.template_object, self.template_group, "template")
        t_uv = corner_uvs(target, self.target_uv, field)
        s_uv = corner_uvs(tmpl_obj, self.template_uv, tmpl_field or field)
        work = edit_copy(field)
        template = edit_copy(tmpl_field) if tmpl_field is not None else None
        scale = float(self.scale)

        def run(progress):
            return [nm.fill_texture(work, t_idx, t_uv, work if template is None else template, s_idx, s_uv,
                                    scale=scale, progress=progress)]
        return [(target, work, path)], run


class NEUMESH_PT_swap(EditSubPanel, bpy.types.Panel):
    bl_label = "Swap texture"
    extra_draw: list = []   # draw(context, layout, obj) functions added below (swap_preview: the preview)

    def draw_edit(self, context, col, obj):
        s = context.scene.neumesh_edit
        labelled_search(col, s, "swap_target_group", obj, "vertex_groups", "Target vertex group")
        labelled(col, s, "swap_source", "Source object")
        src = s.swap_source or obj
        labelled_search(col, s, "swap_source_group", src, "vertex_groups", "Source vertex group")
        col.prop(s, "swap_use_pairs")
        col.operator("neumesh.swap_texture", icon="UV_SYNC_SELECT")
        for draw in self.extra_draw:
            draw(context, col, obj)


class NEUMESH_PT_fill(EditSubPanel, bpy.types.Panel):
    bl_label = "Fill texture"

    def draw_edit(self, context, col, obj):
        s = context.scene.neumesh_edit
        labelled_search(col, s, "fill_target_group", obj, "vertex_groups", "Target vertex group")
        labelled_search(col, s, "fill_target_uv", obj.data, "uv_layers", "Target UV map")
        labelled(col, s, "fill_template", "Template object")
        tmpl = s.fill_template or obj
        labelled_search(col, s, "fill_template_group", tmpl, "vertex_groups", "Template vertex group")
        labelled_search(col, s, "fill_template_uv", tmpl.data, "uv_layers", "Template UV map")
        col.prop(s, "fill_scale")
        col.operator("neumesh.fill_texture", icon="TEXTURE")


classes = (NeuMeshEditSettings, NEUMESH_OT_swap_texture, NEUMESH_OT_fill_texture, NEUMESH_PT_swap,
           NEUMESH_PT_fill)


register, unregister = classes_factory(classes, (
    (bpy.types.Scene, "neumesh_edit", lambda: PointerProperty(type=NeuMeshEditSettings)),))
