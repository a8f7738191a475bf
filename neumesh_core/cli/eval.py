"""`neumesh eval`: PSNR/SSIM(/LPIPS) of a field over a dataset split."""
from __future__ import annotations

import os

from .common import (Progress, _add_data_options, _add_device_option, _add_render_options, _device, _print_eval,
                     _render_settings)


def cmd_eval(args) -> int:
    import neumesh_core as nm
    from ..evaluate import write_json

    field = nm.load_field(args.field, device=_device(args))
    scene = nm.load_scene(args.data, downscale=args.downscale, background=args.background)
    masked = scene.kind == "dtu" if args.masked == "auto" else args.masked == "yes"
    progress = Progress()
    r = nm.evaluate(field, scene.split(args.split), background=scene.background, masked=masked,
                    out_dir=args.renders, settings=_render_settings(args),
                    progress=progress.count("evaluation", "views"))
    progress.end()
    _print_eval(r)
    if not scene.has_masks:
        from ..field.background import background_of

        has_bg = background_of(field) is not None
        print(f"full-frame figures ({len(scene.split(args.split))} held-out photos of '{args.split}'); background "
              "model " + (("on" if args.background_model == "on" else "off") if has_bg else
                          "absent (the field alone; train with `neumesh fit` for one)"))
    out = args.json or os.path.splitext(args.field)[0] + f"_eval_{args.split}.json"
    write_json({"field": args.field, "data": args.data, "split": args.split, **r}, out)
    print(f"wrote {out}")
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser("eval", help="PSNR/SSIM(/LPIPS) of a field over a dataset split; prints a table, "
                                    "writes JSON")
    p.add_argument("--field", required=True, help="field file (.neumesh)")
    _add_data_options(p)
    p.add_argument("--split", default="val", help="split to evaluate (default val)")
    p.add_argument("--masked", choices=["auto", "yes", "no"], default="auto",
                   help="foreground (mask) metrics: auto = yes for DTU")
    p.add_argument("--json", help="JSON output path (default: next to the field)")
    p.add_argument("--renders", help="also write the rendered images to this folder")
    _add_render_options(p)
    _add_device_option(p)
    p.set_defaults(func=cmd_eval)
