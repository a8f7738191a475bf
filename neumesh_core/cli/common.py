"""Shared pieces of the command line: option groups, configs from options, the progress bar, the
evaluation table, turntable cameras and frame rendering."""
from __future__ import annotations

import os
import sys

import numpy as np


def _fmt_time(s: float) -> str:
    s = int(max(0, s))
    return f"{s // 3600:d}:{s % 3600 // 60:02d}:{s % 60:02d}"


class ProgressBar:
    """Terminal consumer of the training callback (one line, refreshed in place)."""

    def __init__(self, stream=None):
        self._stream = stream  # None: whatever sys.stderr is at write time (it can be swapped)
        self.tty = self.stream.isatty()

    @property
    def stream(self):
        return self._stream if self._stream is not None else sys.stderr

    def __call__(self, p) -> None:
        frac = p.step / max(1, p.total_steps)
        bar = "#" * int(30 * frac) + "-" * (30 - int(30 * frac))
        line = (f"[{bar}] {p.step}/{p.total_steps} loss {p.loss:.4f} psnr {p.psnr:5.2f} "
                f"{p.rays_per_sec / 1000:6.1f}k rays/s {p.samples_per_ray:4.1f} smp/ray "
                f"elapsed {_fmt_time(p.elapsed_s)} eta {_fmt_time(p.eta_s)}")
        self.stream.write(("\r" + line) if self.tty else (line + "\n"))
        if self.tty and p.step >= p.total_steps:
            self.stream.write("\n")
        self.stream.flush()


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


def turntable_cameras(center, radius: float, n: int, width: int, height: int, fov_deg: float = 40.0,
                      elevation_deg: float = 25.0):
    """n cameras on a circle around ``center`` (z up), OpenCV c2w."""
    import neumesh_core as nm
    from ..data.synthetic import look_at_opencv

    K = nm.intrinsics_from_fov(np.radians(fov_deg), width, height)
    el = np.radians(elevation_deg)
    c2ws = []
    for i in range(n):
        az = 2 * np.pi * i / n
        pos = np.asarray(center) + radius * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        c2ws.append(look_at_opencv(pos, center))
    return nm.Cameras(np.repeat(K[None], n, 0), np.stack(c2ws), width, height)


def _render_cameras(field, cams, out_dir, background, settings=None, prefix="frame"):
    import neumesh_core as nm

    os.makedirs(out_dir, exist_ok=True)
    times = []
    for i in range(len(cams)):
        out = nm.render_camera(field, cams.K[i], cams.c2w[i], cams.width, cams.height, background=background,
                               settings=settings)
        nm.save_image(os.path.join(out_dir, f"{prefix}_{i:04d}.png"), out.rgba(background))
        times.append(out.seconds)
        print(f"\rrendered {i + 1}/{len(cams)} ({out.seconds:.2f}s)", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    return times
