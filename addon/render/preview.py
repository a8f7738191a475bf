"""The rendered viewport's progressive preview: each request rendered at increasing resolutions in a
background thread, the first image within a time budget."""
from __future__ import annotations

import threading
import time

from ..runtime import quiet
from . import field_cache, frame


def same_items(old, new) -> bool:
    """Do two lists of collected items (``field_cache.collect``) show the same picture: the same objects and
    field files, the same remapped fields and equal vertex positions?  Depsgraph updates come for
    many things the field does not show (selection, tools, paint modes); the viewport restarts its
    progressive preview only when this is False, so such updates never keep it coarse."""
    if old is None or new is None or len(old) != len(new):
        return False
    for a, b in zip(old, new):
        if a.key != b.key or a.path != b.path or a.field is not b.field:
            return False
        va, vb = a.vertices, b.vertices
        if va is not vb and (va.shape != vb.shape or not (va == vb).all()):
            return False
    return True


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

    def request(self, items, K, c2w, width, height, transparent=False, background_model=True):
        with self._cv:
            self._serial += 1
            self._pending = (self._serial, items, K, c2w, int(width), int(height), bool(transparent),
                             bool(background_model), time.perf_counter())
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

    def progress(self):
        """Where the progressive passes are: (shown, finest, busy, seconds) with ``shown`` the divisor of
        the image shown now (None before the first), ``finest`` the last level's, ``busy`` whether a
        finer pass (or a new request) is being rendered, ``seconds`` since the request of the shown one."""
        latest, timings = self.latest, list(self.timings)
        shown = latest[1] if latest is not None else None
        seconds = timings[-1][1] if timings and timings[-1][0] == shown else None
        return shown, self.divisors[-1], bool(self.busy), seconds

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
            serial, items, K, c2w, W, H, transparent, background_model, t0 = job
            self.busy = True
            self.timings = []
            try:
                with quiet.worker():   # an operator under a context override waits for a checkpoint
                    self._render(serial, items, K, c2w, W, H, transparent, background_model, t0)
            except Exception as exc:  # noqa: BLE001 - shown in the viewport
                if type(exc).__name__ != "Cancelled":
                    self.error = field_cache.user_message(exc)
            finally:
                self.busy = False

    def _render(self, serial, items, K, c2w, W, H, transparent, background_model, t0):
        """The levels of one request, coarsest first (in the thread; stops when superseded)."""
        for div in self.levels(W, H):
            w, h = max(1, W // div), max(1, H // div)
            Ks = frame.scale_K(K, W, H, w, h)
            t_level = time.perf_counter()

            def prog(_f, serial=serial):
                quiet.checkpoint()
                return self._serial == serial and not self._stop

            rgba = frame.render_items(items, Ks, c2w, w, h, transparent, progress=prog,
                                      background_model=background_model)
            if self._serial != serial:
                break
            self.seconds_per_pixel = (time.perf_counter() - t_level) / (w * h)
            self.latest = (serial, div, frame.to_scene_linear(rgba, transparent))
            self.timings.append((div, time.perf_counter() - t0))
            self.error = ""
            if self.on_image is not None:
                self.on_image()
