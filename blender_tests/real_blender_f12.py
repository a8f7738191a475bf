"""Run inside a real `blender -b` by test_real_blender.py:

    blender -b --factory-startup --python real_blender_f12.py -- ZIP FIELD OUT_DIR

F12 with the add-on preference *CPU threads* at 1, written as a 32-bit EXR, beside the core's own
render of the same frame (the vertices, K and c2w the engine used) in the same process. Prints what
the test checks: the largest difference, how the pixels were handed to Blender, torch's threads
during the render, what the add-on did to Blender's allocator during the render and after it.
"""
import os
import sys

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import addon_module, facts, install_addon, script_args  # noqa: E402

zip_path, field_path, out_dir = script_args()[:3]
os.makedirs(out_dir, exist_ok=True)
module = install_addon(zip_path)
addon = addon_module(module)

import numpy as np  # noqa: E402  (on sys.path once the add-on has added NEUMESH_PYTHONPATH)
from helpers import add_camera, exact_colour_settings, linear_to_srgb, read_exr  # noqa: E402

W, H = 48, 40
for ob in list(bpy.data.objects):
    bpy.data.objects.remove(ob, do_unlink=True)
assert bpy.ops.neumesh.load_field(filepath=field_path, new_object=True) == {"FINISHED"}
cam = add_camera((0.0, -4.6, 0.8), lens=35.0)
scene = bpy.context.scene
scene.render.engine = "NEUMESH"
exact_colour_settings(scene, W, H)
scene.render.image_settings.file_format = "OPEN_EXR"
scene.render.image_settings.color_depth = "32"
scene.render.filepath = os.path.join(out_dir, "f12.exr")
addon.runtime.prefs.get_prefs().torch_threads = 1
bpy.ops.render.render(write_still=True)
phases = dict(addon.render.engine.LAST_RENDER)
got = linear_to_srgb(read_exr(os.path.join(out_dir, "f12.exr"))[..., :3])

nm = addon.runtime.core.get()
dg = bpy.context.evaluated_depsgraph_get()
items = addon.render.field_cache.collect(dg)
K, c2w, _w, _h = addon.scene.camera.camera_K_c2w(cam, scene, dg)
field = nm.load_field(field_path)
field.set_vertices(items[0].vertices)
ref = nm.render_camera(field, K, c2w, W, H, background=(1.0, 1.0, 1.0))
facts(version=list(bpy.app.version), handoff=phases.get("handoff"), torch_threads=phases.get("torch_threads"),
      max_diff=float(np.abs(got - ref.rgb).max()), ref_std=float(ref.rgb.std()),
      jemalloc=addon.runtime.malloc.available(), malloc=addon.runtime.malloc.report(),
      decay_now=addon.runtime.malloc.decay_times(), error=addon.render.engine.LAST_ERROR["message"])
