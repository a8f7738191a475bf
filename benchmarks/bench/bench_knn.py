"""Neighbour search speed: the KD-tree (pykdtree on the CPU) against the torch hash grid.

    python benchmarks/bench/bench_knn.py                        # built-in blob, 163,842 vertices, CPU
    python benchmarks/bench/bench_knn.py --device cuda          # the same on a GPU
    python benchmarks/bench/bench_knn.py --mesh runs/lego/scaffold.ply --queries 1000000

Queries are the field's kind: points within about one edge of the scaffold, K=4, radius 2.5 x the mean
edge.  On a GPU the KD-tree time includes the copies to the host and back (what the field pays).
Prints figures and writes benchmarks/results/log/knn_<mesh>_<device>.json; every backend's answer is
checked against the KD-tree's.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
import neumesh_core as nm  # noqa: E402
from neumesh_core.data.synthetic import default_mesh  # noqa: E402
from neumesh_core.device import resolve_device  # noqa: E402
from neumesh_core.field.knn import KNN_BACKENDS, make_index  # noqa: E402
from neumesh_core.mesh import mean_edge_length  # noqa: E402
from benchmarks._results import add_options, timed, write_results  # noqa: E402


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_backend(name, verts, pts, k, radius, repeats, device):
    _sync(device)
    t0 = time.perf_counter()
    index = make_index(verts, k, radius, name)
    _sync(device)
    build_s = time.perf_counter() - t0
    index.query(pts[:1000])  # warm-up
    _sync(device)
    run = timed(lambda: index.query(pts), repeats, sync=lambda: _sync(device))
    idx, dist = run.result
    return {"build_s": build_s, "query_s": run.best, "queries_per_s": len(pts) / run.best}, idx


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "mesh", "device", "results_dir",
                mesh=dict(help="scaffold mesh (.ply/.obj); default: the built-in blob at --subdiv"))
    ap.add_argument("--subdiv", type=int, default=7, help="built-in blob subdivision (7: 163,842 vertices)")
    ap.add_argument("--queries", type=int, default=500_000)
    ap.add_argument("--k", type=int, default=4)
    ap.add_argument("--radius-scale", type=float, default=2.5, help="radius / mean edge length")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)

    device = resolve_device(args.device)
    mesh = nm.load_mesh(args.mesh) if args.mesh else default_mesh(args.subdiv)
    name = os.path.splitext(os.path.basename(args.mesh))[0] if args.mesh else f"blob{args.subdiv}"
    edge = mean_edge_length(mesh.vertices, mesh.edges())
    radius = args.radius_scale * edge
    g = torch.Generator().manual_seed(0)
    v = torch.as_tensor(mesh.vertices, dtype=torch.float32)
    pts = v[torch.randint(0, len(v), (args.queries,), generator=g)] + edge * torch.randn(args.queries, 3, generator=g)
    v, pts = v.to(device), pts.to(device)

    result = {"mesh": name, "vertices": len(v), "queries": args.queries, "k": args.k, "radius": radius,
              "device": str(device), "backends": {}}
    ref = None
    from neumesh_core.kernels.knn import triton_runs_on

    for b in KNN_BACKENDS:
        if b == "triton" and not triton_runs_on(device):
            print(f"{b:9s} skipped: needs a CUDA GPU with triton (or TRITON_INTERPRET=1, slow)")
            continue
        r, idx = time_backend(b, v, pts, args.k, radius, args.repeats, device)
        if ref is None:
            ref = idx.cpu()
        r["same_indices_as_kdtree"] = float((idx.cpu() == ref).float().mean())
        result["backends"][b] = r
        print(f"{b:9s} build {r['build_s'] * 1e3:7.1f} ms   query {r['query_s'] * 1e3:8.1f} ms "
              f"({r['queries_per_s'] / 1e6:.2f} M/s)   same indices as kdtree {r['same_indices_as_kdtree']:.5f}")
    found = (ref >= 0).float().mean().item()
    result["neighbour_slots_filled"] = found
    print(f"{len(v):,} vertices, {args.queries:,} queries on {device}; {found:.1%} of the K slots filled")
    write_results(result, f"knn_{name}_{device.type}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
