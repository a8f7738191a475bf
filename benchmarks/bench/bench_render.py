"""Where a rendered frame's time goes: a profile of render_camera split into its parts, beside each
part's floor on this machine (matmul rate and memory bandwidth measured in the same run), in both
interpolation modes, plus whole-frame times at 400² and 800² and the viewport's first-preview figures.

    python benchmarks/bench/bench_render.py --field runs/lego/field.neumesh --data ../shared/data/nerf_synthetic/lego
    python benchmarks/bench/bench_render.py --field runs/blob.neumesh      # orbit cameras around the field

Parts (seconds per frame, measured by timing the core's functions from the outside; nothing in the
core changes):
  marching        march_rays minus the density callback: ray/box, per-step occupancy lookups, window
                  bookkeeping, transmittance, packing (``occupancy_lookup`` is its grid-lookup share)
  ray_ranges      the per-pixel intervals where rays can meet occupied cells (OccupancyGrid.camera_ranges;
                  RenderSettings.skip_empty), which let the marcher skip empty pixels and distances
  neighbour_search  the K-nearest-within-radius query (pykdtree)
  indicators      the local indicators h_k = (p_k, w_k) from the neighbours (gathers, products)
  decode_sigma    the geometry decoder on every evaluated sample (codes, encodings, MLP)
  decode_colour   the radiance decoder on the samples that survive marching
  compositing     packed volume compositing
  other           the rest: ray generation, chunking, copies, Python
Floors: decoding = MLP FLOPs / measured matmul rate; memory-bound parts = the bytes they must move at
least (stated per part in the JSON) / measured copy bandwidth.  The floors ignore the latency of random
access, so they are lower bounds, not predictions.  ``--interpolation`` other than the field's own
renders a different image (the codes were trained for one mode): it is a cost profile, not a picture.
``--baseline-tree DIR`` (a checkout of earlier code) also renders the same 400² views with that code
in a subprocess, in ``--rounds`` interleaved rounds with this code's renders: frame times of both
(each view's best) and the PSNR of this code's image against the earlier one (the "same images"
check; that process times with its own loop: it imports the other checkout's modules, not this tree's
helper).  Writes benchmarks/results/log/render_<name>.json.
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from benchmarks._results import add_options, timed, use_threads, write_results  # noqa: E402


_BASELINE = r"""
import json, sys, time
import numpy as np, torch
sys.path.insert(0, sys.argv[1])
import neumesh_core as nm
f = nm.load_field(sys.argv[2]); f.eval()
cams = json.load(open(sys.argv[3]))
times, imgs = [], {}
with torch.no_grad():
    c = cams[0]
    nm.render_camera(f, np.array(c["K"], np.float32), np.array(c["c2w"]), c["size"], c["size"])   # warm up
    for i, c in enumerate(cams):
        t = time.perf_counter()
        o = nm.render_camera(f, np.array(c["K"], np.float32), np.array(c["c2w"]), c["size"], c["size"])
        times.append(time.perf_counter() - t)
        imgs[str(i)] = o.rgb
np.savez(sys.argv[4], **imgs)
print("BASELINE " + json.dumps(times))
"""


def baseline_comparison(field, field_path: str, tree: str, cams, size: int, rounds: int) -> dict:
    """Frame times of this code and of the code in ``tree`` on the same views, interleaved, and the
    PSNR of this code's images against that code's."""
    import neumesh_core as nm
    from neumesh_core.metrics import psnr as image_psnr

    spec = [{"K": scaled(K, size / (2 * K[0, 2])).tolist(), "c2w": np.asarray(c2w).tolist(), "size": size}
            for K, c2w in cams]
    old_t, new_t = [], []
    with tempfile.TemporaryDirectory() as tmp:
        cam_file, img_file = os.path.join(tmp, "cams.json"), os.path.join(tmp, "old.npz")
        with open(cam_file, "w") as fh:
            json.dump(spec, fh)
        new_imgs = {}
        for _ in range(rounds):
            r = subprocess.run([sys.executable, "-c", _BASELINE, os.path.abspath(tree), os.path.abspath(field_path),
                                cam_file, img_file], capture_output=True, text=True, check=True)
            old_t.append(json.loads(r.stdout.split("BASELINE", 1)[1]))
            times = []
            for i, c in enumerate(spec):
                run = timed(lambda: nm.render_camera(field, np.array(c["K"], np.float32), np.array(c["c2w"]), size,
                                                     size))
                times.append(run.best)
                new_imgs[i] = run.result.rgb
            new_t.append(times)
        old_imgs = np.load(img_file)
        psnr = [image_psnr(new_imgs[i], old_imgs[str(i)]) for i in range(len(spec))]
    old_best = np.min(np.array(old_t), 0)
    new_best = np.min(np.array(new_t), 0)
    return {"tree": tree, "size": size, "rounds": rounds, "baseline_s": old_best.tolist(),
            "this_code_s": new_best.tolist(), "baseline_median_s": float(np.median(old_best)),
            "this_code_median_s": float(np.median(new_best)),
            "speed_up": float(np.median(old_best) / np.median(new_best)),
            "psnr_vs_baseline_db": psnr, "min_psnr_vs_baseline_db": float(min(psnr))}


def machine_floors(threads: int) -> dict:
    """Matmul rate (fp32, 2048², best of 5) and copy bandwidth (256 MB, best of 5) in this process."""
    a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
    flops = 2 * 2048 ** 3 / timed(lambda: torch.mm(a, b), 5).best
    x = torch.empty(64 * 2 ** 20)
    x.fill_(1.0)
    y = torch.empty_like(x)
    bw = 2 * x.numel() * 4 / timed(lambda: y.copy_(x), 5).best     # read + write
    return {"threads": threads, "matmul_gflops": flops / 1e9, "copy_gbytes_per_s": bw / 1e9}


class Profiler:
    """Times the core's render functions by wrapping them (restored on exit)."""

    def __init__(self):
        self.t = collections.defaultdict(float)
        self.n = collections.defaultdict(int)
        self._in_sigma = 0
        self._patches = []

    def _wrap(self, owner, name, key, count=None):
        fn = getattr(owner, name)
        prof = self

        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                prof.t[key] += time.perf_counter() - t0
                prof.n[key] += count(a, k) if count else 1
        self._patches.append((owner, name, fn))
        setattr(owner, name, timed)

    @contextlib.contextmanager
    def active(self):
        from neumesh_core.field import field as fmod
        from neumesh_core.field import knn, scaffold
        from neumesh_core.render import renderer
        from neumesh_core.sampling import occupancy

        prof = self
        self._wrap(knn.KDTreeIndex, "query", "neighbour_search", lambda a, k: len(a[1]))
        self._wrap(knn.HashGridIndex, "query", "neighbour_search", lambda a, k: len(a[1]))
        self._wrap(scaffold.Scaffold, "neighbourhood", "_neighbourhood")
        self._wrap(occupancy.OccupancyGrid, "lookup", "occupancy_lookup", lambda a, k: a[1].numel() // 3)
        if hasattr(occupancy.OccupancyGrid, "lookup_steps"):     # the marcher's form (older code: lookup)
            self._wrap(occupancy.OccupancyGrid, "lookup_steps", "occupancy_lookup", lambda a, k: a[3].numel())
        if hasattr(occupancy.OccupancyGrid, "camera_ranges"):   # per-pixel ray ranges (older code: none)
            self._wrap(occupancy.OccupancyGrid, "camera_ranges", "ray_ranges")
        self._wrap(renderer, "composite", "compositing")
        self._wrap(renderer, "march_rays", "_march")
        sigma_fn = fmod.NeuMeshField.sigma_fn
        decode = fmod.NeuMeshField.decode

        def sigma_wrapped(field, x):
            prof._in_sigma += 1
            t0 = time.perf_counter()
            try:
                return sigma_fn(field, x)
            finally:
                prof._in_sigma -= 1
                prof.t["_sigma"] += time.perf_counter() - t0
                prof.n["sigma_samples"] += len(x)

        def decode_wrapped(field, nb, *a, **k):
            if prof._in_sigma:
                return decode(field, nb, *a, **k)
            t0 = time.perf_counter()
            try:
                return decode(field, nb, *a, **k)
            finally:
                prof.t["decode_colour"] += time.perf_counter() - t0
                prof.n["colour_samples"] += len(nb)
        self._patches += [(fmod.NeuMeshField, "sigma_fn", sigma_fn), (fmod.NeuMeshField, "decode", decode)]
        fmod.NeuMeshField.sigma_fn = sigma_wrapped
        fmod.NeuMeshField.decode = decode_wrapped
        try:
            yield self
        finally:
            for owner, name, fn in reversed(self._patches):
                setattr(owner, name, fn)
            self._patches.clear()

    def parts(self, total: float) -> dict:
        t = self.t
        p = {"marching": t["_march"] - t["_sigma"],
             "occupancy_lookup": t["occupancy_lookup"],
             "neighbour_search": t["neighbour_search"],
             "indicators": t["_neighbourhood"] - t["neighbour_search"],
             "decode_sigma": t["_sigma"] - t["_neighbourhood"],
             "decode_colour": t["decode_colour"],
             "compositing": t["compositing"],
             "ray_ranges": t["ray_ranges"]}
        p["other"] = total - sum(v for k, v in p.items() if k != "occupancy_lookup")
        return p


def mlp_flops(module) -> int:
    return sum(2 * m.in_features * m.out_features for m in module.modules() if isinstance(m, torch.nn.Linear))


def floors(field, counts: dict, rays: int, machine: dict) -> dict:
    """Lower bounds per part from the measured rates (see the module docstring)."""
    rate = machine["matmul_gflops"] * 1e9
    bw = machine["copy_gbytes_per_s"] * 1e9
    k = field.config.k
    per = k if field.config.interpolation == "post" else 1     # decoder rows per sample
    ns, nc, nl = counts["sigma_samples"], counts["colour_samples"], counts["occupancy_lookups"]
    geo_in = field.geo_codes.shape[1]
    tex_in = field.tex_codes.shape[1]
    b = {   # bytes each part must move at least
        "marching": nl * (12 + 1) + ns * 16,                       # step points + occupancy bytes; samples out
        "neighbour_search": ns * k * (12 + 12),                    # K vertex rows read; idx + dist written
        "indicators": ns * k * (24 + 12),                          # vertex + normal rows; p, w, valid out
        "decode_sigma": ns * k * geo_in * 4,                       # geometry code rows
        "decode_colour": nc * k * (tex_in + 6) * 4,                # texture codes, normals, mod colours
        "compositing": nc * 4 * 10 + rays * 4 * 10,                # packed samples in, pixels out
    }
    f = {name: v / bw for name, v in b.items()}
    f["decode_sigma"] += ns * per * mlp_flops(field.geo_decoder) / rate
    f["decode_colour"] += nc * per * mlp_flops(field.rad_decoder) / rate
    return {"seconds": f, "bytes": b,
            "decoder_flops": {"geometry_per_row": mlp_flops(field.geo_decoder),
                              "radiance_per_row": mlp_flops(field.rad_decoder), "rows_per_sample": per}}


def orbit_cameras(field, n: int, size: int):
    """Cameras on a circle around the field, looking at its centre (when no dataset is given)."""
    from neumesh_core.data.synthetic import look_at_opencv

    v = field.rest_vertices.numpy()
    centre = (v.min(0) + v.max(0)) / 2
    r = float(np.linalg.norm(v.max(0) - v.min(0)))
    focal = size * 1.1
    K = np.array([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]], np.float32)
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = centre + r * np.array([np.cos(a), np.sin(a), 0.5])
        out.append((K, look_at_opencv(eye, centre)))
    return out


def dataset_cameras(data: str, n: int, size: int):
    import neumesh_core as nm

    cams = nm.load_scene(data).split("val").cameras
    views = [int(i) for i in np.linspace(0, len(cams) - 1, n).round()]
    out = []
    for i in views:
        K = np.array(cams.K[i], np.float32).copy()
        K[:2] *= size / cams.width
        out.append((K, np.array(cams.c2w[i])))
    return out


def scaled(K, factor: float):
    K = np.array(K, np.float32).copy()
    K[:2] *= factor
    return K


def time_frames(field, cams, size: int, repeats: int, settings=None):
    import neumesh_core as nm

    return [timed(lambda: nm.render_camera(field, scaled(K, size / (2 * K[0, 2])), c2w, size, size,
                                           settings=settings), repeats).best for K, c2w in cams]


def profile_mode(field, cams, size: int, machine: dict) -> dict:
    import neumesh_core as nm

    per_view = []
    for K, c2w in cams:
        K = scaled(K, size / (2 * K[0, 2]))
        prof = Profiler()
        with prof.active():
            t = time.perf_counter()
            out = nm.render_camera(field, K, c2w, size, size)
            total = time.perf_counter() - t
        counts = {"rays": size * size, "sigma_samples": prof.n["sigma_samples"],
                  "colour_samples": prof.n["colour_samples"], "kept_samples": int(out.n_samples),
                  "occupancy_lookups": prof.n["occupancy_lookup"], "knn_queries": prof.n["neighbour_search"]}
        per_view.append({"total_s": total, "parts_s": prof.parts(total), "counts": counts})
    med = lambda xs: float(statistics.median(xs))   # noqa: E731
    parts = {k: med([v["parts_s"][k] for v in per_view]) for k in per_view[0]["parts_s"]}
    counts = {k: int(med([v["counts"][k] for v in per_view])) for k in per_view[0]["counts"]}
    fl = floors(field, counts, size * size, machine)
    return {"total_s": med([v["total_s"] for v in per_view]), "parts_s": parts, "counts": counts,
            "floors": fl, "per_view": per_view}


def viewport_figures(field, cams, viewport=(1280, 720), divisors=(8, 16)) -> dict:
    """The add-on's first progressive preview of a ``viewport``-sized 3D view: a 1/d frame for each d in
    ``divisors`` (the add-on starts at 1/8 and goes coarser while its last measured seconds per pixel
    say the first image would miss 0.1 s: addon/engine.py PreviewRenderer.levels), after a camera
    move, and after a deformation (set_vertices of displaced vertices, then the frame)."""
    import neumesh_core as nm

    def frame(d, K, c2w):
        w, h = viewport[0] // d, viewport[1] // d
        Kp = scaled(K, w / (2 * K[0, 2]))
        Kp[1, 2] = h / 2
        nm.render_camera(field, Kp, c2w, w, h)

    out = {"viewport": list(viewport), "vertices": field.num_vertices, "levels": {}}
    rest = field.rest_vertices.clone()
    rng = np.random.default_rng(0)
    for d in divisors:
        frame(d, *cams[0])
        moves = []
        for K, c2w in (cams[1:] or cams):
            t = time.perf_counter()
            frame(d, K, c2w)
            moves.append(time.perf_counter() - t)
        deform = []
        for i in range(3):
            v = rest + torch.from_numpy(rng.normal(0, 1e-4, rest.shape).astype(np.float32))
            t = time.perf_counter()
            field.set_vertices(v)
            t_set = time.perf_counter() - t
            frame(d, *cams[0])
            deform.append({"set_vertices_s": t_set, "first_preview_s": time.perf_counter() - t})
        field.reset_vertices()
        out["levels"][str(d)] = {
            "size": [viewport[0] // d, viewport[1] // d],
            "camera_move_s": float(np.median(moves)),
            "deformation_s": float(np.median([x["first_preview_s"] for x in deform])),
            "set_vertices_s": float(np.median([x["set_vertices_s"] for x in deform])), "deformation_runs": deform}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "field", "data", "threads", "name", "results_dir", field=dict(required=True),
                data=dict(help="dataset whose val cameras are rendered (default: orbit cameras)"))
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--sizes", type=int, nargs="+", default=[400, 800])
    ap.add_argument("--repeats", type=int, default=2, help="renders per view for frame times (best counts)")
    ap.add_argument("--modes", nargs="+", default=["early", "post"], choices=["early", "post"])
    ap.add_argument("--baseline-tree", help="checkout of earlier code to compare frame times and images with")
    ap.add_argument("--rounds", type=int, default=2, help="interleaved rounds of the baseline comparison")
    args = ap.parse_args(argv)
    import neumesh_core as nm

    use_threads(args.threads or None)
    field = nm.load_field(args.field)
    field.eval()
    name = args.name or os.path.splitext(os.path.basename(args.field))[0]
    cams = dataset_cameras(args.data, args.views, 400) if args.data else orbit_cameras(field, args.views, 400)
    machine = machine_floors(torch.get_num_threads())
    print(f"machine: matmul {machine['matmul_gflops']:.0f} GFLOP/s, copy {machine['copy_gbytes_per_s']:.1f} GB/s, "
          f"{machine['threads']} threads")
    own = field.config.interpolation
    result = {"field": args.field, "vertices": field.num_vertices, "trained_interpolation": own,
              "machine": machine, "modes": {}}
    with torch.no_grad():
        for mode in args.modes:
            field.config.interpolation = mode
            nm.render_camera(field, scaled(cams[0][0], 0.25), cams[0][1], 100, 100)   # warm up
            r = {"profile_400": profile_mode(field, cams, 400, machine)}
            r["frame_s"] = {str(s): float(np.median(time_frames(field, cams, s, args.repeats))) for s in args.sizes}
            # the same frames marched through the whole box, every pixel (RenderSettings.skip_empty off)
            r["frame_400_s_skip_empty_off"] = float(np.median(time_frames(
                field, cams, 400, args.repeats, nm.RenderSettings(skip_empty=False))))
            pr = r["profile_400"]
            print(f"[{mode}] frame " + ", ".join(f"{s}²: {v:.3f} s" for s, v in r["frame_s"].items())
                  + f" (400² without skip_empty: {r['frame_400_s_skip_empty_off']:.3f} s)")
            for part, sec in pr["parts_s"].items():
                floor = pr["floors"]["seconds"].get(part)
                print(f"  {part:18s} {sec:7.3f} s" + (f"   floor {floor:.4f} s" if floor is not None else ""))
            print("  counts: " + ", ".join(f"{k} {v}" for k, v in pr["counts"].items()))
            result["modes"][mode] = r
        field.config.interpolation = own
        result["viewport"] = viewport_figures(field, cams)
        if args.baseline_tree:
            b = baseline_comparison(field, args.field, args.baseline_tree, cams, 400, args.rounds)
            result["baseline"] = b
            print(f"baseline {args.baseline_tree}: {b['baseline_median_s']:.3f} s, "
                  f"this code {b['this_code_median_s']:.3f} s "
                  f"(x{b['speed_up']:.2f}); PSNR of this code's images against the baseline's >= "
                  f"{b['min_psnr_vs_baseline_db']:.1f} dB")
    for d, v in result["viewport"]["levels"].items():
        print(f"viewport first preview 1/{d} ({v['size'][0]}x{v['size'][1]}): camera move {v['camera_move_s']:.3f} s, "
              f"deformation {v['deformation_s']:.3f} s (set_vertices {v['set_vertices_s']:.3f} s)")
    write_results(result, f"render_{name}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
