"""The Semantics panel (under *Edit field*) and its settings: Distill semantics (:mod:`distill`), Select
by click (:mod:`select`), Show semantic colours (:mod:`semantic_colours`)."""
from __future__ import annotations

import bpy
from bpy.props import EnumProperty, IntProperty, PointerProperty, StringProperty

from ..runtime import classes_factory, prefs
from ..runtime.text import job_status, labelled, text_width, wrapped_label
from . import distill
from .select import DEFAULT_GROUP

_EXTRACTORS = [("colour-texture", "Colour & texture", "Weight-free: colour and texture statistics over "
                                                      "superpixels (needs nothing downloaded)"),
               ("dino-vits8", "DINO ViT-S/8", "Self-supervised ViT features; weights from $NEUMESH_WEIGHTS "
                                              "(dino-vits8.safetensors) or the Hugging Face cache"),
               ("dino-vitb8", "DINO ViT-B/8", "Larger DINO ViT; local weights as above"),
               ("dinov2-small", "DINOv2 ViT-S/14", "DINOv2 features; local weights as above")]


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
        width = text_width(context)
        job = distill.current_job()
        if job is None or not job.running:
            prefs.draw_missing(col, "semantics", context)
            labelled(col, s, "extractor", "2D features")
            col.prop(s, "steps")
            col.operator("neumesh.distill_semantics", icon="SHADERFX")
        if job is not None:
            job_status(col, job, context, cancel="neumesh.distill_cancel")
        col.separator()
        prefs.draw_missing(col, "select", context)
        if prefs.draw_missing(col, "shape", context):   # selection still works, on colour alone
            wrapped_label(col, "Without it Select by click uses colour only (no shape)", width, context=context)
        labelled(col, s, "group_name", "Selection group")
        wrapped_label(col, "The clicked part goes into this vertex group", width, context=context)
        op = col.operator("neumesh.select_by_click", icon="EYEDROPPER")
        op.group_name = s.group_name
        col.operator("neumesh.semantic_colours", icon="COLOR")


classes = (NeuMeshSemanticSettings, NEUMESH_PT_semantics)
register, unregister = classes_factory(classes, (
    (bpy.types.Scene, "neumesh_semantics", lambda: PointerProperty(type=NeuMeshSemanticSettings)),))
