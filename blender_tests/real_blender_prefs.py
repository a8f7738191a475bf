"""The install steps of README/docs/addon.md in a real `blender` window, then a shell batch render
while that window stays open: driven by test_real_blender.py.

    blender --python real_blender_prefs.py -- ZIP TORCH_DIR SCENE.blend OUT_DIR [manual]

The Blender runs with the artist's own (empty) preferences, not --factory-startup.  From timers it
does what the buttons do: *Install…* (``preferences.addon_install``) and the tick
(``preferences.addon_enable``); two seconds later *Existing environment* = TORCH_DIR; two seconds
later, this Blender still open, ``blender -b SCENE.blend -E NEUMESH -o OUT_DIR/frame_#### -f 1`` (no
NEUMESH_PYTHONPATH: torch must come from the saved preferences); it prints NEUMESH_FACTS and quits.
With ``manual`` Auto-Save Preferences is off first: nothing may be saved, and the add-on's preferences
must say so.
"""
import os
import subprocess
import sys
import traceback

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import facts, script_args  # noqa: E402

ZIP, TORCH, SCENE, OUT = script_args()[:4]
MANUAL = script_args()[4:5] == ["manual"]
F = {"errors": []}
T = {"t": 0}


def step():
    try:
        prefs = bpy.context.preferences
        if not T["t"]:                  # Install…, then the tick
            if MANUAL:
                prefs.use_preferences_save = False
            F["install"] = sorted(bpy.ops.preferences.addon_install(filepath=ZIP, overwrite=True))
            F["enable"] = sorted(bpy.ops.preferences.addon_enable(module="neumesh"))
            T["t"] = 1
            return 2.0
        mod = sys.modules["neumesh"]
        if T["t"] == 1:                 # then Existing environment
            F["enabled"] = [mod.runtime.persist.LAST["result"], prefs.is_dirty]
            prefs.addons["neumesh"].preferences.env_path = TORCH
            T["t"] = 2
            return 2.0
        F["env_path"] = [mod.runtime.persist.LAST["result"], prefs.is_dirty]
        F["note"] = mod.runtime.persist.unsaved_note()
        env = {k: v for k, v in os.environ.items() if k != "NEUMESH_PYTHONPATH"}
        cmd = [bpy.app.binary_path, "-b", SCENE, "-E", "NEUMESH", "-o", os.path.join(OUT, "frame_####"), "-f", "1"]
        r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=240)
        F["batch_rc"] = r.returncode
        F["batch_log"] = (r.stdout + r.stderr)[-3000:]
        F["frames"] = sorted(n for n in os.listdir(OUT) if n.startswith("frame_"))
    except Exception:  # noqa: BLE001
        F["errors"].append(traceback.format_exc())
    facts(**F)
    bpy.context.preferences.view.use_save_prompt = False
    bpy.ops.wm.quit_blender()
    return None


os.makedirs(OUT, exist_ok=True)
bpy.app.timers.register(step, first_interval=1.0)
