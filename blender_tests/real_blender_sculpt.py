"""Sculpt mode and the Rendered viewport in a real `blender` window, driven by
test_real_blender_ui.py after real_blender_ui.py's setup step made OUT_DIR/ui.blend:

    blender OUT_DIR/ui.blend --enable-event-simulate --python real_blender_sculpt.py -- sculpt OUT_DIR

From timers: NeuMesh engine, Rendered shading through the scene camera, the field object in Sculpt
Mode with the Grab brush; a stroke is dragged across the object with simulated mouse events; then it
counts the engine's view_update calls and preview restarts (generations) after the stroke ended and
waits for the preview's last (finest) level; prints NEUMESH_FACTS and quits.
"""
import os
import sys
import time
import traceback

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import addon_module, facts, overridden, preview_done, script_args, viewport_engines  # noqa: E402

ARGS = script_args()
MODE = ARGS[2] if len(ARGS) > 2 else "SCULPT"   # OBJECT: the same steps in Object Mode, for comparison


class SculptDriver:
    def __init__(self):
        self.t0 = time.time()
        self.state, self.state_t = "start", time.time()
        self.facts = {"errors": []}
        self.updates = 0
        eng = addon_module().render.engine.NeuMeshRenderEngine
        original = eng.view_update

        def view_update(engine, context, depsgraph):
            self.updates += 1
            return original(engine, context, depsgraph)

        eng.view_update = view_update
        self.draws = 0
        original_draw = eng.view_draw

        def view_draw(engine, context, depsgraph):
            self.draws += 1
            return original_draw(engine, context, depsgraph)

        eng.view_draw = view_draw

    def engines(self):
        return viewport_engines()

    def done(self):
        return preview_done()

    def generation(self):
        return max([e._generation for e in self.engines()] or [-1])

    def goto(self, s):
        self.state, self.state_t = s, time.time()

    def tick(self):
        try:
            return self._tick()
        except Exception:  # noqa: BLE001
            self.facts["errors"].append(traceback.format_exc())
            self.finish()
            return None

    def _tick(self):
        if time.time() - self.t0 > 420:
            self.facts["errors"].append(f"timed out in state {self.state}")
            self.finish()
            return None
        win = bpy.context.window_manager.windows[0]
        area = max((a for a in win.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.width * a.height)
        region = next(r for r in area.regions if r.type == "WINDOW")
        if self.state == "start":
            bpy.context.scene.render.engine = "NEUMESH"
            space = area.spaces.active
            space.region_3d.view_perspective = "CAMERA"
            space.shading.type = "RENDERED"
            obj = bpy.data.objects["blob"]
            bpy.context.view_layer.objects.active = obj
            with overridden(window=win, area=area, region=region):
                bpy.ops.object.mode_set(mode=MODE)
                try:
                    bpy.ops.wm.tool_set_by_id(name="builtin_brush.Grab")
                except Exception:  # noqa: BLE001
                    self.facts["errors"].append("no Grab tool: " + traceback.format_exc())
            self.goto("first")
            return 1.0
        if self.state == "first":
            if not self.done() and time.time() - self.state_t < 150:
                return 0.5
            self.facts["first_done"] = self.done()
            self.gen_before = self.generation()
            x, y = region.x + region.width // 2, region.y + region.height // 2
            win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
            win.event_simulate(type="LEFTMOUSE", value="PRESS", x=x, y=y)
            for i in range(1, 9):
                win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x + 4 * i, y=y + 2 * i)
            win.event_simulate(type="LEFTMOUSE", value="RELEASE", x=x + 32, y=y + 16)
            self.goto("stroke")
            return 1.0
        if self.state == "stroke":
            self.facts["stroke_restarts"] = self.generation() - self.gen_before
            self.updates_after, self.gen_after = self.updates, self.generation()
            self.goto("after")
            return 0.5
        if self.state == "after":
            if not self.done() and time.time() - self.state_t < 150:
                return 0.5
            self.facts.update(after_done=self.done(), after_s=round(time.time() - self.state_t, 2),
                              updates_after_stroke=self.updates - self.updates_after,
                              restarts_after_stroke=self.generation() - self.gen_after,
                              mode=bpy.context.object.mode if bpy.context.object else None)
            # 3 s more: updates keep coming in Sculpt Mode?
            self.updates_idle = self.updates
            self.gen_idle = self.generation()
            self.goto("idle")
            return 3.0
        if self.state == "idle":
            self.facts.update(updates_idle=self.updates - self.updates_idle,
                              restarts_idle=self.generation() - self.gen_idle, idle_done=self.done())
            self.finish()
            return None
        return 0.5

    def finish(self):
        self.facts["draws"] = self.draws
        self.facts["engines"] = [dict(latest=None if e._preview is None or e._preview.latest is None
                                      else list(e._preview.latest[:2]), busy=getattr(e._preview, "busy", None),
                                      texture=list(e._texture_serial or []), dirty=e._dirty,
                                      error=e._error or getattr(e._preview, "error", ""),
                                      timings=getattr(e._preview, "timings", None))
                                 for e in self.engines()]
        facts(version=list(bpy.app.version), **self.facts)
        bpy.context.preferences.view.use_save_prompt = False
        bpy.ops.wm.quit_blender()


if ARGS and ARGS[0] == "sculpt":
    _driver = SculptDriver()
    bpy.app.timers.register(_driver.tick, first_interval=1.0)
