"""Run inside a real `blender -b` by test_real_blender.py (real captures):

    blender -b --factory-startup --python real_blender_capture.py -- ZIP CAPTURE_DIR

Installs the add-on and runs Import Cameras on a COLMAP folder the test wrote (cameras, photos as
backgrounds, "NeuMesh Points" drawn by a Mesh to Points node group, "NeuMesh Box"): the node-group
code differs between Blender 3.x and 4+. Prints JSON facts on a line starting with NEUMESH_FACTS.
"""
import os
import sys

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import addon_module, facts, install_addon, script_args  # noqa: E402

zip_path, capture_dir = script_args()[:2]
module = install_addon(zip_path)
addon = addon_module(module)
res = bpy.ops.neumesh.import_dataset(directory=capture_dir)
coll = bpy.data.collections["NeuMesh Dataset"]
cams = [o for o in coll.objects if o.type == "CAMERA"]
pts = bpy.data.objects.get("NeuMesh Points")
box = bpy.data.objects.get("NeuMesh Box")
dg = bpy.context.evaluated_depsgraph_get()
ev = pts.evaluated_get(dg) if pts is not None else None
facts(result=sorted(res), version=bpy.app.version_string, cameras=len(cams),
      backgrounds=sum(len(c.data.background_images) for c in cams),
      points=len(pts.data.vertices) if pts else 0,
      colour=pts.data.color_attributes[0].name if pts and len(pts.data.color_attributes) else None,
      modifiers=[m.type for m in pts.modifiers] if pts else [],
      node_inputs=[s.name for s in pts.modifiers[0].node_group.nodes["Mesh to Points"].inputs]
      if pts and pts.modifiers else [],
      evaluated_type=type(ev.data).__name__ if ev is not None and ev.data is not None else None,
      box=[list(box.location), list(box.scale)] if box else None)
