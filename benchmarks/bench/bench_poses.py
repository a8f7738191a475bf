"""Real captures: load time and memory of a transforms.json/COLMAP capture at several
downscales, and poses recovered from its photos with pycolmap against the poses it ships.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench/bench_poses.py --data ../shared/data/real/fox \
        [--downscales 1 2 4] [--threads 2] [--max-image-size 1600] [--max-features 8192] [--skip-poses]

Load: each downscale in a fresh process (peak RSS is per process), first with an empty undistortion
cache (cold) then again (warm, the cache reused). ``--before-repo DIR`` (a checkout of an older commit,
e.g. ``git archive f2bf72a | tar -x -C /tmp/before``) measures the same loads with that code too
(``load_before``: photos stored as float32 before the uint8 storage). Poses: ``estimate_poses`` on the
photo folder (read in place), then a similarity (Umeyama on camera centres) maps the recovered cameras
onto the given ones; rotation error = angle of R_given^T R_aligned per camera, centre error relative to
the rig radius (mean distance of the given camera centres from their centroid). Goals: all
photos registered, median rotation error <= 1 deg, median centre error <= 1 % of the rig radius.
Writes benchmarks/results/log/poses_<name>.json (``--results-dir``; a section skipped keeps the file's).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, REPO)
from benchmarks._results import LOG_DIR, add_options, write_results  # noqa: E402

_LOAD_CHILD = r"""
import json, os, resource, sys, time
sys.path.insert(0, sys.argv[1])
import neumesh_core as nm
t0 = time.perf_counter()
s = nm.load_scene(sys.argv[2], downscale=float(sys.argv[3]), log=lambda m: None)
dt = time.perf_counter() - t0
imgs = sum(v.images.nbytes for v in s.splits.values())
tr = s.split("train")
print(json.dumps({"seconds": dt, "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "images_mib": imgs / 2**20, "width": tr.cameras.width, "height": tr.cameras.height,
                  "splits": {k: len(v) for k, v in s.splits.items()}, "kind": s.kind}))
"""


def bench_load(data: str, downscales, repo: str) -> dict:
    out = {}
    with tempfile.TemporaryDirectory(prefix="nm_cache_") as cache:
        env = dict(os.environ, NEUMESH_CACHE=cache, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore")
        base = subprocess.run([sys.executable, "-c", "import resource, neumesh_core; "
                               "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)"],
                              env=env, capture_output=True, text=True, check=True, cwd=repo)
        out["import_rss_mib"] = float(base.stdout.strip())
        for ds in downscales:
            row = {}
            for run in ("cold", "warm"):
                r = subprocess.run([sys.executable, "-c", _LOAD_CHILD, repo, data, str(ds)], env=env,
                                   capture_output=True, text=True, cwd=repo)
                if r.returncode:
                    raise SystemExit(r.stderr)
                row[run] = json.loads(r.stdout.strip().splitlines()[-1])
                print(f"load downscale {ds:g} {run}: {row[run]['seconds']:.2f} s, peak RSS "
                      f"{row[run]['peak_rss_mib']:.0f} MiB, images {row[run]['images_mib']:.0f} MiB "
                      f"({row[run]['width']}x{row[run]['height']})", flush=True)
            out[f"downscale_{ds:g}"] = row
    return out


def pose_agreement(est_c2w: np.ndarray, ref_c2w: np.ndarray) -> dict:
    """Similarity-align estimated cameras onto the given cameras (by centres) and measure the errors."""
    from neumesh_core.edit.align import umeyama

    ce, cr = est_c2w[:, :3, 3], ref_c2w[:, :3, 3]
    sim = umeyama(ce, cr, with_scale=True)
    c_al = sim.apply(ce)
    R_al = np.einsum("ij,njk->nik", sim.R, est_c2w[:, :3, :3])
    rel = np.einsum("nji,njk->nik", ref_c2w[:, :3, :3], R_al)
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    rot = np.degrees(np.arccos(cos))
    radius = float(np.linalg.norm(cr - cr.mean(0), axis=1).mean())
    cen = np.linalg.norm(c_al - cr, axis=1) / radius
    return {"rig_radius": radius, "rotation_deg": {"median": float(np.median(rot)), "mean": float(rot.mean()),
                                                   "max": float(rot.max())},
            "centre_rel": {"median": float(np.median(cen)), "mean": float(cen.mean()), "max": float(cen.max())},
            "scale": float(sim.scale)}


def bench_poses(data: str, args) -> dict:
    from neumesh_core.data.loader import read_capture
    from neumesh_core.data.colmap import read_colmap
    from neumesh_core.reconstruct.poses import PosesConfig, estimate_poses

    ref = read_capture(data)
    img_dir = os.path.dirname(ref.image_paths[0])
    out = args.poses_out or (None if args.poses_from else tempfile.mkdtemp(prefix="nm_poses_"))
    cfg = PosesConfig(max_image_size=args.max_image_size, max_num_features=args.max_features,
                      num_threads=args.threads, camera_model=args.camera_model)
    last = [0.0]

    def cb(p):
        if p.elapsed_s - last[0] > 20:
            last[0] = p.elapsed_s
            print(f"  {p.elapsed_s:6.0f} s  {p.stage}: {p.message}", flush=True)

    if args.poses_from:  # evaluate the model of an earlier run (its report gives the times)
        from neumesh_core.reconstruct.poses import PosesReport

        out = args.poses_from
        with open(os.path.join(out, "poses_report.json")) as fh:
            r = json.load(fh)
        r.pop("images", None)
        rep = PosesReport(**r)
        wall = rep.seconds
    else:
        t0 = time.perf_counter()
        rep = estimate_poses(img_dir, out, cfg, callback=cb)
        wall = time.perf_counter() - t0
    est = read_colmap(out)
    by_name = {os.path.basename(n): i for i, n in enumerate(ref.names)}
    pairs = [(i, by_name[os.path.basename(n)]) for i, n in enumerate(est.names) if os.path.basename(n) in by_name]
    ei, ri = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
    agree = pose_agreement(est.c2w[ei], ref.c2w[ri])
    res = {"photos": rep.num_images, "registered": rep.registered, "unregistered": rep.unregistered,
           "mean_reprojection_error_px": rep.mean_reprojection_error, "points": rep.num_points,
           "seconds": wall, "stage_seconds": rep.stage_seconds, "matcher": rep.matcher,
           "threads": args.threads, "max_image_size": args.max_image_size, "max_features": args.max_features,
           "camera_model": args.camera_model, "compared_cameras": len(pairs), **agree,
           "recovered_lens": est.lenses[0].to_dict(), "given_lens": ref.lenses[0].to_dict(),
           "goals": {"all_registered": rep.registered == rep.num_images,
                     "median_rotation_le_1deg": agree["rotation_deg"]["median"] <= 1.0,
                     "median_centre_le_1pct": agree["centre_rel"]["median"] <= 0.01},
           "loadavg_at_end": os.getloadavg()[0]}
    print(f"poses: {rep.registered}/{rep.num_images} registered in {wall:.0f} s ({args.threads} threads; "
          f"stages {', '.join(f'{k} {v:.0f} s' for k, v in rep.stage_seconds.items())}), reprojection "
          f"{rep.mean_reprojection_error:.2f} px; rotation median {agree['rotation_deg']['median']:.3f} deg, "
          f"centre median {100 * agree['centre_rel']['median']:.3f} % of the rig radius", flush=True)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "data", "name", "results_dir",
                data=dict(required=True, help="capture folder (transforms.json or COLMAP) with its photos"),
                name=dict(help="results name (default: the folder's name)"))
    ap.add_argument("--downscales", type=float, nargs="*", default=[1, 2, 4])
    ap.add_argument("--threads", type=int, default=2, help="pycolmap threads")
    ap.add_argument("--max-image-size", type=int, default=1600)
    ap.add_argument("--max-features", type=int, default=8192)
    ap.add_argument("--camera-model", default="OPENCV")
    ap.add_argument("--poses-out", default=None, help="where the recovered model goes (default: a temp folder)")
    ap.add_argument("--poses-from", default=None,
                    help="evaluate the model an earlier run wrote in this folder (no new reconstruction; its "
                         "poses_report.json gives the times; --threads/--max-* must name what that run used)")
    ap.add_argument("--skip-poses", action="store_true")
    ap.add_argument("--skip-load", action="store_true")
    ap.add_argument("--before-repo", default=None,
                    help="also measure the loads with the code of this folder (an older checkout) as load_before")
    args = ap.parse_args(argv)
    repo = REPO
    name = args.name or os.path.basename(os.path.normpath(args.data))
    res = {"data": name}
    if not args.skip_load:
        res["load"] = bench_load(os.path.abspath(args.data), args.downscales, repo)
        if args.before_repo:
            print(f"the same loads with {args.before_repo}:", flush=True)
            res["load_before"] = bench_load(os.path.abspath(args.data), args.downscales,
                                            os.path.abspath(args.before_repo))
            res["load_before"]["repo"] = args.before_repo
            res["load"]["loadavg_at_end"] = os.getloadavg()
    if not args.skip_poses:
        res["poses"] = bench_poses(os.path.abspath(args.data), args)
    old = os.path.join(args.results_dir or LOG_DIR, f"poses_{name}.json")
    if os.path.isfile(old):  # a section skipped in this run keeps its earlier figures
        with open(old) as fh:
            prev = json.load(fh)
        for key in ("load", "load_before", "poses"):
            if key not in res and key in prev:
                res[key] = prev[key]
    write_results(res, f"poses_{name}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
