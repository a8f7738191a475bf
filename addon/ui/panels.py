"""Panels: 3D View sidebar tab 'NeuMesh', Object properties field path, Render properties.

The sidebar is narrow (about 280 px at its default width, less than half of it for a label beside a
field), so every property whose name would be cut is drawn with its label above it, buttons are
stacked rather than put side by side, and longer messages are wrapped to the region's width
(:func:`text.wrapped_label`).
"""
from __future__ import annotations

import bpy

from ..render import colour, engine, images
from ..runtime import jobs, prefs
from ..train import capture, worker
from ..runtime.text import job_status, labelled as _labelled, text_width, wrapped_label

SCAFFOLD_HELP = ("The scaffold is the mesh the field is stored on: every vertex keeps the learned codes "
                 "of the surface around it, so moving or bending the mesh moves the field with it. Build "
                 "it from the dataset's photos, or import a mesh of the object")


def _fraction(divisor: int) -> str:
    return "full" if divisor <= 1 else f"1/{divisor}"


def viewport_level_text(progress) -> str:
    """What the Rendered viewport's progressive preview shows, from ``engine.viewport_progress()``
    ((shown divisor, finest divisor, busy, seconds) or None): '' when no viewport renders."""
    if progress is None:
        return ""
    shown, finest, busy, seconds = progress
    if shown is None:
        return "Viewport preview: rendering its first pass" if busy else ""
    after = f" ({seconds:.1f} s)" if seconds is not None else ""
    now = f"Viewport preview: {_fraction(shown)} resolution{after}"
    if busy and shown > finest:
        return f"{now}, finest {_fraction(finest)} to come"
    if busy:
        return f"{now}, rendering the changed view"
    if shown <= finest:
        return f"{now}, the finest (Preferences > Preview ends at)"
    return now


def _job_progress(col, label: str, context) -> bool:
    """The running job of the operator labelled ``label`` (Import Mesh, Load Field): its stage and
    percentage, Esc cancels. False when none runs."""
    job = jobs.active(label)
    if job is None:
        return False
    text = f"{100 * job.fraction:.0f}% {job.message} (Esc cancels)"
    if hasattr(col, "progress"):
        col.progress(factor=job.fraction, text=f"{100 * job.fraction:.0f}%")
        wrapped_label(col, f"{job.message} (Esc cancels)", text_width(context), context=context)
    else:
        wrapped_label(col, text, text_width(context), icon="SORTTIME", context=context)
    return True


# ---------------------------------------------------------------------------------------- sidebar
class _Sidebar:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NeuMesh"


class _Step(_Sidebar):
    """A step of the workflow: one setting with its label above it, more settings, then
    ``draw_step(context, col, settings)``."""

    labelled_prop = ("", "")
    props: tuple = ()   # (property, text or None)

    def draw(self, context):
        s = context.scene.neumesh
        col = self.layout.column()
        _labelled(col, s, *self.labelled_prop)
        for prop, text in self.props:
            col.prop(s, prop, **({} if text is None else {"text": text}))
        self.draw_step(context, col, s)


class NEUMESH_PT_data(_Step, bpy.types.Panel):
    bl_label = "Dataset"
    bl_description = "The photos and their cameras that a field is trained on"
    labelled_prop, props = ("dataset_path", "Dataset folder"), (("downscale", None),)

    def draw_step(self, context, col, s):
        op = col.operator("neumesh.import_dataset", text="Import Cameras", icon="OUTLINER_OB_CAMERA")
        op.directory = s.dataset_path
        op.downscale = s.downscale
        col.label(text=f"{len(images.dataset_cameras())} dataset camera(s)")
        col.separator()
        _labelled(col, s, "capture_source", "Photos or video")
        col.prop(s, "capture_fps", text="Video fps")
        prefs.draw_missing(col, "capture", context)
        job = capture.active_job()
        if job is None:
            col.operator("neumesh.poses_from_photos", text="Poses from Photos", icon="CON_CAMERASOLVER")
        else:
            job_status(col, job, context, cancel="neumesh.capture_cancel")


class NEUMESH_PT_scaffold(_Step, bpy.types.Panel):
    bl_label = "Scaffold"
    bl_description = SCAFFOLD_HELP
    labelled_prop, props = ("scaffold_method", "Method"), (("scaffold_vertices", "Vertices"),)

    def draw_step(self, context, col, s):
        prefs.draw_missing(col, "scaffold", context)
        col.operator("neumesh.build_scaffold", text="Build from Photos", icon="MESH_ICOSPHERE")
        if not _job_progress(col, "Import scaffold mesh", context):
            col.operator("neumesh.import_mesh", text="Import Mesh", icon="IMPORT")


class NEUMESH_PT_train(_Step, bpy.types.Panel):
    bl_label = "Training"
    bl_description = "Train the field of a scaffold mesh on the dataset, in the background"
    labelled_prop, props = ("train_object", "Scaffold mesh"), (("train_steps", None), ("train_background", None))

    def draw_step(self, context, col, s):
        job = worker.current()
        if job is None or not job.running:
            row = col.row(align=True)
            row.operator("neumesh.train", text="Train", icon="PLAY").resume = False
            row.operator("neumesh.train", text="Resume", icon="FF").resume = True
        if job is not None:
            job_status(col, job, context, cancel="neumesh.train_cancel")


class NEUMESH_PT_field(_Sidebar, bpy.types.Panel):
    bl_label = "Field & Render"
    bl_description = "The field file of the active mesh, and rendering to image files"

    def draw(self, context):
        col = self.layout.column()
        obj = context.active_object
        if obj is not None and obj.type == "MESH":
            _labelled(col, obj.neumesh, "field_path", f"Field of '{obj.name}'")
            col.prop(obj.neumesh, "enabled")
        if not _job_progress(col, "Load field", context):
            col.operator("neumesh.load_field", text="Load Field", icon="FILE_FOLDER")
        level = viewport_level_text(engine.viewport_progress())
        if level:
            wrapped_label(col, level, text_width(context), icon="SHADING_RENDERED", context=context)
        s = context.scene.neumesh
        col.separator()
        _labelled(col, s, "render_cameras", "Render cameras")
        col.prop(s, "render_samples")
        col.prop(s, "render_background")
        _labelled(col, s, "output_dir", "Output folder")
        col.operator("neumesh.render_images", text="Render to Images", icon="RENDER_STILL")
        col.separator()
        col.operator("neumesh.composite_with_scene", icon="NODE_COMPOSITING")
        if s.composite_scene is not None:
            wrapped_label(col, f"Fields render in scene '{s.composite_scene.name}'", text_width(context),
                          icon="SCENE_DATA", context=context)


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
        col.prop(scene.neumesh, "render_background")
        issues = colour.photo_colour_issues(scene)
        width = text_width(context)
        if issues:
            box = col.box()
            wrapped_label(box, "Colours look flat: " + ", ".join(issues) + ". NeuMesh fields hold the "
                          "photos' colours; show them with 'Standard'.", width, icon="ERROR", context=context)
            box.operator("neumesh.photo_colour", icon="COLOR")
        elif scene.render.dither_intensity != 0:
            wrapped_label(col, "Dither adds noise of about 1/255; set it to 0 (Output > Post Processing) "
                          "for the field's exact pixel values.", width, icon="INFO", context=context)


classes = (NEUMESH_PT_data, NEUMESH_PT_scaffold, NEUMESH_PT_train, NEUMESH_PT_field, NEUMESH_PT_object,
           NEUMESH_PT_render)


register, unregister = bpy.utils.register_classes_factory(classes)
