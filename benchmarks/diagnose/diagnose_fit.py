"""Where does a trained field lose PSNR on held-out views?  Splits the foreground error by cause.

    python benchmarks/diagnose/diagnose_fit.py --field runs/fit_scan24/field.neumesh \
        --data ../shared/data/dtu/scan24 --downscale 4

Per view (foreground = mask > 0.5; needs masks or alpha):
  psnr_fg         the headline figure (as bench_fit reports it)
  uncovered       fraction of mask pixels the field leaves empty (opacity < 0.5): scaffold coverage
  psnr_covered    PSNR on the mask pixels the field does cover
  psnr_gain       after one best colour gain per view (exposure)
  psnr_shading    after a smooth (--sigma px) per-pixel colour correction (metrics.shading_corrected):
                  what is left is detail (blur, misalignment, texture), not lighting
  coverage        (unless --no-coverage) the mask pixels split by how many training views see their
                  surface point unoccluded (seen by <3, 3-9, >=10 views; depth maps of the training
                  cameras rendered at --coverage-scale): fraction, PSNR and share of the squared error
                  in each group.  Error in rarely seen parts is a capture limit; error on well-seen
                  surface is the field's (or the light's)
Prints a table and writes benchmarks/results/log/diagnose_<scene>.json.  Diagnostic only: the corrected
figures use the held-out images and are never results.
"""
from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from benchmarks._results import add_options, write_results  # noqa: E402


COVERAGE_GROUPS = {"<3": (0, 3), "3-9": (3, 10), ">=10": (10, 1 << 30)}


def coverage_split(pred, gt, covered, depth, K, c2w, cov_cams, cov_depths) -> dict:
    """Split the error on the covered mask pixels by how many coverage views see their surface."""
    import numpy as np

    from neumesh_core.evaluate import surface_points, view_coverage

    ys, xs = np.nonzero(covered & np.isfinite(depth))
    counts = view_coverage(surface_points(K, c2w, depth, np.stack([xs, ys], 1)), cov_cams, cov_depths)
    se = ((pred[ys, xs] - gt[ys, xs]) ** 2).mean(-1)
    out = {}
    for name, (lo, hi) in COVERAGE_GROUPS.items():
        g = (counts >= lo) & (counts < hi)
        out[name] = {"fraction": float(g.mean()) if len(g) else 0.0,
                     "psnr": float(-10 * np.log10(max(se[g].mean(), 1e-12))) if g.any() else float("nan"),
                     "error_share": float(se[g].sum() / max(se.sum(), 1e-12))}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "field", "data", "results_dir", field=dict(required=True, help="trained field (.neumesh)"),
                data=dict(required=True, help="dataset folder (Blender or DTU format)"))
    ap.add_argument("--downscale", type=float, default=1)
    ap.add_argument("--split", default="val")
    ap.add_argument("--sigma", type=float, default=16.0, help="shading correction blur (px)")
    ap.add_argument("--no-coverage", action="store_true", help="skip the training-view coverage split")
    ap.add_argument("--coverage-split", default="train", help="views that count for coverage")
    ap.add_argument("--coverage-scale", type=float, default=0.5, help="resolution of their depth maps")
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
    cov_cams = cov_depths = None
    if not args.no_coverage:
        cov_cams = scene.split(args.coverage_split).cameras.scaled(args.coverage_scale)
        cov_depths = np.stack([render_camera(field, cov_cams.K[j], cov_cams.c2w[j], cov_cams.width,
                                             cov_cams.height, background=(0.0, 0.0, 0.0)).depth
                               for j in range(len(cov_cams))])
        print(f"coverage: depth maps of {len(cov_cams)} {args.coverage_split} views at "
              f"{cov_cams.width}x{cov_cams.height}")
    rows = []
    print(f"{'view':>10} {'psnr_fg':>8} {'uncov':>7} {'covered':>8} {'gain':>7} {'shading':>8}")
    for i in range(len(images)):
        cam = images.cameras
        out = render_camera(field, cam.K[i], cam.c2w[i], cam.width, cam.height, background=(0.0, 0.0, 0.0))
        gt, mask = images.float_view(i), images.float_mask(i) > 0.5
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
        if cov_cams is not None:
            row["coverage"] = coverage_split(pred, gt, covered, out.depth, cam.K[i], cam.c2w[i], cov_cams,
                                             cov_depths)
        rows.append(row)
        print(f"{row['view']:>10} {row['psnr_fg']:8.2f} {row['uncovered']:7.2%} {row['psnr_covered']:8.2f} "
              f"{row['psnr_gain']:7.2f} {row['psnr_shading']:8.2f}"
              + ("" if cov_cams is None else "   seen by " + "  ".join(
                  f"{k}: {g['fraction']:.0%} of px {g['psnr']:.2f} dB {g['error_share']:.0%} of err"
                  for k, g in row["coverage"].items())))
    keys = [k for k in rows[0] if k not in ("view", "coverage")]
    mean = {k: float(np.nanmean([r[k] for r in rows])) for k in keys}
    print(f"{'mean':>10} {mean['psnr_fg']:8.2f} {mean['uncovered']:7.2%} {mean['psnr_covered']:8.2f} "
          f"{mean['psnr_gain']:7.2f} {mean['psnr_shading']:8.2f}")
    name = os.path.basename(os.path.normpath(args.data))
    write_results({"field": args.field, "data": args.data, "downscale": args.downscale, "split": args.split,
                   "sigma": args.sigma, "mean": mean, "views": rows}, f"diagnose_{name}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
