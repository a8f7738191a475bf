"""Real captures in a real `blender` window (Xvfb), driven by test_real_blender_ui.py:

    blender --factory-startup --enable-event-simulate --python real_blender_capture_ui.py -- ZIP PHOTOS CAPTURE

From timers, as a person would: *Poses from Photos* invoked (modal, progress in the status bar), Esc
pressed while it runs (the job ends CANCELLED, nothing imported); *Import Cameras* of the COLMAP folder
CAPTURE invoked (modal job), then Ctrl+Z pressed and undo / redo of its step (cameras, points and box
gone, then back).
Every NeuMesh panel's draw() is wrapped to record whether it raised. Prints NEUMESH_FACTS and quits.
"""
import os
import sys
import time
import traceback

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import addon_module, facts, install_addon, overridden, script_args  # noqa: E402

ZIP, PHOTOS, CAPTURE = script_args()[:3]


def _objects():
    coll = bpy.data.collections.get("NeuMesh Dataset")
    cams = 0 if coll is None else sum(o.type == "CAMERA" for o in coll.objects)
    return {"cameras": cams, "points": "NeuMesh Points" in bpy.data.objects, "box": "NeuMesh Box" in bpy.data.objects}


class Driver:
    def __init__(self):
        self.state, self.t0, self.state_t = "install", time.time(), time.time()
        self.f = {"errors": [], "drawn": {}, "fractions": []}

    def goto(self, s):
        self.state, self.state_t = s, time.time()

    def ctx(self):
        win = bpy.context.window_manager.windows[0]
        area = next(a for a in win.screen.areas if a.type == "VIEW_3D")
        region = next(r for r in area.regions if r.type == "WINDOW")
        return win, area, region

    def key(self, type, **kw):
        win, area, region = self.ctx()
        x, y = region.x + region.width // 2, region.y + region.height // 2
        win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
        mods = [m for m in ("ctrl", "shift") if kw.get(m)]
        held = {}
        for m in mods:   # modifier keys go down first, as on a keyboard
            win.event_simulate(type=f"LEFT_{m.upper()}", value="PRESS", x=x, y=y, **held)
            held[m] = True
        win.event_simulate(type=type, value="PRESS", x=x, y=y, **kw)
        win.event_simulate(type=type, value="RELEASE", x=x, y=y, **kw)
        for m in reversed(mods):
            held.pop(m)
            win.event_simulate(type=f"LEFT_{m.upper()}", value="RELEASE", x=x, y=y, **held)

    def invoke(self, op, **kw):
        win, area, region = self.ctx()
        with overridden(window=win, area=area, region=region):
            return sorted(op("INVOKE_DEFAULT", **kw))

    def wrap_panels(self):
        def wrapper(name, original):
            def draw(panel, context):
                self.f["drawn"][name] = self.f["drawn"].get(name, 0) + 1
                try:
                    original(panel, context)
                except Exception:  # noqa: BLE001
                    self.f["errors"].append(f"{name}: {traceback.format_exc()}")
            return draw

        for name in [n for n in dir(bpy.types) if n.startswith("NEUMESH_PT")]:
            cls = getattr(bpy.types, name)
            cls.draw = wrapper(name, cls.draw)

    def tick(self):
        try:
            return self._tick()
        except Exception:  # noqa: BLE001
            self.f["errors"].append("driver: " + traceback.format_exc())
            return self.finish()

    def _tick(self):
        if time.time() - self.t0 > 300:
            self.f["errors"].append(f"driver: timed out in state {self.state}")
            return self.finish()
        if self.state == "install":
            install_addon(ZIP)
            self.wrap_panels()
            win, area, region = self.ctx()
            area.spaces[0].show_region_ui = True
            self.f["poses_invoke"] = self.invoke(bpy.ops.neumesh.poses_from_photos, source=PHOTOS,
                                                 camera_model="PINHOLE", num_features=1500)
            self.goto("poses_running")
            return 0.05
        cap = addon_module().train.capture
        job = cap.active_job()
        if self.state == "poses_running":
            if job is not None:
                self.f["fractions"].append(job.fraction)
                self.f["poses_job"] = job
                if job.fraction > 0.02:
                    self.key("ESC")
                    self.goto("poses_cancelled")
            elif time.time() - self.state_t > 5:
                self.f["errors"].append("poses job never ran")
                return self.finish()
            return 0.05
        if self.state == "poses_cancelled":
            if job is not None:
                return 0.1
            pj = self.f.pop("poses_job")
            self.f["poses_state"], self.f["after_cancel"] = pj.state, _objects()
            self.f["import_invoke"] = self.invoke(bpy.ops.neumesh.import_capture, directory=CAPTURE)
            self.goto("importing")
            return 0.2
        if self.state == "importing":
            if job is not None or time.time() - self.state_t < 0.5:
                return 0.1
            self.f["imported"] = _objects()
            self.key("Z", ctrl=True)
            self.goto("undone")
            return 0.5
        if self.state == "undone":
            self.f["after_key_undo"] = _objects()
            # under --enable-event-simulate in Blender 3.4 the simulated Ctrl+Z reaches no keymap (Esc
            # reaches the modal handler): the undo step the import pushed is taken with ed.undo here
            self.f["undo_op"] = self.invoke(bpy.ops.ed.undo) if self.f["after_key_undo"]["cameras"] else None
            self.f["after_undo"] = _objects()
            self.f["redo_op"] = self.invoke(bpy.ops.ed.redo)
            self.goto("redone")
            return 0.5
        if self.state == "redone":
            self.f["after_redo"] = _objects()
            return self.finish()
        return 0.1

    def finish(self):
        self.f.pop("poses_job", None)
        facts(**self.f)
        bpy.context.preferences.view.use_save_prompt = False
        bpy.ops.wm.quit_blender()
        return None


_driver = Driver()
bpy.app.timers.register(_driver.tick, first_interval=1.0)
