"""Fill's redo panel and the viewport's redraw after an edit, in a real window (issue 47.4), driven by
test_real_blender_redo.py after real_blender_ui.py's ``setup`` step made OUT_DIR/ui.blend:

``blender OUT_DIR/ui.blend --enable-event-simulate --python real_blender_redo.py -- gui OUT_DIR``

From timers: UV map and vertex groups on the object, the Fill panel's settings, a key (F5) bound to
*Fill texture* in the Window keymap, the 3D view Rendered through the camera. Then a simulated F5
press over the viewport starts Fill the way a click on its button does (invoke -> modal job -> undo
step, operator registered for the redo panel); the mouse is not moved again. Once the edit is
committed the viewport's pixels are compared with the image before it, screenshot by screenshot.
Then what the redo panel does when Scale changes (``ED_undo_operator_repeat`` on the last operator:
undo its step, ``execute`` with the new properties) through ``ed.undo_redo``, and the facts printed.
"""
import os
import sys
import time
import traceback

import bpy
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import addon_module, facts, script_args  # noqa: E402

ARGS = script_args()


class Driver:
    def __init__(self, out_dir):
        self.out = out_dir
        self.t0 = time.time()
        self.state, self.state_t = "start", time.time()
        self.f = {"errors": []}
        self.shots = []

    def goto(self, s):
        self.state, self.state_t = s, time.time()

    def view3d(self):
        win = bpy.context.window_manager.windows[0]
        area = next(a for a in win.screen.areas if a.type == "VIEW_3D")
        return win, area, next(r for r in area.regions if r.type == "WINDOW")

    def engines(self):
        return list(addon_module().render.engine._PollRedraw._engines)

    def preview_done(self):
        for e in self.engines():
            pv = getattr(e, "_preview", None)
            if pv is None or pv.busy or pv.latest is None or pv.latest[1] != pv.divisors[-1]:
                return False
            return getattr(e, "_texture_serial", None) == pv.latest[:2]
        return False

    def shot(self, name):
        win, area, main = self.view3d()
        path = os.path.join(self.out, name)
        with bpy.context.temp_override(window=win, area=area):
            bpy.ops.screen.screenshot(filepath=path)
        from PIL import Image  # noqa: F401 - the test decodes; here only the path is kept
        self.shots.append(path)
        return path

    def tick(self):
        try:
            return self._tick()
        except Exception:  # noqa: BLE001
            self.f["errors"].append(f"driver in {self.state}: " + traceback.format_exc())
            self.finish()
            return None

    def _tick(self):
        if time.time() - self.t0 > 300:
            self.f["errors"].append(f"driver: timed out in state {self.state}")
            self.finish()
            return None
        win, area, main = self.view3d()
        scene = bpy.context.scene
        obj = bpy.data.objects["blob"]
        if self.state == "start":
            scene.render.engine = "NEUMESH"
            self.prepare_object(obj, scene)
            space = area.spaces.active
            space.region_3d.view_perspective = "CAMERA"
            space.shading.type = "RENDERED"
            space.overlay.show_outline_selected = False
            space.overlay.show_extras = False
            kc = bpy.context.window_manager.keyconfigs.addon
            km = kc.keymaps.new(name="Window", space_type="EMPTY")
            km.keymap_items.new("neumesh.fill_texture", "F5", "PRESS")
            # set up by a script, as in the issue: no undo step holds these changes (the groups, the
            # UV map, the selection); the redo must still undo to exactly the state Fill started from
            self.goto("render")
            return 0.5
        if self.state == "render":
            if not self.preview_done() and time.time() - self.state_t < 120:
                return 0.5
            self.f["before_path"] = obj.neumesh.field_path
            self.f["before_shot"] = self.shot("before.png")
            x, y = main.x + main.width // 2, main.y + main.height // 2
            win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
            win.event_simulate(type="F5", value="PRESS", x=x, y=y)
            win.event_simulate(type="F5", value="RELEASE", x=x, y=y)
            self.goto("edit")
            return 0.1
        if self.state == "edit":
            path = obj.neumesh.field_path
            if path == self.f["before_path"] and time.time() - self.state_t < 120:
                return 0.1
            self.f["after_path"] = path
            self.f["committed_s"] = time.time() - self.state_t
            self.goto("edit_shot")
            return 1.0   # one second, the mouse not moved
        if self.state == "edit_shot":
            self.f["after_shot"] = self.shot("after_edit.png")
            wm = bpy.context.window_manager
            self.f["last_operator"] = wm.operators[-1].bl_idname if len(wm.operators) else ""
            self.f["selected_before_redo"] = obj.select_get()
            self.edit_files = self.files()
            self.f["files_after_edit"] = self.edit_files
            self.watch_execute()
            self.f["jobs_running"] = {t: bpy.app.is_job_running(t) for t in
                                      ("RENDER", "RENDER_PREVIEW", "OBJECT_BAKE", "COMPOSITE", "SHADER_COMPILATION")}
            if len(wm.operators):
                wm.operators[-1].properties.scale = 3.0
            with bpy.context.temp_override(window=win, area=area, region=main):
                try:
                    self.f["redo"] = sorted(bpy.ops.ed.undo_redo())
                except Exception as exc:  # noqa: BLE001
                    self.f["redo"] = [f"raised: {exc}"]
            self.goto("redo")
            return 0.5
        if self.state == "redo":
            self.f["files_after_redo"] = self.files()
            self.f["redo_path"] = bpy.data.objects["blob"].neumesh.field_path
            self.f["selected_after_redo"] = bpy.data.objects["blob"].select_get()
            self.f["active_after_redo"] = getattr(bpy.context.view_layer.objects.active, "name", None)
            self.goto("redo_shot")
            return 1.0
        if self.state == "redo_shot":
            self.f["redo_shot"] = self.shot("after_redo.png")
            self.finish()
            return None
        return 0.5

    def watch_execute(self):
        """Record each call of Fill's execute (the redo runs it): the file the object shows then, and
        what it returned."""
        cls = addon_module().edit.swap_fill.NEUMESH_OT_fill_texture
        original = cls.execute
        calls = self.f.setdefault("execute_calls", [])

        report = cls.report if "report" in cls.__dict__ else None

        def record_report(op, kind, message):
            calls[-1].setdefault("reports", []).append(message)
            return bpy.types.Operator.report(op, kind, message)

        cls.report = record_report

        def execute(op, context):
            ob = context.active_object
            entry = {"path": getattr(getattr(ob, "neumesh", None), "field_path", None),
                     "active": getattr(ob, "name", None), "scale": op.scale}
            calls.append(entry)
            try:
                entry["result"] = sorted(original(op, context))
            except Exception:  # noqa: BLE001
                entry["result"] = traceback.format_exc()
                raise
            return set(entry["result"])

        cls.execute = execute

    def files(self):
        d = os.path.dirname(bpy.path.abspath(bpy.data.objects["blob"].neumesh.field_path))
        return sorted(n for n in os.listdir(d) if ".edit-" in n)

    def prepare_object(self, obj, scene):
        me = obj.data
        co = np.array([v.co[:] for v in me.vertices])
        uv = me.uv_layers.new(name="Sphere")
        vi = np.empty(len(me.loops), np.int32)
        me.loops.foreach_get("vertex_index", vi)
        c = co - co.mean(0)
        u = (np.arctan2(c[:, 1], c[:, 0]) / (2 * np.pi)) % 1.0
        w = np.arccos(np.clip(c[:, 2] / np.linalg.norm(c, axis=1), -1, 1)) / np.pi
        uv.data.foreach_set("uv", np.stack([u[vi], w[vi]], 1).astype(np.float32).ravel())
        for name, idx in (("region", np.nonzero(c[:, 0] > 0.0)[0]), ("template", np.nonzero(c[:, 0] < 0.0)[0])):
            g = obj.vertex_groups.new(name=name)
            g.add([int(i) for i in idx], 1.0, "REPLACE")
        s = scene.neumesh_edit
        s.fill_target_group, s.fill_target_uv = "region", "Sphere"
        s.fill_template_group, s.fill_template_uv, s.fill_scale = "template", "Sphere", 2.0
        bpy.context.view_layer.objects.active = obj
        obj.select_set(True)

    def finish(self):
        facts(**self.f)
        bpy.context.preferences.view.use_save_prompt = False
        bpy.ops.wm.quit_blender()


if ARGS and ARGS[0] == "gui":
    _driver = Driver(ARGS[1])
    bpy.app.timers.register(_driver.tick, first_interval=1.0)
