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
3. ``... -- gui OUT_DIR docs`` (scripts/make_docs_images.py) also takes the documentation's pictures
   (selection outline and camera wires hidden) after window.png: deform.png (a Simple Deform twist on
   the object, the viewport rendering it and the modifier in the Properties editor), edit.png (the
   sidebar's *Edit field* panels, opened, with the panels above them unregistered) and, after
   error.png, prefs.png (the 3D View turned into the Preferences, the add-on's entry expanded).

Every NeuMesh panel's draw() is wrapped to record that it ran and whether it raised.
"""
import os
import sys
import time
import traceback

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import (addon_module, facts, install_addon, overridden, preview_done,  # noqa: E402
                                 register_open_copy, script_args, viewport_engines)

ARGS = script_args()
EDIT_PANELS = ("NEUMESH_PT_edit", "NEUMESH_PT_swap", "NEUMESH_PT_fill", "NEUMESH_PT_paint", "NEUMESH_PT_semantics")
TOP_PANELS = ("NEUMESH_PT_data", "NEUMESH_PT_scaffold", "NEUMESH_PT_train", "NEUMESH_PT_field")


def open_edit_panels():
    """Show the Edit field panels open (they are closed by default). Blender keeps a panel's open or
    closed state by its name once drawn, so the panels are registered again under new names
    (<name>_docs, children pointing at the new parent) without DEFAULT_CLOSED."""
    classes = [getattr(bpy.types, n) for n in EDIT_PANELS]
    for cls in reversed(classes):
        bpy.utils.unregister_class(cls)
    for cls in classes:
        register_open_copy(cls, "_docs")


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
    def __init__(self, out_dir, docs=False):
        self.out_dir = out_dir
        self.docs = docs
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
        if self.state == "prefs":
            return self._tick_error(self.window(), next(a for a in self.window().screen.areas
                                                       if a.type == "PREFERENCES"))
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
                if self.docs:  # the pictures show the render, not the selection outline and camera wires
                    space.overlay.show_outline_selected = False
                    space.overlay.show_extras = False
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
            with overridden(window=win):
                res = bpy.ops.neumesh.check_dependencies()
            self.facts["check_dependencies"] = sorted(res)
            self.goto("shot")
            return 1.0
        if self.state == "shot":
            path = os.path.join(self.out_dir, "window.png")
            with overridden(window=win, area=area):
                bpy.ops.screen.screenshot(filepath=path)
            self.facts.update(screenshot=path, sidebar=[sidebar.x, sidebar.y, sidebar.width, sidebar.height],
                              viewport=[main.x, main.y, main.width, main.height],
                              window=[win.width, win.height], ui_scale=bpy.context.preferences.system.ui_scale)
            self.facts["viewport_errors"] = self.viewport_errors()
            if self.docs:
                self.goto("deform")
                return 0.3
            return self.start_error()
        if self.state == "deform":
            obj = bpy.data.objects["blob"]
            mod = obj.modifiers.new("Twist", "SIMPLE_DEFORM")
            mod.deform_method, mod.deform_axis, mod.angle = "TWIST", "Z", 1.2
            props = next((a for a in win.screen.areas if a.type == "PROPERTIES"), None)
            if props is not None:
                props.spaces.active.context = "MODIFIER"
            self.serial_before = self.preview_serial()
            self.goto("deform_wait")
            return 1.0
        if self.state == "deform_wait":
            # the preview of the deformed object (a newer render than the one before it) is drawn
            new = self.preview_serial() > self.serial_before
            if not (new and self.preview_done()) and time.time() - self.state_t < 90:
                return 0.5
            self.docs_shot("deform.png", win, area)
            self.facts["deform_errors"] = self.viewport_errors()
            props = next((a for a in win.screen.areas if a.type == "PROPERTIES"), None)
            if props is not None:
                self.facts["properties"] = [props.x, props.y, props.width, props.height]
            # the Edit field panels, open, at the top of the sidebar: the panels above them go away
            for name in TOP_PANELS:
                bpy.utils.unregister_class(getattr(bpy.types, name))
            open_edit_panels()
            sidebar.tag_redraw()
            self.goto("edit")
            return 1.0
        if self.state == "edit":
            self.docs_shot("edit.png", win, area)
            return self.start_error()
        return self._tick_error(win, area)

    def docs_shot(self, name, win, area):
        path = os.path.join(self.out_dir, name)
        with overridden(window=win, area=area):
            bpy.ops.screen.screenshot(filepath=path)
        self.facts.setdefault("docs_shots", []).append(name)

    def start_error(self):
        # an error long enough to need several lines: the field file goes missing
        obj = bpy.data.objects["blob"]
        obj.neumesh.field_path = "//a folder that does not exist/with a long name/" + "x" * 40 + ".neumesh"
        self.goto("error")
        return 0.5

    def _tick_error(self, win, area):
        if self.state == "error":
            if not addon_module().render.engine.VIEWPORT_MESSAGE["lines"] and time.time() - self.state_t < 60:
                return 0.5
            path = os.path.join(self.out_dir, "error.png")
            with overridden(window=win, area=area):
                bpy.ops.screen.screenshot(filepath=path)
            self.facts["viewport_message"] = dict(addon_module().render.engine.VIEWPORT_MESSAGE)
            self.facts["error_errors"] = self.viewport_errors()
            if self.docs:
                self.show_preferences(area)
                self.goto("prefs")
                return 1.0
            self.finish()
            return None
        if self.state == "prefs":
            path = os.path.join(self.out_dir, "prefs.png")
            with overridden(window=win, area=area):
                bpy.ops.screen.screenshot(filepath=path)
            self.facts.setdefault("docs_shots", []).append("prefs.png")
            self.finish()
            return None
        return 0.5

    def show_preferences(self, area):
        """The 3D View becomes a Preferences editor showing the add-on's entry, expanded."""
        import addon_utils

        area.type = "PREFERENCES"
        prefs = bpy.context.preferences
        prefs.active_section = "ADDONS" if bpy.app.version < (4, 2, 0) else "EXTENSIONS"
        bpy.context.window_manager.addon_search = "NeuMesh"
        name = addon_module().__name__
        try:  # the Add-ons list draws addon_utils' file-parsed modules: expand the add-on's entry there
            addon_utils.modules(refresh=False)
            addon_utils.module_bl_info(addon_utils.addons_fake_modules[name])["show_expanded"] = True
        except Exception:  # noqa: BLE001 - extensions expand differently; the shot still shows the entry
            traceback.print_exc()

    def preview_done(self):
        """The viewport's NeuMesh preview has drawn its last (finest) pass."""
        return preview_done()

    def preview_serial(self):
        """The newest preview render's serial number (-1 before the first)."""
        return max([e._preview.latest[0] for e in viewport_engines()
                    if getattr(e, "_preview", None) is not None and e._preview.latest is not None] or [-1])

    def viewport_errors(self):
        """The messages the viewport's NeuMesh engines show instead of an image ('' = none)."""
        out = []
        for e in viewport_engines():
            pv = getattr(e, "_preview", None)
            out.append(getattr(e, "_error", "") or (pv.error if pv is not None else ""))
        return out

    def finish(self):
        addon = addon_module()
        st = addon.runtime.prefs._status_cache.get("blas") or {}
        facts(drawn=self.drawn, errors=self.errors, version=list(bpy.app.version),
              train_object=getattr(bpy.context.scene.neumesh.train_object, "name", None),
              speed=addon.runtime.prefs.speed_message(st), sgemm_own=st.get("own"),
              last_render_error=addon.render.engine.LAST_ERROR["message"], **self.facts)
        bpy.context.preferences.view.use_save_prompt = False
        bpy.ops.wm.quit_blender()


if ARGS and ARGS[0] == "setup":
    setup(*ARGS[1:5])
elif ARGS and ARGS[0] == "gui":
    _docs = ARGS[2:3] == ["docs"]
    _driver = Driver(ARGS[1], docs=_docs)
    bpy.app.timers.register(_driver.tick, first_interval=1.0)
