"""The NEUMESH render engine: F12 / `blender -b -a` renders and a progressive rendered viewport."""
from __future__ import annotations

import time
import weakref

import bpy
from ..runtime._np import np
from ..runtime import settings, text
from ..scene import camera
from . import colour, field_cache, frame
from .preview import PreviewRenderer, same_items

LAST_ERROR = {"message": ""}
MOD_PASS = "NeuMesh Mod"   # the render pass of the rendered modification colour
# seconds spent in each phase of the last final render (F12 / -a), for benchmarks and tests
LAST_RENDER: dict = {}
# the last message drawn in a viewport: its wrapped lines, the widest one's right end, the region's width
# and the part of it that the sidebar does not cover (pixels)
VIEWPORT_MESSAGE = {"lines": [], "widest": 0.0, "region_width": 0, "visible_width": 0}
# bumped by refresh_viewports(): a viewport engine whose own count differs collects the fields anew
# (an edit, undo or revert changed which file an object shows, with or without a depsgraph update)
FIELD_EPOCH = [0]


def refresh_viewports(context=None) -> int:
    """After an edit, undo or revert (operator, script call or timer alike): every Rendered viewport
    collects its fields again and renders anew (its render cache is invalidated), and the 3D views'
    WINDOW regions and sidebars of every window are tagged for redraw, so the new image shows without
    moving the mouse. Returns the new epoch.

    Then twice more, 0.25 s and 1 s later, each viewport collects its fields again (without forcing a
    new render: only when what they show changed): a Ctrl+Z pressed while the preview thread renders
    could leave the first draw after the undo with the objects as they were before Blender restored
    them (seen in 4 of 10 real-window runs: the viewport kept the redone image)."""
    _refresh(True, context)
    for delay in (0.25, 1.0):
        try:   # one closure per delay (a function registered twice is one timer); None: runs once
            bpy.app.timers.register(lambda: _refresh(False), first_interval=delay)
        except Exception:  # noqa: BLE001 - no timers (some background runs): the first refresh stands
            pass
    return FIELD_EPOCH[0]


def _refresh(force: bool, context=None) -> None:
    FIELD_EPOCH[0] += 1
    for e in list(_PollRedraw._engines):
        try:
            if force:
                e._key = None
            e.tag_redraw()
        except ReferenceError:
            pass
    try:
        wm = (context or bpy.context).window_manager
        for win in wm.windows:
            for area in win.screen.areas:
                if area.type != "VIEW_3D":
                    continue
                for region in area.regions:
                    if region.type in ("WINDOW", "UI"):
                        region.tag_redraw()
    except Exception:  # noqa: BLE001 - no window manager in background mode
        pass


class NeuMeshRenderEngine(bpy.types.RenderEngine):
    bl_idname = "NEUMESH"
    bl_label = "NeuMesh"
    bl_use_preview = False
    bl_use_postprocess = True

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._preview = None
        self._items = []
        self._error = ""
        self._generation = 0
        self._key = None
        self._texture = None
        self._texture_serial = None
        self._dirty = False
        self._epoch = FIELD_EPOCH[0]

    def __del__(self):
        pv = getattr(self, "_preview", None)
        if pv is not None:
            pv.stop()

    # ------------------------------------------------------------------ final render (F12, -a)
    def render(self, depsgraph):
        t0 = time.perf_counter()
        scene = depsgraph.scene
        # the size Blender allocated (a scene rendered for another scene's compositor gets that scene's)
        W, H = (int(self.resolution_x), int(self.resolution_y)) if self.resolution_x > 0 else \
            camera.render_size(scene)
        transparent = bool(scene.render.film_transparent)
        LAST_ERROR["message"] = ""
        LAST_RENDER.clear()
        issues = colour.photo_colour_issues(scene)
        if issues:   # the pixels are right, but what Blender shows and saves is tone-mapped
            note = (f"NeuMesh: scene '{scene.name}': {', '.join(issues)}: the field's photo colours come out "
                    "flat with a grey background; Render properties > NeuMesh > Use Photo Colours")
            print(note)
            self.report({"WARNING"}, note)
        try:
            cam = scene.camera
            K, c2w, W, H = camera.camera_K_c2w(cam, scene, depsgraph, W, H)
            col, row, w, h = camera.border_rect(scene, W, H)   # Render Region: only that part
            K = camera.crop_K(K, col, row)
            items = field_cache.collect(depsgraph, for_render=True)
            occluder_z = frame.holdout_z(depsgraph, K, c2w, w, h)
            t1 = time.perf_counter()
            if not items:
                self.report({"WARNING"}, "NeuMesh: no object with a field in the scene (Object properties > "
                                         "NeuMesh field)")
            self.update_stats("NeuMesh", f"rendering {len(items)} field(s) at {w}x{h}")

            def prog(f):
                self.update_progress(float(f))
                return not self.test_break()

            passes = frame.render_passes(items, K, c2w, w, h, transparent, progress=prog,
                                          supersample=scene.neumesh.render_samples, occluder_z=occluder_z,
                                          background_model=scene.neumesh.render_background)
            t2 = time.perf_counter()
        except Exception as exc:  # noqa: BLE001 - reported to the user, no (wrong) image written
            if type(exc).__name__ == "Cancelled":
                return
            msg = prefixed(field_cache.user_message(exc))
            LAST_ERROR["message"] = msg
            print(msg)
            if hasattr(self, "error_set"):
                self.error_set(msg)
            self.report({"ERROR"}, msg)
            return
        pixels = {"Combined": passes.combined, "Depth": passes.z[..., None], MOD_PASS: passes.mod}
        t3 = time.perf_counter()
        result = self.begin_result(0, 0, w, h, layer=depsgraph.view_layer.name)
        how, names = "", []
        for rp in result.layers[0].passes:
            names.append(rp.name)
            img = pixels.get(rp.name)
            if img is not None:   # Blender rows go bottom-up
                flat = np.ascontiguousarray(img[::-1].reshape(-1, img.shape[-1]), dtype=np.float32)
                got = set_pass_pixels(rp, flat)
                how = got if rp.name == "Combined" else how
        t4 = time.perf_counter()
        self.end_result(result)
        t5 = time.perf_counter()
        LAST_RENDER.update(collect_s=t1 - t0, render_s=t2 - t1, colour_s=t3 - t2, handoff_s=t4 - t3,
                           end_result_s=t5 - t4, total_s=t5 - t0, handoff=how, size=(w, h),
                           passes=names, **frame.LAST_TIMINGS)

    def update_render_passes(self, scene=None, renderlayer=None):
        """The passes this engine writes, for the compositor's Render Layers node: Combined (its
        alpha is the node's Alpha output), Depth when View Layer > Passes > Z is on, and the
        modification colour ("NeuMesh Mod")."""
        self.register_pass(scene, renderlayer, "Combined", 4, "RGBA", "COLOR")
        if renderlayer.use_pass_z:
            self.register_pass(scene, renderlayer, "Depth", 1, "Z", "VALUE")
        self.register_pass(scene, renderlayer, MOD_PASS, 3, "RGB", "COLOR")

    # ------------------------------------------------------------------ viewport
    def view_update(self, context, depsgraph):
        """A depsgraph update: collect the fields again; the preview restarts (coarse first) only when
        what they show changed (see same_items)."""
        try:
            items = field_cache.collect(depsgraph, for_render=False)
            error = ""
        except Exception as exc:  # noqa: BLE001 - drawn in the viewport
            items, error = [], field_cache.user_message(exc)
        if error or self._error or not same_items(self._items, items):
            self._generation += 1
        self._items, self._error = items, error

    def _ensure_preview(self):
        if self._preview is None:
            ref = weakref.ref(self)

            def on_image():
                e = ref()
                if e is not None:
                    e._dirty = True

            self._preview = PreviewRenderer(settings.preview_divisors(), on_image=on_image)
            _PollRedraw.add(self)
        return self._preview

    def view_draw(self, context, depsgraph):
        import gpu

        region, rv3d, scene = context.region, context.region_data, depsgraph.scene
        transparent = bool(scene.render.film_transparent)
        if self._error:
            self._draw_message(context, self._error)
            return
        try:
            K, c2w, W, H = camera.viewport_K_c2w(region, rv3d)
        except camera.CameraError as exc:
            self._draw_message(context, str(exc))
            return
        if self._epoch != FIELD_EPOCH[0]:   # an edit/undo/revert since the last draw: the fields anew
            self._epoch = FIELD_EPOCH[0]
            self.view_update(context, depsgraph)
            if self._error:
                self._draw_message(context, self._error)
                return
        pv = self._ensure_preview()
        background = bool(scene.neumesh.render_background)
        key = (self._generation, K.tobytes(), c2w.tobytes(), W, H, transparent, background)
        if key != self._key:
            self._key = key
            pv.request(self._items, K, c2w, W, H, transparent, background)
        latest = pv.latest
        if pv.error:
            self._draw_message(context, pv.error)
            return
        if latest is None:
            return
        serial, _div, rgba = latest
        if self._texture_serial != (serial, _div):
            h, w = rgba.shape[:2]
            flat = np.ascontiguousarray(rgba[::-1], dtype=np.float32).reshape(-1)
            try:   # a buffer is copied in one go (a list of the floats: 0.8 s at 960x540 in blender 3.4)
                buf = gpu.types.Buffer("FLOAT", flat.size, flat)
            except TypeError:
                buf = gpu.types.Buffer("FLOAT", flat.size, flat.tolist())
            self._texture = gpu.types.GPUTexture((w, h), format="RGBA16F", data=buf)
            self._texture_serial = (serial, _div)
        from gpu_extras.presets import draw_texture_2d

        gpu.state.blend_set("ALPHA_PREMULT")
        self.bind_display_space_shader(scene)
        draw_texture_2d(self._texture, (0, 0), region.width, region.height)
        self.unbind_display_space_shader()
        gpu.state.blend_set("NONE")

    def _draw_message(self, context, message):
        """The error in the viewport, "NeuMesh: ..." wrapped to the region's width."""
        try:
            import blf

            scale = text.ui_scale(context)
            px = 13 * scale

            def measure(s):
                return blf.dimensions(0, s)[0]

            if bpy.app.version >= (4, 0, 0):
                blf.size(0, px)
            else:
                blf.size(0, 13, int(72 * scale))
            region = context.region
            width = _visible_width(context)
            lines = text.wrap_text(prefixed(message), max(40.0, width - 24 * scale), measure)
            step = px * 1.4
            max_lines = max(1, int((region.height - 60 * scale) // step))
            if len(lines) > max_lines:
                lines = lines[:max_lines - 1] + [lines[max_lines - 1] + " ..."]
            VIEWPORT_MESSAGE.update(lines=lines, widest=max(measure(x) for x in lines) + 12 * scale,
                                    region_width=region.width, visible_width=width)
            blf.color(0, 1.0, 0.3, 0.3, 1.0)
            y = 12 * scale + step * (len(lines) - 1)
            for line in lines:
                blf.position(0, 12 * scale, y, 0)
                blf.draw(0, line)
                y -= step
        except Exception as exc:  # noqa: BLE001 - drawing must never raise into Blender
            print(f"NeuMesh: cannot draw the viewport message: {exc}")


def set_pass_pixels(render_pass, pixels) -> str:
    """Copy ``pixels`` ((W*H, 4) float32, C-contiguous, bottom row first) into a render pass in one
    memory copy, and say how: ``foreach_set`` takes a buffer (numpy array) and copies it whole, but
    Blender 4+ checks its length against all W*H*4 floats ("flat") and 3.x against the W*H rows
    ("rows"). A Python list of pixels ("list", the fallback) costs ~0.2-0.45 s at 400x400 in 3.4."""
    rect = render_pass.rect
    for how, arr in (("flat", pixels.reshape(-1)), ("rows", pixels)):
        try:
            rect.foreach_set(arr)
            return how
        except (AttributeError, TypeError):
            continue
    render_pass.rect = pixels.tolist()
    return "list"


def _visible_width(context) -> int:
    """Width of the part of the viewport region not covered by the sidebar (with 'Region Overlap' the
    sidebar floats over the region, which then spans the whole area)."""
    region, area = context.region, context.area
    width = region.width
    for r in getattr(area, "regions", ()):
        if r.type == "UI" and r.width > 1 and region.x < r.x < region.x + region.width:
            width = min(width, r.x - region.x)
    return width


def prefixed(message: str) -> str:
    """``message`` with one "NeuMesh: " in front."""
    return message if message.startswith("NeuMesh") else "NeuMesh: " + message


class _PollRedraw:
    """Main-thread timer: redraw viewports whose preview thread produced a new image."""

    _engines: "weakref.WeakSet" = weakref.WeakSet()
    _registered = False

    @classmethod
    def add(cls, engine):
        cls._engines.add(engine)
        if not cls._registered and not bpy.app.background:
            bpy.app.timers.register(cls._tick, first_interval=0.05)
            cls._registered = True

    @classmethod
    def _tick(cls):
        drawn = False
        for e in list(cls._engines):
            try:
                if getattr(e, "_dirty", False):
                    e._dirty = False
                    e.tag_redraw()
                    drawn = True
            except ReferenceError:
                pass
        if drawn:   # the sidebar says which pass the viewport shows (viewport_progress)
            _tag_sidebars()
        if not len(cls._engines):
            cls._registered = False
            return None
        return 0.05


def viewport_progress():
    """The progressive passes of the Rendered viewport (the first with a preview):
    ``PreviewRenderer.progress()`` = (shown divisor, finest divisor, busy, seconds), or None when no
    viewport renders with NeuMesh."""
    for e in list(_PollRedraw._engines):
        try:
            pv = getattr(e, "_preview", None)
        except ReferenceError:
            continue
        if pv is not None:
            return pv.progress()
    return None


def _tag_sidebars() -> None:
    try:
        for win in bpy.context.window_manager.windows:
            for area in win.screen.areas:
                if area.type == "VIEW_3D":
                    for region in area.regions:
                        if region.type == "UI":
                            region.tag_redraw()
    except Exception:  # noqa: BLE001 - no window manager in background mode
        pass


def compatible_panels():
    """Blender's own panels that make sense for this engine (output, colour management, ...)."""
    exclude = {"VIEWLAYER_PT_filter", "VIEWLAYER_PT_layer_passes"}
    out = []
    for name in dir(bpy.types):
        p = getattr(bpy.types, name, None)
        ce = getattr(p, "COMPAT_ENGINES", None)
        if ce is not None and "BLENDER_RENDER" in ce and name not in exclude:
            out.append(p)
    return out


def register():
    bpy.utils.register_class(NeuMeshRenderEngine)
    for p in compatible_panels():
        p.COMPAT_ENGINES.add("NEUMESH")


def unregister():
    for p in compatible_panels():
        p.COMPAT_ENGINES.discard("NEUMESH")
    bpy.utils.unregister_class(NeuMeshRenderEngine)
    field_cache.clear_cache()
