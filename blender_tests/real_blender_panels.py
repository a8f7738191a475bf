"""The add-on's panels at Blender's default widths, in a real window (driven by
test_real_blender_panels.py after real_blender_ui.py's ``setup`` step made OUT_DIR/ui.blend):

    blender OUT_DIR/ui.blend --enable-event-simulate --python real_blender_panels.py -- panels OUT_DIR DATA

From timers it: chooses NeuMesh as render engine, shows the sidebar's NeuMesh tab, switches the view
to Rendered shading through the scene camera and, while the progressive preview runs and once it is
done, takes the sidebar (sidebar_busy.png, sidebar.png); applies a painting and sets up Texture Paint
and ARAP deform on the field object, then shows the *Edit field* panels open (edit.png, edit_more.png);
selects a camera (edit_no_field.png); the Render properties' NeuMesh panel (render_props.png); the
Preferences window as *Edit > Preferences* opens it, the add-on expanded (prefs.png); the file browsers
of Import Cameras on the capture folder DATA (browser_capture.png) and of Import Mesh (browser_mesh.png),
whose button then imports the mesh as a modal job. Every screenshot is of the default layout and
widths. It prints what it found (NEUMESH_FACTS): the panels drawn and any error, the labels each
NeuMesh panel drew with the width they had, the file browsers' folders and filters, the reports.
"""
import os
import sys
import time
import traceback

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import (addon_module, facts, overridden, preview_done,  # noqa: E402
                                 register_open_copy, script_args)
from real_blender_ui import TOP_PANELS  # noqa: E402

ARGS = script_args()
MORE_PANELS = ("NEUMESH_PT_texture_paint", "NEUMESH_PT_arap")


def edit_children():
    """The panels under *Edit field*, in their order."""
    return [n for n in dir(bpy.types) if n.startswith("NEUMESH_PT") and
            getattr(getattr(bpy.types, n), "bl_parent_id", "") == "NEUMESH_PT_edit"]


_ORIGINAL: dict = {}


def show_open(children):
    """*Edit field* and only the panels ``children`` under it, open (Blender keeps a panel's closed
    state by name once drawn, so they are registered as <name>_open without DEFAULT_CLOSED)."""
    for n in [n for n in dir(bpy.types) if n.startswith("NEUMESH_PT") and n.endswith("_open")]:
        bpy.utils.unregister_class(getattr(bpy.types, n))
    if not _ORIGINAL:
        names = ["NEUMESH_PT_edit"] + edit_children()
        _ORIGINAL.update({n: getattr(bpy.types, n) for n in names})
        for n in reversed(names):
            bpy.utils.unregister_class(_ORIGINAL[n])
    classes = [_ORIGINAL["NEUMESH_PT_edit"]] + [_ORIGINAL[n] for n in children]
    for cls in classes:
        register_open_copy(cls, "_open")


class Driver:
    def __init__(self, out_dir, data_dir):
        self.out, self.data = out_dir, data_dir
        self.f = {"errors": [], "labels": {}, "shots": [], "reports": []}
        self.t0 = time.time()
        self._steps = self.steps()
        self._wrap_panels()

    # ------------------------------------------------------------------ recording
    def _wrap_panels(self):
        drawn = self.f.setdefault("drawn", {})

        def wrapper(name, original):
            def draw(panel, context):
                try:
                    original(panel, context)
                    drawn[name] = drawn.get(name, 0) + 1
                except Exception:  # noqa: BLE001
                    self.f["errors"].append(f"{name}: {traceback.format_exc()}")
                    raise
            return draw

        for name in [n for n in dir(bpy.types) if n.startswith("NEUMESH_PT")]:
            cls = getattr(bpy.types, name)
            cls.draw = wrapper(name, cls.draw)

    def labels_of_text(self):
        """Every label text the add-on's wrapped_label and panels drew, with the width they measured."""
        text = addon_module().runtime.text
        seen = self.f["labels"]
        original = text.wrapped_label

        def wrapped_label(layout, t, width, icon="NONE", context=None):
            lines = text.wrap_text(t, width, text.text_measure(context))
            seen.setdefault(t, {"width": width, "lines": lines})
            return original(layout, t, width, icon=icon, context=context)

        text.wrapped_label = wrapped_label
        for mod in list(sys.modules.values()):   # the modules that imported it by name
            if getattr(mod, "__name__", "").startswith(addon_module().__name__) and \
                    getattr(mod, "wrapped_label", None) is original:
                mod.wrapped_label = wrapped_label

    def window(self):
        return bpy.context.window_manager.windows[0]

    def view3d(self):
        win = self.window()
        area = next(a for a in win.screen.areas if a.type == "VIEW_3D")
        return win, area, next(r for r in area.regions if r.type == "UI")

    def shot(self, name, win=None, area=None):
        path = os.path.join(self.out, name)
        kw = {"window": win or self.window()}
        if area is not None:
            kw["area"] = area
        with overridden(**kw):
            bpy.ops.screen.screenshot(filepath=path)
        self.f["shots"].append(name)

    # ------------------------------------------------------------------ the steps (a generator of delays)
    def tick(self):
        try:
            if time.time() - self.t0 > 420:
                raise TimeoutError("driver timed out")
            return next(self._steps)
        except StopIteration:
            self.finish()
        except Exception:  # noqa: BLE001
            self.f["errors"].append("driver: " + traceback.format_exc())
            self.finish()
        return None

    def steps(self):
        self.labels_of_text()
        win, area, sidebar = self.view3d()
        scene = bpy.context.scene
        scene.render.engine = "NEUMESH"
        area.spaces.active.show_region_ui = True
        yield 0.5
        turns = 0
        while not self.f["drawn"].get("NEUMESH_PT_data") and turns < 16:
            x, y = sidebar.x + sidebar.width - 8, sidebar.y + 20
            win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
            win.event_simulate(type="WHEELDOWNMOUSE", value="PRESS", ctrl=True, x=x, y=y)
            turns += 1
            yield 1.0
        self.shot("sidebar_top.png", win, area)
        # Field & Render at the top (the panels above it away), to see the viewport's pass in it
        for name in TOP_PANELS[:3]:
            bpy.utils.unregister_class(getattr(bpy.types, name))
        space = area.spaces.active
        space.region_3d.view_perspective = "CAMERA"
        space.shading.type = "RENDERED"
        space.overlay.show_outline_selected = False
        t = time.time()
        while not any(k.startswith("Viewport preview: 1/") and "to come" in k for k in self.f["labels"]) \
                and time.time() - t < 60:
            sidebar.tag_redraw()
            yield 0.1
        self.shot("sidebar_busy.png", win, area)
        t = time.time()
        while not preview_done() and time.time() - t < 120:
            yield 0.5
        sidebar.tag_redraw()
        yield 1.0
        self.shot("sidebar.png", win, area)
        self.f["viewport_level"] = [k for k in self.f["labels"] if k.startswith("Viewport preview")]

        # ---- edits: a painting applied, Texture Paint with unsaved texels, ARAP deform
        obj = bpy.data.objects["blob"]
        with overridden(window=win, area=area):
            assert bpy.ops.neumesh.paint_view() == {"FINISHED"}
        paint = addon_module().edit.paint
        img = bpy.data.images[paint.PAINT_IMAGE]
        px = paint._image_pixels(img)
        h, w = px.shape[:2]
        px[h // 2 - 20:h // 2 + 20, w // 2 - 30:w // 2 + 30, :3] = (0.1, 0.9, 0.9)
        paint._set_pixels(img, px)
        with overridden(window=win, area=area):
            self.f["apply"] = sorted(bpy.ops.neumesh.apply_paint())
        self.f["edited"] = obj.neumesh.field_path
        for o in bpy.context.view_layer.objects:
            o.select_set(o == obj)
        bpy.context.view_layer.objects.active = obj
        # paint in Texture Paint: the field gets a paint layer, the image some unsaved texels
        with overridden(window=win, area=area):
            self.f["texture_paint"] = sorted(bpy.ops.neumesh.texture_paint(resolution=256))
        tp = addon_module().edit.texture_paint
        timg = tp.paint_image(obj)
        import numpy as np

        tpx = np.empty(len(timg.pixels), np.float32)
        timg.pixels.foreach_get(tpx)
        tpx = tpx.reshape(timg.size[1], timg.size[0], 4)
        tpx[40:120, 40:200, :3] = (0.9, 0.2, 0.1)
        timg.pixels.foreach_set(tpx.ravel())
        timg.update()
        tp.sync_object(obj, force=True)
        with overridden(window=win, area=area):
            bpy.ops.object.mode_set(mode="OBJECT")
        # ARAP: an anchor group and a handle group
        co = np.array([v.co[:] for v in obj.data.vertices])
        for name, idx in (("Anchor", np.nonzero(co[:, 2] < -0.2)[0]), ("Handle top", np.nonzero(co[:, 2] > 0.3)[0])):
            g = obj.vertex_groups.get(name) or obj.vertex_groups.new(name=name)
            g.add(idx.tolist(), 1.0, "REPLACE")
        with overridden(window=win, area=area):
            self.f["arap_add"] = sorted(bpy.ops.neumesh.arap_add())
        for o in bpy.context.view_layer.objects:
            o.select_set(o == obj)
        bpy.context.view_layer.objects.active = obj
        space.shading.type = "SOLID"   # the panels, not the render, are what these pictures show
        bpy.utils.unregister_class(getattr(bpy.types, TOP_PANELS[3]))
        show_open(["NEUMESH_PT_paint"])
        sidebar.tag_redraw()
        yield 1.5
        self.shot("edit.png", win, area)
        show_open(list(MORE_PANELS))
        sidebar.tag_redraw()
        yield 1.5
        self.shot("edit_more.png", win, area)
        show_open(["NEUMESH_PT_swap", "NEUMESH_PT_fill"])
        sidebar.tag_redraw()
        yield 1.5
        self.shot("edit_swap.png", win, area)
        # a camera selected: the Edit field panel says what to select
        cam = bpy.context.scene.camera
        for o in bpy.context.view_layer.objects:
            o.select_set(o == cam)
        bpy.context.view_layer.objects.active = cam
        sidebar.tag_redraw()
        yield 1.0
        self.shot("edit_no_field.png", win, area)

        # ---- Render properties > NeuMesh (dither note)
        props = next((a for a in win.screen.areas if a.type == "PROPERTIES"), None)
        if props is not None:
            props.spaces.active.context = "RENDER"
            props.tag_redraw()
            yield 1.0
            self.shot("render_props.png", win, props)
            self.f["properties_width"] = props.width

        # ---- Preferences, as Edit > Preferences opens them
        n_win = len(bpy.context.window_manager.windows)
        with overridden(window=win, area=area):
            bpy.ops.screen.userpref_show(section="ADDONS")
        yield 1.0
        pwin = bpy.context.window_manager.windows[-1] if len(bpy.context.window_manager.windows) > n_win else None
        if pwin is not None:
            import addon_utils

            bpy.context.window_manager.addon_search = "NeuMesh"
            try:
                addon_utils.modules(refresh=False)
                addon_utils.module_bl_info(addon_utils.addons_fake_modules[addon_module().__name__])[
                    "show_expanded"] = True
            except Exception:  # noqa: BLE001
                self.f["errors"].append("prefs: " + traceback.format_exc())
            with overridden(window=win, area=area):
                bpy.ops.neumesh.check_dependencies()
            # two optional packages missing, as on a machine without them: their rows say what for
            prefs = addon_module().runtime.prefs
            statuses = prefs._status_cache["statuses"]
            kept = [(s, s.found, s.error) for s in statuses if s.dist in ("scipy", "scikit-image")]
            for s, _, _ in kept:
                s.found, s.error = False, "not found"
            for a in pwin.screen.areas:
                a.tag_redraw()
            yield 1.5
            self.f["prefs_window"] = [pwin.width, pwin.height]
            self.shot("prefs.png", pwin)
            main = next(a for a in pwin.screen.areas if a.type == "PREFERENCES")
            region = next(r for r in main.regions if r.type == "WINDOW")
            x, y = region.x + region.width // 2, region.y + region.height // 2
            pwin.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
            for _ in range(30):
                pwin.event_simulate(type="WHEELDOWNMOUSE", value="PRESS", x=x, y=y)
            yield 1.0
            self.shot("prefs_bottom.png", pwin)
            for s, found, error in kept:
                s.found, s.error = found, error
            with overridden(window=pwin):
                bpy.ops.wm.window_close()
            yield 0.5

        # ---- file browsers
        bpy.context.scene.neumesh.dataset_path = self.data
        with overridden(window=win, area=area):
            self.f["browse_cameras"] = sorted(bpy.ops.neumesh.import_dataset("INVOKE_DEFAULT", directory=self.data))
        yield 1.5
        fwin, farea = self.browser()
        if farea is not None:
            p = farea.spaces.active.params
            p.directory = self.data.encode() if isinstance(p.directory, bytes) else self.data
            yield 1.0
            self.shot("browser_capture.png", fwin)
            with overridden(window=fwin, area=farea):
                bpy.ops.file.cancel()
            yield 1.0
        with overridden(window=win, area=area):
            self.f["browse_mesh"] = sorted(bpy.ops.neumesh.import_mesh("INVOKE_DEFAULT"))
        yield 1.5
        fwin, farea = self.browser()
        if farea is not None:
            p = farea.spaces.active.params
            d = p.directory.decode() if isinstance(p.directory, bytes) else p.directory
            self.f["mesh_browser"] = {"directory": d, "filter_glob": p.filter_glob, "use_filter": p.use_filter}
            self.shot("browser_mesh.png", fwin)
            p.filename = "mesh.ply"
            self.f["objects_before"] = len(bpy.data.objects)
            region = next(r for r in farea.regions if r.type == "WINDOW")
            with overridden(window=fwin, area=farea, region=region):
                self.f["browser_execute"] = sorted(bpy.ops.file.execute())
            t = time.time()
            while len(bpy.data.objects) == self.f["objects_before"] and time.time() - t < 60:
                yield 0.2
            self.f["objects_after"] = len(bpy.data.objects)
            self.f["imported"] = bpy.context.active_object.name if bpy.context.active_object else None

    def browser(self):
        for w in bpy.context.window_manager.windows:
            for a in w.screen.areas:
                if a.type == "FILE_BROWSER":
                    return w, a
        self.f["errors"].append("no file browser opened")
        return None, None

    def finish(self):
        self.f["version"] = list(bpy.app.version)
        facts(**self.f)
        bpy.context.preferences.view.use_save_prompt = False
        bpy.ops.wm.quit_blender()


if ARGS and ARGS[0] == "panels":
    _driver = Driver(ARGS[1], ARGS[2])
    bpy.app.timers.register(_driver.tick, first_interval=1.0)
