#!/usr/bin/env python3
"""Blender add-on timings (bpy==5.0.1 in the venv and the real `blender` binary, CPU).

1. Viewport preview latency: a bone of an armature deforming a 100k-vertex scaffold is rotated;
   time until the first progressive-preview image exists (1/8 of an 800x600 viewport, or coarser when
   the preview's measured rate says 1/8 would miss 0.1 s: PreviewRenderer.levels), and until the 1/8
   image. Broken down into depsgraph evaluation + sync (evaluated world vertices), set_vertices, and
   the low-res render. Target: <= 0.5 s at 300k vertices (``--vertices 300000``).
2. F12: `bpy.ops.render.render()` through the NEUMESH engine at 400x400 for the same scaffold.
   An untrained field is semi-transparent everywhere (no early ray termination): a worst case for
   the marcher; a trained field renders faster.

3. F12 beside the core (section ``f12``): F12 (``bpy.ops.render.render()``, the engine's default
   settings: one ray per pixel unless the scene's *Anti-aliasing* says more) at 400x400 in the real
   `blender` binary (Debian's 3.4, ``blender -b``) and in bpy 5.0.1, interleaved (F12, core, F12,
   core, ...) with the core's own render of the same frame (``nm.render_camera``: the same field
   posed with the vertices the engine used, the same K, c2w, size, supersampling and background) in a
   plain Python process, and in the Blender process itself. Each Blender and the core are persistent
   worker processes (benchmarks/workers/f12_worker.py) driven in turn, so machine load hits both alike.
   Target: median F12 / median core <= 1.3. ``--threads N`` sets the add-on preference *CPU threads*
   and the core's torch threads alike (0: all cores); on a busy 2-core machine use 1 (two OpenMP
   threads there alternate between ~1x and ~8x the time). ``--label`` keeps a run as a variant;
   ``--blender-env NEUMESH_JEMALLOC=off`` measures Blender's allocator as it was.

The field is created untrained (timings do not depend on training). Prints figures and writes
benchmarks/results/log/addon.json (``--results-dir``, ``--name``; a run of some sections keeps the file's
other sections; each section holds the machine record of its run).

    .venv/bin/python benchmarks/bench/bench_addon.py [--vertices 100000] [--repeat 3] [--sections preview,f12]
    .venv/bin/python benchmarks/bench/bench_addon.py --sections f12 --threads 1 --in-blender-core   # the docs' figures
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import threading
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "blender_tests"))
import user_dirs  # noqa: E402
from benchmarks._results import LOG_DIR, add_options, machine_record, timed, write_results  # noqa: E402

_BASE = user_dirs.redirect("neumesh_bench_")

import numpy as np  # noqa: E402

import build_addon  # noqa: E402

MODULE = "bl_ext.user_default.neumesh"


def sphere_grid(n_target: int, radius=1.0):
    """Closed lat-long sphere with ~n_target vertices; (V,3) float32, (F,3) int64."""
    n_lat = max(4, int(round(math.sqrt(n_target / 2))))
    n_lon = max(8, (n_target - 2) // (n_lat - 1))
    th = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    V = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3) * radius
    V = np.concatenate([[[0, 0, radius]], V, [[0, 0, -radius]]]).astype(np.float32)
    F = []
    rows = n_lat - 1
    idx = lambda r, c: 1 + r * n_lon + (c % n_lon)  # noqa: E731
    for c in range(n_lon):
        F.append((0, idx(0, c), idx(0, c + 1)))
        F.append((len(V) - 1, idx(rows - 1, c + 1), idx(rows - 1, c)))
    r = np.arange(rows - 1)[:, None]
    c = np.arange(n_lon)[None, :]
    a, b = idx(r, c), idx(r, c + 1)
    d, e = idx(r + 1, c), idx(r + 1, c + 1)
    quads = np.stack([np.stack([a, d, e], -1), np.stack([a, e, b], -1)], -2).reshape(-1, 3)
    return V, np.concatenate([np.asarray(F), quads]).astype(np.int64)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--vertices", type=int, default=100_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--viewport", default="800x600")
    ap.add_argument("--sections", default="preview,f12", help="comma-separated: preview (1. and 2.), f12 (3.)")
    ap.add_argument("--f12-size", type=int, default=400)
    ap.add_argument("--f12-pairs", type=int, default=5, help="F12 / core pairs per Blender")
    ap.add_argument("--blenders", default="blender,bpy",
                    help="f12: 'blender' (the binary, --blender-bin) and/or 'bpy' (the module in this Python)")
    ap.add_argument("--blender-bin", default=shutil.which("blender") or "/usr/bin/blender")
    ap.add_argument("--blender-torch", default=os.environ.get("NEUMESH_BLENDER_TORCH",
                                                              os.path.join(ROOT, ".blender_torch")))
    ap.add_argument("--blender-env", action="append", default=[], metavar="KEY=VALUE",
                    help="f12: extra environment of the Blender workers (e.g. LD_PRELOAD=..., MALLOC_CONF=...)")
    ap.add_argument("--in-blender-core", action="store_true",
                    help="f12: also time the core render inside the Blender process (a diagnostic column)")
    add_options(ap, "threads", "name", "results_dir",
                threads=dict(default=0, help="f12: the add-on preference CPU threads in each Blender, and torch's "
                                             "threads in the core process (0: all cores, the add-on's default)"),
                name=dict(default="addon", help="results name (default addon)"))
    ap.add_argument("--label", default="",
                    help="f12: store the run under f12_vs_core.variants[LABEL] instead of as the main figures")
    a = ap.parse_args(argv)
    sections = {x.strip() for x in a.sections.split(",") if x.strip()}
    res = {}
    path = os.path.join(a.results_dir or LOG_DIR, f"{a.name}.json")
    if os.path.isfile(path):
        with open(path) as fh:
            res = json.load(fh)
    if "preview" in sections:
        res.update(bench_preview(a))
    if "f12" in sections:
        f12 = bench_f12_vs_core(a)
        old = res.get("f12_vs_core", {})
        if a.label:
            old.setdefault("variants", {})[a.label] = f12
            res["f12_vs_core"] = old
        else:
            f12["variants"] = old.get("variants", {})
            res["f12_vs_core"] = f12
    write_results(res, f"{a.name}.json", a.results_dir)
    return 0


def bench_preview(a) -> dict:
    import bpy

    vw, vh = (int(x) for x in a.viewport.split("x"))

    zip_path = build_addon.build(os.path.join(_BASE, "neumesh.zip"))
    bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    import addon_utils

    addon_utils.enable(MODULE, default_set=True)
    addon = sys.modules[MODULE]
    from helpers import add_armature_bend, add_camera, manual_K_c2w

    nm = addon.runtime.core.get()

    V, F = sphere_grid(a.vertices)
    t = time.perf_counter()
    field = nm.create_field(nm.Mesh(V, F), nm.FieldConfig())
    t_create = time.perf_counter() - t
    fpath = os.path.join(_BASE, "big.neumesh")
    nm.save_field(field, fpath)
    del field
    t = time.perf_counter()
    obj = addon.scene.sync.new_mesh_object("scaffold", V, F)
    t_mesh = time.perf_counter() - t
    addon.scene.props.set_field_path(obj, fpath)
    bpy.context.view_layer.objects.active = obj
    arm, _root, tip = add_armature_bend(obj, split_x=0.3, angle_deg=0.0)
    cam = add_camera((0.0, -3.6, 0.6), lens=35.0)
    scene = bpy.context.scene
    scene.render.engine = "NEUMESH"

    # warm-up: load + first collect (loads the field into the cache)
    t = time.perf_counter()
    dg = bpy.context.evaluated_depsgraph_get()
    items = addon.render.field_cache.collect(dg, for_render=False)
    t_load = time.perf_counter() - t

    K, c2w = manual_K_c2w(cam, vw, vh)
    pv = addon.render.preview.PreviewRenderer(divisors=(8, 4))
    serial = pv.request(items, K, c2w, vw, vh)
    pv.wait(serial, divisor=4, timeout=600)

    pb = arm.pose.bones["tip"]
    runs = []
    for i in range(a.repeat):
        angle = math.radians(15 + 10 * i)
        t0 = time.perf_counter()
        pb.rotation_euler = (0.0, angle, 0.0)                       # the deformation
        dg = bpy.context.evaluated_depsgraph_get()                  # what view_update receives
        dg.update()
        t1 = time.perf_counter()
        items = addon.render.field_cache.collect(dg, for_render=False)          # sync: evaluated world vertices
        t2 = time.perf_counter()
        sv0 = addon.render.field_cache.STATS["set_vertices"]
        serial = pv.request(items, K, c2w, vw, vh)                  # view_draw -> preview thread
        ok = pv.wait(serial, divisor=pv.max_divisor, timeout=120)   # its first image, at any level
        t3 = time.perf_counter()
        assert ok, pv.error
        assert addon.render.field_cache.STATS["set_vertices"] == sv0 + 1
        first = pv.latest[1]
        ok8 = pv.wait(serial, divisor=8, timeout=120)
        t4 = time.perf_counter()
        assert ok8, pv.error
        runs.append({"depsgraph_s": t1 - t0, "sync_s": t2 - t1, "first_preview_s": t3 - t2,
                     "first_preview_divisor": first, "total_s": t3 - t0, "preview_1_8_s": t4 - t2,
                     "total_to_1_8_s": t4 - t0})
        pv.wait(serial, divisor=4, timeout=600)
    pv.stop()

    # set_vertices alone (the part of the preview that is not rendering)
    f_cached = addon.render.field_cache.get_field(obj.name_full, addon.scene.props.field_abspath(obj))
    t = time.perf_counter()
    f_cached.set_vertices(items[0].vertices + 1e-4)
    t_setv = time.perf_counter() - t
    addon.render.field_cache._CACHE[obj.name_full].last_vertices = None
    low_w, low_h = vw // 8, vh // 8
    # best of 3: the 2-core machine is shared, single timings are noisy
    t_low = timed(lambda: nm.render_camera(f_cached, addon.render.frame.scale_K(K, vw, vh, low_w, low_h), c2w,
                                           low_w, low_h), repeats=3).best

    # F12 at 400x400
    scene.render.resolution_x = scene.render.resolution_y = 400
    scene.render.resolution_percentage = 100
    scene.render.filepath = os.path.join(_BASE, "f12.png")
    f12 = []
    for i in range(max(1, a.repeat - 1)):
        pb.rotation_euler = (0.0, math.radians(40 + 5 * i), 0.0)
        t = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        f12.append(time.perf_counter() - t)
    assert not addon.render.engine.LAST_ERROR["message"], addon.render.engine.LAST_ERROR["message"]

    best = min(runs, key=lambda r: r["total_s"])
    res = {
        "scaffold": {"vertices": int(len(V)), "faces": int(len(F)), "create_field_s": t_create,
                     "blender_mesh_foreach_set_s": t_mesh, "first_load_and_sync_s": t_load},
        "preview": {"viewport": [vw, vh], "first_level": [vw // 8, vh // 8], "runs": runs,
                    "median_total_s": float(np.median([r["total_s"] for r in runs])),
                    "median_total_to_1_8_s": float(np.median([r["total_to_1_8_s"] for r in runs])),
                    "first_preview_divisors": [r["first_preview_divisor"] for r in runs],
                    "best_total_s": best["total_s"], "set_vertices_s": t_setv, "render_1_8_only_s": t_low,
                    "target_s": 0.5, "meets_target": float(np.median([r["total_s"] for r in runs])) <= 0.5,
                    "machine": {**machine_record(), "bpy": bpy.app.version_string}},
        "f12_400x400": {"seconds": f12, "median_s": float(np.median(f12))},
    }
    print(f"scaffold: {len(V)} vertices, {len(F)} faces; create_field {t_create:.2f}s, "
          f"mesh via foreach_set {t_mesh:.3f}s, first load+sync {t_load:.2f}s")
    for i, r in enumerate(runs):
        print(f"preview run {i}: depsgraph {r['depsgraph_s']*1e3:.0f} ms, sync {r['sync_s']*1e3:.0f} ms, "
              f"set_vertices + first image (1/{r['first_preview_divisor']}) {r['first_preview_s']*1e3:.0f} ms, "
              f"total {r['total_s']*1e3:.0f} ms (to 1/8: {r['total_to_1_8_s']*1e3:.0f} ms)")
    print(f"  set_vertices alone {t_setv*1e3:.0f} ms, 1/8 render ({vw//8}x{vh//8}) alone, best of 3: "
          f"{t_low*1e3:.0f} ms; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"preview refresh median {res['preview']['median_total_s']:.3f}s (target <= 0.5 s: "
          f"{'met' if res['preview']['meets_target'] else 'NOT met'})")
    print("F12 400x400: " + ", ".join(f"{s:.2f}s" for s in f12))
    return res


class _Worker:
    """A benchmarks/workers/f12_worker.py process: one command a line in, 'NEUMESH_BENCH {json}' lines out."""

    def __init__(self, name, cmd, env, timeout=600):
        self.name, self.log = name, []
        self.proc = subprocess.Popen(cmd, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, bufsize=1)
        self.ready = self._answer(timeout)

    def _answer(self, timeout):
        box = {}

        def read():
            for line in self.proc.stdout:
                self.log.append(line)
                if line.startswith("NEUMESH_BENCH "):
                    box["v"] = json.loads(line[len("NEUMESH_BENCH "):])
                    return
        th = threading.Thread(target=read, daemon=True)
        th.start()
        th.join(timeout)
        if "v" not in box:
            self.close()
            raise RuntimeError(f"{self.name}: no answer; its output ends with:\n" + "".join(self.log[-40:]))
        if "error" in box["v"]:
            raise RuntimeError(f"{self.name}: {box['v']['error']}\n" + "".join(self.log[-40:]))
        return box["v"]

    def ask(self, cmd, timeout=600):
        self.proc.stdin.write(cmd + "\n")
        self.proc.stdin.flush()
        return self._answer(timeout)

    def close(self):
        try:
            self.proc.stdin.write("quit\n")
            self.proc.stdin.flush()
            self.proc.wait(60)
        except Exception:  # noqa: BLE001
            self.proc.kill()
            self.proc.wait()


def _blender_env(tmp, extra=()):
    env = dict(os.environ)
    env.update({
        "BLENDER_USER_CONFIG": os.path.join(tmp, "config"), "BLENDER_USER_SCRIPTS": os.path.join(tmp, "scripts"),
        "BLENDER_USER_DATAFILES": os.path.join(tmp, "datafiles"),
        "BLENDER_USER_RESOURCES": os.path.join(tmp, "resources"), "HOME": os.path.join(tmp, "home"),
        "TMPDIR": tmp, "XDG_CACHE_HOME": os.path.join(tmp, "cache"), "PYTHONNOUSERSITE": "1",
    })
    os.makedirs(env["HOME"], exist_ok=True)
    for kv in extra:
        k, _, v = kv.partition("=")
        env[k] = v
    return env


def _median(x):
    return float(np.median(np.asarray(x, np.float64)))


def bench_f12_vs_core(a) -> dict:
    """F12 in each Blender beside the core's own render of the same frame (see the module docstring)."""
    sys.path.insert(0, ROOT)
    import neumesh_core as nm

    worker = os.path.join(ROOT, "benchmarks", "workers", "f12_worker.py")
    V, F = sphere_grid(a.vertices)
    fpath = os.path.join(_BASE, "f12_field.neumesh")
    nm.save_field(nm.create_field(nm.Mesh(V, F), nm.FieldConfig()), fpath)
    zip_path = build_addon.build(os.path.join(_BASE, "neumesh_f12.zip"))
    out = {"size": [a.f12_size, a.f12_size], "vertices": int(len(V)), "pairs": a.f12_pairs,
           "threads_setting": a.threads, "blender_env": list(a.blender_env), "label": a.label,
           "started": time.strftime("%Y-%m-%d %H:%M:%S"), "loadavg_at_start": list(os.getloadavg()),
           "cpu_count": os.cpu_count(), "field": "untrained sphere (semi-transparent: no early ray termination)",
           "what": "seconds of bpy.ops.render.render() (F12) in the Blender process and of nm.render_camera "
                   "with the same inputs in a plain Python process ('core'; with --in-blender-core also in "
                   "the Blender process, 'core_in_blender'), interleaved F12, core, F12, core, ...; the first "
                   "F12 (field load + posing) is a warm-up, not counted",
           "target_ratio": 1.3, "runs": {}, "machine": machine_record()}
    for kind in [k.strip() for k in a.blenders.split(",") if k.strip()]:
        tmp = tempfile.mkdtemp(prefix=f"f12_{kind}_", dir=_BASE)
        inputs = os.path.join(tmp, "inputs.npz")
        env = _blender_env(tmp, a.blender_env)
        if kind == "blender":
            if not os.path.exists(a.blender_bin):
                print(f"f12: no blender binary at {a.blender_bin}; skipped")
                continue
            env["NEUMESH_PYTHONPATH"] = a.blender_torch
            cmd = [a.blender_bin, "-b", "--factory-startup", "--python", worker, "--", "blender", zip_path, fpath,
                   inputs, str(a.f12_size), str(a.threads)]
        elif kind == "bpy":
            cmd = [sys.executable, worker, "blender", zip_path, fpath, inputs, str(a.f12_size), str(a.threads)]
        else:
            raise SystemExit(f"unknown Blender kind {kind!r}")
        print(f"f12 [{kind}]: starting {' '.join(cmd[:3])} ...", flush=True)
        bw = _Worker(kind, cmd, env)
        cw = None
        try:
            cenv = {k: v for k, v in os.environ.items() if k not in ("LD_PRELOAD", "MALLOC_CONF")}
            cw = _Worker("core", [sys.executable, worker, "core", fpath, inputs, str(a.threads)], cenv)
            rows = []
            for i in range(a.f12_pairs):
                row = {"loadavg": list(os.getloadavg())}
                f = bw.ask("f12")
                row["f12_s"], row["f12_phases"] = f["seconds"], f["phases"]
                c = cw.ask("core")
                row["core_s"], row["core_threads"] = c["seconds"], c["threads"]
                if a.in_blender_core:
                    ci = bw.ask("core")
                    row["core_in_blender_s"], row["core_in_blender_threads"] = ci["seconds"], ci["threads"]
                    row["mean_rgb_same"] = abs(ci["mean_rgb"] - c["mean_rgb"]) < 1e-5
                rows.append(row)
                print(f"  {kind} pair {i}: F12 {row['f12_s']:.2f} s (engine's core call "
                      f"{f['phases'].get('core_s', float('nan')):.2f} s), core {row['core_s']:.2f} s"
                      + ("" if not a.in_blender_core else f", core in Blender {row['core_in_blender_s']:.2f} s")
                      + f"; load {row['loadavg'][0]:.2f}", flush=True)
        finally:
            bw.close()
            if cw is not None:
                cw.close()
        f12 = [r["f12_s"] for r in rows]
        core = [r["core_s"] for r in rows]
        entry = {
            "blender": bw.ready["blender"], "python": bw.ready["python"], "torch": bw.ready["torch"],
            "torch_threads_in_blender": rows[-1]["f12_phases"].get("torch_threads"),
            "torch_threads_core": cw.ready["threads"], "supersample": bw.ready["supersample"],
            "transparent": bw.ready["transparent"], "env": bw.ready["env"], "first_f12": bw.ready["first_f12"],
            "malloc": bw.ready.get("malloc"),
            "pairs": rows, "median_f12_s": _median(f12), "median_core_s": _median(core),
            "ratio_of_medians": _median(f12) / _median(core),
            "median_pair_ratio": _median([x / y for x, y in zip(f12, core)]),
            "median_phases_s": {k: _median([r["f12_phases"][k] for r in rows])
                                for k in rows[0]["f12_phases"] if k.endswith("_s")},
            "handoff": rows[-1]["f12_phases"].get("handoff"),
            "loadavg_median_1min": _median([r["loadavg"][0] for r in rows]),
        }
        if a.in_blender_core:
            entry["median_core_in_blender_s"] = _median([r["core_in_blender_s"] for r in rows])
            entry["ratio_core_in_blender_to_core"] = entry["median_core_in_blender_s"] / entry["median_core_s"]
        entry["meets_target"] = entry["ratio_of_medians"] <= out["target_ratio"]
        out["runs"][kind] = entry
        print(f"f12 [{kind}] {entry['blender']}: median F12 {entry['median_f12_s']:.2f} s, core "
              f"{entry['median_core_s']:.2f} s, ratio {entry['ratio_of_medians']:.2f} (pairs: "
              f"{entry['median_pair_ratio']:.2f}); torch threads in Blender {entry['torch_threads_in_blender']}; "
              f"load {entry['loadavg_median_1min']:.2f}", flush=True)
    return out


if __name__ == "__main__":
    sys.exit(main())
