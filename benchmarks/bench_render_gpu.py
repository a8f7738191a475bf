"""Frames per second of the CUDA path at 800² (and 400²), against the 60 fps goal, with the image
checked against the CPU render of the same views.  Needs a CUDA GPU; nothing else here does.

    python benchmarks/bench_render_gpu.py --field runs/lego/field.neumesh --data ../shared/data/nerf_synthetic/lego
    python benchmarks/bench_render_gpu.py --field f.neumesh --cameras cams.json   # [{"K", "c2w", "width"}, ...]

Measured per configuration (neighbour search backend x rays per chunk (0: the default) x marching
window x RenderSettings.skip_empty): each view's
best of ``--repeats`` frames of ``render_camera`` (synchronised, images copied to the host as the
add-on receives them) and of ``render_rays`` alone (the frame left on the GPU).  The fastest
configuration's images are compared with the CPU render (PSNR), and one of its frames is profiled
(torch.profiler: the ops by CUDA time, kernel launches, and the share of the frame the GPU was busy).
Writes benchmarks/results/render_gpu_<name>.json.
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

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _results import write_results  # noqa: E402
from bench_render import dataset_cameras, orbit_cameras, scaled  # noqa: E402
from neumesh_core.metrics import psnr  # noqa: E402


def cameras_from_file(path: str, n: int):
    spec = json.load(open(path))
    views = [int(i) for i in np.linspace(0, len(spec) - 1, min(n, len(spec))).round()]
    out = []
    for i in views:
        K = np.array(spec[i]["K"], np.float32)
        K[:2] *= 400 / spec[i]["width"]
        out.append((K, np.array(spec[i]["c2w"], np.float64)))
    return out


def set_knn(field, backend: str) -> None:
    from neumesh_core.field.knn import make_index

    sc = field.scaffold
    sc.knn = field.config.knn = backend
    sc.index = make_index(sc.vertices_, sc.k, sc.radius, backend)


def sync(device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def frame_times(field, cams, size, settings, repeats, device):
    """(render_camera seconds, render_rays seconds) per view, each the best of ``repeats``."""
    import neumesh_core as nm
    from neumesh_core.data.cameras import pixel_rays

    cam_t, rays_t = [], []
    for K, c2w in cams:
        Ks = scaled(K, size / (2 * K[0, 2]))
        best_c = best_r = 1e9
        for _ in range(repeats):
            sync(device)
            t = time.perf_counter()
            nm.render_camera(field, Ks, c2w, size, size, settings=settings)
            sync(device)
            best_c = min(best_c, time.perf_counter() - t)
            t = time.perf_counter()
            o, d = pixel_rays(Ks, c2w, size, size, device=device)
            c = settings.chunk_rays or size * size
            for s in range(0, size * size, c):
                nm.render_rays(field, o[s:s + c], d[s:s + c],
                               (1.0, 1.0, 1.0), settings)
            sync(device)
            best_r = min(best_r, time.perf_counter() - t)
        cam_t.append(best_c)
        rays_t.append(best_r)
    return cam_t, rays_t


def profile_frame(field, cam, size, settings, device) -> dict:
    import neumesh_core as nm
    from torch.profiler import ProfilerActivity, profile

    K, c2w = cam
    Ks = scaled(K, size / (2 * K[0, 2]))
    sync(device)
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=acts) as prof:
        t = time.perf_counter()
        nm.render_camera(field, Ks, c2w, size, size, settings=settings)
        sync(device)
        wall = time.perf_counter() - t
    events = prof.key_averages()
    attr = "self_device_time_total" if hasattr(events[0], "self_device_time_total") else "self_cuda_time_total"
    busy_us = sum(getattr(e, attr) for e in events)
    launches = sum(e.count for e in events if e.key in ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC"))
    syncs = sum(e.count for e in events if e.key in ("cudaStreamSynchronize", "cudaDeviceSynchronize",
                                                      "cudaMemcpyAsync"))
    key = attr if device.type == "cuda" else "self_cpu_time_total"
    top = sorted(events, key=lambda e: -getattr(e, key))[:20]
    table = [{"op": e.key, "calls": e.count, "cuda_ms": getattr(e, attr) / 1e3,
              "cpu_ms": e.self_cpu_time_total / 1e3} for e in top]
    return {"wall_s_profiled": wall, "gpu_busy_s": busy_us / 1e6, "kernel_launches": launches,
            "memcpy_and_syncs": syncs, "top_ops": table}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", required=True)
    ap.add_argument("--data", help="dataset whose val cameras are rendered")
    ap.add_argument("--cameras", help="JSON list of {K, c2w, width} (instead of --data)")
    ap.add_argument("--views", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--chunks", type=int, nargs="+", default=[0], help="rays per chunk; 0: the default")
    ap.add_argument("--windows", type=int, nargs="+", default=[32, 64])
    ap.add_argument("--skip-empty", type=int, nargs="+", default=[1, 0], help="RenderSettings.skip_empty values")
    ap.add_argument("--backends", nargs="+", default=["hashgrid"],
                    help="knn backends (on a GPU 'kdtree' also gives the hash grid: make_index)")
    ap.add_argument("--device", default="cuda", help="cuda (default); cpu only to try the script out")
    ap.add_argument("--name", default=None)
    ap.add_argument("--results-dir", default=None)
    args = ap.parse_args(argv)
    import neumesh_core as nm

    dev = torch.device(args.device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        print("bench_render_gpu: torch sees no CUDA GPU; run it on a GPU machine", file=sys.stderr)
        return 2
    name = args.name or os.path.splitext(os.path.basename(args.field))[0]
    cpu_field = nm.load_field(args.field)
    cpu_field.eval()
    if args.cameras:
        cams = cameras_from_file(args.cameras, args.views)
    elif args.data:
        cams = dataset_cameras(args.data, args.views, 400)
    else:
        cams = orbit_cameras(cpu_field, args.views, 400)
    field = nm.load_field(args.field).to(dev)
    field.eval()
    result = {"field": args.field, "vertices": field.num_vertices, "interpolation": field.config.interpolation,
              "gpu": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "none (cpu dry run)", "torch": torch.__version__, "views": len(cams),
              "configs": []}
    print(f"{result['gpu']}, torch {torch.__version__}, {field.num_vertices} vertices, {len(cams)} views")
    with torch.no_grad():
        # the CPU render is the reference image
        t = time.perf_counter()
        ref = [nm.render_camera(cpu_field, scaled(K, 2.0), c2w, 800, 800).rgb for K, c2w in cams]
        result["cpu_800_s_per_frame"] = (time.perf_counter() - t) / len(cams)
        result["cpu_threads"] = torch.get_num_threads()
        print(f"CPU reference 800²: {result['cpu_800_s_per_frame']:.3f} s per frame ({torch.get_num_threads()} threads)")
        best = None
        for backend, chunk, window, skip in itertools.product(args.backends, args.chunks, args.windows,
                                                              args.skip_empty):
            set_knn(field, backend)
            st = nm.RenderSettings(chunk_rays=chunk or None, window=window, skip_empty=bool(skip))
            nm.render_camera(field, scaled(cams[0][0], 0.5), cams[0][1], 200, 200, settings=st)   # warm up
            row = {"knn": backend, "chunk_rays": chunk, "window": window, "skip_empty": bool(skip)}
            for size in (400, 800):
                cam_t, rays_t = frame_times(field, cams, size, st, args.repeats, dev)
                row[f"frame_{size}_s"] = float(statistics.median(cam_t))
                row[f"rays_only_{size}_s"] = float(statistics.median(rays_t))
            row["fps_800"] = 1.0 / row["frame_800_s"]
            print(f"  knn {backend:8s} chunk {chunk:7d} window {window:3d} skip_empty {skip}: 400² {row['frame_400_s'] * 1e3:7.1f} ms, "
                  f"800² {row['frame_800_s'] * 1e3:7.1f} ms ({row['fps_800']:.1f} fps; rays only "
                  f"{row['rays_only_800_s'] * 1e3:.1f} ms)")
            result["configs"].append(row)
            if best is None or row["frame_800_s"] < best["frame_800_s"]:
                best = row
        result["best"] = best
        set_knn(field, best["knn"])
        st = nm.RenderSettings(chunk_rays=best["chunk_rays"] or None, window=best["window"],
                               skip_empty=best["skip_empty"])
        gpu_imgs = [nm.render_camera(field, scaled(K, 2.0), c2w, 800, 800, settings=st).rgb for K, c2w in cams]
        result["psnr_gpu_vs_cpu_db"] = [psnr(a, b) for a, b in zip(gpu_imgs, ref)]
        result["profile_800"] = profile_frame(field, cams[0], 800, st, dev)
    p = result["profile_800"]
    print(f"best: {best}")
    print(f"PSNR GPU vs CPU 800²: min {min(result['psnr_gpu_vs_cpu_db']):.1f} dB")
    print(f"profiled 800² frame: wall {p['wall_s_profiled'] * 1e3:.1f} ms, GPU busy {p['gpu_busy_s'] * 1e3:.1f} ms, "
          f"{p['kernel_launches']} kernel launches, {p['memcpy_and_syncs']} copies/syncs")
    for r in p["top_ops"]:
        print(f"  {r['op'][:60]:60s} {r['calls']:6d} calls  cuda {r['cuda_ms']:8.2f} ms  cpu {r['cpu_ms']:8.2f} ms")
    write_results(result, f"render_gpu_{name}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
