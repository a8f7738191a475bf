"""ARAP deformation: speed on a big scaffold and its cage, and fidelity against ground truth.

    python benchmarks/bench/bench_arap.py                            # both parts, built-in defaults
    python benchmarks/bench/bench_arap.py --mesh /work/runs/lego/scaffold.ply --skip-drop
    python benchmarks/bench/bench_arap.py --skip-speed --field runs/blob.neumesh

*Speed* (``--mesh``, else an ellipsoid icosphere of 164k vertices, the size of lego's scaffold): the bottom
15% of the object anchored, the top 10% a handle dragged through ``--moves`` small rotations (a drag).
For the full mesh and for a ``--cage``-vertex cage: set-up (weights, cage, factorisation), the per-move
solve (``--iterations`` local-global iterations, warm-started; in cage mode including the carry to every
vertex) and ``field.set_vertices`` of the result on a field made on that mesh (what a viewport preview
waits for before rendering).  Goal: >= 10 solves/s on the cage, <= 1 s per move on the full mesh.

*Drop* (``--field``, a field of the built-in scene, trained if missing as in bench_deform.py): the
blob's bottom anchored, its top a handle moved as an analytic bend of 35/70/140 degrees would move it
(relative to the bottom); ARAP places the rest.  The deformed field is scored against the mesh tracer's
ground truth of that same deformed surface (bench_deform.py's truth and cameras), beside the undeformed
field and the analytic bend.  Variants: the full solve (texture frames from ``set_vertices``), the same
vertices with the texture frames taken from ARAP's own rotations, and the cage solve.  Goal: drop <= 1 dB
up to 70 degrees.  Writes benchmarks/results/log/arap.json (``--name``).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import neumesh_core as nm  # noqa: E402
from neumesh_core.data.deformations import bend  # noqa: E402
from neumesh_core.data.mesh_truth import render_mesh_truth  # noqa: E402
from neumesh_core.deform import ArapConfig, ArapSolver, polar_rotations  # noqa: E402
from neumesh_core.metrics import masked_psnr, psnr, ssim  # noqa: E402
from benchmarks._results import add_options, use_threads, write_results  # noqa: E402
from bench_deform import cameras, check_builtin, trained_field, ROOT  # noqa: E402


def ellipsoid(subdiv: int = 7):
    import trimesh

    m = trimesh.creation.icosphere(subdiv)
    return np.asarray(m.vertices) * np.array([0.6, 0.6, 1.3]), np.asarray(m.faces, np.int64)


def rot(axis: int, deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def regions(v: np.ndarray, anchor_frac=0.15, handle_frac=0.10):
    z = v[:, 2]
    lo, hi = z.min(), z.max()
    return (np.nonzero(z < lo + anchor_frac * (hi - lo))[0], np.nonzero(z > hi - handle_frac * (hi - lo))[0])


def drag(solver: ArapSolver, v: np.ndarray, moves: int, iterations: int):
    """Per-move seconds of a drag: the handle turns by 3 degrees about its centre's x axis and moves
    sideways per move (:func:`res_targets`)."""
    times, cpu, res = [], [], None
    for k in range(1, moves + 1):
        q = res_targets(solver, v, k)
        t0, c0 = time.perf_counter(), time.process_time()
        res = solver.solve(q, iterations=iterations)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return times, cpu, res


def speed(args) -> dict:
    if args.mesh:
        mesh = nm.load_mesh(args.mesh)
        v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
        name = os.path.basename(args.mesh)
    else:
        v, f = ellipsoid(args.subdiv)
        name = f"ellipsoid icosphere({args.subdiv})"
    anchors, handles = regions(v)
    print(f"speed: {name}: {len(v)} vertices, {len(f)} faces; {len(anchors)} anchors, {len(handles)} handles")
    field = nm.create_field(nm.Mesh(v.astype(np.float32), f), nm.FieldConfig())
    out = {"mesh": name, "vertices": int(len(v)), "faces": int(len(f)), "anchors": int(len(anchors)),
           "handles": int(len(handles)), "iterations_per_move": args.iterations, "moves": args.moves,
           "note": "2 shared cores, other jobs running: see the load averages"}
    for label, cage in (("full", 0), ("cage", args.cage)):
        cfg = ArapConfig(cage_vertices=cage, iterations=args.iterations[0])
        t0 = time.perf_counter()
        solver = ArapSolver(v, f, anchors, handles, cfg)
        setup = time.perf_counter() - t0
        solver.solve(v[handles], iterations=1)           # the drag starts at rest
        start = (solver._x.copy(), solver._R.copy())
        r = {"setup_s": round(setup, 3),
             "factorisation_s": round(getattr(solver.core, "factor_seconds", float("nan")), 3),
             "unknowns": int(solver.num_unknowns), "load_average_at_start": round(os.getloadavg()[0], 2)}
        if cage:
            r["cage_vertices"] = int(len(solver.cage.samples))
            r["cage_edges"] = int(len(solver.cage.edges))
        for its in args.iterations:   # the same drag from the same start, per iterations-per-move setting
            solver._x, solver._R = start[0].copy(), start[1].copy()
            times, cpu, res = drag(solver, v, args.moves, its)
            per_move = float(np.median(times))
            # how far the drag's last pose lags behind the converged one (in mean edge lengths of the
            # solved mesh): what fewer iterations per move cost
            xd = solver._x.copy()
            conv = solver.solve(res_targets(solver, v, args.moves), iterations=args.converge)
            lag = np.linalg.norm(xd - solver._x, axis=1) / solver.core.unit
            r[f"iterations_{its}"] = {
                "solve_per_move_s": round(per_move, 4), "solves_per_s": round(1.0 / per_move, 2),
                "solve_per_move_all_s": [round(t, 4) for t in times],
                # CPU seconds of this one-threaded process: what the move costs without the waits for
                # the other jobs on the shared cores (wall time = CPU time on an idle machine)
                "solve_per_move_cpu_s": round(float(np.median(cpu)), 4),
                "solves_per_cpu_s": round(1.0 / float(np.median(cpu)), 2),
                "lag_mean_edges": round(float(lag.mean()), 3), "lag_max_edges": round(float(lag.max()), 3),
                "lag_reference_iterations": conv.iterations}
            print(f"  {label:5s} {its} it/move: per move {per_move:.3f} s ({1 / per_move:5.1f}/s; CPU "
                  f"{np.median(cpu):.3f} s), lag "
                  f"{lag.mean():.2f} edges (mean) behind {conv.iterations} more iterations")
        t0 = time.perf_counter()
        field.set_vertices(np.asarray(res.vertices, np.float32))
        r["set_vertices_s"] = round(time.perf_counter() - t0, 4)
        first = r[f"iterations_{args.iterations[0]}"]
        r["solve_per_move_s"], r["solves_per_s"] = first["solve_per_move_s"], first["solves_per_s"]
        r["move_to_vertices_set_s"] = round(first["solve_per_move_s"] + r["set_vertices_s"], 4)
        if label == "full" and args.frame_iterations:   # a frame change / render: solved from rest
            t0 = time.perf_counter()
            fr = solver.solve(res_targets(solver, v, args.moves), iterations=args.frame_iterations,
                              warm_start=False)
            r["frame_from_rest_s"] = round(time.perf_counter() - t0, 3)
            r["frame_iterations"] = int(fr.iterations)
        r["load_average_at_end"] = round(os.getloadavg()[0], 2)
        out[label] = r
        print(f"  {label:5s} setup {setup:6.2f} s (factorisation {r['factorisation_s']:.2f} s)  set_vertices "
              f"{r['set_vertices_s']:.3f} s" + (f"  cage {r['cage_vertices']} vertices" if cage else "")
              + (f"  frame from rest {r['frame_from_rest_s']} s" if "frame_from_rest_s" in r else ""))
        field.reset_vertices()
    out["goals"] = {"cage_solves_per_s>=10": {str(k): out["cage"][f"iterations_{k}"]["solves_per_s"] >= 10
                                              for k in args.iterations},
                    "full_solve_per_move_s<=1": {str(k): out["full"][f"iterations_{k}"]["solve_per_move_s"] <= 1.0
                                                 for k in args.iterations}}
    return out


def res_targets(solver: ArapSolver, v: np.ndarray, k: int) -> np.ndarray:
    """The handle positions of :func:`drag`'s move ``k``."""
    h = v[solver.handles]
    c = h.mean(0)
    return (h - c) @ rot(0, 3.0 * k).T + c + np.array([0.0, 0.02 * k, 0.0])


def bend_targets(v, anchors, handles, degrees):
    """Handle positions of an analytic bend by ``degrees``, relative to the (anchored) bottom."""
    b = bend(v, degrees)
    src, dst = v[anchors], b[anchors]
    R = polar_rotations(((dst - dst.mean(0)).T @ (src - src.mean(0)))[None])[0]
    t = dst.mean(0) - R @ src.mean(0)
    return (b - t) @ R


def score(field, V, cams, size, rotations=None, images=None) -> dict:
    """Render the field with its vertices at ``V`` (texture frames from set_vertices, or from
    ``rotations`` (N,3,3) rest->deformed when given) against the mesh tracer's truth of ``V``."""
    rest = field.rest_vertices.cpu().numpy().astype(np.float64)
    faces = field.faces.cpu().numpy()
    field.set_vertices(V.astype(np.float32))
    if rotations is not None:   # current -> rest is the transpose of ARAP's rest -> current
        field.scaffold.to_rest = torch.as_tensor(np.ascontiguousarray(rotations.transpose(0, 2, 1)),
                                                 dtype=torch.float32)
    ps, fg, ss = [], [], []
    try:
        for K, c2w in cams:
            o = nm.render_camera(field, K, c2w.astype(np.float32), size, size, background=(1, 1, 1))
            pred = np.clip(o.rgb, 0, 1)
            gt, alpha = render_mesh_truth(K, c2w, size, size, V, faces, rest_vertices=rest)
            ps.append(psnr(pred, gt))
            fg.append(masked_psnr(pred, gt, np.maximum(alpha, o.opacity)))
            ss.append(ssim(pred, gt))
            if images is not None:
                images.append((pred, gt))
    finally:
        field.reset_vertices()
    return {"psnr": float(np.mean(ps)), "psnr_fg": float(np.mean(fg)), "ssim": float(np.mean(ss)),
            "psnr_views": [round(p, 3) for p in ps]}


def frame_angle(field, V, R) -> dict:
    """Angles (degrees) between the texture frames set_vertices derives and ARAP's rotations."""
    field.set_vertices(V.astype(np.float32))
    to_rest = field.scaffold.to_rest.double().numpy()
    field.reset_vertices()
    M = np.einsum("nab,nbc->nac", to_rest, R)     # identity where both agree
    ang = np.degrees(np.arccos(np.clip((np.trace(M, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return {"median_deg": round(float(np.median(ang)), 3), "p95_deg": round(float(np.percentile(ang, 95)), 3),
            "max_deg": round(float(ang.max()), 3)}


def drop(args) -> dict:
    field, trained = trained_field(args.field, args.steps)
    check_builtin(field)
    rest = field.rest_vertices.cpu().numpy().astype(np.float64)
    faces = field.faces.cpu().numpy()
    anchors, handles = regions(rest)
    cams = cameras(args.views, args.size)
    pics = []
    base = score(field, rest, cams, args.size, images=pics if args.picture else None)
    sheet = [("rest", *pics[0])] if args.picture else []
    print(f"drop: {len(rest)} vertices; undeformed PSNR {base['psnr']:.2f}  fg {base['psnr_fg']:.2f}")
    rows = {}
    for deg in args.degrees:
        truth_bend = bend_targets(rest, anchors, handles, deg)
        q = truth_bend[handles]
        row = {}
        full = ArapSolver(rest, faces, anchors, handles, ArapConfig(iterations=args.solve_iterations))
        t0 = time.perf_counter()
        res = full.solve(q, warm_start=False)
        row["solve_s"] = round(time.perf_counter() - t0, 3)
        row["iterations"] = res.iterations
        row["max_distance_to_analytic_bend"] = round(float(np.linalg.norm(res.vertices - truth_bend, axis=1).max()), 4)
        variants = {"arap": (res.vertices, None), "arap_frames_from_arap_rotations": (res.vertices, res.rotations),
                    "analytic_bend": (truth_bend, None)}
        if args.cage_ratio:
            cs = ArapSolver(rest, faces, anchors, handles,
                            ArapConfig(iterations=args.solve_iterations,
                                       cage_vertices=max(64, len(rest) // args.cage_ratio)))
            rc = cs.solve(q, warm_start=False)
            variants["arap_cage"] = (rc.vertices, None)
            row["cage_vertices"] = int(len(cs.cage.samples))
            row["cage_mean_distance_to_full"] = round(
                float(np.linalg.norm(rc.vertices - res.vertices, axis=1).mean()), 4)
        row["frames_vs_arap_rotations"] = frame_angle(field, res.vertices, res.rotations)
        for name, (V, R) in variants.items():
            pics = []
            r = score(field, V, cams, args.size, R, images=pics if args.picture and name == "arap" else None)
            if pics:
                sheet.append((f"ARAP {deg:g} deg {r['psnr_views'][0]:.1f}dB", *pics[0]))
            r["drop_db"] = base["psnr"] - r["psnr"]
            r["drop_fg_db"] = base["psnr_fg"] - r["psnr_fg"]
            row[name] = r
            print(f"  bend {deg:5.0f}  {name:32s} PSNR {r['psnr']:6.2f} drop {r['drop_db']:5.2f} dB  "
                  f"fg drop {r['drop_fg_db']:5.2f} dB")
        rows[f"bend{deg:g}"] = row
    if sheet:
        from bench_deform import picture

        picture(sheet, args.picture)
    return {"field": os.path.relpath(args.field, ROOT) if os.path.abspath(args.field).startswith(ROOT) else args.field,
            "trained_here": trained, "vertices": int(len(rest)), "anchors": int(len(anchors)),
            "handles": int(len(handles)), "size": args.size, "views": args.views, "undeformed": base,
            "bends": rows, "goal_drop_db<=1_to_70deg": all(rows[k]["arap"]["drop_db"] <= 1.0 for k in rows
                                                             if float(k[4:]) <= 70)}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "mesh", "field", "threads", "name", "results_dir",
                mesh=dict(help="the big mesh for the speed part (default: 164k ellipsoid)"),
                field=dict(default=os.path.join(ROOT, "runs", "blob.neumesh"), help="the drop part's field"),
                threads=dict(default=max(1, int(os.environ.get("OMP_NUM_THREADS", "1"))),
                             help="torch threads (default: OMP_NUM_THREADS, else 1)"),
                name=dict(default="arap", help="results name (default arap)"))
    ap.add_argument("--subdiv", type=int, default=7)
    ap.add_argument("--cage", type=int, default=30000, help="cage vertices of the speed part's preview")
    ap.add_argument("--iterations", type=int, nargs="+", default=[4, 2],
                    help="local-global iterations per move (speed), one drag per value")
    ap.add_argument("--converge", type=int, default=100,
                    help="iterations after the drag that give the pose its lag is measured against")
    ap.add_argument("--frame-iterations", type=int, default=0,
                    help="also time a solve from rest on the full mesh with this many iterations (a frame change)")
    ap.add_argument("--moves", type=int, default=5)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--degrees", type=float, nargs="*", default=[35, 70, 140])
    ap.add_argument("--solve-iterations", type=int, default=100, help="iterations of the drop part's solves")
    ap.add_argument("--cage-ratio", type=int, default=8, help="drop part's cage: vertices / this (0: no cage)")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--picture", default=None, help="PNG: the field (top) and its truth (bottom), rest and "
                    "each ARAP bend, first view")
    ap.add_argument("--skip-speed", action="store_true")
    ap.add_argument("--skip-drop", action="store_true")
    args = ap.parse_args(argv)
    use_threads(args.threads)
    result = {}
    if not args.skip_speed:
        result["speed"] = speed(args)
    if not args.skip_drop:
        result["drop"] = drop(args)
    write_results(result, f"{args.name}.json", args.results_dir)
    return result


if __name__ == "__main__":
    main()
