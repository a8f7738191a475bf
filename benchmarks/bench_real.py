"""Real captures: fit a phone capture without masks, scaffold included, and measure the
held-out photos full frame (every 8th photo), with the background model on and off.

    .venv/bin/python benchmarks/bench_real.py --data /work/shared/data/real/fox --downscale 4 \
        --minutes 60 --threads 2 --name fox_ds4_60min
    .venv/bin/python benchmarks/bench_real.py --minutes 3 --threads 1 --smoke --name fox_smoke

Figures (JSON in benchmarks/results/real_<name>.json): scaffold vertices and seconds, training
steps and seconds, held-out PSNR/SSIM with the field's background model rendered on, and the same
field rendered with it off (the object alone on black: what the background model brings), render
seconds of one frame on/off, peak memory (ru_maxrss).  ``--no-background-model`` trains without a
background model (the field alone explains the whole frame) for the comparison.  ``--minutes`` is
the training budget; a 15- and a 60-minute figure are two runs.  ``--smoke``: small scaffold budget
and ``--eval-views`` held-out photos only (a pipeline check, not a quality figure).  ``--pictures
DIR`` writes each held-out photo beside its render (never commit pictures of the photos).
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from benchmarks._results import write_results  # noqa: E402


def score_views(field, images) -> dict:
    """PSNR/SSIM of each photo of ``images`` against the field's render with its background model on,
    and PSNR split where the field's object covers the frame (its own opacity > 0.5: "object") and
    where the background model does ("room")."""
    import numpy as np

    from neumesh_core import metrics
    from neumesh_core.render.renderer import render_camera

    cam, rows = images.cameras, []
    for i in range(len(images)):
        out = render_camera(field, cam.K[i], cam.c2w[i], cam.width, cam.height, background=(0.0, 0.0, 0.0))
        gt, pred = images.float_view(i), np.clip(out.rgb, 0.0, 1.0)
        obj = (out.opacity > 0.5).astype(np.float32)
        rows.append({"view": images.names[i] if images.names else str(i), "psnr": metrics.psnr(pred, gt),
                     "ssim": metrics.ssim(pred, gt), "object_share": float(obj.mean()),
                     "psnr_object": metrics.masked_psnr(pred, gt, obj) if obj.any() else float("nan"),
                     "psnr_room": metrics.masked_psnr(pred, gt, 1.0 - obj) if not obj.all() else float("nan"),
                     "render_s": out.seconds})
    mean = {k: float(np.nanmean([r[k] for r in rows])) for k in rows[0] if k != "view"}
    return {"mean": mean, "views": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="/work/shared/data/real/fox")
    ap.add_argument("--downscale", type=float, default=4)
    ap.add_argument("--minutes", type=float, default=15.0, help="training budget (wall minutes)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=10**7, help="training steps (the budget is whichever ends first: "
                    "equal-step comparisons on a busy machine)")
    ap.add_argument("--out", default=None, help="working folder (default: /tmp/bench_real_<name>)")
    ap.add_argument("--name", default=None)
    ap.add_argument("--smoke", action="store_true")
    ap.add_argument("--eval-views", type=int, default=0, help="held-out photos evaluated (0: all)")
    ap.add_argument("--no-background-model", action="store_true")
    ap.add_argument("--pictures", default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--results-dir", default=None, help="where the JSON goes (default benchmarks/results)")
    ap.add_argument("--appearance", action="store_true", help="per-image appearance codes while training")
    ap.add_argument("--background-tv", type=float, default=None,
                    help="weight of the background planes' total variation (default: TrainConfig's)")
    ap.add_argument("--snapshot-minutes", type=float, default=None,
                    help="also save the field at this training minute and evaluate it (e.g. 15 in a 60-minute run)")
    ap.add_argument("--scaffold", default=None, help="reuse this scaffold.ply (its build time is not counted)")
    ap.add_argument("--off-views", type=int, default=0,
                    help="held-out photos evaluated with the background off (0: all)")
    ap.add_argument("--train-views", type=int, default=7,
                    help="training photos (evenly spaced) scored like the held-out ones: the memorisation gap")
    args = ap.parse_args(argv)

    import numpy as np
    import torch

    import neumesh_core as nm
    from neumesh_core.fit import fit
    from neumesh_core.reconstruct.build import ScaffoldConfig
    from neumesh_core.render.renderer import RenderSettings, render_camera
    from neumesh_core.train.trainer import TrainConfig

    torch.set_num_threads(args.threads)
    name = args.name or f"{os.path.basename(os.path.normpath(args.data))}_ds{args.downscale:g}_{args.minutes:g}min"
    out = args.out or f"/tmp/bench_real_{name}"
    os.makedirs(out, exist_ok=True)
    scfg = ScaffoldConfig(compute_iou=False, chamfer_samples=0)   # "auto": fusion for photos without masks
    if args.smoke:
        scfg.density_iters, scfg.density_resolutions, scfg.target_vertices = (150, 150), (48, 96), 60_000
    tcfg = TrainConfig(steps=args.steps, max_seconds=args.minutes * 60.0, threads=args.threads, log_every=25,
                       checkpoint_every=10**9, appearance_codes=args.appearance)
    if args.background_tv is not None:
        tcfg.weight_background_tv = args.background_tv
    if args.scaffold:
        import shutil

        shutil.copyfile(args.scaffold, os.path.join(out, "scaffold.ply"))
    snap_path = os.path.join(out, "snapshot.neumesh")
    snap = {}
    fit_state = {"field": None}
    import importlib

    trainer_mod = importlib.import_module("neumesh_core.train.trainer")

    plain_train = trainer_mod.train

    def train_keeping_field(field, *a, **k):   # the snapshot needs the field fit() trains
        fit_state["field"] = field
        return plain_train(field, *a, **k)

    trainer_mod.train = train_keeping_field
    t0 = time.perf_counter()
    load_start = os.getloadavg()
    log_lines = []

    def log(m):
        log_lines.append(m)
        print(m, file=sys.stderr, flush=True)

    def cb(p):
        if p.step % 250 == 0:
            log(f"step {p.step} train psnr {p.psnr:.2f} {p.elapsed_s:.0f}s load {os.getloadavg()[0]:.1f}")
        if args.snapshot_minutes and not snap and p.elapsed_s >= args.snapshot_minutes * 60:
            field_now = fit_state["field"]
            if field_now is not None:
                nm.save_field(field_now, snap_path)
                snap.update(step=p.step, seconds=p.elapsed_s)
                log(f"snapshot at step {p.step} ({p.elapsed_s:.0f}s): {snap_path}")

    summary = fit(args.data, out, downscale=args.downscale, background=None, scaffold_config=scfg,
                  train_config=tcfg, train_progress=cb, evaluate_split="none", log=log, device=args.device,
                  background_model=not args.no_background_model)
    field = nm.load_field(os.path.join(out, "field.neumesh"), device=args.device)
    scene = nm.load_scene(args.data, downscale=args.downscale)
    val = scene.split("val")
    if args.eval_views:
        val = val.subset(np.arange(min(args.eval_views, len(val))))
    res = {"data": os.path.abspath(args.data), "downscale": args.downscale, "threads": args.threads,
           "minutes": args.minutes, "smoke": args.smoke, "device": args.device,
           "weight_background_tv": tcfg.weight_background_tv,
           "background_model_trained": not args.no_background_model,
           "size": [val.cameras.width, val.cameras.height], "held_out_views": len(val),
           "scaffold": summary.get("scaffold"), "train": summary.get("train"),
           "object_box": summary.get("object_box"), "load_start": load_start,
           "background_config": (nm.background_of(field).config() if nm.background_of(field) is not None else None)}
    res["load_before_eval"] = os.getloadavg()
    if snap:
        sf = nm.load_field(snap_path, device=args.device)
        ev = score_views(sf, val)
        res["snapshot"] = dict(snap, **ev["mean"], views=ev["views"],
                               note="the same run's field at this point (its lr schedule spans the whole run)")
        log(f"held-out at the snapshot (step {snap['step']}): PSNR {ev['mean']['psnr']:.2f} "
            f"SSIM {ev['mean']['ssim']:.3f}")
    ev = score_views(field, val)
    res["background_on"] = dict(ev["mean"], views=ev["views"])
    log(f"held-out, background model on: PSNR {ev['mean']['psnr']:.2f} SSIM {ev['mean']['ssim']:.3f} (object "
        f"{ev['mean']['psnr_object']:.2f}, room {ev['mean']['psnr_room']:.2f}) "
        f"render {ev['mean']['render_s']:.1f}s/frame")
    for v in ev["views"]:
        log(f"  {v['view']}: {v['psnr']:.2f} dB (object {v['psnr_object']:.2f} on {v['object_share']:.0%} of the "
            f"frame, room {v['psnr_room']:.2f})")
    if args.train_views:
        tr = scene.split("train")
        tr = tr.subset(np.unique(np.linspace(0, len(tr) - 1, min(args.train_views, len(tr))).round().astype(int)))
        et = score_views(field, tr)
        res["training_views"] = dict(et["mean"], views=et["views"])
        res["gap_db"] = et["mean"]["psnr"] - ev["mean"]["psnr"]
        log(f"training photos ({len(tr)}): PSNR {et['mean']['psnr']:.2f} (object {et['mean']['psnr_object']:.2f}, "
            f"room {et['mean']['psnr_room']:.2f}); gap to held-out {res['gap_db']:.2f} dB")
    vv = val.subset(np.arange(min(args.off_views, len(val)))) if args.off_views else val
    ev = nm.evaluate(field, vv, background=(0.0, 0.0, 0.0), settings=RenderSettings(background_model=False))
    res["background_off"] = {"views": len(vv), "psnr": ev["mean"]["psnr"], "ssim": ev["mean"]["ssim"],
                             "render_s": ev["mean"]["render_s"]}
    log(f"held-out, background model off: PSNR {ev['mean']['psnr']:.2f} (the object alone on black)")
    if args.pictures:
        os.makedirs(args.pictures, exist_ok=True)
        cam = val.cameras
        for i in range(min(2, len(val))):
            on = render_camera(field, cam.K[i], cam.c2w[i], cam.width, cam.height, background=(0, 0, 0))
            off = render_camera(field, cam.K[i], cam.c2w[i], cam.width, cam.height, background=(1, 1, 1),
                                settings=RenderSettings(background_model=False))
            side = np.concatenate([val.float_view(i), np.clip(on.rgb, 0, 1), np.clip(off.rgb, 0, 1)], 1)
            nm.save_image(os.path.join(args.pictures, f"heldout_{i}_photo_render_object.png"), side)
    res["appearance_codes"] = args.appearance
    if str(args.device).startswith("cuda"):
        res["machine"] = f"{torch.cuda.get_device_name(torch.device(args.device))}, {os.cpu_count()} CPU cores"
    else:
        res["machine"] = (f"{os.cpu_count()} cores, load 1-min avg {os.getloadavg()[0]:.1f} at the end (shared with "
                          f"other jobs when above the thread count); {args.threads} torch thread(s)")
    res["log"] = log_lines[-40:]
    res["peak_rss_gib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    res["total_s"] = time.perf_counter() - t0
    write_results(res, f"real_{name}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
