"""Training in a background :class:`jobs.Job` (Blender's UI keeps running).

The thread never touches bpy: the operator extracts everything it needs (mesh arrays, paths) on the
main thread, and a ``bpy.app.timers`` callback (main thread, :func:`jobs.watch`) reads the progress
the thread records. Cancelling saves the field as trained so far; "Resume" continues from the saved file.
"""
from __future__ import annotations

import os

from ..runtime._np import np
from ..runtime import core
from ..runtime.jobs import Job


class TrainJob(Job):
    """States: RUNNING while loading, TRAINING, SAVING, then DONE, CANCELLED (saved) or ERROR."""

    def __init__(self, *, dataset_path: str, field_path: str, steps: int, vertices=None, faces=None,
                 resume: bool = False, downscale: int = 1, background: str = "white", train_kwargs=None,
                 object_name: str = "", box=None, background_model: bool = True):
        super().__init__("train")
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
        self.box = box                      # (centre, half_extents, rotation) of the NeuMesh Box, or None
        self.background_model = bool(background_model)
        self.step = 0
        self.total_steps = self.steps
        self.loss = float("nan")
        self.psnr = float("nan")
        self.rays_per_sec = 0.0
        self.elapsed_s = 0.0
        self.eta_s = float("nan")

    @property
    def fraction(self) -> float:
        return min(1.0, self.step / max(1, self.total_steps))

    @fraction.setter
    def fraction(self, _value):   # Job.__init__ sets it; the step count is the truth here
        pass

    def status_text(self) -> str:
        if self.state == "TRAINING":
            eta = "" if not np.isfinite(self.eta_s) else f", ETA {self.eta_s:.0f}s"
            psnr = "" if not np.isfinite(self.psnr) else f", PSNR {self.psnr:.2f} dB"
            return (f"NeuMesh training {self.step}/{self.total_steps}: loss {self.loss:.4f}{psnr}, "
                    f"{self.rays_per_sec / 1000:.1f}k rays/s{eta}")
        state = "loading" if self.state == "RUNNING" else self.state.lower()
        return f"NeuMesh training: {state} {self.message}".strip()

    def status_lines(self) -> list[str]:
        """The status as short lines for the narrow sidebar (each is wrapped further if needed)."""
        if self.state == "TRAINING":
            psnr = "" if not np.isfinite(self.psnr) else f", PSNR {self.psnr:.2f} dB"
            eta = "" if not np.isfinite(self.eta_s) else f", ETA {_duration(self.eta_s)}"
            return [f"Step {self.step}/{self.total_steps} ({100 * self.fraction:.0f}%)",
                    f"Loss {self.loss:.4f}{psnr}", f"{self.rays_per_sec / 1000:.1f}k rays/s{eta}"]
        lines = [f"Training: {'loading' if self.state == 'RUNNING' else self.state.lower()}"]
        if self.message:
            lines.append(self.message)
        return lines

    # ---------------------------------------------------------------- thread
    def _progress(self, p):
        self.step = int(getattr(p, "step", self.step))
        self.total_steps = int(getattr(p, "total_steps", self.total_steps))
        self.loss = float(getattr(p, "loss", self.loss))
        self.psnr = float(getattr(p, "psnr", self.psnr) if getattr(p, "psnr", None) is not None else np.nan)
        self.rays_per_sec = float(getattr(p, "rays_per_sec", 0.0) or 0.0)
        self.elapsed_s = float(getattr(p, "elapsed_s", 0.0) or 0.0)
        eta = getattr(p, "eta_s", None)
        self.eta_s = float(eta) if eta is not None else float("nan")
        return not self.cancel_requested

    def run(self):
        nm = core.get()
        with core.CoreNotes() as notes:   # the core's warnings as plain lines, not Python warnings
            scene = nm.load_scene(self.dataset_path, downscale=self.downscale, background=self.background)
        for note in notes:
            print(f"NeuMesh training: {note}")
        box = nm.capture_box(scene, None if self.box is None else nm.ObjectBox(*self.box))
        if self.cancel_requested:
            self.state, self.message = "CANCELLED", "before training started"
            return None
        if self.resume:
            if not os.path.isfile(self.field_path):
                raise FileNotFoundError(f"cannot resume: no field file at {self.field_path}")
            field = nm.load_field(self.field_path)  # rest pose; the saved step/optimizer continue
        else:
            if self.vertices is None or self.faces is None:
                raise ValueError("no mesh given to train a new field on")
            field = nm.create_field(nm.Mesh(self.vertices, self.faces), nm.FieldConfig())
            # photos without masks: the field keeps the box, a background model learns the rest
            nm.prepare_capture_field(field, scene, box, background_model=self.background_model)
        self.state = "TRAINING"
        os.makedirs(os.path.dirname(os.path.abspath(self.field_path)) or ".", exist_ok=True)
        kw = dict(self.train_kwargs)
        kw.setdefault("log_every", 1)                   # progress + cancel checks every step
        kw.setdefault("checkpoint_path", self.field_path)   # checkpoints with optimizer state + step
        try:
            result = nm.train(field, scene, nm.TrainConfig(steps=self.steps, **kw), progress=self._progress)
        except nm.Cancelled:
            result = None
        self.state = "SAVING"
        if result is None or kw.get("checkpoint_path") != self.field_path:
            nm.save_field(field, self.field_path)
        if result is not None and getattr(result, "steps_done", None) is not None:
            self.step = int(result.steps_done)
        if self.cancel_requested:
            self.state = "CANCELLED"
            self.message = f"at step {self.step}; saved to {self.field_path} (Resume continues)"
        else:
            self.state = "DONE"
            self.message = f"saved to {self.field_path}"
        return self.field_path


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
