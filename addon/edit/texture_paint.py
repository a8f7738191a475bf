"""Blender's own Texture Paint on a field's paint atlas (texel paint, ``neumesh_core/field/paint_atlas.py``).

*Texture Paint* (operator ``neumesh.texture_paint``) gives the active object's field a paint atlas
when it has none (the mesh's own UV map when it has one, else the core's unwrap), writes the atlas's
UVs as the UV map "NeuMesh Paint" of the object's mesh, and makes the paint layer an ordinary Blender
image ("NeuMesh Paint <object>", packed into the .blend) that Texture Paint mode paints into (Single
Image mode, that image as the canvas).  The artist paints on the object with Blender's brushes,
stencils and masks.

The image is the truth while painting: :mod:`paint_sync` pushes its changed texels into the cached
field's paint atlas and the Rendered viewports follow.  *Save paint* writes the field with its atlas
as a new edit file in the edits folder (``nm.edit.paint_image_record`` + :func:`base.commit_edit`:
atomic; Undo edit / Ctrl+Z go back as for every edit).
"""
from __future__ import annotations

import bpy
from bpy.props import IntProperty

from ..runtime._np import np
from ..runtime import core
from ..runtime.errors import UserError
from ..runtime.text import file_size, text_width, wrapped_label
from ..scene import props
from ..render import engine, field_cache
from .base import EditSubPanel, commit_edit
from .paint_sync import (POLL_S, STATS, STATE, UV_NAME, WATCH, ensure_timer, mesh_uvs, new_image,  # noqa: F401
                         on_undo, own_field, paint_image, sync_all, sync_object, tick, triangles, write_uv_layer)


class NEUMESH_OT_texture_paint(bpy.types.Operator):
    """Paint the active field object with Blender's brushes (Texture Paint mode): its paint layer becomes
    an image on the UV map "NeuMesh Paint", and the Rendered viewport shows the paint as you paint"""

    bl_idname = "neumesh.texture_paint"
    bl_label = "Texture Paint"
    bl_options = {"REGISTER", "UNDO"}     # Ctrl+Z after the first stroke undoes the stroke, not this

    resolution: IntProperty(name="Resolution", default=0, min=0, max=16384,
                            description="Paint image size in texels (0: 2048, or 4096 for scaffolds over 50,000 "
                                        "faces); used only when the field has no paint layer yet")

    def execute(self, context):
        obj = context.active_object
        try:
            nm = core.get()
            field, loops = own_field(obj)
            made = False
            if getattr(field, "paint_atlas", None) is None:
                res = self.resolution or (4096 if len(loops) > 50_000 else 2048)
                uvs = mesh_uvs(obj.data, loops)
                nm.edit.create_paint_atlas(field, resolution=res, uvs=uvs)
                made = True
            atlas = field.paint_atlas
            write_uv_layer(obj.data, loops, atlas.uv.numpy())
            img = paint_image(obj)
            if img is None or tuple(img.size) != (atlas.size[1], atlas.size[0]):
                img = new_image(obj, atlas)
            # the paint as the field's file holds it (none when the layer was just made): Save paint
            # records what changed since
            STATE.setdefault(obj.name, {}).setdefault(
                "saved", np.zeros_like(atlas.image.numpy()) if made else atlas.image.numpy().copy())
            sync_object(obj, force=True)
        except (UserError, core.CoreUnavailable) as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        except Exception as exc:  # noqa: BLE001
            self.report({"ERROR"}, f"NeuMesh: cannot set up Texture Paint: {field_cache.user_message(exc)}")
            return {"CANCELLED"}
        ip = context.scene.tool_settings.image_paint
        ip.mode = "IMAGE"          # Single Image: paint into this image through the active UV map
        ip.canvas = img
        try:
            if obj.mode != "TEXTURE_PAINT":
                bpy.ops.object.mode_set(mode="TEXTURE_PAINT")
        except RuntimeError:      # no 3D View (scripts, background): the image and UV map are ready
            pass
        ensure_timer()
        if not bpy.app.background and context.window is not None and not WATCH["running"]:
            bpy.ops.neumesh.texture_paint_watch("INVOKE_DEFAULT")
        h, w = atlas.size
        self.report({"INFO"}, f"NeuMesh: paint on '{obj.name}' ({w}x{h} texels, UV map '{UV_NAME}'); the "
                              "Rendered viewport follows; Save paint keeps it in the field")
        return {"FINISHED"}


def unsaved_texels(obj) -> int:
    st = STATE.get(obj.name)
    img = paint_image(obj)
    if st is None or img is None or st.get("saved") is None:
        return 0
    try:
        field = field_cache.cached_field(obj.name_full, props.field_abspath(obj))
    except Exception:  # noqa: BLE001
        return 0
    if getattr(field, "paint_atlas", None) is None or field.paint_atlas.image.shape != st["saved"].shape:
        return 0
    return int((field.paint_atlas.image.numpy() != st["saved"]).any(-1).sum())


class NEUMESH_OT_save_paint(bpy.types.Operator):
    """Save the field with the paint made in Texture Paint (a new file in the Edits folder; Undo edit goes
    back)"""

    bl_idname = "neumesh.save_paint"
    bl_label = "Save paint"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        obj = context.active_object
        try:
            nm = core.get()
            if paint_image(obj) is None:
                raise UserError("this object has no Texture Paint image; press Texture Paint first")
            sync_object(obj)
            field, _ = own_field(obj)
            if getattr(field, "paint_atlas", None) is None:
                raise UserError("the field has no paint layer; press Texture Paint first")
            st = STATE.setdefault(obj.name, {})
            saved = st.get("saved")
            if saved is None or saved.shape != tuple(field.paint_atlas.image.shape):
                saved = np.zeros(tuple(field.paint_atlas.image.shape), np.float32)
            rec = nm.edit.paint_image_record(field, saved)
            if rec.num_changed == 0:
                self.report({"INFO"}, "NeuMesh: nothing was painted since the last save; nothing written")
                return {"CANCELLED"}
            out = commit_edit(obj, field, rec, props.field_abspath(obj))
            st["saved"] = field.paint_atlas.image.numpy().copy()
        except (UserError, core.CoreUnavailable) as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        except Exception as exc:  # noqa: BLE001
            self.report({"ERROR"}, f"NeuMesh: cannot save the paint: {field_cache.user_message(exc)}")
            return {"CANCELLED"}
        engine.refresh_viewports(context)
        self.report({"INFO"}, f"NeuMesh: paint saved ({rec.num_changed:,} texels) in {out} ({file_size(out)})")
        return {"FINISHED"}


class NEUMESH_PT_texture_paint(EditSubPanel, bpy.types.Panel):
    bl_label = "Texture Paint"

    def draw_edit(self, context, col, obj):
        width = text_width(context)
        wrapped_label(col, "Paint the field with Blender's brushes; the Rendered viewport follows", width,
                      context=context)
        col.operator("neumesh.texture_paint", icon="TPAINT_HLT")
        row = col.row()
        row.enabled = paint_image(obj) is not None
        row.operator("neumesh.save_paint", icon="FILE_TICK")
        n = unsaved_texels(obj) if row.enabled else 0
        if n:
            wrapped_label(col, f"{n:,} texels not saved in the field yet", width, icon="INFO", context=context)


classes = (NEUMESH_OT_texture_paint, NEUMESH_OT_save_paint, NEUMESH_PT_texture_paint)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()


def unregister():
    _unregister_classes()
