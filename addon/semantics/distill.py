"""Distill semantics: ``nm.semantics.distill_semantics`` on the active object's field (loaded afresh: the
render cache's field is not touched) in a background :class:`jobs.Job`, with progress in the panel and
the status bar; Cancel writes nothing. The result is saved in the edits folder as an edit
(``<name>.edit-NNN.neumesh``, see ``props.edits_folder``) and the object points at it, so "Undo edit" /
Ctrl+Z go back to the field without semantics."""
from __future__ import annotations

import os

import bpy
from bpy.props import BoolProperty, IntProperty

from ..runtime._np import np
from ..runtime import core, jobs
from ..runtime.errors import UserError
from ..runtime.text import file_size
from ..scene import props
from ..edit.base import edits_folder_ready

STAGES = {"features": "2D features", "rays": "Marching rays", "train": "Training"}


class DistillJob(jobs.Job):
    """Distillation in a thread; never touches bpy (the operator reads Blender state beforehand)."""

    def __init__(self, *, object_name: str, field_path: str, dataset_path: str, downscale: int = 1,
                 background: str = "white", extractor: str = "colour-texture", steps: int = 1500,
                 config=None, out_dir: str = ""):
        super().__init__("semantics")
        self.object_name = object_name
        self.field_path = field_path
        self.out_dir = out_dir or os.path.dirname(os.path.abspath(field_path))
        self.dataset_path = dataset_path
        self.downscale = int(downscale)
        self.background = background
        self.extractor = extractor
        self.steps = int(steps)
        self.config = dict(config or {})
        self.stage = ""
        self.step = 0
        self.total = 1
        self.loss = float("nan")
        self.out_path = None

    @property
    def fraction(self) -> float:
        # features and rays take the first 20%, training the rest
        base = {"features": 0.0, "rays": 0.1, "train": 0.2}.get(self.stage, 0.0)
        span = 0.1 if self.stage in ("features", "rays") else 0.8
        return min(1.0, base + span * self.step / max(1, self.total))

    @fraction.setter
    def fraction(self, _value):   # Job.__init__ sets it; the stages are the truth here
        pass

    def status_lines(self) -> list[str]:
        """Short lines for the sidebar: the stage, then the count and the percentage."""
        if self.state == "RUNNING":
            what = STAGES.get(self.stage, "Loading")
            loss = f", loss {self.loss:.4f}" if self.stage == "train" and np.isfinite(self.loss) else ""
            return [f"Semantics: {what}", f"{self.step}/{self.total} ({100 * self.fraction:.0f}%){loss}"]
        lines = [f"Semantics: {self.state.lower()}"]
        return lines + ([self.message] if self.message else [])

    def status_text(self) -> str:
        return "NeuMesh " + ": ".join(self.status_lines()).replace("Semantics", "semantics", 1)

    def _progress(self, p):
        self.stage, self.step, self.total, self.loss = p.stage, int(p.step), int(p.total), float(p.loss)
        return not self.cancel_requested

    def run(self):
        nm = core.get()
        sem = nm.semantics
        field = nm.load_field(self.field_path)   # a copy: the render cache's field is not touched
        with core.CoreNotes() as notes:   # the core's warnings as plain lines, not Python warnings
            scene = nm.load_scene(self.dataset_path, downscale=self.downscale, background=self.background)
        for note in notes:
            print(f"NeuMesh semantics: {note}")
        extractor = sem.make_extractor(self.extractor)
        cfg = sem.DistillConfig(steps=self.steps, **self.config)
        res = sem.distill_semantics(field, scene, extractor, cfg, progress=self._progress)
        if res.cancelled or self.cancel_requested:
            self.state, self.message = "CANCELLED", "nothing was written"
            return None
        out = nm.edit.next_edit_path(os.path.join(self.out_dir, os.path.basename(self.field_path)))
        self.out_path = nm.edit.save_edited(field, self.field_path, sem.semantics_record(field, res), out_path=out)
        self.message = (f"{res.steps_done} steps in {res.seconds:.0f}s, loss {res.final_loss:.3f}; "
                        f"saved {os.path.basename(self.out_path)} ({file_size(self.out_path)}) in {self.out_dir}")
        return self.out_path


_job: DistillJob | None = None
_watch = None


def current_job() -> DistillJob | None:
    return _job


def _point_at_result(job):
    """Main thread: point the object at the file the finished job wrote."""
    if job.state == "DONE" and job.out_path and os.path.isfile(job.out_path):
        obj = bpy.data.objects.get(job.object_name)
        if obj is not None:
            props.set_field_path(obj, job.out_path)


class _Distill:
    """Distill semantic codes into the active object's field from 2D features of the dataset's training
    images (background thread; the result is saved in the Edits folder as an edit)"""

    bl_label = "Distill semantics"

    steps: IntProperty(name="Steps", default=0, min=0, options={"SKIP_SAVE"}, description="0 = panel setting")
    max_views: IntProperty(default=0, min=0, options={"HIDDEN", "SKIP_SAVE"}, description="0 = all views")
    rays_per_view: IntProperty(default=0, min=0, options={"HIDDEN", "SKIP_SAVE"}, description="0 = default")
    wait: BoolProperty(default=False, options={"HIDDEN", "SKIP_SAVE"},
                       description="Block until distillation ends (scripts, background mode)")

    def execute(self, context):
        global _job, _watch
        s = context.scene.neumesh_semantics
        obj = context.active_object
        dataset = bpy.path.abspath(context.scene.neumesh.dataset_path)
        try:
            path = props.field_path_of(obj)
            if not dataset or not os.path.isdir(dataset):
                raise UserError("set the dataset folder the field was trained on (NeuMesh > Dataset)")
            if _job is not None and _job.running:
                raise UserError("a semantic distillation is already running; cancel it first")
            core.require("semantics")
            out_dir = edits_folder_ready(props.scene_edits_folder(context.scene))
        except UserError as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        cfg = {k: v for k, v in (("max_views", self.max_views), ("rays_per_view", self.rays_per_view)) if v}
        _job = DistillJob(object_name=obj.name, field_path=path, dataset_path=dataset,
                         downscale=context.scene.neumesh.downscale, extractor=s.extractor,
                         steps=self.steps or s.steps, config=cfg, out_dir=out_dir).start()
        if self.wait:
            _job.join()
            jobs.finish(_job, _point_at_result)
            self.report({"INFO" if _job.state in ("DONE", "CANCELLED") else "ERROR"}, _job.status_text())
            return {"FINISHED"} if _job.state == "DONE" else {"CANCELLED"}
        _watch = jobs.watch(_job, _point_at_result)
        self.report({"INFO"}, f"NeuMesh: distilling semantics of '{obj.name}'")
        return {"FINISHED"}


class _DistillCancel:
    """Stop the semantic distillation (nothing is written)"""

    bl_label = "Cancel distillation"

    def execute(self, context):
        if _job is None or not _job.running:
            self.report({"WARNING"}, "NeuMesh: no distillation is running")
            return {"CANCELLED"}
        _job.cancel()
        return {"FINISHED"}


class NEUMESH_OT_distill_semantics(_Distill, bpy.types.Operator):
    __doc__ = _Distill.__doc__
    bl_idname = "neumesh.distill_semantics"


class NEUMESH_OT_distill_cancel(_DistillCancel, bpy.types.Operator):
    __doc__ = _DistillCancel.__doc__
    bl_idname = "neumesh.distill_cancel"


class NEUMESH_OT_distil_semantics(_Distill, bpy.types.Operator):
    """Distill semantics (the operator's former id, kept for scripts and keymaps that call it)"""

    bl_idname = "neumesh.distil_semantics"
    bl_options = {"INTERNAL"}


class NEUMESH_OT_distil_cancel(_DistillCancel, bpy.types.Operator):
    """Cancel distillation (the operator's former id, kept for scripts and keymaps that call it)"""

    bl_idname = "neumesh.distil_cancel"
    bl_options = {"INTERNAL"}


classes = (NEUMESH_OT_distill_semantics, NEUMESH_OT_distill_cancel, NEUMESH_OT_distil_semantics,
           NEUMESH_OT_distil_cancel)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()


def unregister():
    jobs.stop_timer(_watch)
    if _job is not None and _job.running:
        _job.cancel()
    _unregister_classes()
