"""Capture benchmark: images -> scaffold -> trained field within a wall-clock budget -> evaluation.

    python benchmarks/bench/bench_fit.py --data ../shared/data/nerf_synthetic/lego --budget-min 60 \
        --interpolation early --radius-scale 3 --eval-views 0 --supersample 1 --eval-step-scale 0
    python benchmarks/bench/bench_fit.py --data ../shared/data/dtu/scan24 --budget-min 60 --marks 15,30,45 \
        --downscale 4 --interpolation early --radius-scale 2.5 --vertices 2000000

The budget covers scaffold + training (the clock starts before the scaffold).  Snapshots are saved when
the clock passes each --marks minute; all evaluation happens after training, so it does not eat the
budget.  Evaluation renders 2 x 2 rays per pixel (--supersample: the area filter of the downscaled
photographs) at half the training step (--eval-step-scale); the final figures of a plain render, one ray
per pixel at the training step, are in the JSON too ("plain_render").  Prints the figures and writes
benchmarks/results/log/fit_<scene>.json.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
import neumesh_core as nm  # noqa: E402
from neumesh_core.field.knn import KNN_BACKENDS  # noqa: E402
from neumesh_core.reconstruct import ScaffoldConfig, build_scaffold  # noqa: E402
from benchmarks._results import add_options, use_threads, write_results  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "data", "threads", "device", "results_dir",
                data=dict(required=True, help="dataset folder (Blender or DTU format)"),
                threads=dict(default=0, help="torch threads (default 0: one per core)"),
                device=dict(help="cpu (default) | cuda | auto: where the field trains"),
                results_dir=dict(help="folder for the results JSON (default benchmarks/results/log; on a "
                                      "borrowed GPU machine point it at a folder that comes back)"))
    ap.add_argument("--out", help="work folder (default runs/fit_<scene>)")
    ap.add_argument("--budget-min", type=float, default=60.0, help="scaffold + training wall budget")
    ap.add_argument("--marks", default="15,30", help="minutes at which snapshots are evaluated")
    ap.add_argument("--downscale", type=float, default=1)
    ap.add_argument("--vertices", type=int, default=200_000, help="scaffold vertex target")
    ap.add_argument("--max-mesh-grid", type=int, default=None,
                    help=f"ScaffoldConfig.max_mesh_grid (default {ScaffoldConfig.max_mesh_grid}): raise it "
                         "(e.g. 760) for more than ~2M vertices")
    ap.add_argument("--max-faces", type=int, default=None,
                    help=f"ScaffoldConfig.max_faces (default {ScaffoldConfig.max_faces}); a 3M-vertex scaffold "
                         "has ~6M faces")
    ap.add_argument("--scaffold-method", default="auto", help="auto | hull | hull+mvs | hull+density | density")
    ap.add_argument("--scaffold-downscale", type=float, default=None,
                    help="image downscale for the scaffold stage (default: --downscale); e.g. DTU trains at 4 "
                         "and builds the scaffold at 2")
    ap.add_argument("--mvs-side", type=int, default=400, help="longest image side used by the stereo stage")
    ap.add_argument("--radius-scale", type=float, default=2.5, help="field radius / mean edge length")
    ap.add_argument("--interpolation", default="post", choices=["post", "early"])
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--step-scale", type=float, default=None, help="marching step / radius (default: FieldConfig's)")
    ap.add_argument("--lr-codes", type=float, default=None, help="default: TrainConfig's")
    ap.add_argument("--lr-decoders", type=float, default=None, help="default: TrainConfig's")
    ap.add_argument("--lr-final", type=float, default=None,
                    help="learning rate at the end of the budget / at the start (default: TrainConfig's)")
    ap.add_argument("--average-from", type=float, default=None,
                    help="average the parameters from this fraction of the training budget on (SWA; "
                         "default off). A mark just before the end keeps the plain weights to compare")
    ap.add_argument("--weight-tv", type=float, default=None, help="total variation weight (default: TrainConfig's)")
    ap.add_argument("--tv-samples", type=int, default=None,
                    help="vertices sampled per step for the TV loss (default: TrainConfig's)")
    ap.add_argument("--tv-vertices", default=None, choices=["random", "batch"],
                    help="TV over random vertices or the ones each batch looked up (default: TrainConfig's)")
    ap.add_argument("--code-levels", type=int, default=None,
                    help="coarse code levels while training (default: TrainConfig's; 0 = off)")
    ap.add_argument("--code-levels-until", type=float, default=None,
                    help="bake the coarse levels into the vertex codes at this fraction of the budget and "
                         "train plain codes from there (default: keep them to the end)")
    ap.add_argument("--eval-views", type=int, default=25, help="val views in the final evaluation (0 = all)")
    ap.add_argument("--mark-views", type=int, default=10, help="val views evaluated at each mark")
    ap.add_argument("--supersample", type=int, default=2,
                    help="evaluation renders S x S rays per pixel (default 2); figures at 1 are reported too")
    ap.add_argument("--eval-step-scale", type=float, default=0.25,
                    help="marching step / radius when evaluating (default 0.25; 0: the field's training step)")
    ap.add_argument("--seed", type=int, default=None,
                    help="seed of the ray batches and TV samples (default: TrainConfig's; the field's init is fixed)")
    ap.add_argument("--knn", default="auto", choices=KNN_BACKENDS,
                    help="neighbour search: auto (pykdtree on the CPU, the Triton index on a GPU), hashgrid "
                         "(torch, on the field's device) or triton")
    ap.add_argument("--results-name", default=None, help="results file name (default fit_<scene>.json)")
    args = ap.parse_args(argv)
    use_threads(args.threads)
    from neumesh_core.device import resolve_device

    device = resolve_device(args.device)

    name = os.path.basename(os.path.normpath(args.data))
    out = args.out or os.path.join("runs", f"fit_{name}")
    os.makedirs(out, exist_ok=True)
    scene = nm.load_scene(args.data, downscale=args.downscale)
    masked = scene.kind == "dtu"
    budget = args.budget_min * 60
    marks = [float(m) for m in args.marks.split(",") if m]
    t0 = time.perf_counter()

    sd = args.scaffold_downscale
    scaffold_scene = scene if sd is None or sd == args.downscale else nm.load_scene(args.data, downscale=sd)
    skw = {k: v for k, v in (("max_mesh_grid", args.max_mesh_grid), ("max_faces", args.max_faces))
           if v is not None}
    mesh, report = build_scaffold(scaffold_scene, ScaffoldConfig(method=args.scaffold_method,
                                                                 target_vertices=args.vertices,
                                                                 mvs_max_image_side=args.mvs_side, **skw),
                                  progress=lambda stage, frac: print(f"\rscaffold {stage} {frac:.0%}", end=""))
    scaffold_s = time.perf_counter() - t0
    print(f"\nscaffold: {mesh.num_vertices} vertices in {scaffold_s:.0f}s")
    nm.save_mesh(mesh, os.path.join(out, "scaffold.ply"))

    fkw = {} if args.step_scale is None else {"step_scale": args.step_scale}
    field = nm.create_field(mesh, nm.FieldConfig(interpolation=args.interpolation,
                                                  radius_scale=args.radius_scale, knn=args.knn, **fkw),
                             device=device)
    print(f"field radius {field.radius:.4f}")
    pending = list(marks)
    snaps = {}
    history = []

    def on_progress(p):
        wall = time.perf_counter() - t0
        history.append({"step": p.step, "wall_s": wall, "train_psnr": p.psnr, "rays_per_sec": p.rays_per_sec,
                        "samples_per_ray": p.samples_per_ray})
        if p.step % 100 == 0:
            print(f"step {p.step} wall {wall / 60:.1f} min psnr {p.psnr:.2f} {p.rays_per_sec:.0f} rays/s "
                  f"{p.samples_per_ray:.1f} smp/ray occ {p.occupied_fraction:.3f}", flush=True)
        while pending and wall >= pending[0] * 60:
            m = pending.pop(0)
            path = os.path.join(out, f"snapshot_{int(m)}min.neumesh")
            nm.save_field(field, path)
            snaps[m] = {"path": path, "step": p.step}
        return True

    tkw = {k: v for k, v in (("lr_codes", args.lr_codes), ("lr_decoders", args.lr_decoders),
                             ("lr_final_factor", args.lr_final), ("average_from", args.average_from),
                             ("weight_tv", args.weight_tv), ("tv_samples", args.tv_samples),
                             ("tv_vertices", args.tv_vertices), ("code_levels", args.code_levels),
                             ("code_levels_until", args.code_levels_until), ("seed", args.seed))
           if v is not None}
    cfg = nm.TrainConfig(steps=10 ** 6, rays_per_batch=args.rays, max_seconds=budget - scaffold_s, log_every=10,
                         **tkw)
    res = nm.train(field, scene, cfg, progress=on_progress)
    total_s = time.perf_counter() - t0
    final_path = os.path.join(out, "field.neumesh")
    nm.save_field(field, final_path)
    print(f"trained {res.steps_done} steps; scaffold + training {total_s / 60:.1f} min")

    split = "val" if "val" in scene.splits else "test"
    val = scene.split(split)

    def ev(f, n, ss=args.supersample, step=args.eval_step_scale or None, plain=False):
        sub = val if n <= 0 or n >= len(val) else val.subset(np.linspace(0, len(val) - 1, n).astype(int))
        r = nm.evaluate(f, sub, background=scene.background, masked=masked,
                        settings=nm.RenderSettings(supersample=ss, step_scale=step))
        out = {"n_views": r["n_views"], "supersample": ss, "step_scale": step or f.config.step_scale,
               **r["headline"], "mean": r["mean"], "per_view": [v.get("psnr_fg", v["psnr"]) for v in r["views"]]}
        if plain and (ss > 1 or step is not None):   # also one ray per pixel at the training step
            out["plain_render"] = {k: v for k, v in ev(f, n, 1, None).items()
                                   if k in ("psnr", "ssim", "per_view", "step_scale")}
        return out

    result = {"scene": name, "data": os.path.abspath(args.data), "downscale": args.downscale,
              "device": str(device), "cpu_threads": torch.get_num_threads(),
              "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
              "budget_min": args.budget_min, "scaffold_downscale": sd or args.downscale, "mvs_side": args.mvs_side,
              "scaffold_s": scaffold_s, "scaffold": report.to_dict(),
              "train_steps": res.steps_done, "total_wall_s": total_s, "radius": field.radius,
              "interpolation": args.interpolation, "step_scale": field.config.step_scale,
              "lr_codes": cfg.lr_codes, "lr_decoders": cfg.lr_decoders, "lr_final_factor": cfg.lr_final_factor,
              "average_from": cfg.average_from, "weight_tv": cfg.weight_tv, "tv_samples": cfg.tv_samples,
              "tv_vertices": cfg.tv_vertices, "code_levels": cfg.code_levels,
              "code_levels_until": cfg.code_levels_until, "seed": cfg.seed, "knn": field.config.knn,
              "averaged_snapshots": res.averaged, "marks": {},
              "history": history}
    for m, s in snaps.items():
        snap = nm.load_field(s["path"], device=device)
        result["marks"][f"{m:g}min"] = {"step": s["step"], **ev(snap, args.mark_views)}
        print(f"at {m:g} min (step {s['step']}): {result['marks'][f'{m:g}min']}")
    result["final"] = ev(field, args.eval_views, plain=True)
    print(f"final ({split}, {result['final']['n_views']} views): PSNR {result['final']['psnr']:.2f} "
          f"SSIM {result['final']['ssim']:.4f} LPIPS {result['final']['lpips']}")
    write_results(result, args.results_name or f"fit_{name}.json", args.results_dir, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
