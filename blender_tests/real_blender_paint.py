"""Paint on view in a real `blender` window, driven by test_real_blender_ui.py after
real_blender_ui.py's setup step made OUT_DIR/ui.blend:

    blender OUT_DIR/ui.blend --enable-event-simulate --python real_blender_paint.py -- paint OUT_DIR

From timers: NeuMesh as render engine, *Paint on view* pressed in the 3D View (its sidebar's context),
then it records what the window shows: how many windows, the areas of the main window, the Image
Editor with the paint image and whether its sidebar's NeuMesh panel (Apply / Cancel) drew (the tab is
turned with simulated Ctrl+Wheel as real_blender_ui.py does); saves OUT_DIR/paint.png (Blender's
screenshot); presses *Cancel painting* from that Image Editor and records the areas again; prints
NEUMESH_FACTS and quits.
"""
import os
import sys
import time
import traceback

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import addon_module, facts, overridden, script_args  # noqa: E402

ARGS = script_args()


class PaintDriver:
    def __init__(self, out_dir):
        self.out_dir = out_dir
        self.t0 = time.time()
        self.state = "start"
        self.facts = {"errors": []}
        self.drawn = 0
        self.turns = 0
        cls = bpy.types.NEUMESH_PT_paint_image
        original = cls.draw

        def draw(panel, context):
            original(panel, context)
            self.drawn += 1

        cls.draw = draw

    def areas(self):
        win = bpy.context.window_manager.windows[0]
        return win, [a.type for a in win.screen.areas]

    def tick(self):
        try:
            return self._tick()
        except Exception:  # noqa: BLE001
            self.facts["errors"].append(traceback.format_exc())
            self.finish()
            return None

    def _tick(self):
        if time.time() - self.t0 > 200:
            self.facts["errors"].append(f"timed out in state {self.state}")
            self.finish()
            return None
        win, types = self.areas()
        if self.state == "start":
            bpy.context.scene.render.engine = "NEUMESH"
            self.facts.update(windows_before=len(bpy.context.window_manager.windows), areas_before=types)
            area = max((a for a in win.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.width * a.height)
            region = next(r for r in area.regions if r.type == "WINDOW")
            with overridden(window=win, area=area, region=region):
                self.facts["paint_view"] = sorted(bpy.ops.neumesh.paint_view())
            self.state = "tab"
            return 1.0
        ed = next((a for a in win.screen.areas if a.type == "IMAGE_EDITOR"), None)
        if self.state == "tab":
            if ed is None:
                self.facts["errors"].append("no Image Editor in the main window")
                self.finish()
                return None
            side = next(r for r in ed.regions if r.type == "UI")
            if self.drawn or self.turns > 12:
                self.facts.update(windows_after=len(bpy.context.window_manager.windows), areas_after=types,
                                  image=getattr(ed.spaces.active.image, "name", None),
                                  ui_mode=getattr(ed.spaces.active, "ui_mode", ""),
                                  sidebar_width=side.width, panel_drawn=self.drawn, turns=self.turns)
                path = os.path.join(self.out_dir, "paint.png")
                with overridden(window=win, area=ed):
                    bpy.ops.screen.screenshot(filepath=path)
                self.facts["screenshot"] = path
                self.facts["editor"] = [ed.x, ed.y, ed.width, ed.height]
                with overridden(window=win, area=ed):
                    self.facts["cancel"] = sorted(bpy.ops.neumesh.cancel_paint())
                self.state = "cancelled"
                return 1.0
            x, y = side.x + side.width - 8, side.y + 20
            win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
            win.event_simulate(type="WHEELDOWNMOUSE", value="PRESS", ctrl=True, x=x, y=y)
            self.turns += 1
            return 1.0
        if self.state == "cancelled":
            self.facts.update(areas_cancelled=types, images=[i.name for i in bpy.data.images])
            self.finish()
            return None
        return 0.5

    def finish(self):
        facts(version=list(bpy.app.version), **self.facts)
        bpy.context.preferences.view.use_save_prompt = False
        bpy.ops.wm.quit_blender()


if ARGS and ARGS[0] == "paint":
    addon_module()
    _driver = PaintDriver(ARGS[1])
    bpy.app.timers.register(_driver.tick, first_interval=1.0)
