"""The add-on as a person sees it: a real `blender` window (in a virtual X display), driven by
test_real_blender_ui.py in two steps.

1. ``blender -b --factory-startup --python real_blender_ui.py -- setup ZIP FIELD DATASET OUT_DIR``
   installs the add-on (user preferences saved), imports the dataset's cameras, loads the field onto
   a new object, points the camera at it and saves OUT_DIR/ui.blend. The render engine stays
   Blender's default, with its default view transform.
2. ``blender OUT_DIR/ui.blend --enable-event-simulate --python real_blender_ui.py -- gui OUT_DIR``
   opens the file in a window. From timers it: chooses NeuMesh as render engine the way the
   interface does (the colour management must follow), shows the 3D View's sidebar and turns its
   tabs with simulated Ctrl+Wheel until the NeuMesh panels draw, switches the view to Rendered
   shading through the scene camera, presses 'Check dependencies', saves OUT_DIR/window.png with
   Blender's own screenshot operator, prints what it found (NEUMESH_FACTS) and quits.

Every NeuMesh panel's draw() is wrapped to record that it ran and whether it raised.
"""
import os
import sys
import time
import traceback

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import addon_module, facts, install_addon, script_args  # noqa: E402

ARGS = script_args()


# ------------------------------------------------------------------------------------------ setup
def setup(zip_path, field_path, dataset, out_dir):
    install_addon(zip_path)
    from helpers import add_camera

    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob, do_unlink=True)
    os.makedirs(out_dir, exist_ok=True)
    blend = os.path.join(out_dir, "ui.blend")
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    assert bpy.ops.neumesh.import_dataset(directory=dataset, background_images=False) == {"FINISHED"}
    assert bpy.ops.neumesh.load_field(filepath=field_path, new_object=True) == {"FINISHED"}
    cam = add_camera((0.0, -3.4, 1.2), lens=35.0, name="view")
    scene = bpy.context.scene
    scene.camera = cam
    scene.render.resolution_x, scene.render.resolution_y = 400, 300
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    facts(setup="ok", engine=scene.render.engine, view_transform=scene.view_settings.view_transform)


# ------------------------------------------------------------------------------------------ window
class Driver:
    def __init__(self, out_dir):
        self.out_dir = out_dir
        self.t0 = time.time()
        self.drawn: dict[str, int] = {}
        self.errors: list[str] = []
        self.facts: dict = {}
        self.wheel_turns = 0
        self.state = "start"
        self.state_t = time.time()
        self._wrap_panels()

    def _wrap_panels(self):
        # Blender passes as many arguments as the function's code declares (co_argcount): the wrapper
        # takes exactly (self, context), so what it wraps comes from a closure, not default arguments
        def wrapper(name, original):
            def draw(panel, context):
                try:
                    original(panel, context)
                    self.drawn[name] = self.drawn.get(name, 0) + 1
                except Exception:  # noqa: BLE001 - recorded, then Blender reports it as usual
                    self.errors.append(f"{name}: {traceback.format_exc()}")
                    raise

            return draw

        for name in [n for n in dir(bpy.types) if n.startswith("NEUMESH_PT")]:
            cls = getattr(bpy.types, name)
            cls.draw = wrapper(name, cls.draw)

    def window(self):
        return bpy.context.window_manager.windows[0]

    def view3d(self):
        win = self.window()
        area = next(a for a in win.screen.areas if a.type == "VIEW_3D")
        return win, area, next(r for r in area.regions if r.type == "UI"), next(r for r in area.regions
                                                                               if r.type == "WINDOW")

    def goto(self, state):
        self.state, self.state_t = state, time.time()

    def tick(self):
        try:
            return self._tick()
        except Exception:  # noqa: BLE001
            self.errors.append("driver: " + traceback.format_exc())
            self.finish()
            return None

    def _tick(self):
        if time.time() - self.t0 > 240:
            self.errors.append(f"driver: timed out in state {self.state}")
            self.finish()
            return None
        win, area, sidebar, main = self.view3d()
        scene = bpy.context.scene
        if self.state == "start":
            self.facts["view_transform_before"] = scene.view_settings.view_transform
            scene.render.engine = "NEUMESH"  # as the Render properties' engine menu does (RNA + msgbus)
            area.spaces.active.show_region_ui = True
            self.goto("engine")
            return 0.5
        if self.state == "engine":
            self.facts["view_transform_after"] = scene.view_settings.view_transform
            self.facts["look_after"] = scene.view_settings.look
            self.goto("tabs")
            return 0.3
        if self.state == "tabs":
            if self.drawn.get("NEUMESH_PT_data"):
                self.facts["wheel_turns"] = self.wheel_turns
                space = area.spaces.active
                space.region_3d.view_perspective = "CAMERA"
                space.shading.type = "RENDERED"
                self.goto("render")
                return 0.5
            if self.wheel_turns > 16:
                self.errors.append("driver: the NeuMesh tab never showed")
                self.finish()
                return None
            # over the tab strip at the sidebar's right edge, below the tabs: Ctrl+Wheel there turns the
            # tabs (over a number field it would change the number instead)
            x, y = sidebar.x + sidebar.width - 8, sidebar.y + 20
            win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
            win.event_simulate(type="WHEELDOWNMOUSE", value="PRESS", ctrl=True, x=x, y=y)
            self.wheel_turns += 1
            return 1.0
        if self.state == "render":
            # wait for the progressive preview's last pass (1/8, 1/4, 1/2 of the viewport)
            if not self.preview_done() and time.time() - self.state_t < 90:
                return 0.5
            self.facts["preview_done"] = self.preview_done()
            with bpy.context.temp_override(window=win):
                res = bpy.ops.neumesh.check_dependencies()
            self.facts["check_dependencies"] = sorted(res)
            self.goto("shot")
            return 1.0
        if self.state == "shot":
            path = os.path.join(self.out_dir, "window.png")
            with bpy.context.temp_override(window=win, area=area):
                bpy.ops.screen.screenshot(filepath=path)
            self.facts.update(screenshot=path, sidebar=[sidebar.x, sidebar.y, sidebar.width, sidebar.height],
                              viewport=[main.x, main.y, main.width, main.height],
                              window=[win.width, win.height], ui_scale=bpy.context.preferences.system.ui_scale)
            self.facts["viewport_errors"] = self.viewport_errors()
            # an error long enough to need several lines: the field file goes missing
            obj = bpy.data.objects["blob"]
            obj.neumesh.field_path = "//a folder that does not exist/with a long name/" + "x" * 40 + ".neumesh"
            self.goto("error")
            return 0.5
        if self.state == "error":
            if not addon_module().engine.VIEWPORT_MESSAGE["lines"] and time.time() - self.state_t < 60:
                return 0.5
            path = os.path.join(self.out_dir, "error.png")
            with bpy.context.temp_override(window=win, area=area):
                bpy.ops.screen.screenshot(filepath=path)
            self.facts["viewport_message"] = dict(addon_module().engine.VIEWPORT_MESSAGE)
            self.facts["error_errors"] = self.viewport_errors()
            self.finish()
            return None
        return 0.5

    def preview_done(self):
        """The viewport's NeuMesh preview has drawn its last (finest) pass."""
        for e in list(addon_module().engine._PollRedraw._engines):
            pv = getattr(e, "_preview", None)
            if pv is None or pv.busy or pv.latest is None or pv.latest[1] != pv.divisors[-1]:
                return False
            if getattr(e, "_texture_serial", None) != pv.latest[:2]:  # drawn, not only rendered
                return False
            return True
        return False

    def viewport_errors(self):
        """The messages the viewport's NeuMesh engines show instead of an image ('' = none)."""
        out = []
        for e in list(addon_module().engine._PollRedraw._engines):
            pv = getattr(e, "_preview", None)
            out.append(getattr(e, "_error", "") or (pv.error if pv is not None else ""))
        return out

    def finish(self):
        addon = addon_module()
        st = addon.prefs._status_cache.get("blas") or {}
        facts(drawn=self.drawn, errors=self.errors, version=list(bpy.app.version),
              train_object=getattr(bpy.context.scene.neumesh.train_object, "name", None),
              speed=addon.prefs.speed_message(st), sgemm_own=st.get("own"),
              last_render_error=addon.engine.LAST_ERROR["message"], **self.facts)
        bpy.context.preferences.view.use_save_prompt = False
        bpy.ops.wm.quit_blender()


if ARGS and ARGS[0] == "setup":
    setup(*ARGS[1:5])
elif ARGS and ARGS[0] == "gui":
    _driver = Driver(ARGS[1])
    bpy.app.timers.register(_driver.tick, first_interval=1.0)
