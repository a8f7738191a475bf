#!/usr/bin/env python3
"""Blender add-on timings (bpy==5.0.1 in the venv, CPU).

1. Viewport preview latency: a bone of an armature deforming a 100k-vertex scaffold is rotated;
   time until the first progressive-preview image (1/8 of an 800x600 viewport) exists. Broken down
   into depsgraph evaluation + sync (evaluated world vertices), set_vertices, and the low-res render.
   Target: <= 1 s.
2. F12: `bpy.ops.render.render()` through the NEUMESH engine at 400x400 for the same scaffold.
   An untrained field is semi-transparent everywhere (no early ray termination): a worst case for
   the marcher; a trained field renders faster.

The field is created untrained (timings do not depend on training). Prints figures and writes
benchmarks/results/addon.json.

    .venv/bin/python benchmarks/bench_addon.py [--vertices 100000] [--repeat 3]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import tempfile
import time

_BASE = tempfile.mkdtemp(prefix="neumesh_bench_")
for _v, _s in (("BLENDER_USER_RESOURCES", "user"), ("XDG_CACHE_HOME", "cache"), ("TMPDIR", "tmp")):
    os.makedirs(os.path.join(_BASE, _s), exist_ok=True)
    os.environ[_v] = os.path.join(_BASE, _s)
tempfile.tempdir = os.environ["TMPDIR"]

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "blender_tests"))

import bpy  # noqa: E402
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
    ap.add_argument("--out", default=os.path.join(ROOT, "benchmarks", "results", "addon.json"))
    a = ap.parse_args(argv)
    vw, vh = (int(x) for x in a.viewport.split("x"))

    zip_path = build_addon.build(os.path.join(_BASE, "neumesh.zip"))
    bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    import addon_utils

    addon_utils.enable(MODULE, default_set=True)
    addon = sys.modules[MODULE]
    from helpers import add_armature_bend, add_camera, manual_K_c2w

    nm = addon.core.get()
    import torch

    V, F = sphere_grid(a.vertices)
    t = time.perf_counter()
    field = nm.create_field(nm.Mesh(V, F), nm.FieldConfig())
    t_create = time.perf_counter() - t
    fpath = os.path.join(_BASE, "big.neumesh")
    nm.save_field(field, fpath)
    del field
    t = time.perf_counter()
    obj = addon.sync.new_mesh_object("scaffold", V, F)
    t_mesh = time.perf_counter() - t
    addon.props.set_field_path(obj, fpath)
    bpy.context.view_layer.objects.active = obj
    arm, _root, tip = add_armature_bend(obj, split_x=0.3, angle_deg=0.0)
    cam = add_camera((0.0, -3.6, 0.6), lens=35.0)
    scene = bpy.context.scene
    scene.render.engine = "NEUMESH"

    # warm-up: load + first collect (loads the field into the cache)
    t = time.perf_counter()
    dg = bpy.context.evaluated_depsgraph_get()
    items = addon.render.collect(dg, for_render=False)
    t_load = time.perf_counter() - t

    K, c2w = manual_K_c2w(cam, vw, vh)
    pv = addon.engine.PreviewRenderer(divisors=(8, 4))
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
        items = addon.render.collect(dg, for_render=False)          # sync: evaluated world vertices
        t2 = time.perf_counter()
        sv0 = addon.render.STATS["set_vertices"]
        serial = pv.request(items, K, c2w, vw, vh)                  # view_draw -> preview thread
        ok = pv.wait(serial, divisor=8, timeout=120)
        t3 = time.perf_counter()
        assert ok, pv.error
        assert addon.render.STATS["set_vertices"] == sv0 + 1
        runs.append({"depsgraph_s": t1 - t0, "sync_s": t2 - t1, "preview_1_8_s": t3 - t2, "total_s": t3 - t0})
        pv.wait(serial, divisor=4, timeout=600)
    pv.stop()

    # set_vertices alone (the part of the preview that is not rendering)
    f_cached = addon.render.get_field(obj.name_full, addon.props.field_abspath(obj))
    t = time.perf_counter()
    f_cached.set_vertices(items[0].vertices + 1e-4)
    t_setv = time.perf_counter() - t
    addon.render._CACHE[obj.name_full].last_vertices = None
    low_w, low_h = vw // 8, vh // 8
    lows = []
    for _ in range(3):  # best of 3: the 2-core machine is shared, single timings are noisy
        t = time.perf_counter()
        nm.render_camera(f_cached, addon.render.scale_K(K, vw, vh, low_w, low_h), c2w, low_w, low_h)
        lows.append(time.perf_counter() - t)
    t_low = min(lows)

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
    assert not addon.engine.LAST_ERROR["message"], addon.engine.LAST_ERROR["message"]

    best = min(runs, key=lambda r: r["total_s"])
    res = {
        "machine": {"cpu_count": os.cpu_count(), "loadavg_at_end": list(os.getloadavg()), "torch_threads": torch.get_num_threads(),
                    "platform": platform.platform(), "bpy": bpy.app.version_string, "torch": torch.__version__},
        "scaffold": {"vertices": int(len(V)), "faces": int(len(F)), "create_field_s": t_create,
                     "blender_mesh_foreach_set_s": t_mesh, "first_load_and_sync_s": t_load},
        "preview": {"viewport": [vw, vh], "first_level": [vw // 8, vh // 8], "runs": runs,
                    "median_total_s": float(np.median([r["total_s"] for r in runs])),
                    "best_total_s": best["total_s"], "set_vertices_s": t_setv, "render_1_8_only_s": t_low,
                    "target_s": 1.0, "meets_target": float(np.median([r["total_s"] for r in runs])) <= 1.0},
        "f12_400x400": {"seconds": f12, "median_s": float(np.median(f12))},
    }
    print(f"scaffold: {len(V)} vertices, {len(F)} faces; create_field {t_create:.2f}s, "
          f"mesh via foreach_set {t_mesh:.3f}s, first load+sync {t_load:.2f}s")
    for i, r in enumerate(runs):
        print(f"preview run {i}: depsgraph {r['depsgraph_s']*1e3:.0f} ms, sync {r['sync_s']*1e3:.0f} ms, "
              f"set_vertices+1/8 render {r['preview_1_8_s']*1e3:.0f} ms, total {r['total_s']*1e3:.0f} ms")
    print(f"  set_vertices alone {t_setv*1e3:.0f} ms, 1/8 render ({vw//8}x{vh//8}) alone, best of 3: "
          f"{t_low*1e3:.0f} ms; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"preview refresh median {res['preview']['median_total_s']:.3f}s (target <= 1 s: "
          f"{'met' if res['preview']['meets_target'] else 'NOT met'})")
    print(f"F12 400x400: " + ", ".join(f"{s:.2f}s" for s in f12))
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w") as fh:
        json.dump(res, fh, indent=1)
    print("wrote", a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
