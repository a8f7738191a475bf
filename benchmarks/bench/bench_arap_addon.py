#!/usr/bin/env python3
"""ARAP deform in Blender (bpy==5.0.1 in the venv): from a handle move to the first preview.

A mesh object (the built-in scene's scaffold by default, or ``--mesh`` such as lego's scaffold.ply) gets
an 'Anchor' group (bottom 15%) and a 'Handle' group (top 10%), *Add ARAP deform* (the Empty at rest: the
rest shape is written without a solve; the preview cage is factorised in the background), then the
handle Empty is dragged by ``--moves`` small steps through the viewport path (the drag thread on the
``--preview`` cage): per move, the seconds from the moved Empty to the live shape key written (*Add*
starts factorising the cage in the background; the moves start once it is ready:
``preview_ready_after_add_s``).  Then a frame change (the solve from rest on the full mesh, *Frame
iterations*).  Writes benchmarks/results/log/<name>.json.

    .venv/bin/python benchmarks/bench/bench_arap_addon.py                   # built-in scene
    .venv/bin/python benchmarks/bench/bench_arap_addon.py --mesh /work/runs/lego/scaffold.ply --name arap_addon_lego
"""
from __future__ import annotations

import argparse
import os
import sys
import time

from bench_addon import _BASE, MODULE, ROOT  # noqa: F401  (sets up a private Blender home)

import bpy  # noqa: E402
import mathutils  # noqa: E402
import numpy as np  # noqa: E402

import build_addon  # noqa: E402
from benchmarks._results import add_options, write_results  # noqa: E402
from neumesh_core.data.synthetic.shape import default_mesh as _default_mesh  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "mesh", "name", "results_dir", mesh=dict(help="a .ply (default: the built-in scene's scaffold)"),
                name=dict(default="arap_addon_builtin", help="results name (default arap_addon_builtin)"))
    ap.add_argument("--subdiv", type=int, default=5, help="built-in scaffold's subdivisions")
    ap.add_argument("--preview", type=int, default=30000, help="preview cage vertices (0: full mesh)")
    ap.add_argument("--iterations", type=int, default=2, help="Iterations per move (the add-on default: 2)")
    ap.add_argument("--frame-iterations", type=int, default=30)
    ap.add_argument("--moves", type=int, default=4)
    ap.add_argument("--skip-frame", action="store_true", help="no full-mesh frame solve (slow on big meshes)")
    a = ap.parse_args(argv)

    zip_path = build_addon.build(os.path.join(_BASE, "neumesh.zip"))
    bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    import addon_utils

    addon_utils.enable(MODULE, default_set=True)
    addon = sys.modules[MODULE]
    nm = addon.runtime.core.get()
    arap = addon.deform.arap
    mesh = nm.load_mesh(a.mesh) if a.mesh else _default_mesh(a.subdiv)
    V = np.asarray(mesh.vertices, np.float32)
    F = np.asarray(mesh.faces, np.int64)
    obj = addon.scene.sync.new_mesh_object("arap", V, F)
    bpy.context.view_layer.objects.active = obj
    z = V[:, 2]
    lo, hi = z.min(), z.max()
    anchors = np.nonzero(z < lo + 0.15 * (hi - lo))[0]
    handles = np.nonzero(z > hi - 0.10 * (hi - lo))[0]
    for name, idx in (("Anchor", anchors), ("Handle", handles)):
        obj.vertex_groups.new(name=name).add(idx.tolist(), 1.0, "REPLACE")
    s = obj.neumesh_arap
    s.preview_vertices, s.iterations, s.frame_iterations = a.preview, a.iterations, a.frame_iterations
    print(f"{len(V)} vertices, {len(F)} faces; {len(anchors)} anchors, {len(handles)} handles")

    t = time.perf_counter()
    assert bpy.ops.neumesh.arap_add() == {"FINISHED"}
    add_s = time.perf_counter() - t
    t = time.perf_counter()
    prep = arap._SOLVERS[obj.name_full].get("prepare")
    if prep is not None:   # the preview cage, factorised in the background after Add
        prep.join()
    prepare_wait_s = time.perf_counter() - t
    timings = dict(arap.TIMINGS[obj.name_full])
    print(f"Add ARAP deform (rest shape written; preview cage factorised beside): {add_s:.2f} s")
    e = bpy.data.objects[s.handle_empties.split("\n")[0]]
    size = float(np.ptp(V, 0).max())
    moves = []
    for i in range(a.moves):
        e.matrix_world = mathutils.Matrix.Translation((0.02 * size, 0, 0.01 * size)) @ e.matrix_world
        t, c = time.perf_counter(), time.process_time()
        assert arap.drag(obj) is True
        arap.wait_for_drags()
        total, cpu = time.perf_counter() - t, time.process_time() - c
        tm = arap.TIMINGS[obj.name_full]
        # CPU seconds of the process (all threads; the drag thread works while the main one waits):
        # the move's cost without the waits for the other jobs on a shared machine
        moves.append({"move_to_preview_s": round(total, 4), "move_to_preview_cpu_s": round(cpu, 4),
                      "solve_s": round(tm["solve_s"], 4), "cage": bool(tm["cage"])})
        print(f"move {i}: {total:.3f} s to the preview (solve {tm['solve_s']:.3f} s, cage {tm['cage']})")
    steady = [m["move_to_preview_s"] for m in moves[1:]] or [moves[0]["move_to_preview_s"]]
    out = {"mesh": os.path.basename(a.mesh) if a.mesh else f"built-in scaffold (subdiv {a.subdiv})",
           "vertices": int(len(V)), "faces": int(len(F)), "anchors": int(len(anchors)),
           "handles": int(len(handles)), "preview_vertices": a.preview, "iterations": a.iterations,
           "add_s": round(add_s, 3), "preview_ready_after_add_s": round(prepare_wait_s, 3),
           "setup_full_s_at_add": timings.get("setup_full_s"),
           "moves": moves, "first_move_s": moves[0]["move_to_preview_s"] if moves else None,
           "setup_preview_s": round(arap.TIMINGS[obj.name_full].get("setup_preview_s", 0.0), 3),
           "move_to_preview_median_s": round(float(np.median(steady)), 4),
           "move_to_preview_cpu_median_s": round(float(np.median(
               [m["move_to_preview_cpu_s"] for m in (moves[1:] or moves)])), 4),
           "previews_per_s": round(1.0 / float(np.median(steady)), 2)}
    if not a.skip_frame:
        t, c = time.perf_counter(), time.process_time()
        arap.solve(obj, from_rest=True, force=True)
        out["frame_solve_s"] = round(time.perf_counter() - t, 3)
        out["frame_solve_cpu_s"] = round(time.process_time() - c, 3)
        out["frame_iterations"] = a.frame_iterations
        print(f"frame change (full mesh from rest, {a.frame_iterations} iterations): {out['frame_solve_s']} s")
    result = {"machine": {"omp_threads": os.environ.get("OMP_NUM_THREADS"),
                          "note": "2 shared cores, other jobs running: see the load averages and CPU times"},
              "arap_addon": out}
    write_results(result, f"{a.name}.json", a.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
