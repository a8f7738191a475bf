"""Fill's redo panel, the viewport's redraw after an edit and Ctrl+Z, with real X input:
driven by test_real_blender_redo.py after real_blender_ui.py's ``setup`` step made OUT_DIR/ui.blend:

``blender OUT_DIR/ui.blend --python real_blender_xdo.py -- xdo OUT_DIR``   (no --enable-event-simulate:
with it Blender drops the window system's events, xdotool's included)

Every input is a real X event that ``xdotool`` sends through the XTEST extension (pointer moves, button
clicks, key presses), the way a mouse and keyboard do; Blender reads them from its event loop, so each
``xdotool`` runs as a child process while this script's timer returns.  From timers:

1. the object gets a UV map and two vertex groups, the Fill panel its settings; the sidebar shows the
   *Edit field* and *Fill texture* panels only (open); the 3D view renders through the camera.
2. Ctrl+Wheel over the sidebar's tab strip until the NeuMesh tab shows.
3. The *Fill texture* button is located on screen: two screenshots, the second with the button drawn
   in alert red (the panel's ``draw_edit`` gets a layout whose ``operator("neumesh.fill_texture")`` sits
   in an alert row), their difference is the button.  A click on its centre starts Fill (invoke ->
   modal job -> commit).  Once committed, the viewport must draw an image of the new field within a
   second, the pointer not moved: the engine's drawn texture serial passes the serial it had at the
   commit while its items show the new file (counters, not pixels).
4. The *Adjust Last Operation* panel (the 3D view's HUD region): its last widget row is Scale (Fill
   has no ``draw``: its properties in order, Scale last), found in a screenshot of the region by the
   widget colour.  A click on the field, Ctrl+A, "3", Return: Blender's redo undoes Fill and runs its
   ``execute`` with Scale 3 (recorded), a new file, drawn in the viewport within a second.
5. Ctrl+Z: the object shows the file from before Fill again, drawn within a second.
The facts (NEUMESH_FACTS) and the screenshots (OUT_DIR/*.png) go back to the test.

Two more modes on the same OUT_DIR/ui.blend: ``swap`` (the refused swap preview, test_real_blender_redo.py)
and ``sculpt`` (a measurement for docs/addon.md: seconds to the preview's finest level in
Object Mode and after a real Grab stroke in Sculpt Mode; run by hand as the test runs ``xdo``).
"""
import os
import subprocess
import sys
import time
import traceback

import bpy
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import addon_module, facts, overridden, preview_done, script_args, viewport_engines  # noqa: E402

ARGS = script_args()
TOP_PANELS = ("NEUMESH_PT_data", "NEUMESH_PT_scaffold", "NEUMESH_PT_train", "NEUMESH_PT_field")
HIDDEN_EDIT = ("NEUMESH_PT_swap", "NEUMESH_PT_paint", "NEUMESH_PT_semantics")
SHOWN = ("NEUMESH_PT_edit", "NEUMESH_PT_fill")
FILL = "neumesh.fill_texture"


def read_png(path):
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB"), np.int16)


def changed_box(a, b, level=24):
    """(x0, y0, x1, y1) of the pixels that differ between two screenshots (top-left origin), or None."""
    ys, xs = np.nonzero(np.abs(a - b).max(-1) > level)
    if len(xs) < 20:
        return None
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def widget_rows(img, x0, x1, background):
    """Vertical extents (top, bottom) of the rows of widgets in img[:, x0:x1]: runs of lines where many
    pixels differ from the panel background colour."""
    strip = img[:, x0:x1]
    busy = (np.abs(strip - background).max(-1) > 3).mean(1) > 0.5
    rows, start = [], None
    for y, b in enumerate(list(busy) + [False]):
        if b and start is None:
            start = y
        elif not b and start is not None:
            if y - start >= 12:
                rows.append((start, y))
            start = None
    return rows


class _AlertFill:
    """The layout handed to the Fill panel's ``draw_edit`` while the button is being located: the same
    layout, except that the *Fill texture* button sits in a row drawn in alert red."""

    def __init__(self, layout):
        self._layout = layout

    def __getattr__(self, name):
        return getattr(self._layout, name)

    def operator(self, idname, **kw):
        if idname != FILL:
            return self._layout.operator(idname, **kw)
        row = self._layout.row()
        row.alert = True
        return row.operator(idname, **kw)


class Driver:
    def __init__(self, out_dir):
        self.out = out_dir
        self.t0 = time.time()
        self.state, self.state_t = "start", time.time()
        self.f = {"errors": [], "xdotool": []}
        self.drawn = {}
        self.mark = False
        self.proc = None
        self.win_id = None
        self.tries = 0
        self.shown = SHOWN

    # ---------------------------------------------------------------- helpers
    def goto(self, s):
        self.state, self.state_t = s, time.time()
        self.tries = 0
        print(f"NEUMESH_STATE {s} at {time.time() - self.t0:.1f} s", flush=True)

    def view3d(self):
        win = bpy.context.window_manager.windows[0]
        area = next(a for a in win.screen.areas if a.type == "VIEW_3D")
        regions = {r.type: r for r in area.regions}
        return win, area, regions

    def xdo(self, *args):
        """Send real input: ``xdotool ARGS`` in a child process (Blender reads the events meanwhile)."""
        cmd = ["xdotool"] + [str(a) for a in args]
        self.f["xdotool"].append(" ".join(cmd[1:]))
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def xdo_busy(self):
        if self.proc is None or self.proc.poll() is not None:
            if self.proc is not None and self.proc.returncode != 0:
                self.f["errors"].append("xdotool failed: " + self.proc.stderr.read())
            self.proc = None
            return False
        return True

    def to_x(self, win, bx, by):
        """Blender window coordinates (y up from the bottom) -> X coordinates in the window (y down)."""
        return int(round(bx)), int(round(win.height - 1 - by))

    def pointer_to(self, win, bx, by, *then):
        x, y = self.to_x(win, bx, by)
        self.xdo("mousemove", "--window", self.win_id, x, y, "sleep", "0.2", *then)

    def find_window(self, win):
        out = subprocess.run(["xdotool", "search", "--name", "Blender"], capture_output=True, text=True).stdout
        for wid in out.split():
            g = subprocess.run(["xdotool", "getwindowgeometry", wid], capture_output=True, text=True).stdout
            if f"{win.width}x{win.height}" in g:
                self.f["x_window"] = g.split()
                return wid
        raise RuntimeError(f"no X window of {win.width}x{win.height} named Blender: {out!r}")

    def shot(self, name):
        win, area, _ = self.view3d()
        path = os.path.join(self.out, name)
        with overridden(window=win, area=area):
            bpy.ops.screen.screenshot(filepath=path)
        return path

    def engines(self):
        return viewport_engines()

    def view_state(self):
        """(drawn texture serial, paths the viewport's items show) of the first viewport engine."""
        for e in self.engines():
            ts = getattr(e, "_texture_serial", None)
            items = getattr(e, "_items", None) or []
            return (ts[0] if ts else -1), sorted(str(getattr(i, "path", "")) for i in items)
        return -1, []

    def preview_done(self):
        return preview_done()

    def preview(self):
        return next((e._preview for e in self.engines() if getattr(e, "_preview", None) is not None), None)

    def time_draws(self):
        """Timestamps taken inside Blender's calls, not by this (timer-polled) driver: each run of the
        viewport engine's view_draw (when, how long, the preview serial it asked for, the image it drew,
        the files its items show) and each refresh_viewports() of the edit module (an edit's commit, a
        redo, Ctrl+Z's undo_post)."""
        addon = addon_module()
        cls = addon.render.engine.NeuMeshRenderEngine
        original = cls.view_draw
        draws = self.draws = []
        refreshes = self.refreshes = []

        engine_mod = addon.render.engine

        def view_draw(engine, context, depsgraph):
            t = time.time()
            before = {"key_none": getattr(engine, "_key", 0) is None, "epoch": getattr(engine, "_epoch", None),
                      "field_epoch": engine_mod.FIELD_EPOCH[0], "gen": getattr(engine, "_generation", None)}
            try:
                return original(engine, context, depsgraph)
            finally:
                pv = getattr(engine, "_preview", None)
                ts = getattr(engine, "_texture_serial", None)
                draws.append({"t": t, "s": time.time() - t, "asked": pv._serial if pv else -1,
                              "shown": list(ts) if ts else None,
                              "timings": [list(x) for x in pv.timings] if pv else [],
                              "paths": [os.path.basename(str(getattr(i, "path", ""))) for i in engine._items or []],
                              "before": before, "error": getattr(engine, "_error", ""), "id": id(engine),
                              "message": list(engine_mod.VIEWPORT_MESSAGE.get("lines", []))[:2],
                              "gen": getattr(engine, "_generation", None)})

        cls.view_draw = view_draw
        base = addon.edit.base
        refresh = base.refresh_viewports

        def refresh_viewports(*args, **kw):
            # per engine: Blender may hold more than one viewport engine instance (an old one lives on
            # in the add-on's weak set until collected), each with its own preview serials
            refreshes.append({"t": time.time(), "asked": {id(e): e._preview._serial for e in self.engines()
                                                          if getattr(e, "_preview", None) is not None}})
            return refresh(*args, **kw)

        base.refresh_viewports = refresh_viewports

    def start_watch(self, key, path):
        """The object now shows ``path``: from the last refresh (the commit, redo or undo that changed
        it), the viewport must draw an image of that file without any input."""
        if not self.refreshes:
            raise RuntimeError("the field file changed without refresh_viewports()")
        self.watch = {"key": key, "path": os.path.basename(path), "t": time.time(), "refresh": self.refreshes[-1]}

    def poll_watch(self):
        """True once the viewport drew an image of the watched file asked for after the refresh (or
        10 s passed).  Facts, in seconds from the refresh: ``<key>_asked_s``, when the viewport's
        draw asked for an image of the new file (it was redrawn without input);  ``<key>_drawn_s``, when
        it drew the first one;  ``<key>_render_s``, the preview thread's time for that image (from its
        request);  ``<key>_wait_s``: drawn - asked - render, how long the finished image waited to be
        drawn (the add-on's redraw path)."""
        w = self.watch
        r = w["refresh"]
        after = [d for d in self.draws if d["t"] >= r["t"] and w["path"] in d["paths"]]
        asked = next((d for d in after if d["asked"] > r["asked"].get(d["id"], -1)), None)
        shown = next((d for d in after if d["shown"] and d["shown"][0] > r["asked"].get(d["id"], -1)), None)
        if shown is not None and asked is not None:
            k = w["key"]
            level = dict((int(dv), t) for dv, t in shown["timings"]).get(int(shown["shown"][1]))
            self.f[k + "_asked_s"] = round(asked["t"] + asked["s"] - r["t"], 3)
            self.f[k + "_drawn_s"] = round(shown["t"] + shown["s"] - r["t"], 3)
            self.f[k + "_render_s"] = None if level is None else round(level, 3)
            self.f[k + "_wait_s"] = round(self.f[k + "_drawn_s"] - self.f[k + "_asked_s"] - (level or 0.0), 3)
            self.f[k + "_level"] = shown["shown"][1]
            return True
        if time.time() - w["t"] > 10.0:
            self.f[w["key"] + "_drawn_s"] = None
            self.f[w["key"] + "_draws"] = [dict(d, t=round(d["t"] - r["t"], 3)) for d in self.draws
                                           if d["t"] > r["t"] - 1]
            self.f[w["key"] + "_refresh"] = {str(k): v for k, v in r["asked"].items()}
            self.f[w["key"] + "_refreshes"] = [[round(x["t"] - r["t"], 3), {str(k): v for k, v in x["asked"].items()}]
                                               for x in self.refreshes[-4:]]
            return True
        return False

    # ---------------------------------------------------------------- the steps
    def tick(self):
        try:
            return self._tick()
        except Exception:  # noqa: BLE001
            self.f["errors"].append(f"driver in {self.state}: " + traceback.format_exc())
            self.finish()
            return None

    def _tick(self):
        if time.time() - self.t0 > 360:
            self.f["errors"].append(f"driver: timed out in state {self.state}")
            self.finish()
            return None
        if self.xdo_busy():
            return 0.05
        win, area, regions = self.view3d()
        scene = bpy.context.scene
        obj = bpy.data.objects["blob"]
        step = getattr(self, "step_" + self.state)
        return step(win, area, regions, scene, obj)

    def step_start(self, win, area, regions, scene, obj):
        self.win_id = self.find_window(win)
        self.time_draws()
        scene.render.engine = "NEUMESH"
        self.prepare_object(obj, scene)
        space = area.spaces.active
        space.region_3d.view_perspective = "CAMERA"
        space.shading.type = "RENDERED"
        space.overlay.show_outline_selected = False
        space.overlay.show_extras = False
        space.show_region_ui = True
        self.show_fill_panel()
        self.goto("tabs")
        return 1.0

    def step_tabs(self, win, area, regions, scene, obj):
        if self.drawn.get(self.shown[-1] + "_x"):
            self.goto("render")
            return 0.5
        if self.tries > 16:
            raise RuntimeError("the NeuMesh tab never showed")
        self.tries += 1
        side = regions["UI"]
        # Ctrl+Wheel over the tab strip at the sidebar's right edge turns the tabs
        self.pointer_to(win, side.x + side.width - 8, side.y + 20, "keydown", "ctrl", "click", "5", "keyup", "ctrl")
        return 1.0

    def step_render(self, win, area, regions, scene, obj):
        if not self.preview_done() and time.time() - self.state_t < 60:
            return 0.5
        self.f["first_preview_done"] = self.preview_done()
        self.plain = read_png(self.shot("plain.png"))
        self.mark = True
        regions["UI"].tag_redraw()
        self.goto("locate")
        return 0.5

    def step_locate(self, win, area, regions, scene, obj):
        box = changed_box(self.plain, read_png(self.shot("marked.png")))
        if box is None and self.tries < 10:
            self.tries += 1
            regions["UI"].tag_redraw()
            return 0.5
        self.mark = False
        regions["UI"].tag_redraw()
        if box is None:
            raise RuntimeError("the Fill texture button was not found on screen")
        x0, y0, x1, y1 = box
        self.f["fill_button"] = list(box)
        side = regions["UI"]
        # in the sidebar, and button-sized (one row)
        self.f["fill_button_in_sidebar"] = (side.x <= x0 and x1 <= side.x + side.width
                                            and win.height - (side.y + side.height) <= y0
                                            and y1 <= win.height - side.y)
        self.f["before_path"] = obj.neumesh.field_path
        self.watch_execute()
        cx, cy = (x0 + x1) // 2, (y0 + y1) // 2
        self.xdo("mousemove", "--window", self.win_id, cx, cy, "sleep", "0.3", "click", "1")
        self.goto("edit")
        return 0.2

    def step_edit(self, win, area, regions, scene, obj):
        path = obj.neumesh.field_path
        if path == self.f["before_path"]:
            if time.time() - self.state_t > 120:
                raise RuntimeError("the click on Fill texture changed nothing in 120 s")
            return 0.05
        self.f["after_path"] = path
        self.f["execute_calls_after_click"] = len(self.f["execute_calls"])
        self.f["edit_s"] = round(time.time() - self.state_t, 2)
        self.start_watch("edit", path)
        wm = bpy.context.window_manager
        self.f["last_operator"] = wm.operators[-1].bl_idname if len(wm.operators) else ""
        self.f["files_after_edit"] = self.files()
        self.goto("edit_view")
        return 0.02

    def step_edit_view(self, win, area, regions, scene, obj):
        if not self.poll_watch():
            return 0.02
        self.goto("hud")
        return 0.5

    def step_hud(self, win, area, regions, scene, obj):
        hud = regions.get("HUD")
        if (hud is None or hud.width < 50) and time.time() - self.state_t < 30:
            return 0.5
        if hud is None or hud.width < 50:
            raise RuntimeError("no Adjust Last Operation panel (HUD region) after Fill")
        if hud.height < 60:   # collapsed (Blender remembers it so): a click on its header opens it
            if self.tries > 3:
                raise RuntimeError(f"the redo panel did not open: {[hud.x, hud.y, hud.width, hud.height]}")
            self.tries += 1
            self.f["hud_collapsed"] = [hud.x, hud.y, hud.width, hud.height]
            self.pointer_to(win, hud.x + 30, hud.y + hud.height // 2, "click", "1")
            return 1.0
        img = read_png(self.shot("fill_redo.png"))
        top, left = win.height - (hud.y + hud.height), hud.x
        crop = img[top:top + hud.height, left:left + hud.width]
        self.f["hud"] = [hud.x, hud.y, hud.width, hud.height]
        # the panel's background: the most common colour at its left edge, beside the labels
        band = crop[:, 8:14].reshape(-1, 3)
        vals, counts = np.unique(band, axis=0, return_counts=True)
        rows = widget_rows(crop, hud.width // 2, hud.width - 12, vals[counts.argmax()])
        self.f["hud_rows"] = rows
        if len(rows) < 6:
            raise RuntimeError(f"the redo panel shows {len(rows)} widget rows, expected Fill's 6 properties")
        r0, r1 = rows[-1]   # Scale: Fill's last property
        x, y = left + int(hud.width * 0.7), top + (r0 + r1) // 2
        self.f["scale_field"] = [x, y]
        self.execute_calls_before = len(self.f["execute_calls"])
        self.xdo("mousemove", "--window", self.win_id, x, y, "sleep", "0.3", "click", "1", "sleep", "0.3",
                 "key", "ctrl+a", "type", "3")
        self.goto("hud_type")
        return 0.3

    def step_hud_type(self, win, area, regions, scene, obj):
        self.shot("fill_redo_typing.png")
        self.xdo("key", "Return")
        self.goto("redo")
        return 0.05

    def step_redo(self, win, area, regions, scene, obj):
        path = obj.neumesh.field_path
        if path == self.f["after_path"]:
            if time.time() - self.state_t > 120:
                raise RuntimeError("the redo panel's Scale 3 changed nothing in 120 s")
            return 0.05
        self.f["redo_path"] = path
        self.start_watch("redo", path)
        self.f["files_after_redo"] = self.files()
        self.f["selected_after_redo"] = obj.select_get()
        self.f["active_after_redo"] = getattr(bpy.context.view_layer.objects.active, "name", None)
        self.goto("redo_view")
        return 0.02

    def step_redo_view(self, win, area, regions, scene, obj):
        if not self.poll_watch():
            return 0.02
        self.goto("redo_shot")
        return 0.5

    def step_redo_shot(self, win, area, regions, scene, obj):
        if not self.preview_done() and time.time() - self.state_t < 20:
            return 0.5
        self.shot("fill_redone.png")
        hud = regions.get("HUD")
        self.f["hud_after_redo"] = [hud.x, hud.y, hud.width, hud.height] if hud is not None else None
        wm = bpy.context.window_manager
        if len(wm.operators):
            self.f["scale_after_redo"] = wm.operators[-1].properties.scale
        # Ctrl+Z with the pointer over the viewport
        main = regions["WINDOW"]
        self.pointer_to(win, main.x + main.width // 3, main.y + main.height // 2, "key", "ctrl+z")
        self.goto("undo")
        return 0.05

    def step_undo(self, win, area, regions, scene, obj):
        path = obj.neumesh.field_path
        if path == self.f["redo_path"]:
            if time.time() - self.state_t > 30:
                raise RuntimeError("Ctrl+Z changed nothing in 30 s")
            return 0.05
        self.f["undo_path"] = path
        self.start_watch("undo", path)
        self.goto("undo_view")
        return 0.02

    def step_undo_view(self, win, area, regions, scene, obj):
        if not self.poll_watch():
            return 0.02
        self.finish()
        return None

    # ---------------------------------------------------------------- set-up
    def show_fill_panel(self):
        """The sidebar shows *Edit field* and *Fill texture* (``self.shown``) only, open: the panels are registered
        again under new names (Blender keeps a panel's open state by name) without DEFAULT_CLOSED, and
        every NeuMesh panel's draw records that it ran."""
        for name in TOP_PANELS + HIDDEN_EDIT + SHOWN:
            if hasattr(bpy.types, name):
                bpy.utils.unregister_class(getattr(bpy.types, name))
        self.f["shown"] = list(self.shown)
        for name in self.shown:
            cls = getattr(addon_module().edit.base if name == "NEUMESH_PT_edit" else addon_module().edit.swap_fill,
                          name)
            if cls.__name__ != name:
                raise RuntimeError(f"{name} is not in the add-on where it is looked for")
            opts = set(getattr(cls, "bl_options", set())) - {"DEFAULT_CLOSED"}
            attrs = {"bl_idname": name + "_x", "bl_options": opts}
            if getattr(cls, "bl_parent_id", ""):
                attrs["bl_parent_id"] = cls.bl_parent_id + "_x"
            attrs["draw"] = self._counting_draw(cls, name + "_x")
            if name == "NEUMESH_PT_fill":
                attrs["draw_edit"] = self._marking_draw_edit(cls.draw_edit)
            bpy.utils.register_class(type(name + "_x", (cls,), attrs))

    def _counting_draw(self, cls, name):
        # Blender passes as many arguments as draw's code declares: exactly (panel, context)
        def draw(panel, context):
            cls.draw(panel, context)
            self.drawn[name] = self.drawn.get(name, 0) + 1

        return draw

    def _marking_draw_edit(self, original):
        def draw_edit(panel, context, col, ob):
            return original(panel, context, _AlertFill(col) if self.mark else col, ob)

        return draw_edit

    def watch_execute(self):
        """Record each call of Fill's execute (a redo runs it) with its Scale and result."""
        cls = addon_module().edit.swap_fill.NEUMESH_OT_fill_texture
        original = cls.execute
        calls = self.f.setdefault("execute_calls", [])

        def execute(op, context):
            entry = {"scale": op.scale, "active": getattr(context.active_object, "name", None)}
            calls.append(entry)
            try:
                entry["result"] = sorted(original(op, context))
            except Exception:  # noqa: BLE001
                entry["result"] = traceback.format_exc()
                raise
            return set(entry["result"])

        cls.execute = execute

    def files(self):
        """The edited field files in the scene's edits folder (beside ui.blend, ui_neumesh/)."""
        d = addon_module().scene.props.scene_edits_folder()
        return sorted(n for n in os.listdir(d) if ".edit-" in n) if os.path.isdir(d) else []

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
        self.f["drawn"] = self.drawn
        facts(**self.f)
        bpy.context.preferences.view.use_save_prompt = False
        bpy.ops.wm.quit_blender()


class SwapDriver(Driver):
    """In the real window: *Preview alignment* of a swap whose pairs squeeze one cap of the
    blob onto a few vertices of the other (as a careless pick would: the fit check fails).  The Swap
    panel shows the figures and the whole message; the aligned source is drawn as a wireframe; no file
    is written.  The sidebar shows *Edit field* and *Swap texture* only, turned to with real Ctrl+Wheel
    (xdotool); the preview runs from a script call (what is checked is what the panel shows)."""

    def __init__(self, out_dir):
        super().__init__(out_dir)
        self.shown = ("NEUMESH_PT_edit", "NEUMESH_PT_swap")

    def prepare_object(self, obj, scene):
        from helpers import careless_cap_pairs

        careless_cap_pairs(obj)
        s = scene.neumesh_edit
        s.swap_target_group, s.swap_source_group, s.swap_use_pairs = "cap-", "cap+", True
        bpy.context.view_layer.objects.active = obj
        obj.select_set(True)

    def step_render(self, win, area, regions, scene, obj):
        if not self.preview_done() and time.time() - self.state_t < 60:
            return 0.5
        self.f["before_path"] = obj.neumesh.field_path
        self.f["files_before"] = self.files()
        with overridden(window=win, area=area, region=regions["WINDOW"]):
            self.f["preview"] = sorted(bpy.ops.neumesh.swap_preview(target_group="cap-", source_object="",
                                                                    source_group="cap+", use_pairs=True,
                                                                    nonrigid=False))
        p = addon_module().edit.swap_preview.preview_of(obj)
        al = p["alignment"] if p else None
        self.f["ok"] = None if al is None else bool(al.ok)
        self.f["message"] = "" if al is None else al.message
        tag = addon_module().edit.swap_preview.WIRE_TAG
        self.f["wires"] = [ob.name for ob in bpy.data.objects if ob.get(tag)]
        regions["UI"].tag_redraw()
        self.goto("swap_view")
        return 1.0

    def step_swap_view(self, win, area, regions, scene, obj):
        if not self.preview_done() and time.time() - self.state_t < 30:
            return 0.5
        self.f["screenshot"] = self.shot("swap_refused.png")
        side, main = regions["UI"], regions["WINDOW"]
        self.f["sidebar"] = [side.x, side.y, side.width, side.height]
        self.f["viewport"] = [main.x, main.y, main.width, main.height]
        self.f["after_path"] = obj.neumesh.field_path
        self.f["files_after"] = self.files()
        self.finish()
        return None


class SculptDriver(Driver):
    """Measured: seconds from a request to the preview's finest level in Object Mode, then
    in Sculpt Mode after a real Grab stroke (xdotool: button down, eight moves, button up over the
    object), the pointer then left alone.  Facts only (``object_levels``, ``sculpt_levels``: the
    preview's (divisor, seconds since the request) of the image finally drawn; ``sculpt_done_s``:
    seconds from the stroke's end to the finest level drawn)."""

    def __init__(self, out_dir):
        super().__init__(out_dir)
        self.shown = ("NEUMESH_PT_edit",)

    def prepare_object(self, obj, scene):
        bpy.context.view_layer.objects.active = obj
        obj.select_set(True)

    def step_render(self, win, area, regions, scene, obj):
        if not self.preview_done() and time.time() - self.state_t < 120:
            return 0.5
        pv = self.preview()
        self.f["object_done"] = self.preview_done()
        self.f["object_levels"] = [[d, round(t, 3)] for d, t in pv.timings]
        self.f["viewport"] = [regions["WINDOW"].width, regions["WINDOW"].height]
        with overridden(window=win, area=area, region=regions["WINDOW"]):
            bpy.ops.object.mode_set(mode="SCULPT")
            bpy.ops.wm.tool_set_by_id(name="builtin_brush.Grab")
        self.goto("sculpt_idle")
        return 1.0

    def step_sculpt_idle(self, win, area, regions, scene, obj):
        if not self.preview_done() and time.time() - self.state_t < 120:
            return 0.5
        pv = self.preview()
        self.f["sculpt_idle_done"] = self.preview_done()
        self.f["serial_before_stroke"] = pv._serial
        main = regions["WINDOW"]
        from bpy_extras.view3d_utils import location_3d_to_region_2d
        from mathutils import Vector

        # the stroke starts on the object: its vertex nearest the camera-facing centre, projected
        co = np.array([v.co[:] for v in obj.data.vertices])
        centre = obj.matrix_world @ Vector(co[np.argmin(co[:, 1])])   # the camera looks along +y
        p = location_3d_to_region_2d(main, area.spaces.active.region_3d, centre)
        self.f["stroke_start"] = None if p is None else [round(p.x), round(p.y)]
        bx, by = (p.x, p.y) if p is not None else (main.width / 2, main.height / 2)
        x, y = self.to_x(win, main.x + bx, main.y + by)
        moves = []
        for i in range(1, 9):
            moves += ["mousemove", "--window", self.win_id, x + 6 * i, y - 3 * i, "sleep", "0.05"]
        self.xdo("mousemove", "--window", self.win_id, x, y, "sleep", "0.2", "mousedown", "1", "sleep", "0.1",
                 *moves, "mouseup", "1")
        self.goto("stroke")
        return 0.05

    def step_stroke(self, win, area, regions, scene, obj):   # runs once xdotool has finished
        self.stroke_end = time.time()
        pv = self.preview()
        self.f["stroke_requests"] = pv._serial - self.f["serial_before_stroke"]
        self.goto("sculpt_after")
        return 0.1

    def step_sculpt_after(self, win, area, regions, scene, obj):
        if not self.preview_done() and time.time() - self.state_t < 150:
            return 0.2
        pv = self.preview()
        self.f["sculpt_done"] = self.preview_done()
        self.f["sculpt_done_s"] = round(time.time() - self.stroke_end, 2)
        self.f["sculpt_levels"] = [[d, round(t, 3)] for d, t in pv.timings]
        self.f["requests_after_stroke"] = pv._serial - self.f["serial_before_stroke"]
        self.f["mode"] = obj.mode
        self.finish()
        return None


if ARGS and ARGS[0] == "sculpt":
    _driver = SculptDriver(ARGS[1])
    bpy.app.timers.register(_driver.tick, first_interval=1.0)
if ARGS and ARGS[0] == "swap":
    _driver = SwapDriver(ARGS[1])
    bpy.app.timers.register(_driver.tick, first_interval=1.0)
if ARGS and ARGS[0] == "xdo":
    _driver = Driver(ARGS[1])
    bpy.app.timers.register(_driver.tick, first_interval=1.0)
