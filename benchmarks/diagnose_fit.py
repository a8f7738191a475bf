"""Where does a trained field lose PSNR on held-out views?  Splits the foreground error by cause.

    python benchmarks/diagnose_fit.py --field runs/fit_scan24/field.neumesh --data ../shared/data/dtu/scan24 --downscale 4

Per view (foreground = mask > 0.5; needs masks or alpha):
  psnr_fg         the headline figure (as bench_fit reports it)
  uncovered       fraction of mask pixels the field leaves empty (opacity < 0.5): scaffold coverage
  psnr_covered    PSNR on the mask pixels the field does cover
  psnr_gain       after one best colour gain per view (exposure)
  psnr_shading    after a smooth (--sigma px) per-pixel colour correction (metrics.shading_corrected):
                  what is left is detail (blur, misalignment, texture), not lighting
Prints a table and writes benchmarks/results/diagnose_<scene>.json.  Diagnostic only: the corrected
figures use the held-out images and are never results.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", required=True, help="trained field (.neumesh)")
    ap.add_argument("--data", required=True, help="dataset folder (Blender or DTU format)")
    ap.add_argument("--downscale", type=float, default=1)
    ap.add_argument("--split", default="val")
    ap.add_argument("--sigma", type=float, default=16.0, help="shading correction blur (px)")
    ap.add_argument("--out", default=None, help="JSON path (default benchmarks/results/diagnose_<scene>.json)")
    args = ap.parse_args(argv)

    import numpy as np

    import neumesh_core as nm
    from neumesh_core import metrics
    from neumesh_core.render.renderer import render_camera

    scene = nm.load_scene(args.data, downscale=args.downscale)
    images = scene.split(args.split)
    if images.masks is None:
        print("this dataset has no masks/alpha: the diagnosis needs a foreground", file=sys.stderr)
        return 2
    field = nm.load_field(args.field)
    rows = []
    print(f"{'view':>10} {'psnr_fg':>8} {'uncov':>7} {'covered':>8} {'gain':>7} {'shading':>8}")
    for i in range(len(images)):
        cam = images.cameras
        out = render_camera(field, cam.K[i], cam.c2w[i], cam.width, cam.height, background=(0.0, 0.0, 0.0))
        gt, mask = images.images[i], images.masks[i] > 0.5
        pred = np.clip(out.rgb, 0.0, 1.0)
        covered = mask & (out.opacity >= 0.5)
        g = (gt[mask] * pred[mask]).sum(0) / np.maximum((pred[mask] ** 2).sum(0), 1e-12)
        row = {
            "view": images.names[i] if images.names else str(i),
            "psnr_fg": metrics.masked_psnr(pred, gt, mask),
            "uncovered": float((mask & ~covered).sum() / max(mask.sum(), 1)),
            "psnr_covered": metrics.masked_psnr(pred, gt, covered) if covered.any() else float("nan"),
            "psnr_gain": metrics.masked_psnr(np.clip(pred * g, 0, 1), gt, mask),
            "psnr_shading": metrics.masked_psnr(metrics.shading_corrected(pred, gt, mask, args.sigma), gt, mask),
        }
        rows.append(row)
        print(f"{row['view']:>10} {row['psnr_fg']:8.2f} {row['uncovered']:7.2%} {row['psnr_covered']:8.2f} "
              f"{row['psnr_gain']:7.2f} {row['psnr_shading']:8.2f}")
    keys = [k for k in rows[0] if k != "view"]
    mean = {k: float(np.nanmean([r[k] for r in rows])) for k in keys}
    print(f"{'mean':>10} {mean['psnr_fg']:8.2f} {mean['uncovered']:7.2%} {mean['psnr_covered']:8.2f} "
          f"{mean['psnr_gain']:7.2f} {mean['psnr_shading']:8.2f}")
    name = os.path.basename(os.path.normpath(args.data))
    path = args.out or os.path.join(HERE, "results", f"diagnose_{name}.json")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as fh:
        json.dump({"field": args.field, "data": args.data, "downscale": args.downscale, "split": args.split,
                   "sigma": args.sigma, "mean": mean, "views": rows}, fh, indent=2)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
