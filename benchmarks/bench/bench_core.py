"""Core speed benchmark: training step time, render time at 400^2 and 800^2, fraction of matmul peak.

    python benchmarks/bench/bench_core.py                 # built-in scene with its true mesh
    python benchmarks/bench/bench_core.py --data ../shared/data/nerf_synthetic/lego --mesh lego_scaffold.ply

Prints figures and writes benchmarks/results/log/core_<scene>.json.  The matmul peak is measured in the
same run, so compare ratios across machines (they drift up to 2x), not seconds.
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
from benchmarks._results import add_options, machine_record, timed, use_threads, write_results  # noqa: E402


def matmul_peak(seconds: float = 2.0) -> float:
    a = torch.randn(2048, 2048)
    b = torch.randn(2048, 2048)
    for _ in range(3):
        a @ b
    n = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        a @ b
        n += 1
    return 2 * 2048 ** 3 * n / (time.perf_counter() - t0) / 1e9


class FlopCounter:
    """Counts MLP FLOPs (2*rows*in*out per linear layer, forward only) through forward hooks."""

    def __init__(self, field):
        self.flops = 0
        self.handles = []
        for mlp in (field.geo_decoder, field.rad_decoder):
            per_row = sum(m.in_features * m.out_features for m in mlp if isinstance(m, torch.nn.Linear))
            self.handles.append(mlp.register_forward_hook(self._hook(per_row)))

    def _hook(self, per_row):
        def hook(_m, inp, _out):
            self.flops += 2 * inp[0].shape[0] * per_row
        return hook

    def reset(self):
        self.flops = 0


def time_train_steps(field, scene, steps: int, rays: int, warmup: int) -> dict:
    cfg = nm.TrainConfig(steps=warmup + steps, rays_per_batch=rays, log_every=10 ** 9, resume=False)
    # warm up (also lets the occupancy grid prune), then time `steps` steps
    nm.train(field, scene, nm.TrainConfig(steps=warmup, rays_per_batch=rays, log_every=10 ** 9, resume=False))
    field._checkpoint_meta = {"train_state": {"step": warmup}}
    cfg.resume = True
    counter = FlopCounter(field)
    run = timed(lambda: nm.train(field, scene, cfg))
    res, dt = run.result, run.best / steps
    for h in counter.handles:
        h.remove()
    field._checkpoint_meta = None
    return {"step_ms": dt * 1e3, "rays": rays, "samples_per_ray": res.history[-1].samples_per_ray,
            "mlp_fwd_gflop_per_step": counter.flops / steps / 1e9,
            # backward of an MLP costs ~2x its forward
            "mlp_gflops_achieved": 3 * counter.flops / steps / dt / 1e9, "train_psnr": res.final_psnr}


def time_render(field, cams: nm.Cameras, size: int, n_frames: int, background) -> dict:
    scale = size / cams.width
    cs = cams.scaled(scale)
    counter = FlopCounter(field)
    times, samples = [], []
    for i in range(n_frames):
        out = nm.render_camera(field, cs.K[i], cs.c2w[i], cs.width, cs.height, background=background)
        times.append(out.seconds)
        samples.append(out.n_samples)
    for h in counter.handles:
        h.remove()
    t = float(np.mean(times))
    return {"size": size, "seconds_per_frame": t, "samples_per_frame": float(np.mean(samples)),
            "mlp_gflops_achieved": counter.flops / n_frames / t / 1e9}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "data", "mesh", "threads", "results_dir",
                data=dict(help="dataset folder (default: the built-in scene)"),
                mesh=dict(help="scaffold mesh (default: the dataset's mesh.ply)"),
                threads=dict(default=0, help="torch threads (default 0: one per core)"))
    ap.add_argument("--downscale", type=float, default=1)
    ap.add_argument("--train-steps", type=int, default=800, help="training before timing renders")
    ap.add_argument("--timed-steps", type=int, default=20)
    ap.add_argument("--frames", type=int, default=2, help="frames timed per resolution")
    ap.add_argument("--interpolation", nargs="+", default=["post", "early"])
    args = ap.parse_args(argv)
    use_threads(args.threads)

    data = args.data or nm.default_scene_dir()
    scene = nm.load_scene(data, downscale=args.downscale)
    mesh_path = args.mesh or scene.mesh_path
    if not mesh_path:
        print("error: this dataset has no mesh.ply; pass --mesh (e.g. from `neumesh scaffold`)")
        return 2
    mesh = nm.load_mesh(mesh_path)
    name = os.path.basename(os.path.normpath(data))
    peak = matmul_peak()
    machine = machine_record()
    print(f"machine: {machine['cpu']}, {machine['cores']} cores, {machine['torch_threads']} torch threads, "
          f"fp32 matmul peak {peak:.1f} GFLOP/s")
    eval_split = "val" if "val" in scene.splits else "train"
    result = {"scene": name, "vertices": mesh.num_vertices, "matmul_peak_gflops": peak, "runs": {}}
    for interp in args.interpolation:
        field = nm.create_field(mesh, nm.FieldConfig(interpolation=interp))
        t0 = time.perf_counter()
        nm.train(field, scene, nm.TrainConfig(steps=args.train_steps, rays_per_batch=4096, log_every=10 ** 9))
        train_s = time.perf_counter() - t0
        cams = scene.split(eval_split).cameras
        r400 = time_render(field, cams, 400, args.frames, scene.background)
        r800 = time_render(field, cams, 800, max(1, args.frames // 2), scene.background)
        ts = time_train_steps(field, scene, args.timed_steps, 4096, warmup=0)
        ev = nm.evaluate(field, scene.split(eval_split).subset(np.arange(min(4, len(scene.split(eval_split))))),
                         background=scene.background)
        run = {"train_s": train_s, "train_steps": args.train_steps, "train_step": ts, "render_400": r400,
               "render_800": r800, "psnr_after_training": ev["mean"]["psnr"],
               "fraction_of_peak_train": ts["mlp_gflops_achieved"] / peak,
               "fraction_of_peak_render400": r400["mlp_gflops_achieved"] / peak}
        result["runs"][interp] = run
        print(f"[{interp}] train step (4096 rays): {ts['step_ms']:.0f} ms, {ts['samples_per_ray']:.1f} "
              f"samples/ray, MLP {ts['mlp_gflops_achieved']:.1f} GFLOP/s = {run['fraction_of_peak_train']:.0%} of peak")
        print(f"[{interp}] render 400^2: {r400['seconds_per_frame']:.2f} s/frame "
              f"({r400['mlp_gflops_achieved']:.1f} GFLOP/s = {run['fraction_of_peak_render400']:.0%} of peak); "
              f"800^2: {r800['seconds_per_frame']:.2f} s/frame")
        print(f"[{interp}] PSNR after {args.train_steps} steps ({train_s:.0f}s): {ev['mean']['psnr']:.2f} dB")
    write_results(result, f"core_{name}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
