"""Training in a background thread (Blender's UI keeps running).

The thread never touches bpy: the operator extracts everything it needs (mesh arrays, paths) on the
main thread, and a ``bpy.app.timers`` callback (main thread) reads the progress the thread records.
Cancelling saves the field as trained so far; "Resume" continues from the saved file.
"""
from __future__ import annotations

import os
import threading
import time
import traceback

from ._np import np

from . import core


class TrainJob:
    def __init__(self, *, dataset_path: str, field_path: str, steps: int, vertices=None, faces=None,
                 resume: bool = False, downscale: int = 1, background: str = "white", train_kwargs=None,
                 object_name: str = ""):
        self.dataset_path = dataset_path
        self.field_path = field_path
        self.steps = int(steps)
        self.vertices = None if vertices is None else np.asarray(vertices, np.float32)
        self.faces = None if faces is None else np.asarray(faces, np.int64)
        self.resume = bool(resume)
        self.downscale = int(downscale)
        self.background = background
        self.train_kwargs = dict(train_kwargs or {})
        self.object_name = object_name
        self.threads = core.wanted_threads()   # read here, on the main thread
        # progress, written by the thread, read by the UI
        self.state = "PENDING"  # LOADING, TRAINING, SAVING, DONE, CANCELLED, ERROR
        self.message = ""
        self.step = 0
        self.total_steps = self.steps
        self.loss = float("nan")
        self.psnr = float("nan")
        self.rays_per_sec = 0.0
        self.elapsed_s = 0.0
        self.eta_s = float("nan")
        self.started = time.time()
        self.finished_at = None
        self._cancel = threading.Event()
        self._thread = threading.Thread(target=self._run_in_torch_work, name="neumesh-train", daemon=True)

    # ---------------------------------------------------------------- control
    def start(self):
        self.state = "LOADING"
        self._thread.start()
        return self

    def cancel(self):
        self._cancel.set()

    @property
    def cancel_requested(self) -> bool:
        return self._cancel.is_set()

    def join(self, timeout=None):
        self._thread.join(timeout)
        return not self._thread.is_alive()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    @property
    def fraction(self) -> float:
        return min(1.0, self.step / max(1, self.total_steps))

    def status_text(self) -> str:
        if self.state == "TRAINING":
            eta = "" if not np.isfinite(self.eta_s) else f", ETA {self.eta_s:.0f}s"
            psnr = "" if not np.isfinite(self.psnr) else f", PSNR {self.psnr:.2f} dB"
            return (f"NeuMesh training {self.step}/{self.total_steps}: loss {self.loss:.4f}{psnr}, "
                    f"{self.rays_per_sec / 1000:.1f}k rays/s{eta}")
        return f"NeuMesh training: {self.state.lower()} {self.message}".strip()

    def status_lines(self) -> list[str]:
        """The status as short lines for the narrow sidebar (each is wrapped further if needed)."""
        if self.state == "TRAINING":
            psnr = "" if not np.isfinite(self.psnr) else f", PSNR {self.psnr:.2f} dB"
            eta = "" if not np.isfinite(self.eta_s) else f", ETA {_duration(self.eta_s)}"
            return [f"Step {self.step}/{self.total_steps}", f"Loss {self.loss:.4f}{psnr}",
                    f"{self.rays_per_sec / 1000:.1f}k rays/s{eta}"]
        lines = [f"Training: {self.state.lower()}"]
        if self.message:
            lines.append(self.message)
        return lines

    # ---------------------------------------------------------------- thread
    def _callback(self, p):
        self.step = int(getattr(p, "step", self.step))
        self.total_steps = int(getattr(p, "total_steps", self.total_steps))
        self.loss = float(getattr(p, "loss", self.loss))
        self.psnr = float(getattr(p, "psnr", self.psnr) if getattr(p, "psnr", None) is not None else np.nan)
        self.rays_per_sec = float(getattr(p, "rays_per_sec", 0.0) or 0.0)
        self.elapsed_s = float(getattr(p, "elapsed_s", 0.0) or 0.0)
        eta = getattr(p, "eta_s", None)
        self.eta_s = float(eta) if eta is not None else float("nan")
        return not self._cancel.is_set()

    def _run_in_torch_work(self):
        with core.torch_work(self.threads):   # the preference's threads; jemalloc keeps freed memory
            self._run()

    def _run(self):
        try:
            nm = core.get()
            scene = nm.load_scene(self.dataset_path, downscale=self.downscale, background=self.background)
            if self._cancel.is_set():
                self.state, self.message = "CANCELLED", "before training started"
                return
            if self.resume:
                if not os.path.isfile(self.field_path):
                    raise FileNotFoundError(f"cannot resume: no field file at {self.field_path}")
                field = nm.load_field(self.field_path)  # rest pose; the saved step/optimizer continue
            else:
                if self.vertices is None or self.faces is None:
                    raise ValueError("no mesh given to train a new field on")
                mesh = nm.Mesh(self.vertices, self.faces)
                field = nm.create_field(mesh, nm.FieldConfig())
            self.state = "TRAINING"
            os.makedirs(os.path.dirname(os.path.abspath(self.field_path)) or ".", exist_ok=True)
            kw = dict(self.train_kwargs)
            known = set(getattr(nm.TrainConfig, "__dataclass_fields__", {}))
            if "log_every" in known:  # progress + cancel checks every step keep the UI responsive
                kw.setdefault("log_every", 1)
            core_saves = "checkpoint_path" in known
            if core_saves:  # the core writes checkpoints (with optimizer state + step) and the final file
                kw.setdefault("checkpoint_path", self.field_path)
            cfg = nm.TrainConfig(steps=self.steps, **kw)
            try:
                result = nm.train(field, scene, cfg, callback=self._callback)
            except Exception as exc:  # a core that raises on cancel instead of returning early
                if type(exc).__name__ != "Cancelled":
                    raise
                result = None
            self.state = "SAVING"
            if result is None or not core_saves or kw.get("checkpoint_path") != self.field_path:
                nm.save_field(field, self.field_path)
            if result is not None and getattr(result, "steps_done", None) is not None:
                self.step = int(result.steps_done)
            if self._cancel.is_set():
                self.state = "CANCELLED"
                self.message = f"at step {self.step}; saved to {self.field_path} (Resume continues)"
            else:
                self.state = "DONE"
                self.message = f"saved to {self.field_path}"
        except Exception as exc:  # noqa: BLE001 - shown in the UI
            if type(exc).__name__ == "Cancelled":
                self.state, self.message = "CANCELLED", "cancelled"
            else:
                self.state = "ERROR"
                self.message = f"{type(exc).__name__}: {exc}"
                traceback.print_exc()
        finally:
            try:
                core.guard_torch_namespaces()
            except Exception:  # noqa: BLE001
                pass
            self.finished_at = time.time()


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"


_job: TrainJob | None = None


def current() -> TrainJob | None:
    return _job


def start(**kwargs) -> TrainJob:
    global _job
    if _job is not None and _job.running:
        raise RuntimeError("a NeuMesh training is already running; cancel it first")
    _job = TrainJob(**kwargs).start()
    return _job
