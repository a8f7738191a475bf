"""`neumesh fit`: images alone -> scaffold -> trained field -> evaluation (resumable)."""
from __future__ import annotations

import os
import sys
import time

from .common import (Progress, _add_data_options, _add_device_option, _add_field_options,
                     _add_train_options, _device, _field_config, _fmt_time, _train_config)
from .poses import add_colmap_log_option
from .scaffold import add_scaffold_options


def cmd_fit(args) -> int:
    from ..reconstruct.colmap_run import colmap_log

    # pycolmap's own log lines stay hidden through every stage (poses, and any stage that calls it)
    with colmap_log(args.colmap_log):
        return _fit(args)


def _fit(args) -> int:
    from ..data.frame import parse_box
    from ..fit import fit
    from .scaffold import config_from_args

    t0 = time.perf_counter()
    progress = Progress()
    started = []

    def log(message):   # fit() logs between stages: the stage before is over
        progress.end()
        progress.say(message)

    def train_cb(p):
        if not started:
            started.append(True)
            log("stage 2/3: training")
        progress.training(p)
        if p.fraction >= 1.0:   # the budget is spent: fit() saves the field and evaluates next
            log("stage 3/3: evaluation")
            progress.update("evaluation", 0.0, "saving the field, rendering the held-out photos")

    data = _data_or_poses(args, progress)
    if data is None:
        return 2
    progress.say("stage 1/3: scaffold (skipped when OUT/scaffold.ply exists)")
    summary = fit(data, args.out, downscale=args.downscale, background=args.background,
                  scaffold_config=config_from_args(args), field_config=_field_config(args),
                  train_config=_train_config(args, os.path.join(args.out, "field.neumesh")),
                  scaffold_progress=progress.scaffold, train_progress=train_cb, log=log, device=_device(args),
                  box=None if args.box is None else parse_box(args.box),
                  background_model=args.background_model == "on",
                  eval_progress=progress.count("evaluation", "held-out photos"))
    ev = summary.get("eval")
    figures = ", ".join(f"{k} {v:.4f}" for k, v in ev.items() if k != "render_s") if ev else ""
    if progress.stage == "evaluation":
        progress.end(figures or "no held-out photos")
    progress.end()
    if ev:
        print("evaluation: " + figures)
    print(f"fit done in {_fmt_time(time.perf_counter() - t0)}; outputs in {args.out}")
    return 0


def _data_or_poses(args, progress: Progress):
    """The dataset folder: --data, or OUT/poses made from --images / --video first (reused when a
    previous run left it complete). None (after an error line) when the options do not say which."""
    given = [n for n in ("data", "images", "video") if getattr(args, n)]
    if len(given) != 1:
        print("error: give one of --data DIR (a dataset or capture with poses), --images DIR (plain photos: "
              "poses are recovered first) or --video clip.mp4", file=sys.stderr)
        return None
    if args.data:
        return args.data
    from .poses import recover_poses
    from ..reconstruct.poses import PosesConfig

    poses_dir = os.path.join(args.out, "poses")
    if os.path.isfile(os.path.join(poses_dir, "poses_report.json")) and \
            os.path.isdir(os.path.join(poses_dir, "sparse", "0")):
        progress.say(f"stage 0/3: poses (reusing {poses_dir}; delete it to recover them again)")
        return poses_dir
    progress.say("stage 0/3: poses from the photos (pycolmap on the CPU)")
    recover_poses(poses_dir, images=args.images, video=args.video, fps=args.fps,
                  config=PosesConfig(num_threads=args.threads or -1, colmap_log=args.colmap_log),
                  progress=progress, say=progress.say)
    return poses_dir


def add_commands(sub) -> None:
    p = sub.add_parser("fit", help="images alone -> scaffold -> trained field -> evaluation (resumable); "
                            "plain photos or a video: poses first (--images / --video)",
                       description="Build the scaffold (skipped when OUT/scaffold.ply exists), train the "
                                   "field (resumes OUT/field.neumesh), evaluate on 'val'. Progress per stage. "
                                   "Photos without masks (a phone capture: transforms.json or COLMAP): the "
                                   "object box is found from the sparse points of what the cameras look at, "
                                   "its support (a wall, a table) left out (or --box); the scaffold is one "
                                   "surface fused from the depths of a density grid fitted in the box with a "
                                   "background model behind it, and the field's background model learns the "
                                   "room outside the box; held-out every 8th photo, evaluated full frame.")
    _add_data_options(p, required=False)
    g = p.add_argument_group("photos without poses (instead of --data)")
    g.add_argument("--images", default=None, help="a folder of plain photos: poses are recovered first "
                   "(as `neumesh poses`, into OUT/poses; reused by the next run)")
    g.add_argument("--video", default=None, help="a video clip: sharp frames at --fps, then as --images")
    g.add_argument("--fps", type=float, default=2.0, help="frames per second taken from --video (default 2)")
    p.add_argument("--out", required=True, help="output folder: scaffold.ply, field.neumesh, fit.json")
    p.add_argument("--box", default=None, metavar="CX,CY,CZ,SX,SY,SZ",
                   help="object box: centre and half-sizes in world units (default: automatic, around "
                        "what the cameras look at; only for photos without masks)")
    p.add_argument("--background-model", choices=["on", "off"], default="on",
                   help="photos without masks: learn the room outside the box (default on)")
    add_colmap_log_option(p)
    add_scaffold_options(p)
    _add_field_options(p)
    _add_train_options(p)
    _add_device_option(p)
    p.set_defaults(func=cmd_fit)
