"""`neumesh demo`: the built-in scene made, trained, evaluated and rendered as a turntable."""
from __future__ import annotations

import os
import sys
import time

import numpy as np

from .common import Progress, _held_out_split, _print_eval, _render_cameras, turntable_cameras


def _comparison_figure(images, renders_dir, result, path, n=4):
    """Ground-truth images (top row) above the field's renders (bottom row), PSNR per view in the log."""
    import neumesh_core as nm

    n = min(n, len(images))
    top = np.concatenate([images.float_view(i) for i in range(n)], 1)
    views = result["views"][:n]
    bottom = np.concatenate([nm.read_image(os.path.join(renders_dir, f"{v['view'].replace('/', '_')}.png"))[..., :3]
                             for v in views], 1)
    nm.save_image(path, np.concatenate([top, bottom], 0))


def cmd_demo(args) -> int:
    import neumesh_core as nm
    from ..evaluate import write_json

    t0 = time.perf_counter()
    os.makedirs(args.out, exist_ok=True)
    progress = Progress()
    progress.say("1/4 making the built-in scene (procedural blob, ground-truth ray tracer)...")
    data = nm.default_scene_dir(small=args.small)
    scene = nm.load_scene(data)
    mesh = nm.load_mesh(scene.mesh_path)
    field = nm.create_field(mesh, nm.FieldConfig(interpolation=args.interpolation))
    progress.say(f"2/4 training {args.steps} steps on {len(scene.split('train'))} views "
                 f"({mesh.num_vertices} scaffold vertices)...")
    path = os.path.join(args.out, "field.neumesh")
    cfg = nm.TrainConfig(steps=args.steps, rays_per_batch=args.rays, checkpoint_path=path)
    res = nm.train(field, scene, cfg, progress=progress.training)
    progress.end()
    if res.interrupted:
        print(f"interrupted; the field so far is in {path}", file=sys.stderr)
        return 130
    progress.say("3/4 evaluating on the held-out test views...")
    split = _held_out_split(scene)
    renders = os.path.join(args.out, "test_renders")
    r = nm.evaluate(field, scene.split(split), background=scene.background, out_dir=renders,
                    progress=progress.count("evaluation", "views"))
    progress.end()
    _print_eval(r)
    fig = os.path.join(args.out, "comparison.png")
    _comparison_figure(scene.split(split), renders, r, fig)
    print(f"comparison figure (truth top, field bottom): {fig}", file=sys.stderr)
    write_json({"data": data, "split": split, "steps": res.steps_done, "train_s": res.seconds, **r},
               os.path.join(args.out, "eval.json"))
    progress.say("4/4 rendering a turntable...")
    cams = turntable_cameras((0, 0, 0), 4.0, args.frames, scene.split("train").cameras.width,
                             scene.split("train").cameras.height)
    _render_cameras(field, cams, os.path.join(args.out, "turntable"), scene.background, progress=progress)
    print(f"demo done in {time.perf_counter() - t0:.0f}s: test PSNR {r['mean']['psnr']:.2f} dB, "
          f"SSIM {r['mean']['ssim']:.4f}; field {path}; turntable in {args.out}/turntable")
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser("demo", help="the main job on the built-in scene: make it, train, evaluate, render a "
                                    "turntable, print PSNR")
    p.add_argument("--out", default="outputs/demo", help="output folder (default outputs/demo)")
    p.add_argument("--steps", type=int, default=1500, help="training steps (default 1500)")
    p.add_argument("--rays", type=int, default=4096, help="rays per step (default 4096)")
    p.add_argument("--frames", type=int, default=24, help="turntable frames (default 24)")
    p.add_argument("--small", action="store_true", help="use the small (64 px) built-in scene")
    p.add_argument("--interpolation", choices=["post", "early"], default="post",
                   help="decoder interpolation (see `neumesh train --help`)")
    p.set_defaults(func=cmd_demo)
