"""`fit`: images alone -> scaffold -> trained field -> evaluation (resumable per stage).

Real captures without masks: the object box (``box``, else found in the capture's sparse points,
triangulated from the photos when the capture has none: ``capture_box``) bounds the scaffold (one
surface fused from the photos' depths, ``reconstruct/fusion.py``), is saved with the field, and a
background model (``field.background``) holds everything outside it, the support the object rests on
included: fitted with the scaffold's density grid, then trained on with the field on full frames;
evaluation is full frame with the background on.

out_dir layout: scaffold.ply (+ scaffold.scaffold.json report), field.neumesh, fit.json (summary).
The scaffold stage is skipped when out_dir/scaffold.ply exists (delete it to rebuild); training
resumes from out_dir/field.neumesh (its step and optimiser state) when that exists.
"""
from __future__ import annotations

import json
import os
import time

import numpy as np
from typing import Callable, Optional

from .reconstruct.build import ScaffoldConfig, build_scaffold


def is_unmasked_capture(scene) -> bool:
    """Photos without masks or a known background (a phone capture): the object lives in a box and a
    background model explains the rest of each photo."""
    return not scene.has_masks and scene.background is None and scene.kind != "dtu"


def capture_box(scene, box=None, log=None, progress=None):
    """The object box of ``scene`` and the scaffold's bounds set to it: ``box`` when given (any scene),
    else, for a capture without masks, the box around the object the cameras look at, found in its
    sparse points (``data.frame.find_object``; the capture's own points, else triangulated from its
    training photos: ``reconstruct.points.capture_points``, ``progress(fraction)``); None for masked
    data, whose scaffold the masks bound. The same step for ``neumesh fit`` and the add-on."""
    if box is None and is_unmasked_capture(scene):
        from .data.frame import find_object
        from .reconstruct.points import capture_points

        pts = None if scene.capture is None else capture_points(scene.capture, progress=progress, log=log)
        found = find_object(scene.split("train").cameras.c2w, pts)
        box = found.box
        if log is not None:
            for note in found.notes:
                log(f"object box: {note}")
            log(f"object box (automatic, from {box.source}; --box cx,cy,cz,sx,sy,sz overrides): centre "
                f"{np.round(box.centre, 3).tolist()}, half-sizes {np.round(box.half_extents, 3).tolist()}")
    if box is not None:
        scene.bbox = box.aabb()   # the scaffold is built inside the box
    return box


def prepare_capture_field(field, scene, box, background_model: bool = True, fitted_background=None) -> None:
    """A new field for ``scene``: it keeps ``box`` (saved with it; edits and deformation act inside) and,
    with ``background_model`` and photos without masks (:func:`is_unmasked_capture`), a background
    model for the photos outside the box: ``fitted_background`` (the one the scaffold was fitted with)
    when given, else a new one. Nothing for None."""
    if box is not None:
        field.object_box = box
    if background_model and box is not None and is_unmasked_capture(scene):
        from .field.background import attach_background, fit_background_for

        model = fitted_background
        if model is None or not np.allclose(model.box.centre, box.centre):
            model = fit_background_for(scene.split("train").cameras.c2w, box,
                                       None if scene.capture is None else scene.capture.points)
        attach_background(field, model)


def fit(data_dir: str, out_dir: str, steps: int = 3000, downscale: float = 1, background="white",
        scaffold_config: Optional[ScaffoldConfig] = None, field_config=None, train_config=None,
        scaffold_progress: Optional[Callable[[str, float], object]] = None,
        train_progress=None, evaluate_split: str = "val", log: Callable[[str], None] = print,
        device="cpu", box=None, background_model: bool = True, eval_progress=None, *,
        train_callback=None) -> dict:
    """Run the whole pipeline on a dataset folder; returns a summary dict (also written to fit.json).

    ``device``: where the field trains and is evaluated (the scaffold is built on the CPU).
    ``box``: a ``data.frame.ObjectBox`` for the object (None: automatic for captures without masks).
    ``background_model``: without masks, fit a background model outside the box (off: the field
    alone must explain the whole frame; for comparisons). ``eval_progress(done, total)``: the
    evaluation's progress over the held-out photos. ``train_progress``: the trainer's ``progress``
    (``train_callback``: the same, the name older scripts pass)."""
    from .data.loader import load_scene
    from .errors import VertexMismatchError
    from .evaluate import evaluate
    from .field.field import FieldConfig, create_field
    from .field.io import load_field, save_field
    from .mesh import load_mesh, save_mesh
    from .train.trainer import TrainConfig, train

    os.makedirs(out_dir, exist_ok=True)
    t0 = time.perf_counter()
    scene = load_scene(data_dir, downscale=downscale, background=background)
    summary = {"data": os.path.abspath(data_dir), "downscale": downscale}
    box = capture_box(scene, box, log, progress=None if scaffold_progress is None
                      else (lambda f: scaffold_progress("sparse points", f)))
    if box is not None:
        summary["object_box"] = box.to_dict()

    mesh_path = os.path.join(out_dir, "scaffold.ply")
    report_path = os.path.join(out_dir, "scaffold.scaffold.json")
    fitted_background = None
    if os.path.isfile(mesh_path):
        mesh = load_mesh(mesh_path)
        log(f"scaffold: reusing {mesh_path} ({mesh.num_vertices} vertices); delete it to rebuild")
        summary["scaffold"] = {"reused": True, "vertices": mesh.num_vertices}
    else:
        mesh, rep = build_scaffold(scene, scaffold_config or ScaffoldConfig(), progress=scaffold_progress, box=box)
        fitted_background = rep.background
        save_mesh(mesh, mesh_path)
        rep.save(report_path)
        log(rep.summary())
        summary["scaffold"] = {"reused": False, "vertices": rep.num_vertices,
                               "seconds": rep.timings.get("total"), "silhouette_iou": rep.silhouette_iou}

    field_path = os.path.join(out_dir, "field.neumesh")
    tcfg = train_config or TrainConfig(steps=steps)
    if getattr(tcfg, "checkpoint_path", None) is None:
        tcfg.checkpoint_path = field_path
    if os.path.isfile(field_path):
        field = load_field(field_path, device=device)
        if field.num_vertices != mesh.num_vertices:
            raise VertexMismatchError(
                f"{field_path} has {field.num_vertices} vertices but {mesh_path} has {mesh.num_vertices}; "
                "delete one of them to start over")
        done = field._checkpoint_meta.get("train_state", {}).get("step", 0)
        log(f"training: resuming {field_path} from step {done}")
        summary["resumed_from_step"] = done
    else:
        field = create_field(mesh, field_config or FieldConfig(), device=device)
        prepare_capture_field(field, scene, box, background_model=background_model,
                              fitted_background=fitted_background)
    res = train(field, scene, tcfg, progress=train_progress or train_callback)
    if os.path.abspath(tcfg.checkpoint_path) != os.path.abspath(field_path):
        save_field(field, field_path)  # (the trainer already wrote field_path with its step/optimiser)
    summary["train"] = {"steps": getattr(res, "steps_done", None), "psnr": getattr(res, "final_psnr", None),
                        "seconds": getattr(res, "seconds", None)}
    if evaluate_split in scene.splits:
        metrics = evaluate(field, scene.split(evaluate_split),
                           background=scene.background or (0.0, 0.0, 0.0), masked=scene.kind == "dtu",
                           progress=eval_progress)
        summary["eval"] = metrics.get("mean", metrics) if isinstance(metrics, dict) else metrics
    summary["seconds"] = time.perf_counter() - t0
    with open(os.path.join(out_dir, "fit.json"), "w") as fh:
        json.dump(summary, fh, indent=2, default=str)
    return summary
