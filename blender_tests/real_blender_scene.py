"""Run inside a real `blender -b` (any version >= 3.4) by test_real_blender.py:

    blender -b --factory-startup --python real_blender_scene.py -- ZIP FIELD OUT_DIR

Installs the add-on zip the legacy way (extension install on 4.2+), enables it, saves the user
preferences (so a second `blender -b file.blend -E NEUMESH -a` has it enabled), builds a scene whose
field object is bent by a keyed armature (frame 1: rest, frame 2: bent), and saves OUT_DIR/scene.blend.
Prints JSON facts on a line starting with NEUMESH_FACTS.
"""
import json
import os
import sys

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import install_addon, script_args  # noqa: E402

zip_path, field_path, out_dir = script_args()[:3]
os.makedirs(out_dir, exist_ok=True)
module = install_addon(zip_path)

import numpy as np  # noqa: E402  (available once the add-on put NEUMESH_PYTHONPATH on sys.path)
from helpers import add_armature_bend, add_camera, exact_colour_settings  # noqa: E402

# an empty scene
for ob in list(bpy.data.objects):
    bpy.data.objects.remove(ob, do_unlink=True)
blend = os.path.join(out_dir, "scene.blend")
bpy.ops.wm.save_as_mainfile(filepath=blend)  # saved first, so the field path is stored as '//...'
res = bpy.ops.neumesh.load_field(filepath=field_path, new_object=True)
obj = bpy.context.active_object
arm, idx_root, idx_tip = add_armature_bend(obj, split_x=0.25, angle_deg=70.0, frame=(1, 2))
cam = add_camera((0.0, -4.6, 0.8), lens=35.0)
scene = bpy.context.scene
exact_colour_settings(scene, 48, 40, depth="8")
scene.frame_start, scene.frame_end = 1, 2
bpy.ops.wm.save_as_mainfile(filepath=blend)

facts = {"version": list(bpy.app.version), "module": module, "load_field": sorted(res),
         "field_path": obj.neumesh.field_path}
# vertex positions per frame, to say where the image must change
dg = bpy.context.evaluated_depsgraph_get()
for f in (1, 2):
    scene.frame_set(f)
    dg = bpy.context.evaluated_depsgraph_get()
    from importlib import import_module

    sync = import_module(module + ".scene.sync")
    V = sync.evaluated_world_vertices(obj, dg, expected_count=len(obj.data.vertices))
    np.save(os.path.join(out_dir, f"verts_{f}.npy"), V)
np.save(os.path.join(out_dir, "idx_tip.npy"), idx_tip)
print("NEUMESH_FACTS " + json.dumps(facts))
