"""Texture painting in Blender: paint on a render of the scene camera, then apply the paint to the
fields in view (``nm.edit.paint_fields``; see ``neumesh_core/edit/paint.py``).

*Paint on view* renders the scene camera with the core into an image ("NeuMesh Paint"), keeps the
unpainted render beside it ("NeuMesh Paint (unpainted)") and the view (K, camera-to-world, size) in
the image's custom properties, and opens it in an Image Editor in Paint mode: an Image Editor of the
main window when there is one, else the largest 3D View is split and its new half becomes one (a new
window only when neither can be done).  That editor's sidebar (tab NeuMesh) and header carry *Apply
painting* and *Cancel painting*, where the painting happens.  *Apply painting* reads
the painted image, takes the pixels that differ from the unpainted render as paint, and changes the
modification colours of the fields those pixels' rays hit (each field object that changes gets an
edited file in the edits folder; undo as for every edit).  The camera and the image size must be those
of the render.  The image may be painted on and applied again; *Apply* is enabled only while it holds
strokes not applied yet (:func:`paint_pending`).  *Cancel painting* discards the paint image and closes
the editor the add-on opened; once paint was applied it is called *Close painting* and says that the
applied paint stays in the fields (*Undo edit* takes it out).
"""
from __future__ import annotations

import bpy
from bpy.props import StringProperty

from ..runtime._np import np
from ..runtime import core, quiet
from ..runtime.text import text_width, ui_scale, wrapped_label
from ..scene import camera, props
from ..render import field_cache, frame
from ..runtime.errors import UserError
from .base import EditOperator, EditSubPanel, edit_copy
from .paint_editor import OPENED_KEY, open_in_image_editor

PAINT_IMAGE = "NeuMesh Paint"
ORIGINAL_IMAGE = PAINT_IMAGE + " (unpainted)"
_KEYS = ("neumesh_K", "neumesh_c2w", "neumesh_size", "neumesh_original", "neumesh_camera")
APPLIED_KEY = "neumesh_applied"   # on the paint image: how many times its paint was applied


def _image_pixels(img) -> np.ndarray:
    """(H,W,4) float32 pixels of a Blender image, top row first."""
    w, h = img.size
    px = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(px)
    return px.reshape(h, w, 4)[::-1].copy()


def _set_pixels(img, rgba: np.ndarray) -> None:
    img.pixels.foreach_set(np.ascontiguousarray(rgba[::-1], dtype=np.float32).ravel())
    img.update()


def _new_image(name: str, w: int, h: int):
    old = bpy.data.images.get(name)
    if old is not None:
        bpy.data.images.remove(old)
    # a byte image in sRGB: pixel values are the display-referred colours the field renders
    img = bpy.data.images.new(name, w, h, alpha=True, float_buffer=False)
    img.colorspace_settings.name = "sRGB"
    return img


def _view(context):
    scene = context.scene
    cam = scene.camera
    if cam is None:
        raise UserError("the scene has no camera; add one (or set Scene > Camera) and paint on its view")
    depsgraph = context.evaluated_depsgraph_get()
    W, H = camera.render_size(scene)
    K, c2w, W, H = camera.camera_K_c2w(cam, scene, depsgraph, W, H)
    return cam, depsgraph, np.asarray(K, np.float32), np.asarray(c2w, np.float32), int(W), int(H)


_SURFACE: dict = {}   # paint image name -> (K, c2w, W, H, opacity, depth) of the render painted on
class NEUMESH_OT_paint_view(bpy.types.Operator):
    """Render the scene camera's view of the fields into an image to paint on (Image Editor, Paint
    mode); then press Apply painting"""

    bl_idname = "neumesh.paint_view"
    bl_label = "Paint on view"
    bl_options = {"REGISTER"}

    def execute(self, context):
        try:
            cam, depsgraph, K, c2w, W, H = _view(context)
            items = field_cache.collect(depsgraph, for_render=True)
            if not items:
                raise UserError("no object with a field is in the scene; load or train a field first")
            rgba, opacity, depth = frame.render_items_surface(items, K, c2w, W, H)
        except (UserError, core.CoreUnavailable) as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        except Exception as exc:  # noqa: BLE001 - topology errors, missing files ...
            self.report({"ERROR"}, f"NeuMesh: cannot render the view to paint on: {exc}")
            return {"CANCELLED"}
        rgb = np.clip(rgba[..., :3], 0, 1)
        opaque = np.concatenate([rgb, np.ones((H, W, 1), np.float32)], -1)
        original = _new_image(ORIGINAL_IMAGE, W, H)
        _set_pixels(original, opaque)
        original.pack()
        original.use_fake_user = True
        img = _new_image(PAINT_IMAGE, W, H)
        _set_pixels(img, opaque)
        img.pack()
        img["neumesh_K"] = [float(x) for x in K.ravel()]
        img["neumesh_c2w"] = [float(x) for x in c2w.ravel()]
        img["neumesh_size"] = [W, H]
        img["neumesh_original"] = original.name
        img["neumesh_camera"] = cam.name
        # the surface under each pixel: paint into a field's paint atlas needs no render again
        _SURFACE.clear()
        _SURFACE[img.name] = (K.copy(), c2w.copy(), W, H, opacity, depth)
        open_in_image_editor(context, img)
        self.report({"INFO"}, f"NeuMesh: paint on '{img.name}' ({W}x{H}) in the Image Editor, then Apply painting "
                              "(its sidebar, tab NeuMesh, or its header)")
        return {"FINISHED"}


def paint_image_view(img):
    """(K, c2w, W, H, original pixels) stored with a paint image; :class:`UserError` when it is not one."""
    if img is None:
        raise UserError(f"there is no image '{PAINT_IMAGE}'; press Paint on view first")
    if any(k not in img for k in _KEYS):
        raise UserError(f"image '{img.name}' was not made by Paint on view; press Paint on view and paint on "
                        "that image")
    orig = bpy.data.images.get(img["neumesh_original"])
    if orig is None:
        raise UserError(f"the unpainted render of '{img.name}' is gone; press Paint on view again")
    K = np.asarray(img["neumesh_K"], np.float32).reshape(3, 3)
    c2w = np.asarray(img["neumesh_c2w"], np.float32).reshape(4, 4)
    W, H = (int(x) for x in img["neumesh_size"])
    return K, c2w, W, H, orig


class NEUMESH_OT_apply_paint(EditOperator, bpy.types.Operator):
    """Apply what was painted on the Paint on view image to the fields it covers (their modification
    colours change; each object's field is saved as a new file beside its own; Undo edit / Ctrl+Z go
    back)"""

    bl_idname = "neumesh.apply_paint"
    bl_label = "Apply painting"
    bl_options = {"REGISTER", "UNDO"}
    edit_label = "painting"

    image: StringProperty(name="Image", default=PAINT_IMAGE, description="The painted image")

    def prepare(self, context):
        nm = core.get()
        img = bpy.data.images.get(self.image)
        K, c2w, W, H, orig = paint_image_view(img)
        if tuple(img.size) != (W, H) or tuple(orig.size) != (W, H):
            raise UserError(f"'{img.name}' is {img.size[0]}x{img.size[1]} but the view was rendered at {W}x{H}; "
                            "paint on the image Paint on view made (do not resize it)")
        cam, depsgraph, K_now, c2w_now, W_now, H_now = _view(context)
        if cam.name != img["neumesh_camera"] or (W_now, H_now) != (W, H) or \
                not np.allclose(c2w_now, c2w, atol=1e-5) or not np.allclose(K_now, K, rtol=1e-5):
            raise UserError("the camera or the render size changed since Paint on view; put them back, or press "
                            "Paint on view again (and paint again)")
        layer = nm.edit.paint_layer(_image_pixels(img)[..., :3], _image_pixels(orig)[..., :3])
        if layer[..., 3].max() <= 0:
            raise UserError(f"nothing is painted on '{img.name}'; paint on it in the Image Editor first")
        items = field_cache.collect(depsgraph, for_render=True)
        if not items:
            raise UserError("no object with a field is in the scene")

        targets, posed, plans = [], [], []
        surf = _SURFACE.get(img.name)
        surface = None
        if surf is not None and surf[2:4] == (W, H) and np.allclose(surf[0], K) and np.allclose(surf[1], c2w) \
                and surf[4] is not None:
            surface = (surf[4], surf[5])
        for it in items:
            obj = bpy.data.objects.get(it.key.split("#")[0])
            if it.field is None:                     # the object's own field, vertex by vertex
                field = field_cache.posed_copy(it)        # paint lands on the surface as it is posed now
                targets.append((obj, field, it.path))
                # a field with a paint atlas takes the paint in its texels (as sharp as painted)
                plans.append("atlas" if getattr(field, "paint_atlas", None) is not None else None)
                posed.append(field)
                continue
            shown = field_cache.posed_copy(it)            # a field remapped onto the object's mesh
            posed.append(shown)
            own = props.field_abspath(obj)
            if it.path != own:                       # joined in from another field: shown, not edited
                targets.append((obj, None, it.path))
                plans.append("skip")
                continue
            source = edit_copy(field_cache.get_field(obj.name_full, own))
            ids = field_cache.source_ids(it.key, source)
            targets.append((obj, source, own))
            plans.append((source, ids))

        def run(progress):
            # fields with a paint atlas: texel paint (each alone; the render painted on gives the
            # surface); the others: modification colours, solved jointly
            recs = [None] * len(posed)
            for i, (plan, shown) in enumerate(zip(plans, posed)):
                if plan == "atlas":
                    try:
                        recs[i] = nm.edit.paint_atlas_from_view(shown, K, c2w, W, H, layer, surface=surface)
                    except nm.PaintMissError:   # this field is not under the paint: the others may be
                        pass
            rest = [i for i, plan in enumerate(plans) if plan != "atlas"]
            if rest:
                try:
                    for i, rec in zip(rest, nm.edit.paint_fields([posed[i] for i in rest], K, c2w, W, H, layer,
                                                                 progress=progress)):
                        recs[i] = rec
                except nm.EditError:
                    if not any(r is not None for r in recs):
                        raise
            if not any(r is not None for r in recs):
                raise UserError("the paint covers none of the fields; paint over an object")
            out = []
            for rec, plan, shown in zip(recs, plans, posed):
                if rec is None or plan is None or plan == "atlas":
                    out.append(rec)
                elif plan == "skip":
                    out.append(None)
                else:
                    out.append(nm.edit.paint_onto_source(rec, shown, *plan))
            return out
        return targets, run

    def summary(self, record):
        i = record.info
        return f"{i.get('painted_pixels', 0)} painted pixels, {i.get('seconds', 0):.1f} s"

    def _finish(self, context, job):
        result = EditOperator._finish(self, context, job)
        if "FINISHED" in result:
            mark_applied(bpy.data.images.get(self.image))
        return result


def paint_pending(img) -> bool:
    """Does the paint image hold strokes that were not applied yet?  Blender marks an image dirty when
    its pixels change (a brush stroke, a script writing ``pixels``); packing it, as Paint on view and
    every Apply do, clears that mark."""
    return is_paint_image(img) and bool(img.is_dirty)


def mark_applied(img) -> None:
    """After an Apply: the image counts as applied (and packed, so its strokes stop being pending)."""
    if not is_paint_image(img):
        return
    img[APPLIED_KEY] = int(img.get(APPLIED_KEY, 0)) + 1
    try:
        img.pack()
    except RuntimeError as exc:  # the strokes then still count as pending: Apply stays enabled
        print(f"NeuMesh: could not pack '{img.name}': {exc}")


def applied(img) -> bool:
    return is_paint_image(img) and int(img.get(APPLIED_KEY, 0)) > 0


class NEUMESH_PT_paint(EditSubPanel, bpy.types.Panel):
    bl_label = "Paint texture"

    def draw(self, context):   # painting covers every field in view: no active object needed
        self.draw_edit(context, self.layout.column(), context.active_object)

    def draw_edit(self, context, col, obj):
        width = text_width(context)
        wrapped_label(col, "1. Render the camera view to paint on", width, context=context)
        col.operator("neumesh.paint_view", icon="BRUSH_DATA")
        wrapped_label(col, "2. Paint on it in the Image Editor", width, context=context)
        wrapped_label(col, "3. Apply the paint to the fields (here, or in the Image Editor's sidebar and header)",
                      width, context=context)
        img = bpy.data.images.get(PAINT_IMAGE)
        row = col.row(align=True)
        row.operator("neumesh.apply_paint", icon="CHECKMARK")
        row.enabled = paint_pending(img)
        sub = col.row()
        sub.enabled = is_paint_image(img)
        sub.operator("neumesh.cancel_paint", text=cancel_text(img), icon="CANCEL")
        if applied(img) and not row.enabled:
            wrapped_label(col, "Applied; paint more to apply again", width, icon="CHECKMARK", context=context)


def cancel_text(img, short: bool = False) -> str:
    """The Cancel button's text: what it does to this paint image."""
    if applied(img):
        return "Close" if short else "Close painting"
    return "Cancel" if short else "Cancel painting"


def is_paint_image(img) -> bool:
    return img is not None and all(k in img for k in _KEYS)


def _paint_space_image(context):
    space = getattr(context, "space_data", None)
    img = getattr(space, "image", None) if space is not None and space.type == "IMAGE_EDITOR" else None
    return img if is_paint_image(img) else None


class NEUMESH_OT_cancel_paint(bpy.types.Operator):
    """Discard the Paint on view image and close the Image Editor Paint on view opened (paint applied
    before stays in the fields; Undo edit takes it out)"""

    bl_idname = "neumesh.cancel_paint"
    bl_label = "Cancel painting"
    bl_options = {"REGISTER"}

    image: StringProperty(name="Image", default=PAINT_IMAGE, description="The paint image to discard")

    def execute(self, context):
        img = bpy.data.images.get(self.image)
        if not is_paint_image(img):
            self.report({"ERROR"}, f"NeuMesh: there is no paint image '{self.image}' to cancel")
            return {"CANCELLED"}
        opened = bool(img.get(OPENED_KEY, False))
        message = cancel_message(img)
        closed = 0
        for window in context.window_manager.windows:
            for area in list(window.screen.areas):
                if area.type != "IMAGE_EDITOR" or area.spaces.active.image != img:
                    continue
                if opened and len(window.screen.areas) > 1:
                    with quiet.override(context, window=window, screen=window.screen, area=area):
                        bpy.ops.screen.area_close()
                    closed += 1
                else:
                    area.spaces.active.image = None
        orig = bpy.data.images.get(img.get("neumesh_original", ""))
        bpy.data.images.remove(img)
        if orig is not None:
            bpy.data.images.remove(orig)
        self.report({"INFO"}, f"NeuMesh: {message}")
        return {"FINISHED"}


def cancel_message(img) -> str:
    """What Cancel / Close painting did to this paint image and to the fields."""
    pending = paint_pending(img)
    if not applied(img):
        return "painting cancelled; nothing was applied" if pending else \
            "painting closed; nothing was painted, nothing was applied"
    kept = "the paint applied before stays in the fields (Undo edit takes it out)"
    return f"painting closed; the strokes not applied were discarded, {kept}" if pending else \
        f"painting closed; {kept}"


def _draw_actions(layout, img, header=False):
    box = layout.row(align=True) if header else layout.column(align=True)   # sidebar: one button a row
    sub = box.row(align=True)
    sub.enabled = paint_pending(img)   # Apply only while there are strokes to apply
    op = sub.operator("neumesh.apply_paint", text="Apply" if header else "Apply painting", icon="CHECKMARK")
    op.image = img.name
    op = box.operator("neumesh.cancel_paint", text=cancel_text(img, short=header), icon="CANCEL")
    op.image = img.name


class NEUMESH_PT_paint_image(bpy.types.Panel):
    """The Image Editor's sidebar while it shows the Paint on view image: apply or cancel there."""

    bl_label = "NeuMesh paint"
    bl_space_type = "IMAGE_EDITOR"
    bl_region_type = "UI"
    bl_category = "NeuMesh"

    @classmethod
    def poll(cls, context):
        return _paint_space_image(context) is not None

    def draw(self, context):
        from ..runtime import jobs

        img = _paint_space_image(context)
        col = self.layout.column()
        # the Image Editor's sidebar keeps its tab strip and scroll bar inside the region: a wider margin
        width = max(40.0, text_width(context) - 40 * ui_scale(context))
        job = jobs.active(NEUMESH_OT_apply_paint.bl_label)
        if job is not None and job.running:
            col.label(text=f"Applying {100 * job.fraction:.0f}% (Esc cancels)", icon="SORTTIME")
            return
        wrapped_label(col, "Paint here, then apply the paint to the fields in view", width, context=context)
        _draw_actions(col, img)
        if applied(img) and not paint_pending(img):
            wrapped_label(col, "Applied; paint more to apply again", width, icon="CHECKMARK", context=context)
        wrapped_label(col, "Keep the camera and render size as they are", width, icon="INFO", context=context)


def draw_image_header(self, context):
    """Appended to the Image Editor's header: Apply / Cancel while it shows the paint image."""
    img = _paint_space_image(context)
    if img is not None:
        _draw_actions(self.layout, img, header=True)


classes = (NEUMESH_OT_paint_view, NEUMESH_OT_apply_paint, NEUMESH_OT_cancel_paint, NEUMESH_PT_paint,
           NEUMESH_PT_paint_image)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()
    bpy.types.IMAGE_HT_header.append(draw_image_header)


def unregister():
    bpy.types.IMAGE_HT_header.remove(draw_image_header)
    _unregister_classes()
