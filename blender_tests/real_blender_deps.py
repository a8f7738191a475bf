"""Run inside a real `blender -b` by test_real_blender.py:

    blender -b --factory-startup --python real_blender_deps.py -- ZIP

Installs and enables the add-on, presses 'Check dependencies' (which imports torch and measures its
matrix-multiply rate), prints what the preferences would show, and lets Blender exit normally: the
exit code tells whether Blender survived its exit-time add-on scan after torch was imported.
"""
import os
import sys

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import addon_module, facts, install_addon, script_args  # noqa: E402

module = install_addon(script_args()[0])
res = bpy.ops.neumesh.check_dependencies()
addon = addon_module(module)
st = addon.runtime.prefs._status_cache["blas"]
facts(result=sorted(res), version=list(bpy.app.version), sgemm=st["sgemm"], own=st["own"],
      gflops=st["gflops"], remedy=st["remedy"], rebound=len(st["rebind"]["rebound"]),
      foreign=st["rebind"]["foreign"], rebind_error=st["rebind"]["error"],
      torch_lib=addon.runtime.blas.torch_cpu_library(),
      message=addon.runtime.prefs.speed_message(st), missing=addon.runtime.deps.missing_required())
