"""`neumesh render`: render a field to PNG images (dataset cameras or a turntable)."""
from __future__ import annotations

import numpy as np

from .common import (_add_device_option, _add_render_options, _device, _held_out_split, _render_cameras,
                     _render_settings, turntable_cameras)


def cmd_render(args) -> int:
    import neumesh_core as nm

    field = nm.load_field(args.field, device=_device(args))
    bg = (1.0, 1.0, 1.0) if args.background == "white" else (0.0, 0.0, 0.0)
    if args.data:
        scene = nm.load_scene(args.data, downscale=args.downscale, background=args.background)
        cams = scene.split(_held_out_split(scene, args.split)).cameras
    else:
        w, h = (int(v) for v in args.resolution.lower().split("x"))
        bb = field.grid.aabb.cpu().numpy()
        centre = bb.mean(0)
        dist = float(np.linalg.norm(bb[1] - bb[0])) * 1.3
        cams = turntable_cameras(centre, dist, args.frames, w, h)
    times = _render_cameras(field, cams, args.out, bg, _render_settings(args))
    print(f"wrote {len(times)} images to {args.out}; mean {np.mean(times):.2f}s per frame")
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser("render", help="render a field to PNG images (dataset cameras or a turntable)")
    p.add_argument("--field", required=True, help="field file (.neumesh)")
    p.add_argument("--out", required=True, help="output folder for RGBA PNGs")
    p.add_argument("--data", help="render the cameras of this dataset (else a turntable)")
    p.add_argument("--split", default=None,
                   help="dataset split whose cameras to render (default: test, or val where there is no test)")
    p.add_argument("--downscale", type=float, default=1, help="downscale of the dataset cameras")
    p.add_argument("--frames", type=int, default=36, help="turntable frames (default 36)")
    p.add_argument("--resolution", default="400x400", help="turntable image size WxH (default 400x400)")
    p.add_argument("--background", choices=["white", "black"], default="white", help="background colour")
    _add_render_options(p)
    _add_device_option(p)
    p.set_defaults(func=cmd_render)
