"""Scaffold benchmark: build the mesh scaffold of a dataset and report size, time and quality.

    python benchmarks/bench/bench_scaffold.py --data ../shared/data/nerf_synthetic/lego
    python benchmarks/bench/bench_scaffold.py --data ../shared/data/dtu/scan24 --downscale 2

Prints vertex count, build time per stage and the silhouette IoU on the training masks (plus the
Chamfer distance when the dataset ships a reference mesh.ply) and writes
benchmarks/results/log/scaffold_<name>.json (the mesh itself goes to --out, default /tmp: datasets under
../shared/data are licensed and nothing derived from them is committed).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from benchmarks._results import add_options, use_threads, write_results  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "data", "name", "threads", "results_dir",
                data=dict(required=True, help="dataset folder (Blender/NeRF-synthetic or DTU)"),
                name=dict(help="result name (default: dataset folder name)"))
    ap.add_argument("--out", default=None, help="folder for the mesh (default: a temp folder)")
    ap.add_argument("--downscale", type=float, default=1, help="image downscale factor (default 1)")
    ap.add_argument("--method", default="auto", choices=["auto", "hull", "hull+mvs", "hull+density", "density"])
    ap.add_argument("--vertices", type=int, default=200_000, help="target vertex count (default 200000)")
    ap.add_argument("--resolution", type=int, default=256, help="hull grid resolution (default 256)")
    ap.add_argument("--iters", default="300,300", help="density iterations per stage (hull+density/density)")
    args = ap.parse_args(argv)
    use_threads(args.threads or None)
    from neumesh_core.data.loader import load_scene
    from neumesh_core.mesh import save_mesh
    from neumesh_core.reconstruct import ScaffoldConfig, build_scaffold
    from neumesh_core.cli.common import Progress

    name = args.name or os.path.basename(os.path.normpath(args.data))
    out_dir = args.out or os.path.join("/tmp", f"neumesh_scaffold_{name}")
    t0 = time.perf_counter()
    scene = load_scene(args.data, downscale=args.downscale)
    t_load = time.perf_counter() - t0
    tr = scene.split("train")
    print(f"{name}: {len(tr)} train views {tr.cameras.width}x{tr.cameras.height} "
          f"(loaded in {t_load:.1f}s)", flush=True)
    cfg = ScaffoldConfig(method=args.method, target_vertices=args.vertices, hull_resolution=args.resolution,
                         density_iters=tuple(int(x) for x in args.iters.split(",")))
    prog = Progress(sys.stdout)
    mesh, rep = build_scaffold(scene, cfg, progress=prog.scaffold, log=lambda s: prog.say("  " + s))
    prog.end()
    os.makedirs(out_dir, exist_ok=True)
    mesh_path = os.path.join(out_dir, f"scaffold_{name}.ply")
    save_mesh(mesh, mesh_path)
    print(rep.summary())
    res = {
        "name": name, "data": os.path.abspath(args.data), "downscale": args.downscale,
        "views": len(tr), "image_size": [tr.cameras.width, tr.cameras.height],
        "vertices": rep.num_vertices, "faces": rep.num_faces, "method": rep.method,
        "build_seconds": rep.timings["total"], "load_seconds": t_load, "timings": rep.timings,
        "silhouette_iou": rep.silhouette_iou, "chamfer": rep.chamfer, "hull": rep.hull,
        "density": rep.density, "meshing": rep.meshing, "notes": rep.notes, "mesh": mesh_path,
    }
    print(f"vertices {rep.num_vertices}, build {rep.timings['total']:.1f}s, silhouette IoU "
          f"{(rep.silhouette_iou or {}).get('mean', float('nan')):.4f}")
    write_results(res, f"scaffold_{name}.json", args.results_dir, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
