"""Shared pieces of the command line: option groups, configs from options, the progress printer, the
evaluation table, turntable cameras and frame rendering."""
from __future__ import annotations

import math
import os
import shutil
import sys
import time

import numpy as np


def _fmt_time(s: float) -> str:
    s = int(max(0, s)) if math.isfinite(s) else 0
    return f"{s // 3600:d}:{s % 3600 // 60:02d}:{s % 60:02d}"


_POSES_STAGES = {"extract": "features", "match": "matching", "map": "cameras"}
_SEMANTICS_STAGES = {"features": ("2D features", "views"), "rays": ("marching rays", "views"),
                     "train": ("training", "steps")}


class Progress:
    """The command line's progress printer: the long steps of every command (poses, the scaffold's
    stages, training, evaluation, rendering, baking, edits) report through one.

    ``update(stage, fraction, detail)``: ``fraction`` is of that stage (0..1). On a terminal, one line
    per stage with a bar, redrawn in place (at most every ``redraw_s``) and closed with the stage's time
    when the next stage starts or :meth:`end` is called. Elsewhere (a log file, a pipe) plain lines: one
    when a stage starts, then one each time the stage passes another ``step`` of its work or
    ``every_s`` seconds after the last line, whichever comes first, and one when it ends.
    :meth:`say` prints a message between them. The adapters (:meth:`poses`, :meth:`scaffold`,
    :meth:`training`, :meth:`semantics`, :meth:`fraction`, :meth:`count`) are what the core's
    functions take as ``progress``."""

    def __init__(self, stream=None, *, tty: bool | None = None, step: float = 0.1, every_s: float = 30.0,
                 redraw_s: float = 0.2, clock=time.monotonic):
        self._stream = stream  # None: whatever sys.stderr is at write time (it can be swapped)
        isatty = getattr(self.stream, "isatty", None)
        self.tty = bool(isatty and isatty()) if tty is None else bool(tty)
        self.step, self.every_s, self.redraw_s, self.clock = step, every_s, redraw_s, clock
        self.stage = None
        self.t_stage = self.t_line = 0.0
        self.mark = 0        # steps of the stage's work printed (fraction // step)
        self.open = 0        # terminal: length of the line being redrawn (0: none)

    @property
    def stream(self):
        return self._stream if self._stream is not None else sys.stderr

    def update(self, stage: str, fraction: float, detail: str = "") -> bool:
        """Report ``stage`` at ``fraction`` of its work; True (a progress that never cancels)."""
        now = self.clock()
        fraction = min(max(float(fraction), 0.0), 1.0) if math.isfinite(fraction) else 0.0
        mark = int(fraction / self.step + 1e-9)
        if stage != self.stage:
            self.end()
            self.stage, self.t_stage = stage, now
        elif not (mark > self.mark or now - self.t_line >= (self.redraw_s if self.tty else self.every_s)):
            return True
        self.mark, self.t_line = mark, now
        pct = f"{100 * fraction:3.0f}%"
        tail = (f"  {detail}" if detail else "") + f"  ({_fmt_time(now - self.t_stage)})"
        if self.tty:
            n = int(20 * fraction)
            line = f"[{stage}] {'#' * n}{'-' * (20 - n)} {pct}{tail}"
            width = shutil.get_terminal_size((100, 24)).columns - 1
            line = line[:width]
            self._write("\r" + line.ljust(self.open))
            self.open = len(line)
        else:
            self._write(f"[{stage}] {pct}{tail}\n")
        return True

    def end(self, detail: str = "") -> None:
        """Close the current stage with its time (and ``detail``); nothing when none is open."""
        if self.stage is None:
            return
        line = f"[{self.stage}] done in {_fmt_time(self.clock() - self.t_stage)}" + (f": {detail}" if detail else "")
        self._write(("\r" + line.ljust(self.open) if self.tty else line) + "\n")
        self.stage, self.open = None, 0

    def say(self, message: str) -> None:
        """A message line between progress lines (a terminal's redrawn line is kept above it)."""
        if self.open:
            self._write("\n")
            self.open = 0
        self._write(message + "\n")

    def _write(self, text: str) -> None:
        self.stream.write(text)
        self.stream.flush()

    # what the core's functions take as progress
    def poses(self, p) -> None:
        """``estimate_poses``' progress (a PosesProgress): one stage per pycolmap step."""
        self.update("poses: " + _POSES_STAGES.get(p.stage, p.stage), p.stage_fraction, p.message)

    def scaffold(self, stage: str, fraction: float) -> bool:
        """``build_scaffold``'s progress(stage, fraction)."""
        return self.update(f"scaffold: {stage}", fraction)

    def training(self, p) -> None:
        """The trainer's progress (a TrainProgress). The fraction, the total and the ETA are the
        budget's: its steps, or the time budget (``--max-minutes``) when that ends the run first."""
        if p.limit == "time":
            of = f"step {p.step} ({_fmt_time(p.elapsed_s + p.eta_s)} budget)"
        else:
            of = f"step {p.step}/{p.total_steps}"
        self.update("training", p.fraction,
                    f"{of}  loss {p.loss:.4f}  psnr {p.psnr:5.2f}  {p.rays_per_sec / 1000:.1f}k rays/s  "
                    f"{p.samples_per_ray:.1f} smp/ray  eta {_fmt_time(p.eta_s)}")

    def semantics(self, p) -> None:
        """``distill_semantics``' progress (a DistillProgress): one stage per part of the work."""
        label, unit = _SEMANTICS_STAGES[p.stage]
        detail = f"{p.step} of {p.total} {unit}"
        if p.stage == "train":
            detail += f"  loss {p.loss:.4f}  eta {_fmt_time(p.eta_s)}"
        self.update(f"semantics: {label}", p.step / max(1, p.total), detail)

    def fraction(self, stage: str):
        """A progress(fraction) -> True for ``stage`` (baking, edits)."""
        return lambda fraction: self.update(stage, fraction)

    def count(self, stage: str, unit: str):
        """A progress(done, total) -> True for ``stage`` (evaluation: views)."""
        return lambda done, total: self.update(stage, done / max(1, total), f"{done} of {total} {unit}")


def _add_field_options(ap):
    g = ap.add_argument_group("field")
    g.add_argument("--interpolation", choices=["post", "early"], default="post",
                   help="post: decode each of the K neighbours then average (the paper's default, best "
                        "quality); early: average codes first and decode once (~3x faster, ~0.15 dB worse)")
    g.add_argument("--radius-scale", type=float, default=2.5,
                   help="neighbour search radius = this x the mean edge length of the scaffold (default 2.5)")
    g.add_argument("--radius", type=float, default=0.0,
                   help="absolute neighbour search radius in scene units (overrides --radius-scale)")
    g.add_argument("--grid-res", type=int, default=128,
                   help="occupancy grid cells along the longest axis (default 128)")


def _add_train_options(ap):
    g = ap.add_argument_group("training")
    g.add_argument("--steps", type=int, default=3000, help="optimisation steps (default 3000)")
    g.add_argument("--rays", type=int, default=4096, help="rays per step (default 4096)")
    g.add_argument("--lr-codes", type=float, default=1e-2, help="Adam learning rate of vertex codes")
    g.add_argument("--lr-decoders", type=float, default=2e-3, help="Adam learning rate of the decoders")
    g.add_argument("--tv", type=float, default=1e-3, help="weight of the total-variation loss on codes")
    g.add_argument("--tv-vertices", choices=["random", "batch"], default="random",
                   help="TV over random vertices each step (default) or over the vertices each batch looked up")
    g.add_argument("--lr-final", type=float, default=0.1,
                   help="learning rate at the end of the budget, as a fraction of the start (default 0.1)")
    g.add_argument("--average-from", type=float, default=None, metavar="FRACTION",
                   help="average the weights over the end of training, from this fraction of the budget "
                        "(e.g. 0.5; default off): sharper on new views, free at render time")
    g.add_argument("--code-levels", type=int, default=None, metavar="N",
                   help="coarse code levels while training (each 4x sparser; baked into the vertex codes at "
                        "the end, so the field stays a plain per-vertex field): surfaces that few views see "
                        "inherit their surroundings' appearance. 0 = off (default: TrainConfig's)")
    g.add_argument("--code-levels-until", type=float, default=None, metavar="FRACTION",
                   help="with --code-levels: bake the levels into the vertex codes at this fraction of the "
                        "budget (e.g. 0.3) and train plain per-vertex codes from there (default: to the end)")
    g.add_argument("--mask-weight", type=float, default=0.05,
                   help="weight of the mask BCE (used only when the data has alpha/masks)")
    g.add_argument("--max-minutes", type=float, default=None,
                   help="stop after this many minutes of training (a checkpoint is written)")
    g.add_argument("--checkpoint-every", type=int, default=500, help="steps between checkpoints")
    g.add_argument("--log-every", type=int, default=5,
                   help="steps between progress reports (default 5; speed is averaged over them). A terminal "
                        "redraws one line; a log file gets a line per 10%% of the budget or per 30 s")
    g.add_argument("--threads", type=int, default=None, help="CPU threads for torch (default: all)")
    g.add_argument("--seed", type=int, default=0, help="random seed")


def _add_data_options(ap, required=True):
    g = ap.add_argument_group("data")
    g.add_argument("--data", required=required,
                   help="dataset folder: NeRF-synthetic/Blender (transforms_*.json), NeuS/DTU "
                        "(cameras_sphere.npz + image(s)/ + mask/), instant-ngp/nerfstudio (transforms.json) "
                        "or COLMAP (sparse/0 + images/; `neumesh poses` makes one from photos)")
    g.add_argument("--downscale", type=float, default=None,
                   help="image downscale factor (2 = half resolution); cameras are scaled to match. Default 1, "
                        "except photos over 1600 px, which are reduced to at most 1600 (said when loading)")
    g.add_argument("--background", choices=["white", "black"], default="white",
                   help="background colour that Blender-format RGBA images are composited on")


def _train_config(args, checkpoint_path):
    import neumesh_core as nm

    extra = {k: v for k, v in (("code_levels", args.code_levels), ("code_levels_until", args.code_levels_until))
             if v is not None}
    try:
        return nm.TrainConfig(steps=args.steps, rays_per_batch=args.rays, lr_codes=args.lr_codes,
                              lr_decoders=args.lr_decoders, weight_tv=args.tv, tv_vertices=args.tv_vertices,
                              weight_mask=args.mask_weight,
                              lr_final_factor=args.lr_final, average_from=args.average_from,
                              max_seconds=None if args.max_minutes is None else args.max_minutes * 60,
                              checkpoint_path=checkpoint_path, checkpoint_every=args.checkpoint_every,
                              log_every=max(1, args.log_every),
                              threads=args.threads, seed=args.seed, **extra)
    except ValueError as exc:   # a config check: say it as an option error, not a traceback
        raise nm.NeuMeshError(f"training options: {exc}") from exc


def _field_config(args):
    import neumesh_core as nm

    return nm.FieldConfig(interpolation=args.interpolation, radius_scale=args.radius_scale,
                          radius=args.radius, grid_resolution=args.grid_res)


def _add_render_options(ap) -> None:
    ap.add_argument("--supersample", type=int, default=1,
                    help="S x S rays per pixel, averaged (anti-aliasing; S^2 times slower; default 1)")
    ap.add_argument("--step-scale", type=float, default=None,
                    help="marching step / field radius (default: the step the field was trained with; "
                         "half of it renders finer, twice as slowly)")
    ap.add_argument("--background-model", choices=["on", "off"], default="on",
                    help="a field of a real capture: render its background (on, default: the photo-like "
                         "frame) or the object alone (off)")


def _add_device_option(ap) -> None:
    from ..device import DEVICE_CHOICES

    ap.add_argument("--device", default="cpu", metavar="|".join(DEVICE_CHOICES),
                    help="torch device to train/render on: cpu (default), cuda, cuda:N, or auto "
                         "(CUDA when torch sees a GPU)")


def _device(args):
    from ..device import resolve_device

    return resolve_device(getattr(args, "device", "cpu"))


def _render_settings(args):
    import neumesh_core as nm

    return nm.RenderSettings(supersample=args.supersample, step_scale=args.step_scale,
                             background_model=getattr(args, "background_model", "on") == "on")


def _held_out_split(scene, name=None) -> str:
    """The name of ``scene``'s split ``name``, or without a name of its held-out views: 'test' where the
    dataset has one, else 'val' (a phone capture holds out every 8th photo as 'val'). A split the scene
    lacks is a NeuMeshError that names the ones it has."""
    from ..errors import NeuMeshError

    if name is None:
        name = "test" if "test" in scene.splits else "val"
    if name not in scene.splits:
        raise NeuMeshError(f"the dataset has no '{name}' split; use --split with one of "
                           f"{', '.join(sorted(scene.splits))}")
    return name


def _scene_background(scene):
    return scene.background if scene.background is not None else (0.0, 0.0, 0.0)


def _print_eval(r: dict) -> None:
    keys = [k for k in r["mean"] if k != "render_s"]
    print("view".ljust(24) + "".join(k.rjust(10) for k in keys))
    for row in r["views"]:
        print(str(row["view"])[-24:].ljust(24) + "".join(f"{row[k]:10.4f}" for k in keys))
    print("mean".ljust(24) + "".join(f"{r['mean'][k]:10.4f}" for k in keys))
    if not r["lpips_available"]:
        print("lpips: unavailable (no local weights; see README 'Metrics')")


def turntable_cameras(centre, radius: float, n: int, width: int, height: int, fov_deg: float = 40.0,
                      elevation_deg: float = 25.0):
    """n cameras on a circle around ``centre`` (z up), OpenCV c2w."""
    import neumesh_core as nm
    from ..data.synthetic import look_at_opencv

    K = nm.intrinsics_from_fov(np.radians(fov_deg), width, height)
    el = np.radians(elevation_deg)
    c2ws = []
    for i in range(n):
        az = 2 * np.pi * i / n
        pos = np.asarray(centre) + radius * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        c2ws.append(look_at_opencv(pos, centre))
    return nm.Cameras(np.repeat(K[None], n, 0), np.stack(c2ws), width, height)


def _render_cameras(field, cams, out_dir, background, settings=None, prefix="frame", progress=None):
    import neumesh_core as nm

    os.makedirs(out_dir, exist_ok=True)
    times = []
    progress = progress or Progress()
    for i in range(len(cams)):
        out = nm.render_camera(field, cams.K[i], cams.c2w[i], cams.width, cams.height, background=background,
                               settings=settings)
        nm.save_image(os.path.join(out_dir, f"{prefix}_{i:04d}.png"), out.rgba(background))
        times.append(out.seconds)
        progress.update("rendering", (i + 1) / len(cams), f"{i + 1} of {len(cams)} frames ({out.seconds:.2f}s each)")
    progress.end(out_dir)
    return times
