"""Texture Paint of a field in a real `blender` window, driven by test_real_blender_ui.py
after real_blender_ui.py's setup step made OUT_DIR/ui.blend:

    blender OUT_DIR/ui.blend --enable-event-simulate --python real_blender_texture_paint.py -- tpaint OUT_DIR

From timers: NeuMesh engine, Rendered shading through the scene camera; *Texture Paint* on the field
object (Texture Paint mode, the paint image as the canvas, a green brush); a brush stroke is dragged
across the object with simulated mouse events; it waits until the add-on pushed the image into the
field and the viewport's preview shows it (seconds from the stroke's release), then presses Ctrl+Z
(Blender's texture paint undo) and waits until the viewport is back; prints NEUMESH_FACTS and quits.
"""
import os
import sys
import time
import traceback

import bpy
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import addon_module, facts, overridden, preview_done, viewport_engines  # noqa: E402


class TexturePaintDriver:
    def __init__(self):
        self.t0 = time.time()
        self.state, self.state_t = "start", time.time()
        self.facts = {"errors": []}

    def engines(self):
        return viewport_engines()

    def latest(self):
        for e in self.engines():
            pv = getattr(e, "_preview", None)
            if pv is not None and pv.latest is not None and getattr(e, "_texture_serial", None) == pv.latest[:2]:
                return pv.latest
        return None

    def done(self):
        return preview_done()

    def goto(self, s):
        self.state, self.state_t = s, time.time()

    def tick(self):
        try:
            return self._tick()
        except Exception:  # noqa: BLE001
            self.facts["errors"].append(traceback.format_exc())
            self.finish()
            return None

    def _pixels(self):
        img = addon_module().edit.texture_paint.paint_image(bpy.data.objects["blob"])
        px = np.empty(img.size[0] * img.size[1] * 4, np.float32)
        img.pixels.foreach_get(px)
        return px

    def _changed(self, a, b):
        if a is None or b is None or a.shape != b.shape:
            return -1
        return int((np.abs(a - b).max(-1) > 2 / 255).sum())

    def _tick(self):
        if time.time() - self.t0 > 400:
            self.facts["errors"].append(f"timed out in state {self.state}")
            self.finish()
            return None
        tp = addon_module().edit.texture_paint
        win = bpy.context.window_manager.windows[0]
        area = max((a for a in win.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.width * a.height)
        region = next(r for r in area.regions if r.type == "WINDOW")
        if self.state == "start":
            scene = bpy.context.scene
            # a preview of two levels (1/8, 1/4) on this shared machine: each push re-renders the viewport
            prefs = bpy.context.preferences.addons[addon_module().__name__].preferences
            prefs.preview_start, prefs.preview_final = "8", "4"
            scene.render.engine = "NEUMESH"
            space = area.spaces.active
            space.region_3d.view_perspective = "CAMERA"
            space.shading.type = "RENDERED"
            obj = bpy.data.objects["blob"]
            bpy.context.view_layer.objects.active = obj
            obj.select_set(True)
            with overridden(window=win, area=area, region=region):
                self.facts["texture_paint"] = sorted(bpy.ops.neumesh.texture_paint(resolution=1024))
                # the undo step a click on the button pushes (operators called from Python push none)
                bpy.ops.ed.undo_push(message="Texture Paint")
            self.facts["mode"] = obj.mode
            ip = scene.tool_settings.image_paint
            self.facts["canvas"] = ip.canvas.name if ip.canvas else None
            brush = ip.brush
            brush.color = (0.0, 1.0, 0.0)
            brush.strength = 1.0
            try:
                scene.tool_settings.unified_paint_settings.use_unified_color = False
                scene.tool_settings.unified_paint_settings.size = 30
                brush.size = 30
            except Exception:  # noqa: BLE001
                pass
            self.goto("first")
            return 1.0
        if self.state == "first":
            if not self.done() and time.time() - self.state_t < 200:
                return 0.5
            self.facts["first_done"] = self.done()
            self.base = None if self.latest() is None else self.latest()[2].copy()
            self.px0 = self._pixels()
            self.pushes0 = tp.STATS["pushes"]
            x, y = region.x + region.width // 2, region.y + region.height // 2
            win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x - 40, y=y)
            win.event_simulate(type="LEFTMOUSE", value="PRESS", x=x - 40, y=y)
            for i in range(1, 17):
                win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x - 40 + 5 * i, y=y)
            win.event_simulate(type="LEFTMOUSE", value="RELEASE", x=x + 40, y=y)
            win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x + 41, y=y + 1)
            self.stroke_t = time.time()
            # preview requests until the stroke: the first image of a later one shows the pushed paint
            self.pushed_serial = max([e._preview._serial for e in self.engines() if e._preview] or [0])
            self.goto("pushed")
            return 0.05
        if self.state == "pushed":
            if tp.STATS["pushes"] == self.pushes0 and time.time() - self.state_t < 60:
                return 0.05
            self.facts["stroke_to_push_s"] = round(time.time() - self.stroke_t, 3)
            self.facts["texels_pushed"] = tp.STATS["texels"]
            self.facts["image_texels_painted"] = int(
                (np.abs(self._pixels() - self.px0).reshape(-1, 4).max(-1) > 2 / 255).sum())
            self.goto("shown")
            return 0.05
        if self.state == "shown":
            # the first viewport image rendered after the push (any level of the progressive preview)
            pvs = [e._preview for e in self.engines() if e._preview is not None]
            if not any(pv.latest is not None and pv.latest[0] > self.pushed_serial for pv in pvs) and \
                    time.time() - self.state_t < 120:
                return 0.05
            self.facts["stroke_to_first_image_s"] = round(time.time() - self.stroke_t, 3)
            self.goto("final")
            return 0.1
        if self.state == "final":
            if not self.done() and time.time() - self.state_t < 200:
                return 0.2
            self.facts["stroke_to_final_level_s"] = round(time.time() - self.stroke_t, 3)
            self.facts["viewport_changed"] = self._changed(self.latest()[2], self.base)
            self.pushes1 = tp.STATS["pushes"]
            with overridden(window=win, area=area, region=region):
                win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=region.x + 20, y=region.y + 20)
                win.event_simulate(type="Z", value="PRESS", ctrl=True)
                win.event_simulate(type="Z", value="RELEASE", ctrl=True)
            self.undo_t = time.time()
            self.goto("undone")
            return 0.2
        if self.state == "undone":
            img_ok = tp.paint_image(bpy.data.objects["blob"]) is not None
            if not img_ok:          # undone past Texture Paint itself: nothing to compare
                self.facts.update(image_after_undo=False)
                self.finish()
                return None
            back = self._changed(self._pixels().reshape(-1, 4), self.px0.reshape(-1, 4))
            lt = self.latest()
            if (back != 0 or not self.done() or self._changed(lt[2], self.base) != 0) and \
                    time.time() - self.state_t < 120:
                return 0.2
            self.facts.update(image_back=back, image_after_undo=img_ok, undo_pushes=tp.STATS["pushes"] - self.pushes1,
                              viewport_after_undo_changed=self._changed(lt[2], self.base) if lt is not None else -1,
                              undo_to_viewport_s=round(time.time() - self.undo_t, 3))
            self.finish()
            return None
        return 0.5

    def finish(self):
        self.facts["engines"] = [dict(latest=None if e._preview is None or e._preview.latest is None
                                      else list(e._preview.latest[:2]),
                                      error=e._error or getattr(e._preview, "error", ""),
                                      timings=getattr(e._preview, "timings", None)) for e in self.engines()]
        try:
            self.facts["stats"] = dict(addon_module().edit.texture_paint.STATS)
        except Exception:  # noqa: BLE001
            pass
        facts(version=list(bpy.app.version), **self.facts)
        bpy.context.preferences.view.use_save_prompt = False
        bpy.ops.wm.quit_blender()


if "--" in sys.argv and sys.argv[sys.argv.index("--") + 1:][:1] == ["tpaint"]:
    _driver = TexturePaintDriver()
    bpy.app.timers.register(_driver.tick, first_interval=1.0)
