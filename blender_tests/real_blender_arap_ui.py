"""ARAP deform as a person drives it, in a real `blender` window under Xvfb, run by
test_real_blender_ui.py in two steps:

1. ``blender -b --factory-startup --python real_blender_arap_ui.py -- setup ZIP OUT_DIR``: installs the
   add-on, makes a bar mesh with 'Anchor' (left end) and 'Handle' (right end) groups, presses *Add ARAP
   deform*, makes the handle Empty the only selected, active object and saves OUT_DIR/arap_ui.blend.
2. ``blender OUT_DIR/arap_ui.blend --enable-event-simulate --python real_blender_arap_ui.py -- gui OUT``:
   over the 3D View, real key presses: G, a mouse move, a click (the Empty moves; the viewport path
   solves in the drag thread and a timer writes the shape key), then Ctrl+Z (the move is undone: the
   Empty and the 'NeuMesh ARAP' shape key exactly as before the drag), then Ctrl+Shift+Z (the move is
   back, the shape key solved for it). Prints NEUMESH_FACTS with the handle and anchor displacements
   after each step and the shape key's difference from before the drag.
"""
import os
import sys
import time
import traceback

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import addon_module, facts, install_addon, script_args  # noqa: E402

ARGS = script_args()


def setup(zip_path, out_dir):
    install_addon(zip_path)
    import numpy as np
    from helpers import grid_mesh

    os.makedirs(out_dir, exist_ok=True)
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob, do_unlink=True)
    V, F = grid_mesh(16, 4, size=(1.6, 0.4))
    obj = addon_module().scene.sync.new_mesh_object("bar", V, F)
    for name, idx in (("Anchor", np.nonzero(V[:, 0] < -0.6)[0]), ("Handle", np.nonzero(V[:, 0] > 0.6)[0])):
        obj.vertex_groups.new(name=name).add([int(i) for i in idx], 1.0, "REPLACE")
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    res = bpy.ops.neumesh.arap_add()
    empty = bpy.data.objects[obj.neumesh_arap.handle_empties.split("\n")[0]]
    obj.select_set(False)
    empty.select_set(True)
    bpy.context.view_layer.objects.active = empty
    bpy.ops.wm.save_as_mainfile(filepath=os.path.join(out_dir, "arap_ui.blend"))
    facts(arap_add=sorted(res), empty=empty.name)


def _displacements():
    import numpy as np

    obj = bpy.data.objects["bar"]
    dg = bpy.context.evaluated_depsgraph_get()
    me = obj.evaluated_get(dg).data
    W = np.array([tuple(v.co) for v in me.vertices])
    R = np.array([tuple(v.co) for v in obj.data.vertices])
    d = np.linalg.norm(W - R, axis=1)
    return float(d[R[:, 0] > 0.6].min()), float(d[R[:, 0] < -0.6].max())


def _live_key():
    """(N,3) the 'NeuMesh ARAP' shape key as the mesh holds it."""
    import numpy as np

    kb = bpy.data.objects["bar"].data.shape_keys.key_blocks[addon_module().deform.arap.LIVE_KEY]
    arr = np.empty(len(kb.data) * 3, np.float32)
    kb.data.foreach_get("co", arr)
    return arr.reshape(-1, 3)


def _residue(a, b):
    """(vertices that differ, largest displacement) between two (N,3) shape keys."""
    import numpy as np

    d = np.linalg.norm(a.astype(np.float64) - b, axis=1)
    return int((d > 0).sum()), float(d.max())


class Driver:
    def __init__(self):
        self.state, self.t = "start", time.time()
        self.out: dict = {"errors": []}

    def tick(self):
        try:
            return self._tick()
        except Exception:  # noqa: BLE001
            self.out["errors"].append(traceback.format_exc())
            return self.finish()

    def _tick(self):
        win = bpy.context.window_manager.windows[0]
        area = next(a for a in win.screen.areas if a.type == "VIEW_3D")
        main = next(r for r in area.regions if r.type == "WINDOW")
        cx, cy = main.x + main.width // 2, main.y + main.height // 2
        arap = addon_module().deform.arap
        if time.time() - self.t > 120:
            self.out["errors"].append(f"timed out in {self.state}")
            return self.finish()
        if self.state == "start":
            self.key_before = _live_key()
            win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=cx, y=cy)
            win.event_simulate(type="G", value="PRESS", x=cx, y=cy)
            win.event_simulate(type="G", value="RELEASE", x=cx, y=cy)
            self.state = "move"
            return 0.5
        if self.state == "move":
            for i in range(1, 11):
                win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=cx + 15 * i, y=cy + 12 * i)
            self.state = "click"
            return 0.5
        if self.state == "click":
            win.event_simulate(type="LEFTMOUSE", value="PRESS", x=cx + 150, y=cy + 120)
            win.event_simulate(type="LEFTMOUSE", value="RELEASE", x=cx + 150, y=cy + 120)
            self.state, self.t_click = "moved", time.time()
            return 1.0
        if self.state == "moved":
            if arap.TIMINGS.get("bar", {}).get("mode") != "drag" and time.time() - self.t_click < 30:
                return 0.5
            arap.wait_for_drags()
            self.out["timings_after_move"] = dict(arap.TIMINGS.get("bar", {}))
            self.out["moved"] = _displacements()
            self.key_moved = _live_key()
            self.out["key_moved"] = _residue(self.key_moved, self.key_before)
            self.out["empty_moved"] = list(bpy.data.objects[ARGS_EMPTY].matrix_world.translation)
            win.event_simulate(type="Z", value="PRESS", ctrl=True, x=cx, y=cy)
            win.event_simulate(type="Z", value="RELEASE", ctrl=True, x=cx, y=cy)
            self.state, self.t_undo = "undone", time.time()
            return 2.0
        if self.state == "undone":
            arap.wait_for_drags()
            self.out["undone"] = _displacements()
            self.out["key_residue"] = _residue(_live_key(), self.key_before)
            self.out["mode_after_undo"] = arap.TIMINGS.get("bar", {}).get("mode")
            self.out["empty_undone"] = list(bpy.data.objects[ARGS_EMPTY].matrix_world.translation)
            win.event_simulate(type="Z", value="PRESS", ctrl=True, shift=True, x=cx, y=cy)
            win.event_simulate(type="Z", value="RELEASE", ctrl=True, shift=True, x=cx, y=cy)
            self.state = "redone"
            return 2.0
        if self.state == "redone":
            arap.wait_for_drags()
            self.out["redone"] = _displacements()
            self.out["redone_key_vs_moved"] = _residue(_live_key(), self.key_moved)
            self.out["empty_redone"] = list(bpy.data.objects[ARGS_EMPTY].matrix_world.translation)
            obj = bpy.data.objects["bar"]
            s = obj.neumesh_arap
            moved = arap.handle_transforms(obj, s).round(7).tobytes()
            self.out["redone_key_solved_for_empty"] = obj.data.shape_keys.get(arap.SOLVED_FOR) == arap._digest(moved)
            return self.finish()
        return None

    def finish(self):
        facts(**self.out)
        bpy.context.preferences.view.use_save_prompt = False
        bpy.ops.wm.quit_blender()
        return None


ARGS_EMPTY = "bar Handle"
if ARGS and ARGS[0] == "setup":
    setup(*ARGS[1:3])
elif ARGS and ARGS[0] == "gui":
    _driver = Driver()
    bpy.app.timers.register(_driver.tick, first_interval=1.5)
