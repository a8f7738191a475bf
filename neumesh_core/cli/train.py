"""`neumesh train`: train a field from posed images and a scaffold mesh."""
from __future__ import annotations

import os
import sys

from .common import (Progress, _add_data_options, _add_device_option, _add_field_options,
                     _add_train_options, _device, _field_config, _print_eval, _train_config)


def cmd_train(args) -> int:
    import neumesh_core as nm

    device = _device(args)
    scene = nm.load_scene(args.data, downscale=args.downscale, background=args.background)
    if args.resume and os.path.exists(args.out):
        field = nm.load_field(args.out, device=device)
        done = field._checkpoint_meta.get("train_state", {}).get("step", 0)
        print(f"resuming {args.out} from step {done}", file=sys.stderr)
    else:
        mesh_path = args.mesh or scene.mesh_path
        if not mesh_path:
            print("error: no scaffold mesh. Pass --mesh MESH.ply, or build one with `neumesh scaffold "
                  "--data DIR --out mesh.ply` (or run `neumesh fit`, which does both).", file=sys.stderr)
            return 2
        mesh = nm.load_mesh(mesh_path)
        field = nm.create_field(mesh, _field_config(args), device=device)
        print(f"scaffold {mesh_path}: {mesh.num_vertices} vertices, radius {field.radius:.4g}",
              file=sys.stderr)
    progress = Progress()
    res = nm.train(field, scene, _train_config(args, args.out), progress=progress.training)
    progress.end()
    state = "interrupted (Ctrl-C)" if res.interrupted else ("stopped" if res.cancelled else "done")
    avg = f" (weights averaged over {res.averaged} snapshots)" if res.averaged else ""
    print(f"{state} at step {res.steps_done}: train psnr {res.final_psnr:.2f} in {res.seconds:.0f}s; "
          f"saved {args.out}{avg}", file=sys.stderr)
    if "val" in scene.splits and not res.interrupted and args.eval:
        r = nm.evaluate(field, scene.split("val"), background=scene.background,
                        masked=scene.kind == "dtu", progress=progress.count("evaluation", "views"))
        progress.end()
        _print_eval(r)
    return 130 if res.interrupted else 0


def add_commands(sub) -> None:
    p = sub.add_parser("train", help="train a field from posed images and a scaffold mesh",
                       description="Train a field. Progress shows loss, PSNR, rays/s and ETA. Ctrl-C "
                                   "saves the field and exits; --resume continues from it.")
    _add_data_options(p)
    p.add_argument("--mesh", help="scaffold mesh (.ply/.obj); default: the dataset's mesh.ply if present")
    p.add_argument("--out", required=True, help="field file to write (e.g. runs/lego.neumesh)")
    p.add_argument("--resume", action="store_true", help="continue training the field in --out")
    p.add_argument("--no-eval", dest="eval", action="store_false", help="skip evaluation on 'val'")
    _add_field_options(p)
    _add_train_options(p)
    _add_device_option(p)
    p.set_defaults(func=cmd_train)
