"""Run inside a real `blender -b` (3.4 in CI) by test_real_blender.py's ARAP test:

    blender -b --factory-startup --python real_blender_arap.py -- ZIP FIELD OUT_DIR

Installs the add-on, loads the field as an object, marks its bottom 'Anchor' and top 'Handle', presses
Add ARAP deform, keys the handle Empty (frame 1 rest, frame 2 moved and tilted), saves OUT_DIR/arap.blend
and the evaluated vertices of both frames. Prints JSON facts on a line starting with NEUMESH_FACTS.
"""
import json
import math
import os
import sys

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import install_addon, script_args  # noqa: E402

zip_path, field_path, out_dir = script_args()[:3]
os.makedirs(out_dir, exist_ok=True)
module = install_addon(zip_path)

import numpy as np  # noqa: E402
from helpers import add_camera, exact_colour_settings  # noqa: E402

for ob in list(bpy.data.objects):
    bpy.data.objects.remove(ob, do_unlink=True)
blend = os.path.join(out_dir, "arap.blend")
bpy.ops.wm.save_as_mainfile(filepath=blend)
bpy.ops.neumesh.load_field(filepath=field_path, new_object=True)
obj = bpy.context.active_object
V = np.array([tuple(v.co) for v in obj.data.vertices], np.float32)
z = V[:, 2]
anchors = np.nonzero(z < np.quantile(z, 0.3))[0]
handles = np.nonzero(z > np.quantile(z, 0.8))[0]
for name, idx in (("Anchor", anchors), ("Handle", handles)):
    obj.vertex_groups.new(name=name).add([int(i) for i in idx], 1.0, "REPLACE")
res = bpy.ops.neumesh.arap_add()
empty = bpy.data.objects[obj.neumesh_arap.handle_empties.split("\n")[0]]
empty.keyframe_insert("location", frame=1)
empty.keyframe_insert("rotation_euler", frame=1)
empty.location.x += 0.5
empty.rotation_euler.y = math.radians(35)
empty.keyframe_insert("location", frame=2)
empty.keyframe_insert("rotation_euler", frame=2)
add_camera((0.0, -4.6, 0.8), lens=35.0)
scene = bpy.context.scene
exact_colour_settings(scene, 48, 40, depth="8")
scene.frame_start, scene.frame_end = 1, 2
scene.frame_set(1)
bpy.ops.wm.save_as_mainfile(filepath=blend)
for f in (1, 2):
    scene.frame_set(f)
    dg = bpy.context.evaluated_depsgraph_get()
    me = obj.evaluated_get(dg).data
    np.save(os.path.join(out_dir, f"arap_verts_{f}.npy"), np.array([tuple(v.co) for v in me.vertices], np.float32))
np.save(os.path.join(out_dir, "arap_rest.npy"), V)
np.save(os.path.join(out_dir, "arap_anchors.npy"), anchors)
np.save(os.path.join(out_dir, "arap_handles.npy"), handles)
print("NEUMESH_FACTS " + json.dumps({"version": list(bpy.app.version), "arap_add": sorted(res),
                                     "keys": [k.name for k in obj.data.shape_keys.key_blocks]}))
