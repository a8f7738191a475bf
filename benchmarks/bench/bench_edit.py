"""Texture swap / fill speed on a real scaffold, and the render cost of a field with two decoders.

    python benchmarks/bench/bench_edit.py --mesh runs/lego/scaffold.ply      # untrained field on the mesh
    python benchmarks/bench/bench_edit.py --field runs/lego/field.neumesh     # a trained field
    python benchmarks/bench/bench_edit.py                                     # the built-in blob (subdiv 7)

Regions: the target is the ``--region-size`` vertices nearest the scaffold's +x extreme, the source the
same number nearest the -x extreme (two different shapes: the automatic alignment and the ARAP non-rigid
step do real work; the swap's fit check is off, so the timings do not depend on whether two extremes of
a scaffold fit each other, and ``fit_ok`` records whether the check would pass).  Times: the similarity
(``align_s``), the non-rigid step (``nonrigid_s``), the transfer (``transfer_s``: IDW weights, decoder
binding, row writes), the whole swap, and a fill through planar UVs.  Render: a 400^2 frame of the field
as trained (one decoder), with a second decoder present but unused, and with half the vertices bound to
the second decoder (median of ``--repeats``).  Writes benchmarks/results/log/edit_<name>.json.
"""
from __future__ import annotations

import argparse
import copy
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
import neumesh_core as nm  # noqa: E402
from neumesh_core.cli import turntable_cameras  # noqa: E402
from neumesh_core.data.synthetic import default_mesh  # noqa: E402
from neumesh_core.edit.fill import planar_uvs  # noqa: E402
from benchmarks._results import add_options, timed, use_threads, write_results  # noqa: E402


def _region_near(points: np.ndarray, axis: int, sign: float, n: int) -> np.ndarray:
    order = np.argsort(-sign * points[:, axis])
    return np.sort(order[:n])


def _render_time(field, cam, repeats: int) -> float:
    return timed(lambda: nm.render_camera(field, cam.K[0], cam.c2w[0], cam.width, cam.height), repeats).median


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "field", "mesh", "threads", "name", "results_dir",
                mesh=dict(help="scaffold mesh: an untrained field is made on it (timings only)"))
    ap.add_argument("--subdiv", type=int, default=7, help="built-in blob subdivision when neither is given")
    ap.add_argument("--region-size", type=int, default=50_000, help="vertices per region (default 50,000)")
    ap.add_argument("--repeats", type=int, default=3, help="renders per configuration (median)")
    ap.add_argument("--resolution", type=int, default=400, help="render size (square, default 400)")
    ap.add_argument("--interpolation", choices=["post", "early"], default=None,
                    help="override the field's interpolation for the render timings")
    args = ap.parse_args(argv)
    use_threads(args.threads or None)

    t0 = time.perf_counter()
    if args.field:
        field = nm.load_field(args.field)
        name = args.name or os.path.splitext(os.path.basename(os.path.dirname(os.path.abspath(args.field))))[0]
    else:
        mesh = nm.load_mesh(args.mesh) if args.mesh else default_mesh(subdiv=args.subdiv)
        field = nm.create_field(mesh)
        name = args.name or (os.path.splitext(os.path.basename(args.mesh))[0] if args.mesh else f"blob{args.subdiv}")
    if args.interpolation:
        field.config.interpolation = args.interpolation
    load_s = time.perf_counter() - t0
    field.eval()
    V = field.rest_vertices.numpy()
    n = min(args.region_size, field.num_vertices // 3)
    target = _region_near(V, 0, +1.0, n)
    source = _region_near(V, 0, -1.0, n)
    print(f"{name}: {field.num_vertices:,} vertices, regions of {n:,}; interpolation {field.config.interpolation}")

    # a source field with another decoder (so the decoder travels) and the same geometry
    other = copy.deepcopy(field)
    with torch.no_grad():
        for p in other.rad_decoder.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(0)))

    work = copy.deepcopy(field)
    t = time.perf_counter()
    unchecked = nm.edit.SwapConfig(check_fit=False)
    rec = nm.swap_texture(work, target, other, source, config=unchecked)
    swap_s = time.perf_counter() - t
    info = rec.info
    print(f"swap: align {info['align_s']:.2f} s, non-rigid {info['nonrigid_s']:.2f} s, transfer "
          f"{info['transfer_s']:.3f} s, total {swap_s:.2f} s; residual {info['residual_rigid']:.2f} -> "
          f"{info['residual']:.2f} edge lengths; scale {info['scale']:.3f}")
    t = time.perf_counter()
    rec.undo(work)
    undo_s = time.perf_counter() - t

    fill_field = copy.deepcopy(field)
    t = time.perf_counter()
    frec = nm.fill_texture(fill_field, target, planar_uvs(V[target]), other, source, planar_uvs(V[source]),
                           scale=3.0)
    fill_s = time.perf_counter() - t
    print(f"fill (planar UVs, scale 3): {fill_s:.3f} s; undo of the swap {undo_s * 1000:.1f} ms")

    bb = field.grid.aabb.cpu().numpy()
    cam = turntable_cameras(bb.mean(0), float(np.linalg.norm(bb[1] - bb[0])) * 1.1, 1, args.resolution,
                            args.resolution)
    render = {}
    with torch.no_grad():
        _render_time(field, cam, 1)   # warm-up
        render["one_decoder"] = _render_time(field, cam, args.repeats)
        two = copy.deepcopy(field)
        two.add_decoder(other.rad_decoder)
        render["two_decoders_unused"] = _render_time(two, cam, args.repeats)
        with torch.no_grad():
            two.decoder_id[torch.as_tensor(V[:, 0] > np.median(V[:, 0]))] = 1
        render["two_decoders_half"] = _render_time(two, cam, args.repeats)
        swapped = copy.deepcopy(field)
        nm.swap_texture(swapped, target, other, source, config=unchecked)
        render["after_swap"] = _render_time(swapped, cam, args.repeats)
    print("render {r}^2: one decoder {one_decoder:.2f} s, two (unused) {two_decoders_unused:.2f} s, two "
          "(half the vertices each) {two_decoders_half:.2f} s, after the swap {after_swap:.2f} s".format(
              r=args.resolution, **render))

    result = {
        "input": args.field or args.mesh or f"blob subdiv {args.subdiv}", "vertices": field.num_vertices,
        "region_vertices": n, "interpolation": field.config.interpolation, "load_s": load_s,
        "swap": {"align_s": info["align_s"], "nonrigid_s": info["nonrigid_s"], "transfer_s": info["transfer_s"],
                 "total_s": swap_s, "residual_rigid_edges": info["residual_rigid"],
                 "residual_edges": info["residual"], "scale": info["scale"], "undo_s": undo_s,
                 "fit_ok": info["fit_ok"], "overlap": info["overlap"]},
        "fill": {"total_s": fill_s, "scale": 3.0, "target_corners": frec.info["target_corners"]},
        "render_s": render, "resolution": args.resolution,
        "targets": {"transfer_s": 0.5, "align_with_nonrigid_s": 5.0},
    }
    write_results(result, f"edit_{name}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
