"""Run inside a real `blender -b` by test_real_blender.py:

    blender -b --factory-startup --python real_blender_saveas.py -- ZIP FIELD OUT_DIR

Installs the add-on, saves OUT_DIR/first/scene.blend with the field on a new object (so its path is
stored as '//...'), then saves it again with Save As into OUT_DIR/second/deeper/, as a user moving
their work to another folder would. What Blender 3.x hands the save handlers is recorded; the test
opens the second file in a new process and renders it.
"""
import os
import sys

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import facts, install_addon, script_args  # noqa: E402

zip_path, field_path, out_dir = script_args()[:3]
install_addon(zip_path)
from helpers import add_camera, exact_colour_settings  # noqa: E402

seen = []


def record(*args):
    seen.append([a if isinstance(a, (str, type(None))) else type(a).__name__ for a in args])


bpy.app.handlers.save_pre.append(record)
for ob in list(bpy.data.objects):
    bpy.data.objects.remove(ob, do_unlink=True)
first = os.path.join(out_dir, "first", "scene.blend")
second = os.path.join(out_dir, "second", "deeper", "scene.blend")
os.makedirs(os.path.dirname(first), exist_ok=True)
os.makedirs(os.path.dirname(second), exist_ok=True)
bpy.ops.wm.save_as_mainfile(filepath=first)
bpy.ops.neumesh.load_field(filepath=field_path, new_object=True)
obj = bpy.context.active_object
add_camera((0.0, -4.6, 0.8), lens=35.0)
scene = bpy.context.scene
scene.render.engine = "NEUMESH"
exact_colour_settings(scene, 48, 40, depth="8")
bpy.ops.wm.save_as_mainfile(filepath=first)
path_first = obj.neumesh.field_path
bpy.ops.wm.save_as_mainfile(filepath=second)
facts(version=list(bpy.app.version), save_pre_args=seen, path_first=path_first,
      path_after_save_as=obj.neumesh.field_path, first=first, second=second)
