"""Recovered vs given poses: train a real capture from the poses it ships and from the poses
``neumesh poses`` recovered from its photos, same budget, and compare held-out PSNR.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench/bench_poses_train.py --data /work/shared/data/real/fox \
        --recovered /work/runs/fox_poses --downscale 4 --minutes 15 --threads 1

``--recovered``: a folder written by ``neumesh poses`` (or ``benchmarks/bench/bench_poses.py --poses-out``).
Its model lives in COLMAP's own gauge (arbitrary position, rotation and scale), so it is first moved
onto the given cameras with the similarity of ``bench_poses.pose_agreement`` (Umeyama on the camera
centres of the photos both name) and written as a COLMAP model under ``<work>/recovered_aligned``
(pycolmap ``Reconstruction.transform``; the photos stay where they are). Its sparse points are dropped
so that both runs see cameras only (the given transforms.json has none): the runs differ only in the
poses and lenses (the recovered OPENCV lens undistorts the photos itself). Both runs get the same
object box (automatic, from the given training cameras), the background model, the same scaffold and
the same wall-clock training budget, and run side by side (one process each, ``--threads`` threads
each) so that they share the machine's load. The scaffold (density method, ~60k vertices) is built
once from the given poses and copied to the recovered run (both are in the given frame after the
alignment): the comparison isolates what the poses cost the training, and halves the CPU time on a
loaded machine; ``--own-scaffold`` builds the recovered run's scaffold from its own poses instead.

Held-out photos: every 8th (the same photos in both runs; checked). Figures (mean over them, the
background model rendered on):
  * ``given``: the given field at the given held-out cameras;
  * ``recovered_own``: the recovered field at the recovered held-out cameras (aligned), its own
    undistortion of the photos: what a user who only has photos gets (the main comparison);
  * ``recovered_at_given``: the recovered field at the given held-out cameras and images: adds the
    disagreement between the two pose sets at the held-out views (about 0.7 deg on fox) to the cost.
Goal: the recovered poses cost <= 0.5 dB (given - recovered_own). Writes
benchmarks/results/log/poses_train_<name>.json. Timings are wall-clock on whatever machine runs it.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, REPO)
from benchmarks._results import add_options, use_threads, write_results  # noqa: E402


def align_recovered(recovered: str, given: str, out_root: str, keep_points: bool = False) -> dict:
    """Write the recovered COLMAP model of ``recovered`` moved onto the cameras of ``given`` (a capture
    folder) as a COLMAP folder ``out_root`` (sparse/0 + poses_report.json naming the photo folder);
    returns the similarity and the residual centre error."""
    import pycolmap

    from benchmarks.bench.bench_poses import pose_agreement
    from neumesh_core.data.colmap import REPORT_NAME, find_model, read_colmap
    from neumesh_core.data.loader import read_capture
    from neumesh_core.edit.align import umeyama

    ref, est = read_capture(given), read_colmap(recovered)
    by_name = {os.path.basename(n): i for i, n in enumerate(ref.names)}
    pairs = [(i, by_name[os.path.basename(n)]) for i, n in enumerate(est.names) if os.path.basename(n) in by_name]
    if len(pairs) < 3:
        raise SystemExit(f"{recovered} and {given} share {len(pairs)} photo names; at least 3 are needed")
    ei, ri = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
    sim = umeyama(est.c2w[ei, :3, 3], ref.c2w[ri, :3, 3], with_scale=True)
    rec = pycolmap.Reconstruction(find_model(recovered))
    rec.transform(pycolmap.Sim3d(sim.scale, pycolmap.Rotation3d(sim.R), sim.t))
    if not keep_points:
        for pid in list(rec.point3D_ids()):
            rec.delete_point3D(pid)
    model = os.path.join(out_root, "sparse", "0")
    tmp = model + ".tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    os.makedirs(tmp)
    rec.write(tmp)
    shutil.rmtree(model, ignore_errors=True)
    os.replace(tmp, model)
    with open(os.path.join(recovered, REPORT_NAME)) as fh:
        report = json.load(fh)
    img = report.get("images") or os.path.dirname(est.image_paths[0])
    report["images"] = os.path.abspath(img if os.path.isabs(img) else os.path.join(recovered, img))
    with open(os.path.join(out_root, REPORT_NAME), "w") as fh:
        json.dump(report, fh, indent=2)
    chk = read_colmap(out_root)
    ci = np.array([by_name[os.path.basename(n)] for n in chk.names])
    agree = pose_agreement(chk.c2w, ref.c2w[ci])  # after the move the best similarity is ~identity
    return {"scale": sim.scale, "rotation": sim.R.tolist(), "translation": np.asarray(sim.t).tolist(),
            "shared_photos": len(pairs), "points_kept": keep_points, "residual_scale": agree["scale"],
            "rotation_deg": agree["rotation_deg"], "centre_rel": agree["centre_rel"]}


def run_arm(args) -> int:
    """One training run (a child process): fit with the given object box, then evaluate."""

    import neumesh_core as nm
    from neumesh_core.data.frame import object_box
    from neumesh_core.fit import fit
    from neumesh_core.reconstruct.build import ScaffoldConfig
    from neumesh_core.render.renderer import RenderSettings
    from neumesh_core.train.trainer import TrainConfig

    use_threads(args.threads)
    given = nm.load_scene(args.data, downscale=args.downscale, log=lambda m: None)
    box = object_box(given.split("train").cameras.c2w, None)
    data = args.data if args.arm == "given" else os.path.join(args.work, "recovered_aligned")
    out = os.path.join(args.work, args.arm)
    os.makedirs(out, exist_ok=True)
    if args.scaffold and not os.path.isfile(os.path.join(out, "scaffold.ply")):  # an earlier run's, for both
        shutil.copyfile(args.scaffold, os.path.join(out, "scaffold.ply.tmp"))
        os.replace(os.path.join(out, "scaffold.ply.tmp"), os.path.join(out, "scaffold.ply"))
    if args.arm == "recovered" and not args.own_scaffold and not os.path.isfile(os.path.join(out, "scaffold.ply")):
        src = os.path.join(args.work, "given", "scaffold.ply")
        print(f"[recovered] waiting for the given run's scaffold ({src})", file=sys.stderr, flush=True)
        while not os.path.isfile(src):
            time.sleep(5)
        time.sleep(2)  # save_mesh has finished writing
        shutil.copyfile(src, os.path.join(out, "scaffold.ply.tmp"))
        os.replace(os.path.join(out, "scaffold.ply.tmp"), os.path.join(out, "scaffold.ply"))
    scfg = ScaffoldConfig(method="density", compute_iou=False, chamfer_samples=0)
    scfg.density_iters, scfg.density_resolutions, scfg.target_vertices = (150, 150), (48, 96), 60_000
    tcfg = TrainConfig(steps=10**7, max_seconds=args.minutes * 60.0, threads=args.threads, log_every=100,
                       checkpoint_every=10**9, seed=args.seed)
    t0 = time.perf_counter()

    def log(m):
        print(f"[{args.arm}] {m}", file=sys.stderr, flush=True)

    def cb(p):
        if p.step % 100 == 0:
            log(f"step {p.step} train psnr {p.psnr:.2f} {p.elapsed_s:.0f}s")

    if args.eval_only:  # the run trained already (fit.json written): evaluate its field again
        with open(os.path.join(out, "fit.json")) as fh:
            summary = json.load(fh)
    else:
        summary = fit(data, out, downscale=args.downscale, background=None, scaffold_config=scfg, train_config=tcfg,
                      train_progress=cb, evaluate_split="none", log=log, box=box, background_model=True)
    field = nm.load_field(os.path.join(out, "field.neumesh"))
    st = RenderSettings(background_model=True)
    evals = {"given": given.split("val")} if args.arm == "given" else {}
    if args.arm == "recovered":
        own = nm.load_scene(data, downscale=args.downscale, log=lambda m: None).split("val")
        base = [[os.path.basename(n) for n in s.names] for s in (own, given.split("val"))]
        if base[0] != base[1]:
            raise SystemExit(f"held-out photos differ: recovered {own.names} vs given {given.split('val').names}")
        evals = {"recovered_own": own, "recovered_at_given": given.split("val")}
    res = {"arm": args.arm, "data": data, "scaffold": summary.get("scaffold"), "train": summary.get("train"),
           "scaffold_shared": args.arm == "recovered" and not args.own_scaffold,
           "held_out": list(given.split("val").names)}
    for key, val in evals.items():
        ev = nm.evaluate(field, val, background=(0.0, 0.0, 0.0), settings=st)
        res[key] = {"psnr": ev["mean"]["psnr"], "ssim": ev["mean"]["ssim"], "render_s": ev["mean"]["render_s"],
                    "per_view_psnr": [float(v["psnr"]) for v in ev["views"]]}
        log(f"held-out {key}: PSNR {ev['mean']['psnr']:.2f} SSIM {ev['mean']['ssim']:.3f}")
    res["total_s"] = time.perf_counter() - t0
    res["loadavg_at_end"] = os.getloadavg()
    tmp = os.path.join(out, "arm.json.tmp")
    with open(tmp, "w") as fh:
        json.dump(res, fh, indent=2, default=float)
    os.replace(tmp, os.path.join(out, "arm.json"))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "data", "threads", "name", "results_dir",
                data=dict(default="/work/shared/data/real/fox", help="the capture with its given poses"),
                threads=dict(default=1, help="torch threads of each run"))
    ap.add_argument("--recovered", default="/work/runs/fox_poses", help="folder written by `neumesh poses`")
    ap.add_argument("--downscale", type=float, default=4)
    ap.add_argument("--minutes", type=float, default=15.0, help="training budget of each run (wall minutes)")
    ap.add_argument("--work", default=None, help="working folder (default /work/runs/<name>_posecmp)")
    ap.add_argument("--arm", choices=("given", "recovered"), default=None, help=argparse.SUPPRESS)
    ap.add_argument("--collect", action="store_true", help="only merge the runs already in --work")
    ap.add_argument("--eval-only", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--seed", type=int, default=0, help="training seed (both runs)")
    ap.add_argument("--scaffold", default=None, help="a scaffold.ply both runs start from (e.g. an earlier run's)")
    ap.add_argument("--own-scaffold", action="store_true",
                    help="the recovered run builds its own scaffold (default: a copy of the given run's)")
    args = ap.parse_args(argv)
    name = args.name or f"{os.path.basename(os.path.normpath(args.data))}_ds{args.downscale:g}_{args.minutes:g}min"
    args.work = args.work or f"/work/runs/{name}_posecmp"
    if args.arm:
        return run_arm(args)
    os.makedirs(args.work, exist_ok=True)
    res = {"data": os.path.basename(os.path.normpath(args.data)), "recovered_model": args.recovered,
           "downscale": args.downscale, "minutes_each": args.minutes, "threads_each": args.threads,
           "seed": args.seed, "scaffold": args.scaffold or ("built by the given run, copied to the recovered run"
                                                           if not args.own_scaffold else "each run its own"),
           "machine": "shared machine, loaded by other jobs: step counts and times are upper bounds"}
    align_path = os.path.join(args.work, "alignment.json")
    if not args.collect:
        res["alignment"] = align_recovered(args.recovered, args.data, os.path.join(args.work, "recovered_aligned"))
        with open(align_path, "w") as fh:
            json.dump(res["alignment"], fh, indent=2)
        a = res["alignment"]
        print(f"aligned: scale {a['scale']:.4f}, residual centre median {100 * a['centre_rel']['median']:.3f} % "
              f"of the rig, rotation median {a['rotation_deg']['median']:.3f} deg", flush=True)
        env = dict(os.environ, OMP_NUM_THREADS=str(args.threads), PYTHONPATH=REPO)
        base = [sys.executable, os.path.abspath(__file__), "--data", args.data, "--recovered", args.recovered,
                "--downscale", str(args.downscale), "--minutes", str(args.minutes), "--threads", str(args.threads),
                "--work", args.work, "--seed", str(args.seed)] + (["--own-scaffold"] if args.own_scaffold else []) + \
            (["--scaffold", os.path.abspath(args.scaffold)] if args.scaffold else [])
        procs = [subprocess.Popen(base + ["--arm", arm], env=env, cwd=REPO) for arm in ("given", "recovered")]
        codes = [p.wait() for p in procs]
        if any(codes):
            raise SystemExit(f"a training run failed (exit codes {codes}); see its output above")
    else:
        with open(align_path) as fh:
            res["alignment"] = json.load(fh)
    for arm in ("given", "recovered"):
        with open(os.path.join(args.work, arm, "arm.json")) as fh:
            res[arm] = json.load(fh)
    g = res["given"]["given"]["psnr"]
    r_own = res["recovered"]["recovered_own"]["psnr"]
    r_at = res["recovered"]["recovered_at_given"]["psnr"]
    res["psnr_cost_db"] = {"recovered_own": g - r_own, "recovered_at_given": g - r_at}
    res["psnr_recovered_minus_given_db"] = {"recovered_own": r_own - g, "recovered_at_given": r_at - g}
    res["goal_cost_le_0p5db"] = (g - r_own) <= 0.5
    write_results(res, f"poses_train_{name}.json", args.results_dir)
    print(f"held-out PSNR: given {g:.2f} dB, recovered {r_own:.2f} dB (own held-out cameras; {r_at:.2f} dB at "
          f"the given ones); cost {g - r_own:+.2f} dB (goal <= 0.5)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
