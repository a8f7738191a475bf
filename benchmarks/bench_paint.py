"""Texture painting speed and quality on a trained field: a stroke of ~5,000 pixels on one 400^2 view.

    python benchmarks/bench_paint.py --field runs/lego/field.neumesh --data ../shared/data/nerf_synthetic/lego
    python benchmarks/bench_paint.py                                     # the built-in scene, trained briefly

The stroke is a band of rows through the middle of the object in the chosen view, cut to the object's
pixels (opacity > 0.95) and to ``--pixels`` pixels, painted in a saturated colour.  Prints the apply
time and its split (render: the painted pixels and the box around them; surface: the affected
vertices; weights: how the box's rays depend on their modification colours; solve), the PSNR inside
the stroke afterwards, how many pixels outside the stroke changed, and writes
benchmarks/results/paint_<name>.json.
"""
from __future__ import annotations

import argparse
import copy
import os
import platform
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import neumesh_core as nm  # noqa: E402
from neumesh_core.metrics import psnr  # noqa: E402
from _results import write_results  # noqa: E402


def stroke_mask(opacity: np.ndarray, pixels: int) -> np.ndarray:
    """A horizontal band through the object's middle rows, on opaque pixels, about ``pixels`` big."""
    solid = opacity > 0.95
    rows = np.nonzero(solid.any(1))[0]
    mid = int(np.median(rows))
    mask = np.zeros_like(solid)
    half = 1
    while True:
        band = np.zeros_like(solid)
        band[max(0, mid - half):mid + half + 1] = True
        mask = band & solid
        if mask.sum() >= pixels or half > opacity.shape[0]:
            break
        half += 1
    ys, xs = np.nonzero(mask)
    keep = np.argsort(np.abs(xs - np.median(xs)), kind="stable")[:pixels]   # the middle of the band
    out = np.zeros_like(mask)
    out[ys[keep], xs[keep]] = True
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", help="trained field (.neumesh); default: the built-in scene trained 1500 steps")
    ap.add_argument("--data", help="dataset whose camera is painted on (default: a turntable view)")
    ap.add_argument("--split", default="val")
    ap.add_argument("--view", type=int, default=0)
    ap.add_argument("--resolution", type=int, default=400, help="view size without --data (square)")
    ap.add_argument("--pixels", type=int, default=5000, help="stroke size in pixels (default 5,000)")
    ap.add_argument("--colour", default="1,0,0.8", help="paint colour r,g,b in [0,1] (default magenta)")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--name", default=None)
    ap.add_argument("--results-dir", default=None)
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.field:
        field = nm.load_field(args.field)
        name = args.name or os.path.basename(os.path.dirname(os.path.abspath(args.field)))
    else:
        scene = nm.load_scene(nm.default_scene_dir())
        field = nm.create_field(nm.load_mesh(scene.mesh_path))
        nm.train(field, scene, nm.TrainConfig(steps=1500))
        name = args.name or "default_scene"
    field.eval()
    if args.data:
        cams = nm.load_scene(args.data).split(args.split).cameras
        K, c2w, W, H = cams.K[args.view], cams.c2w[args.view], cams.width, cams.height
    else:
        from neumesh_core.cli import turntable_cameras

        bb = field.grid.aabb.cpu().numpy()
        cams = turntable_cameras(bb.mean(0), float(np.linalg.norm(bb[1] - bb[0])) * 1.1, 8, args.resolution,
                                 args.resolution)
        K, c2w, W, H = cams.K[1], cams.c2w[1], cams.width, cams.height
    before = nm.render_camera(field, K, c2w, W, H)
    mask = stroke_mask(before.opacity, args.pixels)
    colour = np.array([float(x) for x in args.colour.split(",")], np.float32)
    layer = np.zeros((H, W, 4), np.float32)
    layer[mask, :3] = colour
    layer[mask, 3] = 1.0
    edited = copy.deepcopy(field)
    t = time.perf_counter()
    rec = nm.paint_texture(edited, K, c2w, W, H, layer)
    apply_s = time.perf_counter() - t
    after = nm.render_camera(edited, K, c2w, W, H)
    p_in = float(psnr(np.clip(after.rgb[mask], 0, 1), np.broadcast_to(colour, (int(mask.sum()), 3))))
    delta = np.abs(after.rgb - before.rgb).max(-1)
    from scipy.ndimage import binary_dilation

    outside = ~binary_dilation(mask, iterations=2)
    i = rec.info
    print(f"{name}: {field.num_vertices:,} vertices, {W}x{H} view, stroke {int(mask.sum())} px")
    print(f"apply {apply_s:.2f} s: render {i['render_s']:.2f}, surface {i['surface_s']:.2f}, weights "
          f"{i['weights_s']:.2f}, solve {i['solve_s']:.2f} ({i['affected_vertices']:,} vertices, "
          f"{i['ring_pixels']:,} ring pixels, {i['box_pixels']:,} box pixels)")
    print(f"stroke PSNR {p_in:.2f} dB; pixels changed > 1/255 farther than 2 px from the stroke: "
          f"{int((delta[outside] > 1 / 255).sum())} (max {delta[outside].max():.4f})")
    result = {"field": args.field or "default scene (1500 steps)", "vertices": field.num_vertices,
              "view": {"data": args.data, "split": args.split, "index": args.view, "width": W, "height": H},
              "stroke_pixels": int(mask.sum()), "colour": colour.tolist(), "apply_s": apply_s,
              "split_s": {k: i[k] for k in ("render_s", "surface_s", "weights_s", "solve_s")},
              "affected_vertices": i["affected_vertices"], "ring_pixels": i["ring_pixels"],
              "stroke_psnr_db": p_in, "changed_outside_2px": int((delta[outside] > 1 / 255).sum()),
              "max_change_outside_2px": float(delta[outside].max()), "target_apply_s": 10.0,
              "machine": {"cpu": platform.processor() or platform.machine(), "threads": torch.get_num_threads()}}
    write_results(result, f"paint_{name}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
