"""Frames per second on a GPU: the fused Triton renderer against the torch path (the reference), both
interpolation modes, at rest and deformed, at 800² and 400², with kernel launches and host
synchronisations per frame (torch.profiler) and the images compared (PSNR against the torch render).
Needs a CUDA GPU; nothing else here does.

    python benchmarks/bench/bench_render_gpu.py --field runs/lego/field.neumesh \
        --data ../shared/data/nerf_synthetic/lego
    python benchmarks/bench/bench_render_gpu.py                 # no data: a field made on the spot
    python benchmarks/bench/bench_render_gpu.py --field f.neumesh --cameras cams.json   # [{"K", "c2w", "width"}, ...]

Without ``--field`` the field is made here: an untrained field (random codes, a dense shell of density
around the surface, the scaffold's mesh mask as the occupancy grid) on the built-in blob subdivided to
163,842 vertices (``--subdiv``), seen by cameras on a circle around it.  Deformed: a bend of
``--bend`` degrees along z (``data/deformations.bend``) through ``field.set_vertices``.

Each configuration renders ``--views`` views, each the best of ``--repeats`` frames of ``render_camera``
(synchronised; the images copied to the host as the add-on receives them); the figure is the median over
the views.  ``--sweep`` first times the kernel's launch options (rays per program, warps, the static or
refill schedule and its programs per multiprocessor) on one early-interpolation 800² view and keeps the
fastest for the rest.  ``--breakdown`` last times the neighbour search and the decoders alone on one
frame's samples.  Then the seconds from a new pose (``set_vertices`` of host positions) to its first
800² frame on the host.  ``--train-steps N`` first times N training steps (forward and backward of
``--train-rays`` random pixels) with the torch marcher and with the kernel's march.  ``--budget-s``
stops starting new configurations after that many seconds (the JSON then says which were skipped).
Writes benchmarks/results/log/render_gpu_<name>.json.
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from benchmarks._results import add_options, timed, write_results  # noqa: E402
from neumesh_core.metrics import psnr  # noqa: E402


def scaled(K, factor: float):
    K = np.array(K, np.float32).copy()
    K[:2] *= factor
    return K


def cameras_from_file(path: str, n: int):
    spec = json.load(open(path))
    views = [int(i) for i in np.linspace(0, len(spec) - 1, min(n, len(spec))).round()]
    out = []
    for i in views:
        K = np.array(spec[i]["K"], np.float32)
        K[:2] *= 400 / spec[i]["width"]
        out.append((K, np.array(spec[i]["c2w"], np.float64)))
    return out


def dataset_cameras(data: str, n: int):
    import neumesh_core as nm

    cams = nm.load_scene(data).split("val").cameras
    views = [int(i) for i in np.linspace(0, len(cams) - 1, n).round()]
    out = []
    for i in views:
        K = np.array(cams.K[i], np.float32).copy()
        K[:2] *= 400 / cams.width
        out.append((K, np.array(cams.c2w[i])))
    return out


def orbit_cameras(vertices: np.ndarray, n: int):
    """400²-pixel cameras on a circle around the vertices, looking at their centre."""
    from neumesh_core.data.synthetic import look_at_opencv

    centre = (vertices.min(0) + vertices.max(0)) / 2
    r = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    K = np.array([[440.0, 0, 200.0], [0, 440.0, 200.0], [0, 0, 1]], np.float32)
    out = []
    for i in range(n):
        a = 2 * np.pi * (i + 0.25) / n
        eye = centre + r * np.array([np.cos(a), np.sin(a), 0.5])
        out.append((K, look_at_opencv(eye, centre)))
    return out


def procedural_field(subdiv: int, device):
    """An untrained field on the built-in blob: random codes, a dense shell of density."""
    import neumesh_core as nm
    from neumesh_core.data.synthetic import default_mesh

    mesh = default_mesh(subdiv=subdiv)
    torch.manual_seed(0)
    f = nm.NeuMeshField(mesh, nm.FieldConfig(interpolation="early", knn="hashgrid"))
    with torch.no_grad():
        f.geo_codes.normal_(0, 0.5)
        f.tex_codes.normal_(0, 0.5)
        f.geo_decoder[-1].bias.fill_(float(np.log(8.0 / f.radius)))
        f.mod_colours.normal_(0, 0.1)
    f.eval()
    return f.to(device)


def sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def best_time(fn, repeats: int, device) -> float:
    """The fastest of ``repeats`` (at least one) synchronised calls of ``fn``, seconds."""
    sync(device)
    return timed(fn, max(1, repeats), sync=lambda: sync(device)).best


def frame_times(field, cams, size, settings, repeats, device):
    """render_camera seconds per view, each the best of ``repeats``."""
    import neumesh_core as nm

    out = []
    for K, c2w in cams:
        Ks = scaled(K, size / 400)
        out.append(best_time(lambda: nm.render_camera(field, Ks, c2w, size, size, settings=settings), repeats,
                             device))
    return out


def profile_frame(field, cam, size, settings, device) -> dict:
    """One frame under torch.profiler: kernel launches, host synchronisations and copies, GPU busy time,
    the largest items."""
    import neumesh_core as nm
    from torch.profiler import ProfilerActivity, profile

    K, c2w = cam
    Ks = scaled(K, size / 400)
    sync(device)
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if torch.device(device).type == "cuda" else [])
    with profile(activities=acts) as prof:
        t = time.perf_counter()
        nm.render_camera(field, Ks, c2w, size, size, settings=settings)
        sync(device)
        wall = time.perf_counter() - t
    events = prof.key_averages()
    attr = "self_device_time_total" if hasattr(events[0], "self_device_time_total") else "self_cuda_time_total"
    launches = sum(e.count for e in events if "LaunchKernel" in e.key)
    syncs = sum(e.count for e in events if "Synchronize" in e.key)
    copies = sum(e.count for e in events if "Memcpy" in e.key and not e.key.startswith("Memcpy"))
    busy = sum(getattr(e, attr) for e in events if not e.key.startswith("cuda") and not e.key.startswith("cu"))
    top = sorted(events, key=lambda e: -getattr(e, attr))[:12]
    return {"wall_s_profiled": wall, "kernel_launches": launches, "host_syncs": syncs, "memcpy_calls": copies,
            "gpu_busy_s": busy / 1e6,
            "top_ops": [{"op": e.key[:80], "calls": e.count, "cuda_ms": getattr(e, attr) / 1e3,
                         "cpu_ms": e.self_cpu_time_total / 1e3} for e in top]}


def sweep_options(field, cam, device, repeats, grid, size=800) -> list:
    import neumesh_core as nm
    from neumesh_core.kernels import fused as ft

    rows = []
    saved = dict(ft.KERNEL_OPTIONS)
    st = nm.RenderSettings(backend="triton")
    Ks = scaled(cam[0], size / 400)
    ref = nm.render_camera(field, Ks, cam[1], size, size, settings=nm.RenderSettings(backend="torch")).rgb
    for opts in grid:
        ft.KERNEL_OPTIONS.update(opts)
        try:
            t = time.perf_counter()
            w0 = min(200, size)
            nm.render_camera(field, scaled(cam[0], w0 / 400), cam[1], w0, w0, settings=st)   # compile
            sync(device)
            compile_s = time.perf_counter() - t
            s = min(frame_times(field, [cam], size, st, repeats, device))
            db = psnr(nm.render_camera(field, Ks, cam[1], size, size, settings=st).rgb, ref)
            rows.append({**opts, "size": size, "frame_s": s, "fps": 1 / s, "first_call_s": compile_s,
                         "psnr_vs_torch_db": db})
            print(f"  sweep {opts}: {size}² {s * 1e3:.2f} ms ({1 / s:.1f} fps), {db:.1f} dB against torch, "
                  f"first call {compile_s:.1f} s", flush=True)
        except Exception as e:   # an option the compiler rejects on this GPU: record it, go on
            rows.append({**opts, "error": repr(e)[:300]})
            print(f"  sweep {opts}: failed {e!r}"[:300], flush=True)
        finally:
            ft.KERNEL_OPTIONS.clear()
            ft.KERNEL_OPTIONS.update(saved)
    return rows


def sweep_grid(which: str) -> list:
    """The launch options ``--sweep`` times.  "schedule": the static default (the fastest of the first
    H200 sweep, docs/benchmarks.md, now with rays in 8 x 4 tiles) against rays in rows, the refill
    schedule, smaller blocks, a register cap, the neighbour search's early out and half-radius cells.
    "precision": the fp32 default against fp16 and tf32 products (tensor cores; they spill far less,
    benchmarks/diagnose/kernel_resources.py) -- on an H200 with triton 3.6.0 tf32 once ended in an illegal memory
    access that poisons the CUDA context, so gpu_check.sh runs this set last, in a process of its own
    (``--sweep-only``), tf32 at its end.  Only images >= 50 dB from the torch render count."""
    from neumesh_core.kernels import fused as ft

    base = {**ft.KERNEL_OPTIONS, "block": ft.default_block("cuda"), "cells_per_radius": ft.default_cells("cuda")}
    if which == "precision":   # fp16 first (spills a quarter of fp32's), the tf32 that once crashed last
        f16 = {**base, "precision": "fp16"}
        return [base, f16, {**f16, "schedule": "refill", "programs_per_sm": 4}, {**f16, "block": 64},
                {**f16, "block": 16, "num_warps": 2, "schedule": "refill"}, {**f16, "maxnreg": 168},
                {**f16, "knn_early_out": True}, {**f16, "knn_early_out": True, "schedule": "refill"},
                {**f16, "knn_early_out": True, "cells_per_radius": 2},
                {**base, "precision": "tf32"}, {**base, "precision": "tf32", "schedule": "refill"},
                {**base, "precision": "tf32x3"}]
    return [base,
            {**base, "ray_order": "rows"},   # the first H200 sweep's order
            {**base, "schedule": "refill", "programs_per_sm": 4},
            {**base, "schedule": "refill", "programs_per_sm": 16},
            {**base, "block": 16, "num_warps": 2},
            {**base, "block": 16, "num_warps": 2, "schedule": "refill"},
            {**base, "maxnreg": 128},
            {**base, "maxnreg": 128, "schedule": "refill"},
            {**base, "knn_early_out": True},
            {**base, "knn_early_out": True, "schedule": "refill", "programs_per_sm": 4},
            {**base, "cells_per_radius": 2},   # half-radius cells, now read nearest first and pruned
            {**base, "cells_per_radius": 2, "knn_early_out": True}]


def deform_latency(field, cam, device, size, rest: np.ndarray, angles=(4.0, 8.0, 12.0, 16.0, 20.0)) -> dict:
    """What an artist waits for after a deformation (the goal: the first preview within one frame of
    60 Hz): new positions as the add-on hands them over (a host array) -> ``set_vertices`` (normals,
    rotations, neighbour index, occupancy grid) -> the frame on the host, for bends of ``angles``
    degrees in turn (each a new pose). Medians of the seconds: posing, rendering, both."""
    import neumesh_core as nm
    from neumesh_core.data.deformations import bend

    K, c2w = cam
    Ks = scaled(K, size / 400)
    pose, frame = [], []
    for a in angles:
        v = np.ascontiguousarray(bend(rest, a), np.float32)
        sync(device)
        t0 = time.perf_counter()
        field.set_vertices(v)
        sync(device)
        t1 = time.perf_counter()
        nm.render_camera(field, Ks, c2w, size, size)
        sync(device)
        pose.append(t1 - t0)
        frame.append(time.perf_counter() - t1)
    field.reset_vertices()
    total = [a + b for a, b in zip(pose, frame)]
    out = {"size": size, "angles": list(angles), "pose_s": float(statistics.median(pose)),
           "frame_s": float(statistics.median(frame)), "total_s": float(statistics.median(total)),
           "within_60hz_frames": sum(t <= 1 / 60 for t in total)}
    print(f"  deformation -> frame at {size}²: pose {out['pose_s'] * 1e3:.1f} ms + frame "
          f"{out['frame_s'] * 1e3:.1f} ms = {out['total_s'] * 1e3:.1f} ms (median of {len(angles)} poses)", flush=True)
    return out


def breakdown(field, cam, device, size, repeats) -> dict:
    """Where a fused frame's time may go, from its parts run alone on the same work: the neighbour search
    (knn_radius_triton, the fused kernel's knn_keys in a kernel of its own, with and without its early
    out) and both decoders as plain cuBLAS matmuls (fp32 and fp16), each on as many points as the frame
    evaluates: each opaque pixel's surface point, repeated along its ray at the marching step, ordered
    step-major so that neighbouring points are neighbouring rays (as the fused kernel's blocks are)."""
    import neumesh_core as nm
    from neumesh_core.data.cameras import pixel_rays
    from neumesh_core.kernels.knn import TritonHashGrid, knn_radius_triton
    from neumesh_core.render.renderer import default_step

    Ks = scaled(cam[0], size / 400)
    st = nm.RenderSettings(backend="triton")
    out = nm.render_camera(field, Ks, cam[1], size, size, settings=st)
    origins, dirs = pixel_rays(Ks, cam[1], size, size, device=device)
    depth = torch.as_tensor(out.depth.reshape(-1), device=device)
    live = torch.as_tensor(out.opacity.reshape(-1) > 0.5, device=device) & torch.isfinite(depth)
    surf = origins[live] + dirs[live] * depth[live, None]
    n = int(out.n_samples)
    row = {"size": size, "samples": n, "opaque_pixels": int(live.sum())}
    if len(surf) == 0 or n == 0:
        return row
    reps = -(-n // len(surf))
    offs = (torch.arange(reps, device=device, dtype=torch.float32) - reps // 2) * default_step(field, st)
    pts = (surf[None] + dirs[live][None] * offs[:, None, None]).reshape(-1, 3)[:n].contiguous()
    grid = TritonHashGrid(field.scaffold.vertices_.detach(), field.radius, 1)
    k = int(field.config.k)

    def best(fn):   # one call first: the kernel compiles, cuBLAS picks its algorithm
        fn()
        return best_time(fn, repeats, device)

    row["knn_s"] = best(lambda: knn_radius_triton(pts, grid, k, block=32))
    row["knn_early_out_s"] = best(lambda: knn_radius_triton(pts, grid, k, block=32, early_out=True))
    geo = field.geo_decoder
    rad = field.rad_decoders[0]
    xg = torch.randn(n, geo[0].in_features, device=device)
    xr = torch.randn(n, rad[0].in_features, device=device)
    row["decoders_fp32_s"] = best(lambda: (geo(xg), rad(xr)))
    if torch.device(device).type == "cuda":
        with torch.autocast("cuda", dtype=torch.float16):
            row["decoders_fp16_s"] = best(lambda: (geo(xg), rad(xr)))
    print(f"  breakdown {size}²: {n} samples; alone: knn {row['knn_s'] * 1e3:.2f} ms (early out "
          f"{row['knn_early_out_s'] * 1e3:.2f}), decoders fp32 {row['decoders_fp32_s'] * 1e3:.2f} ms"
          + (f", fp16 {row['decoders_fp16_s'] * 1e3:.2f} ms" if "decoders_fp16_s" in row else ""), flush=True)
    return row


def train_steps(field, cams, device, steps: int, rays: int, repeats_warm: int = 3) -> dict:
    """The heavy part of a training step (render_rays(train=True) of ``rays`` random pixels of the views,
    jittered, and the backward pass of an L2 loss) with the torch marcher and with the kernel's march
    (kernels/fused.march_rays_fused; the torch decoders either way): seconds per step, rays per
    second, samples per step, and the two paths' loss and code gradients on the same batch compared."""
    import neumesh_core as nm
    from neumesh_core.data.cameras import pixel_rays
    from neumesh_core.render.renderer import render_rays

    g = torch.Generator().manual_seed(0)
    o_all, d_all = zip(*(pixel_rays(K, c2w, 400, 400, device=device) for K, c2w in cams))
    o_all, d_all = torch.cat(o_all), torch.cat(d_all)
    batches = []
    for _ in range(steps + repeats_warm):
        pick = torch.randint(0, len(o_all), (rays,), generator=g).to(device)
        batches.append((o_all[pick], d_all[pick], torch.rand(rays, generator=g).to(device),
                        torch.rand(rays, 3, generator=g).to(device)))
    field.train()
    field.sparse_grads = True
    bg = torch.ones(3, device=device)
    out = {"rays_per_step": rays, "steps": steps}
    grads = {}
    try:
        for backend in ("torch", "triton"):
            st = nm.RenderSettings(backend=backend)

            def step(b, keep=False):
                field.zero_grad(set_to_none=True)
                o, d, jit, target = b
                r = render_rays(field, o, d, background=bg, settings=st, train=True, jitter=jit)
                loss = (r["rgb"] - target).square().mean()
                loss.backward()
                if keep:
                    grads[backend] = (float(loss.detach()), r["n_samples"],
                                      {n: p.grad.detach().to_dense().clone() for n, p in field.named_parameters()
                                       if p.grad is not None})
                return r["n_samples"]

            t = time.perf_counter()
            step(batches[0], keep=True)
            sync(device)
            first = time.perf_counter() - t
            for b in batches[1:repeats_warm]:
                step(b)
            sync(device)
            t = time.perf_counter()
            samples = [step(b) for b in batches[repeats_warm:]]
            sync(device)
            sec = (time.perf_counter() - t) / max(1, steps)
            out[backend] = {"first_step_s": first, "step_s": sec, "rays_per_s": rays / sec,
                            "samples_per_step": float(np.mean(samples))}
            print(f"  training step, {backend} march: {sec * 1e3:.1f} ms ({rays / sec / 1e3:.0f}k rays/s, "
                  f"{np.mean(samples):.0f} samples)", flush=True)
    finally:
        field.sparse_grads = False
        field.eval()
        field.zero_grad(set_to_none=True)
    if len(grads) == 2:
        (la, na, ga), (lb, nb, gb) = grads["torch"], grads["triton"]
        out["same_batch"] = {"loss_torch": la, "loss_triton": lb, "samples_torch": na, "samples_triton": nb,
                             "grad_max_rel_diff": {k: float((gb[k] - ga[k]).abs().max()
                                                            / ga[k].abs().max().clamp_min(1e-12))
                                                   for k in ga if k in gb}}
        out["speedup"] = out["torch"]["step_s"] / out["triton"]["step_s"]
        print(f"  training step: fused march {out['speedup']:.2f}x the torch marcher; same batch loss "
              f"{la:.6f} / {lb:.6f}, samples {na} / {nb}", flush=True)
    return out


def measure(field, cams, st, args, dev, key) -> dict:
    """One configuration: the first call (Triton compiles), frame times per size, the images at the
    largest size (``outs``, for the PSNR), one profiled frame."""
    import neumesh_core as nm

    t = time.perf_counter()
    w0 = min(200, min(args.sizes))
    nm.render_camera(field, scaled(cams[0][0], w0 / 400), cams[0][1], w0, w0, settings=st)  # warm up
    sync(dev)
    row = dict(key, first_call_s=time.perf_counter() - t)
    for size in args.sizes:
        s = float(statistics.median(frame_times(field, cams, size, st, args.repeats, dev)))
        row[f"frame_{size}_s"] = s
        row[f"fps_{size}"] = 1.0 / s
    big = max(args.sizes)
    outs = [nm.render_camera(field, scaled(K, big / 400), c2w, big, big, settings=st) for K, c2w in cams]
    row["outs"] = [o.rgb for o in outs]
    row["n_samples_per_frame"] = float(np.mean([o.n_samples for o in outs]))
    if not args.no_profile:
        row[f"profile_{big}"] = profile_frame(field, cams[0], big, st, dev)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "field", "data", "device", "name", "results_dir",
                field=dict(help="a .neumesh field; without it a field is made on the spot"),
                data=dict(help="dataset whose val cameras are rendered"),
                device=dict(default="cuda", help="cuda (default); cpu only to try the script out"))
    ap.add_argument("--cameras", help="JSON list of {K, c2w, width} (instead of --data)")
    ap.add_argument("--subdiv", type=int, default=7, help="procedural field: blob subdivisions (7: 163,842 vertices)")
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sizes", type=int, nargs="+", default=[400, 800])
    ap.add_argument("--modes", nargs="+", default=["early", "post"], choices=["early", "post"])
    ap.add_argument("--backends", nargs="+", default=["triton", "torch"], choices=["triton", "torch"])
    ap.add_argument("--bend", type=float, default=20.0, help="degrees of the deformation's bend")
    ap.add_argument("--sweep", action="store_true", help="time the kernel's launch options first, keep the best")
    ap.add_argument("--sweep-set", default="schedule", choices=["schedule", "precision"],
                    help="which launch options --sweep times (see sweep_grid)")
    ap.add_argument("--sweep-only", action="store_true", help="stop after the sweep (with --sweep)")
    ap.add_argument("--budget-s", type=float, default=1e9, help="start no new configuration after this")
    ap.add_argument("--no-profile", action="store_true")
    ap.add_argument("--breakdown", action="store_true",
                    help="last, time the neighbour search and the decoders alone on a frame's samples")
    ap.add_argument("--train-steps", type=int, default=0,
                    help="also time N training steps (forward + backward) with each marcher, before the sweep")
    ap.add_argument("--train-rays", type=int, default=16384, help="rays per training step (--train-steps)")
    args = ap.parse_args(argv)
    import neumesh_core as nm
    from neumesh_core.data.deformations import bend
    from neumesh_core.kernels import fused as ft

    t_start = time.perf_counter()
    dev = torch.device(args.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        print("bench_render_gpu: torch sees no CUDA GPU; run it on a GPU machine", file=sys.stderr)
        return 2
    if args.field:
        name = args.name or os.path.splitext(os.path.basename(args.field))[0]
        field = nm.load_field(args.field, device=str(dev))
    else:
        name = args.name or f"blob{args.subdiv}"
        field = procedural_field(args.subdiv, dev)
    field.eval()
    rest = field.rest_vertices.detach().cpu().numpy()
    if args.cameras:
        cams = cameras_from_file(args.cameras, args.views)
    elif args.data:
        cams = dataset_cameras(args.data, args.views)
    else:
        cams = orbit_cameras(rest, args.views)
    import triton

    result = {"field": args.field or f"procedural blob, subdiv {args.subdiv} (untrained, dense shell)",
              "vertices": field.num_vertices, "trained_interpolation": field.config.interpolation,
              "gpu": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "none (cpu dry run)",
              "torch": torch.__version__, "triton": triton.__version__, "views": len(cams),
              "repeats": args.repeats, "bend_degrees": args.bend, "runs": [], "skipped": []}
    print(f"{result['gpu']}, torch {torch.__version__}, triton {triton.__version__}, "
          f"{field.num_vertices} vertices, {len(cams)} views", flush=True)
    deformed_v = torch.as_tensor(bend(rest, args.bend), dtype=torch.float32)
    trained_mode = field.config.interpolation
    if args.train_steps > 0:
        try:
            result["train"] = train_steps(field, cams, dev, args.train_steps, args.train_rays)
        except Exception as e:   # record it, go on with the renders
            import traceback

            traceback.print_exc()
            result["train"] = {"error": repr(e)[:500]}
    with torch.no_grad():
        if args.sweep and "triton" in args.backends:
            field.config.interpolation = "early"
            grid = sweep_grid(args.sweep_set)
            if dev.type != "cuda":
                grid = grid[:2]
            result["sweep"] = sweep_options(field, cams[0], dev, args.repeats, grid, max(args.sizes))
            # the fastest whose image stays >= 50 dB from the torch render (tf32 products may not)
            ok = [r for r in result["sweep"] if "error" not in r and r["psnr_vs_torch_db"] >= 50.0]
            if ok:
                best = min(ok, key=lambda r: r["frame_s"])
                ft.KERNEL_OPTIONS.update({k: best[k] for k in ft.KERNEL_OPTIONS if k in best})
        result["kernel_options"] = dict(ft.KERNEL_OPTIONS)
        print(f"kernel options: {ft.KERNEL_OPTIONS}", flush=True)
        runs = [] if args.sweep_only else list(itertools.product(args.modes, (False, True)))
        for mode, deformed in runs:
            field.config.interpolation = mode
            if deformed:
                field.set_vertices(deformed_v.to(dev))
            else:
                field.reset_vertices()
            images = {}
            for backend in args.backends:
                key = {"mode": mode, "deformed": deformed, "backend": backend}
                if time.perf_counter() - t_start > args.budget_s:
                    result["skipped"].append(key)
                    print(f"  skipped (budget): {key}", flush=True)
                    continue
                st = nm.RenderSettings(backend=backend)
                try:
                    row = measure(field, cams, st, args, dev, key)
                except Exception as e:   # e.g. a kernel the GPU's compiler rejects: record it, go on
                    import traceback

                    traceback.print_exc()
                    result["runs"].append(dict(key, error=repr(e)[:500]))
                    continue
                if row.get("outs"):
                    images[backend] = row.pop("outs")
                result["runs"].append(row)
                big = max(args.sizes)
                p = row.get(f"profile_{big}", {})
                print(f"  {mode:5s} {'deformed' if deformed else 'rest    '} {backend:6s}: "
                      + ", ".join(f"{sz}² {row[f'frame_{sz}_s'] * 1e3:7.2f} ms ({row[f'fps_{sz}']:6.1f} fps)"
                                  for sz in args.sizes)
                      + (f"; {p['kernel_launches']} launches, {p['host_syncs']} syncs, {p['memcpy_calls']} copies"
                         if p else ""), flush=True)
            if "triton" in images and "torch" in images:
                db = [psnr(a, b) for a, b in zip(images["triton"], images["torch"])]
                for r in result["runs"]:
                    if r["mode"] == mode and r["deformed"] == deformed and r["backend"] == "triton" \
                            and "error" not in r:
                        r["psnr_vs_torch_db"] = db
                print(f"  {mode} {'deformed' if deformed else 'rest'}: triton vs torch {max(args.sizes)}² "
                      f"PSNR min {min(db):.1f} dB", flush=True)
        if not args.sweep_only and time.perf_counter() - t_start <= args.budget_s:
            field.config.interpolation = "early"
            try:   # the first frame after each of a few new poses (the backend "auto" takes)
                result["deform_latency"] = deform_latency(field, cams[0], dev, max(args.sizes), rest)
            except Exception as e:   # record it, keep the rest of the results
                result["deform_latency"] = {"error": repr(e)[:500]}
                print(f"  deformation latency failed: {e!r}"[:300], flush=True)
        if args.breakdown and not args.sweep_only and "triton" in args.backends:
            field.config.interpolation = "early"
            try:
                result["breakdown"] = breakdown(field, cams[0], dev, max(args.sizes), args.repeats)
            except Exception as e:   # record it, keep the rest of the results
                result["breakdown"] = {"error": repr(e)[:500]}
                print(f"  breakdown failed: {e!r}"[:300], flush=True)
        field.config.interpolation = trained_mode
    result["seconds"] = time.perf_counter() - t_start
    summary = {}
    for r in result["runs"]:
        if "error" in r:
            summary[f"{r['mode']}_{'deformed' if r['deformed'] else 'rest'}_{r['backend']}"] = \
                {"error": r["error"][:200]}
            continue
        summary[f"{r['mode']}_{'deformed' if r['deformed'] else 'rest'}_{r['backend']}"] = {
            k: round(r[k], 2) for k in r if k.startswith("fps_")}
        if "psnr_vs_torch_db" in r:
            summary[f"{r['mode']}_{'deformed' if r['deformed'] else 'rest'}_{r['backend']}"]["psnr_min_db"] = \
                round(min(r["psnr_vs_torch_db"]), 1)
    result["summary"] = summary
    # the docs' figure (README / benchmarks.md: `best.fps_800`): the fastest undeformed 800² run in the
    # field's own interpolation mode
    own = [r for r in result["runs"] if "error" not in r and not r["deformed"] and r["mode"] == trained_mode
           and "fps_800" in r]
    if own:
        b = max(own, key=lambda r: r["fps_800"])
        result["best"] = {k: b[k] for k in ("mode", "backend", "fps_800", "frame_800_s") if k in b}
    print(json.dumps(summary, indent=1))
    suffix = f"_sweep_{args.sweep_set}" if args.sweep_only else ""
    write_results(result, f"render_gpu_{name}{suffix}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
