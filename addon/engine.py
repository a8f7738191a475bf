"""The NEUMESH render engine: F12 / `blender -b -a` renders and a progressive rendered viewport."""
from __future__ import annotations

import threading
import time
import weakref

import bpy
from ._np import np

from . import camera, core, render, sync

LAST_ERROR = {"message": ""}
MOD_PASS = "NeuMesh Mod"   # the render pass of the rendered modification colour
# seconds spent in each phase of the last final render (F12 / -a), for benchmarks and tests
LAST_RENDER: dict = {}
# the last message drawn in a viewport: its wrapped lines, the widest one's right end, the region's width
# and the part of it that the sidebar does not cover (pixels)
VIEWPORT_MESSAGE = {"lines": [], "widest": 0.0, "region_width": 0, "visible_width": 0}


def _user_message(exc) -> str:
    if isinstance(exc, (sync.TopologyError, camera.CameraError, FileNotFoundError, core.CoreUnavailable)):
        return str(exc)
    types = core.error_types()
    if types and isinstance(exc, types):
        return str(exc)
    return f"{type(exc).__name__}: {exc}"


class PreviewRenderer:
    """Renders a viewport request at increasing resolutions (1/8, 1/4, ...) in a background thread.

    ``request()`` supersedes (cancels) the render in progress. ``latest`` holds (serial, level, rgba)
    where rgba is scene-linear premultiplied (h,w,4) float32. ``on_image`` is called from the thread.

    The first image must come quickly (``first_budget_s``): the renderer remembers the seconds per
    pixel of its last image, and when the first configured level would take longer than the budget it
    starts one or more coarser levels first (halving the resolution, at most 1/``max_divisor``), so a
    camera move or a deformation shows something within the budget on heavy fields and big viewports.
    """

    def __init__(self, divisors=(8, 4, 2), on_image=None, first_budget_s: float = 0.1, max_divisor: int = 32):
        self.divisors = tuple(divisors)
        self.first_budget_s = float(first_budget_s)
        self.max_divisor = int(max_divisor)
        self.seconds_per_pixel = None   # measured on the last image rendered
        self.on_image = on_image
        self._cv = threading.Condition()
        self._pending = None
        self._serial = 0
        self._stop = False
        self.latest = None
        self.error = ""
        self.busy = False
        self.timings: list[tuple[int, float]] = []  # (divisor, seconds since request)
        self._thread = threading.Thread(target=self._loop, name="neumesh-preview", daemon=True)
        self._thread.start()

    def request(self, items, K, c2w, width, height, transparent=False):
        with self._cv:
            self._serial += 1
            self._pending = (self._serial, items, K, c2w, int(width), int(height), bool(transparent),
                             time.perf_counter())
            self._cv.notify_all()
            return self._serial

    def stop(self):
        with self._cv:
            self._stop = True
            self._serial += 1
            self._cv.notify_all()

    def wait(self, serial, divisor=None, timeout=60.0) -> bool:
        """Block until the image of ``serial`` at ``divisor`` (default: the last level) exists."""
        divisor = divisor or self.divisors[-1]
        t_end = time.perf_counter() + timeout
        while time.perf_counter() < t_end:
            lt = self.latest
            if lt is not None and lt[0] >= serial and (lt[0] > serial or lt[1] <= divisor):
                return True
            if self.error and not self.busy:
                return False
            time.sleep(0.002)
        return False

    def levels(self, width: int, height: int) -> tuple:
        """The divisors a request of ``width`` x ``height`` renders, coarsest first."""
        first = self.divisors[0]
        rate = self.seconds_per_pixel
        if rate is None:
            return self.divisors
        d = first
        while d < self.max_divisor and rate * max(1, width // d) * max(1, height // d) > self.first_budget_s:
            d *= 2
        return (d,) + self.divisors if d > first else self.divisors

    def _loop(self):
        while True:
            with self._cv:
                while self._pending is None and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                job, self._pending = self._pending, None
            serial, items, K, c2w, W, H, transparent, t0 = job
            self.busy = True
            self.timings = []
            try:
                for div in self.levels(W, H):
                    w, h = max(1, W // div), max(1, H // div)
                    Ks = render.scale_K(K, W, H, w, h)
                    t_level = time.perf_counter()

                    def prog(_f, serial=serial):
                        return self._serial == serial and not self._stop

                    rgba = render.render_items(items, Ks, c2w, w, h, transparent, progress=prog)
                    if self._serial != serial:
                        break
                    self.seconds_per_pixel = (time.perf_counter() - t_level) / (w * h)
                    self.latest = (serial, div, render.to_scene_linear(rgba, transparent))
                    self.timings.append((div, time.perf_counter() - t0))
                    self.error = ""
                    if self.on_image is not None:
                        self.on_image()
            except Exception as exc:  # noqa: BLE001 - shown in the viewport
                if type(exc).__name__ != "Cancelled":
                    self.error = _user_message(exc)
            finally:
                self.busy = False


def _prefs_divisors():
    from . import prefs

    p = prefs.get_prefs()
    start, final = (8, 2) if p is None else (int(p.preview_start), int(p.preview_final))
    divs = [d for d in (8, 4, 2, 1) if final <= d <= start]
    return tuple(divs or [final])


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
        try:
            cam = scene.camera
            K, c2w, W, H = camera.camera_K_c2w(cam, scene, depsgraph, W, H)
            col, row, w, h = camera.border_rect(scene, W, H)   # Render Region: only that part
            K = camera.crop_K(K, col, row)
            items = render.collect(depsgraph, for_render=True)
            occluder_z = render.holdout_z(depsgraph, K, c2w, w, h)
            t1 = time.perf_counter()
            if not items:
                self.report({"WARNING"}, "NeuMesh: no object with a field in the scene (Object properties > "
                                         "NeuMesh field)")
            self.update_stats("NeuMesh", f"rendering {len(items)} field(s) at {w}x{h}")

            def prog(f):
                self.update_progress(float(f))
                return not self.test_break()

            passes = render.render_passes(items, K, c2w, w, h, transparent, progress=prog,
                                          supersample=scene.neumesh.render_samples, occluder_z=occluder_z)
            t2 = time.perf_counter()
        except Exception as exc:  # noqa: BLE001 - reported to the user, no (wrong) image written
            if type(exc).__name__ == "Cancelled":
                return
            msg = prefixed(_user_message(exc))
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
                           passes=names, **render.LAST_TIMINGS)

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
        try:
            self._items = render.collect(depsgraph, for_render=False)
            self._error = ""
        except Exception as exc:  # noqa: BLE001 - drawn in the viewport
            self._items = []
            self._error = _user_message(exc)
        self._generation += 1

    def _ensure_preview(self):
        if self._preview is None:
            ref = weakref.ref(self)

            def on_image():
                e = ref()
                if e is not None:
                    e._dirty = True

            self._preview = PreviewRenderer(_prefs_divisors(), on_image=on_image)
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
        pv = self._ensure_preview()
        key = (self._generation, K.tobytes(), c2w.tobytes(), W, H, transparent)
        if key != self._key:
            self._key = key
            pv.request(self._items, K, c2w, W, H, transparent)
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

            from . import text

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
        for e in list(cls._engines):
            try:
                if getattr(e, "_dirty", False):
                    e._dirty = False
                    e.tag_redraw()
            except ReferenceError:
                pass
        if not len(cls._engines):
            cls._registered = False
            return None
        return 0.05


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
    render.clear_cache()
