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

from ._np import np
from . import core, props
from .edits import EditError, EditOperator, EditSubPanel, edit_copy, field_for_edit, region_of
from .text import labelled, labelled_search


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
            raise EditError(f"correspondences: {len(h)} vertices are selected on '{target.name}'; select "
                            "pairs in order (a source vertex, then its target vertex), at least 3 pairs")
        pairs = np.stack([h[0::2], h[1::2]], 1)
    else:
        hs, ht = selection_history(source), selection_history(target)
        if len(hs) != len(ht):
            raise EditError(f"correspondences: {len(hs)} vertices selected on '{source.name}' but {len(ht)} on "
                            f"'{target.name}'; select the same number, in matching order, on both (Edit Mode)")
        pairs = np.stack([hs, ht], 1) if len(hs) else np.zeros((0, 2), np.int64)
    if len(pairs) < 3:
        raise EditError(f"correspondences: {len(pairs)} pairs selected; select at least 3 (or turn off "
                        "'Use selected pairs' for the automatic alignment)")
    if target_field is not None and source_field is not None:
        from . import identity

        pairs = np.stack([identity.vertex_ids(source, source_field, pairs[:, 0]),
                          identity.vertex_ids(target, target_field, pairs[:, 1])], 1)
        if (pairs < 0).any():
            raise EditError("correspondences: some selected vertices are new (made by subdivision or extrusion) "
                            "and belong to no field vertex; pick vertices of the original mesh")
    return pairs


def corner_uvs(obj, uv_map: str, field=None):
    """The mesh's UV map as per-corner (vertex, uv) pairs (seams keep each side's UV); with ``field``
    the corners' vertices are field vertex ids (corners of new vertices are left out)."""
    from . import identity, sync

    nm = core.get()
    me = obj.data
    if not uv_map:
        raise EditError(f"choose a UV map of '{obj.name}'")
    if me.uv_layers.get(uv_map) is None:
        raise EditError(f"'{obj.name}' has no UV map '{uv_map}'; unwrap it (U) or choose another")
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
        raise EditError(f"'{obj.name}' has no NeuMesh field; choose an object that carries one")
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
    fill_target_group: StringProperty(name="Target group", description="Vertex group to fill")
    fill_target_uv: StringProperty(name="Target UV", description="UV map of the active object")
    fill_template: PointerProperty(name="Template", type=bpy.types.Object, poll=lambda s, o: o.type == "MESH",
                                   description="Object whose texture is tiled (empty: the active object)")
    fill_template_group: StringProperty(name="Template group", description="Vertex group of the template")
    fill_template_uv: StringProperty(name="Template UV", description="UV map of the template")
    fill_scale: FloatProperty(name="Scale", default=1.0, min=0.01, soft_max=16.0,
                              description="How many times the template repeats across the target's UV square")


class NEUMESH_OT_swap_texture(EditOperator, bpy.types.Operator):
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

    @classmethod
    def poll(cls, context):
        return _mesh_with_field(context.active_object)

    def invoke(self, context, event):
        s = context.scene.neumesh_edit
        self.target_group = self.target_group or s.swap_target_group
        self.source_object = self.source_object or (s.swap_source.name if s.swap_source else "")
        self.source_group = self.source_group or s.swap_source_group
        self.use_pairs = self.use_pairs or s.swap_use_pairs
        return EditOperator.invoke(self, context, event)

    def prepare(self, context):
        nm = core.get()
        target = context.active_object
        if target is not None and target.mode == "EDIT":
            bpy.ops.object.mode_set(mode="OBJECT")   # vertex groups and selection as the user left them
        field, path = field_for_edit(target)
        src_obj = bpy.data.objects.get(self.source_object) if self.source_object else None
        if self.source_object and src_obj is None:
            raise EditError(f"source object '{self.source_object}' does not exist")
        src_obj, src_field = _source_field(src_obj, target, field)
        t_idx = region_of(target, self.target_group, field, "target")
        s_idx = region_of(src_obj, self.source_group, src_field or field, "source")
        pairs = selected_pairs(target, src_obj, field, src_field or field) if self.use_pairs else None
        work = edit_copy(field)
        source = edit_copy(src_field) if src_field is not None else None
        cfg = nm.edit.SwapConfig(nonrigid=self.nonrigid)

        def run(progress):
            return [nm.swap_texture(work, t_idx, work if source is None else source, s_idx, pairs=pairs,
                                    config=cfg, progress=progress)]
        return [(target, work, path)], run

    def summary(self, record):
        i = record.info
        return f"residual {i.get('residual', 0):.2f} edge lengths, {i.get('seconds', 0):.1f} s"


class NEUMESH_OT_fill_texture(EditOperator, bpy.types.Operator):
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

    @classmethod
    def poll(cls, context):
        return _mesh_with_field(context.active_object)

    def invoke(self, context, event):
        s = context.scene.neumesh_edit
        self.target_group = self.target_group or s.fill_target_group
        self.target_uv = self.target_uv or s.fill_target_uv
        self.template_object = self.template_object or (s.fill_template.name if s.fill_template else "")
        self.template_group = self.template_group or s.fill_template_group
        self.template_uv = self.template_uv or s.fill_template_uv
        self.scale = s.fill_scale
        return EditOperator.invoke(self, context, event)

    def prepare(self, context):
        nm = core.get()
        target = context.active_object
        if target is not None and target.mode == "EDIT":
            bpy.ops.object.mode_set(mode="OBJECT")
        field, path = field_for_edit(target)
        tmpl_obj = bpy.data.objects.get(self.template_object) if self.template_object else None
        if self.template_object and tmpl_obj is None:
            raise EditError(f"template object '{self.template_object}' does not exist")
        tmpl_obj, tmpl_field = _source_field(tmpl_obj, target, field)
        t_idx = region_of(target, self.target_group, field, "target")
        s_idx = region_of(tmpl_obj, self.template_group, tmpl_field or field, "template")
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

    def draw_edit(self, context, col, obj):
        s = context.scene.neumesh_edit
        labelled_search(col, s, "swap_target_group", obj, "vertex_groups", "Target vertex group")
        labelled(col, s, "swap_source", "Source object")
        src = s.swap_source or obj
        labelled_search(col, s, "swap_source_group", src, "vertex_groups", "Source vertex group")
        col.prop(s, "swap_use_pairs")
        col.operator("neumesh.swap_texture", icon="UV_SYNC_SELECT")


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


def register():
    for c in classes:
        bpy.utils.register_class(c)
    bpy.types.Scene.neumesh_edit = PointerProperty(type=NeuMeshEditSettings)


def unregister():
    del bpy.types.Scene.neumesh_edit
    for c in reversed(classes):
        bpy.utils.unregister_class(c)
