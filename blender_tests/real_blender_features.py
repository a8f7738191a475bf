"""Run inside a real `blender -b` by test_real_blender.py (Semantics and Bake out of the box):

    blender -b --factory-startup --python real_blender_features.py -- ZIP OUT_DIR

Installs the add-on, makes a tiny dataset and an untrained field with the core, and runs Distill
semantics, Select by click and Bake to material. Where Blender's Python lacks a feature's packages the
operator must refuse before any job starts, naming them; where it has them the operator must work.
Prints JSON facts on a line starting with NEUMESH_FACTS.
"""
import os
import sys

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import addon_module, facts, install_addon, script_args  # noqa: E402

zip_path, out_dir = script_args()[:2]
os.makedirs(out_dir, exist_ok=True)
module = install_addon(zip_path)
addon = addon_module(module)
nm = addon.runtime.core.get()
data = os.path.join(out_dir, "data")
nm.make_default_scene(data, resolution=16, n_train=2, n_val=1, n_test=1, mesh_subdiv=2)
field_path = os.path.join(out_dir, "f.neumesh")
nm.save_field(nm.create_field(nm.load_mesh(os.path.join(data, "mesh.ply"))), field_path)
for ob in list(bpy.data.objects):
    bpy.data.objects.remove(ob, do_unlink=True)
bpy.ops.neumesh.load_field(filepath=field_path, new_object=True)
obj = bpy.context.active_object
bpy.context.scene.neumesh.dataset_path = data
bpy.context.scene.neumesh.edits_dir = os.path.join(out_dir, "edits")   # the file is never saved
out = {"version": list(bpy.app.version),
       "missing": {f: addon.runtime.deps.missing_for(f) for f in ("semantics", "select", "bake")}}


def run(name, fn):
    try:
        out[name] = sorted(fn())
    except Exception as exc:  # noqa: BLE001 - the refusal is a RuntimeError with the report's text
        out[name] = f"{type(exc).__name__}: {exc}"


run("distill", lambda: bpy.ops.neumesh.distill_semantics(wait=True, steps=2, max_views=2, rays_per_view=32))
job = addon.semantics.distill.current_job()
out["distill_job"] = None if job is None else [job.state, job.message]
run("bake", lambda: bpy.ops.neumesh.bake_material(resolution=64, views=4, view_size=64))
out["baked"] = [o.name for o in bpy.data.objects if o.name.endswith("_baked")]
facts(**out)
