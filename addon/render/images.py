"""Render to images: the scene camera or every imported dataset camera rendered with the core to PNG
files (no render engine involved; the same pixels as F12 with the photo colour settings)."""
from __future__ import annotations

import os

import bpy
from bpy.props import EnumProperty, StringProperty

from ..runtime._np import np
from ..runtime import core
from ..scene import camera
from . import field_cache, frame


def dataset_cameras():
    """The cameras 'Import dataset cameras' made, by name."""
    coll = bpy.data.collections.get(DATASET_COLLECTION)
    if coll is None:
        return []
    return sorted((o for o in coll.objects if o.type == "CAMERA"), key=lambda o: o.name)


DATASET_COLLECTION = "NeuMesh Dataset"


class NEUMESH_OT_render_images(bpy.types.Operator):
    """Render the scene camera or every imported dataset camera with NeuMesh to PNG files"""

    bl_idname = "neumesh.render_images"
    bl_label = "Render to images"

    directory: StringProperty(subtype="DIR_PATH", default="", options={"SKIP_SAVE"},
                              description="Output folder (default: scene setting)")
    cameras: EnumProperty(items=[("SCENE", "Scene setting", ""), ("ACTIVE", "Scene camera", ""),
                                 ("DATASET", "Dataset cameras", "")], default="SCENE", options={"SKIP_SAVE"})
    camera: StringProperty(name="Camera", default="", options={"SKIP_SAVE"},
                           description="Name of one camera object to render (overrides 'cameras')")

    def execute(self, context):
        scene = context.scene
        s = scene.neumesh
        out_dir = bpy.path.abspath(self.directory or s.output_dir)
        mode = s.render_cameras if self.cameras == "SCENE" else self.cameras
        cams = dataset_cameras() if mode == "DATASET" else [scene.camera]
        if self.camera:
            cam = bpy.data.objects.get(self.camera)
            if cam is None or cam.type != "CAMERA":
                self.report({"ERROR"}, f"NeuMesh: no camera object named '{self.camera}'")
                return {"CANCELLED"}
            cams = [cam]
        if not cams or cams[0] is None:
            self.report({"ERROR"}, "NeuMesh: no camera to render (set the scene camera or import a dataset)")
            return {"CANCELLED"}
        transparent = bool(scene.render.film_transparent)
        try:
            nm = core.get()
            os.makedirs(out_dir, exist_ok=True)
            depsgraph = context.evaluated_depsgraph_get()
            items = field_cache.collect(depsgraph, for_render=True)
            wm = context.window_manager
            wm.progress_begin(0, len(cams))
            written = []
            for i, cam in enumerate(cams):
                K, c2w, W, H = camera.camera_K_c2w(cam, scene, depsgraph)
                rgba = frame.render_items(items, K, c2w, W, H, transparent, supersample=s.render_samples,
                                          background_model=s.render_background)
                if transparent:  # PNG wants straight alpha
                    a = rgba[..., 3:4]
                    rgba = np.concatenate([np.where(a > 1e-6, rgba[..., :3] / np.maximum(a, 1e-6), 0), a], -1)
                path = os.path.join(out_dir, bpy.path.clean_name(cam.name) + ".png")
                nm.save_image(path, np.clip(rgba, 0, 1))
                written.append(path)
                wm.progress_update(i + 1)
            wm.progress_end()
        except Exception as exc:  # noqa: BLE001
            msg = str(exc) if isinstance(exc, core.CoreUnavailable) else f"render failed: {exc}"
            self.report({"ERROR"}, f"NeuMesh: {msg}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"NeuMesh: wrote {len(written)} image(s) to {out_dir}")
        return {"FINISHED"}


classes = (NEUMESH_OT_render_images,)


register, unregister = bpy.utils.register_classes_factory(classes)
