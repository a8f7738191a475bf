"""Run inside a real `blender -b` by test_real_blender.py:

    blender -b --factory-startup --python real_blender_composite.py -- ZIP FIELD OUT_DIR

Builds a scene with a field and a Cycles bar partly in front of and partly behind it, runs
"Composite with Scene", renders the two layers separately (image and Depth of each, through a probe
scene's compositor; saved as .npy) and saves OUT_DIR/scene.blend with frames 1..3 step 2 and 32-bit
EXR output, for a second process to render with `blender -b scene.blend -a`.
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

import numpy as np  # noqa: E402
from helpers import add_camera, bar_through_field, cycles_fast, exact_colour_settings, render_pass  # noqa: E402

for ob in list(bpy.data.objects):
    bpy.data.objects.remove(ob, do_unlink=True)
assert bpy.ops.neumesh.load_field(filepath=field_path, new_object=True) == {"FINISHED"}
add_camera((0.0, -4.0, 0.6), lens=35.0)
scene = bpy.context.scene
exact_colour_settings(scene, 64, 48)
bar_through_field()
cycles_fast(scene, samples=4)
result = bpy.ops.neumesh.composite_with_scene()
comp = scene.neumesh.composite_scene
layers = {}
for name, sc in (("cyc", scene), ("fld", comp)):
    layers[name] = render_pass(addon.render.composite, sc, "Image", os.path.join(out_dir, f"{name}.exr"))
    layers["z" + name[0]] = render_pass(addon.render.composite, sc, "Depth",
                                        os.path.join(out_dir, f"z{name}.exr"))[..., 0]
for k, v in layers.items():
    np.save(os.path.join(out_dir, f"{k}.npy"), v)
scene.frame_start, scene.frame_end, scene.frame_step = 1, 3, 2
scene.render.image_settings.file_format = "OPEN_EXR"
scene.render.image_settings.color_depth = "32"
bpy.ops.wm.save_as_mainfile(filepath=os.path.join(out_dir, "scene.blend"))
facts(version=list(bpy.app.version), result=sorted(result), companion=comp.name if comp else "",
      tree="node_tree" if not hasattr(scene, "compositing_node_group") else "compositing_node_group",
      field_path=[o.neumesh.field_path for o in bpy.data.objects if o.type == "MESH" and o.neumesh.field_path])
