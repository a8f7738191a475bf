"""Panels: 3D View sidebar tab 'NeuMesh', Object properties field path, Render properties."""
from __future__ import annotations

import bpy

from . import operators, worker


class _Sidebar:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NeuMesh"


class NEUMESH_PT_data(_Sidebar, bpy.types.Panel):
    bl_label = "NeuMesh data"

    def draw(self, context):
        s = context.scene.neumesh
        col = self.layout.column()
        col.prop(s, "dataset_path")
        col.prop(s, "downscale")
        op = col.operator("neumesh.import_dataset", icon="OUTLINER_OB_CAMERA")
        op.directory = s.dataset_path
        op.downscale = s.downscale
        col.prop(s, "scaffold_method")
        col.prop(s, "scaffold_vertices")
        row = col.row(align=True)
        row.operator("neumesh.build_scaffold", icon="MESH_ICOSPHERE")
        row.operator("neumesh.import_mesh", icon="IMPORT")


class NEUMESH_PT_train(_Sidebar, bpy.types.Panel):
    bl_label = "Training"

    def draw(self, context):
        s = context.scene.neumesh
        col = self.layout.column()
        col.prop(s, "train_object")
        col.prop(s, "train_steps")
        job = worker.current()
        if job is not None and job.running:
            col.label(text=job.status_text(), icon="SORTTIME")
            if hasattr(col, "progress"):
                col.progress(factor=job.fraction, text=f"{job.step}/{job.total_steps}")
            col.operator("neumesh.train_cancel", icon="CANCEL")
        else:
            row = col.row(align=True)
            row.operator("neumesh.train", icon="PLAY").resume = False
            row.operator("neumesh.train", text="Resume", icon="FF").resume = True
            if job is not None:
                col.label(text=job.status_text(),
                          icon={"DONE": "CHECKMARK", "ERROR": "ERROR"}.get(job.state, "INFO"))


class NEUMESH_PT_field(_Sidebar, bpy.types.Panel):
    bl_label = "Field & render"

    def draw(self, context):
        col = self.layout.column()
        obj = context.active_object
        if obj is not None and obj.type == "MESH":
            col.prop(obj.neumesh, "field_path")
            col.prop(obj.neumesh, "enabled")
        col.operator("neumesh.load_field", icon="FILE_FOLDER")
        s = context.scene.neumesh
        col.separator()
        col.prop(s, "render_cameras")
        col.prop(s, "render_samples")
        col.prop(s, "output_dir")
        col.operator("neumesh.render_images", icon="RENDER_STILL")
        col.label(text=f"{len(operators.dataset_cameras())} dataset camera(s)")


class NEUMESH_PT_object(bpy.types.Panel):
    bl_label = "NeuMesh field"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "object"

    @classmethod
    def poll(cls, context):
        return context.object is not None and context.object.type == "MESH"

    def draw(self, context):
        self.layout.prop(context.object.neumesh, "field_path")
        self.layout.prop(context.object.neumesh, "enabled")


class NEUMESH_PT_render(bpy.types.Panel):
    bl_label = "NeuMesh"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    COMPAT_ENGINES = {"NEUMESH"}

    @classmethod
    def poll(cls, context):
        return context.engine in cls.COMPAT_ENGINES

    def draw(self, context):
        scene = context.scene
        col = self.layout.column()
        col.prop(scene.render, "film_transparent")
        col.prop(scene.neumesh, "render_samples")
        vs = scene.view_settings
        if vs.view_transform != "Standard" or scene.render.dither_intensity != 0:
            col.label(text="Exact field colours: view transform 'Standard', dither 0", icon="INFO")


classes = (NEUMESH_PT_data, NEUMESH_PT_train, NEUMESH_PT_field, NEUMESH_PT_object, NEUMESH_PT_render)


def register():
    for c in classes:
        bpy.utils.register_class(c)


def unregister():
    for c in reversed(classes):
        bpy.utils.unregister_class(c)
