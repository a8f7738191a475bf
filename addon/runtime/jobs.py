"""The one background-job class of the add-on, and the operator mixin that runs a job modally.

Training, semantic distillation, edits, bakes and dependency installs all run in a :class:`Job`: one
daemon thread, one cancel event, one join. A job never touches bpy (its operator reads Blender state
on the main thread first); the UI polls ``state``, ``fraction`` and ``message`` from a timer or a modal
operator. A job that runs torch work reads the *CPU threads* preference when it is made (main thread)
and runs inside :func:`core.torch_work` (that thread count, jemalloc keeping freed memory mapped).

States: PENDING -> RUNNING (subclasses may show finer stages while running, e.g. TRAINING) -> DONE,
CANCELLED or ERROR.  ``result`` is what :meth:`Job.run` returned, ``error`` the exception of an ERROR.
"""
from __future__ import annotations

import threading
import time
import traceback

from . import core, quiet
from .errors import UserError

FINAL_STATES = ("DONE", "CANCELLED", "ERROR")


class Job:
    """``Job(label, fn)`` runs ``fn(progress)`` in a thread, ``progress(fraction) -> False`` once
    :meth:`cancel` was called; or subclass and override :meth:`run`. A ``Cancelled`` exception (the
    core's, or any class of that name) ends the job as CANCELLED."""

    uses_torch = True
    # errors whose message is the whole story (no traceback printed)
    quiet_errors: tuple = (UserError, ValueError)

    def __init__(self, label: str = "job", fn=None):
        self.label = label
        self._fn = fn
        self.state = "PENDING"
        self.message = ""
        self.fraction = 0.0
        self.result = None
        self.error: BaseException | None = None
        self.started = time.time()
        self.finished_at = None
        self.threads = core.wanted_threads() if self.uses_torch else None   # read on the main thread
        self._cancel = threading.Event()
        self._thread = threading.Thread(target=self._main, name=f"neumesh-{label}", daemon=True)

    # ---------------------------------------------------------------- control (main thread)
    def start(self):
        self.state = "RUNNING"
        self._thread.start()
        return self

    def cancel(self):
        self._cancel.set()

    @property
    def cancel_requested(self) -> bool:
        return self._cancel.is_set()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    @property
    def cancelled(self) -> bool:
        return self.state == "CANCELLED"

    def join(self, timeout=None) -> bool:
        """Wait for the thread; True when it has ended."""
        self._thread.join(timeout)
        return not self._thread.is_alive()

    # ---------------------------------------------------------------- the thread
    def progress(self, fraction) -> bool:
        """The progress callback handed to the core: records ``fraction``; False once cancelled."""
        self.fraction = min(1.0, max(0.0, float(fraction)))
        quiet.checkpoint()   # an operator under a context override may be waiting (runtime/quiet.py)
        return not self._cancel.is_set()

    def run(self):
        """The work (in the thread); returns the job's result."""
        return self._fn(self.progress)

    def _main(self):
        with quiet.worker():
            self._work()

    def _work(self):
        try:
            if self.uses_torch:
                with core.torch_work(self.threads):
                    self.result = self.run()
            else:
                self.result = self.run()
            if self.state not in FINAL_STATES:
                self.state = "DONE"
        except Exception as exc:  # noqa: BLE001 - shown by the operator / panel
            if type(exc).__name__ == "Cancelled":
                self.state = "CANCELLED"
                self.message = self.message or "cancelled"
            else:
                self.error = exc
                self.state = "ERROR"
                self.message = str(exc) if isinstance(exc, self.quiet_errors) else f"{type(exc).__name__}: {exc}"
                if not isinstance(exc, self.quiet_errors):
                    traceback.print_exc()
        finally:
            if self.uses_torch:
                try:
                    core.guard_torch_namespaces()   # torch may have imported modules lazily
                except Exception:  # noqa: BLE001
                    pass
            self.finished_at = time.time()


def set_status(context, text) -> None:
    """The status bar text (None clears it); nothing in background mode."""
    try:
        ws = context.workspace
        if ws is not None:
            ws.status_text_set(text)
    except Exception:  # noqa: BLE001 - no workspace in background mode
        pass


def redraw(context, area_types=("VIEW_3D", "PROPERTIES", "PREFERENCES"), whole: bool = False) -> None:
    """Tag the panel regions of every area of those types in every window for redraw, so their panels
    are laid out anew at once (not drawn over each other until the mouse moves over them). In a 3D
    view only the sidebar and the header (``whole``: the viewport too, after an edit changed the field)."""
    try:
        for win in context.window_manager.windows:
            for area in win.screen.areas:
                if area.type not in area_types:
                    continue
                if area.type != "VIEW_3D" or whole:
                    area.tag_redraw()
                    continue
                for region in area.regions:
                    if region.type in ("UI", "HEADER", "TOOL_HEADER"):
                        region.tag_redraw()
    except Exception:  # noqa: BLE001 - no window manager in background mode
        pass


_ACTIVE: dict = {}   # bl_label -> the job a JobModal operator runs modally


def active(label: str):
    """The job the modal operator labelled ``label`` runs now, or None (the panel of the same label
    draws its progress)."""
    job = _ACTIVE.get(label)
    return job if job is not None and job.running else None


class JobModal:
    """Mixin: an operator whose work runs in a :class:`Job` (``_start(context)`` -> a job or None;
    ``_finish(context, job)`` -> the operator result). From a script (EXEC) it blocks; invoked from the
    UI it is modal with a percentage in the status bar and Esc to cancel, and the viewport stays usable
    meanwhile. ``edit_label`` names the work."""

    edit_label = "working"

    def execute(self, context):
        job = self._start(context)
        if job is None:
            return {"CANCELLED"}
        job.start().join()
        return self._finish(context, job)

    def invoke(self, context, event):
        job = self._start(context)
        if job is None:
            return {"CANCELLED"}
        self._job = _ACTIVE[self.bl_label] = job.start()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.1, window=context.window)
        wm.progress_begin(0, 100)
        wm.modal_handler_add(self)
        set_status(context, f"NeuMesh: {self.edit_label} 0% (Esc cancels)")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = self._job
        if event.type == "ESC" and job.running:
            job.cancel()
        if event.type == "TIMER":
            context.window_manager.progress_update(int(100 * job.fraction))
            stage = f": {job.message}" if job.running and job.message else ""
            set_status(context, f"NeuMesh: {self.edit_label} {100 * job.fraction:.0f}%{stage} (Esc cancels)")
            redraw(context, ("VIEW_3D", "IMAGE_EDITOR"))
        if job.running:   # the viewport stays usable while the work runs; Esc is ours
            return {"RUNNING_MODAL"} if event.type == "ESC" else {"PASS_THROUGH"}
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        set_status(context, None)
        result = self._finish(context, job)
        redraw(context, ("VIEW_3D", "IMAGE_EDITOR"))
        return result


def finish(job, on_finish=None) -> None:
    """Main thread, once ``job`` has ended: ``on_finish(job)`` (once per job), status bar cleared,
    panels redrawn. Called by :func:`watch`'s timer and by operators that waited for the job."""
    import bpy

    if job is None or job.running or getattr(job, "handled", False):
        return
    job.handled = True
    if on_finish is not None:
        on_finish(job)
    set_status(bpy.context, None)
    redraw(bpy.context)


def watch(job, on_finish=None, interval: float = 0.25):
    """Main thread: follow ``job`` from a ``bpy.app`` timer. While it runs: its ``status_text()`` in the
    status bar and the sidebar redrawn (progress shows without moving the mouse); when it has ended:
    :func:`finish`. Returns the timer function (``tick()`` runs one step of it)."""
    import bpy

    def tick():
        if job.running:
            set_status(bpy.context, job.status_text())
            redraw(bpy.context)
            return interval
        finish(job, on_finish)
        return None

    bpy.app.timers.register(tick, first_interval=interval)
    return tick


def stop_timer(tick) -> None:
    """Unregister a :func:`watch` timer (add-on disabled while a job runs)."""
    import bpy

    if tick is not None and bpy.app.timers.is_registered(tick):
        bpy.app.timers.unregister(tick)
