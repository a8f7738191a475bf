"""Worker process of ``bench_addon.py --sections f12`` (F12 beside the core's own render).

Two kinds, driven over stdin/stdout by the benchmark so that their renders can be interleaved
(A B A B ...): whatever load the machine has then hits both alike.

* Blender (the real binary, or Python with the ``bpy`` module)::

      blender -b --factory-startup --python f12_worker.py -- blender ZIP FIELD INPUTS.npz SIZE THREADS
      python f12_worker.py blender ZIP FIELD INPUTS.npz SIZE THREADS

  installs the add-on zip, makes the field's mesh (Load field > New object), a camera, the scene at
  SIZE x SIZE with the engine NEUMESH and its default settings, the add-on preference *CPU threads*
  at THREADS (0: all cores, the default), renders once (warm-up: loads the
  field, poses it), then writes what the core needs to render the same frame to INPUTS.npz: the
  evaluated world-space vertices the engine handed to the field, K, c2w, width, height, the engine's
  anti-aliasing (supersample) and background.
* Core (plain Python, no bpy)::

      python f12_worker.py core FIELD INPUTS.npz THREADS

  loads the field, poses it with those vertices, sets torch's threads to THREADS (0: all cores, what
  the add-on uses by default), renders once (warm-up).

Then each reads commands, one a line: ``f12`` (``bpy.ops.render.render()``, what F12 runs),
``core`` (``nm.render_camera`` with the same inputs, in that process), ``quit``; and answers each with
one line ``NEUMESH_BENCH {json}`` (seconds, and for F12 the engine's own phase timings).
"""
from __future__ import annotations

import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))


def say(**kw):
    print("NEUMESH_BENCH " + json.dumps(kw), flush=True)


def args():
    if "--" in sys.argv:
        return sys.argv[sys.argv.index("--") + 1:]
    return sys.argv[1:]


def commands(handlers):
    for line in sys.stdin:
        cmd = line.strip()
        if not cmd:
            continue
        if cmd == "quit":
            break
        try:
            say(**handlers[cmd]())
        except Exception as exc:  # noqa: BLE001 - the driver stops on it
            import traceback

            traceback.print_exc()
            say(error=f"{type(exc).__name__}: {exc}")
            sys.stdout.flush()


def core_render(nm, field, inp):
    import torch

    t = time.perf_counter()
    out = nm.render_camera(field, inp["K"], inp["c2w"], int(inp["width"]), int(inp["height"]),
                           background=tuple(float(x) for x in inp["background"]),
                           settings=nm.RenderSettings(supersample=int(inp["supersample"])))
    dt = time.perf_counter() - t
    return {"seconds": dt, "threads": torch.get_num_threads(), "mean_rgb": float(out.rgb.mean())}


def all_cores():
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def run_core(field_path, inputs_path, threads):
    sys.path.insert(0, ROOT)
    import numpy as np
    import torch

    import neumesh_core as nm

    torch.set_num_threads(threads or all_cores())   # the add-on's rule for "0: all cores" (its CPU threads)
    inp = dict(np.load(inputs_path))
    field = nm.load_field(field_path)
    field.set_vertices(inp["vertices"])
    core_render(nm, field, inp)   # warm-up
    say(ready=True, threads=torch.get_num_threads(), python=sys.version.split()[0], torch=torch.__version__,
        env={k: os.environ.get(k) for k in ("LD_PRELOAD", "MALLOC_CONF", "OMP_NUM_THREADS")})
    commands({"core": lambda: core_render(nm, field, inp)})


def run_blender(zip_path, field_path, inputs_path, size, threads):
    import bpy

    sys.path.insert(0, os.path.join(ROOT, "blender_tests"))
    from real_blender_common import install_addon

    module = install_addon(zip_path)
    if not bpy.app.background:
        raise SystemExit("run headless")
    import importlib

    import numpy as np   # the binary: found once the add-on has put NEUMESH_PYTHONPATH on sys.path

    addon = importlib.import_module(module)
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob, do_unlink=True)
    res = bpy.ops.neumesh.load_field(filepath=field_path, new_object=True)
    assert res == {"FINISHED"}, res
    from helpers import add_camera

    # NEUMESH_BENCH_LOOK_AWAY=1: the camera looks away from the field (no ray meets it), so that F12's
    # time is the engine's own overhead (sync, colour, hand-off) at this size
    away = os.environ.get("NEUMESH_BENCH_LOOK_AWAY") == "1"
    cam = add_camera((0.0, -3.6, 0.6), look_at=(0.0, -8.0, 0.6) if away else (0.0, 0.0, 0.0), lens=35.0)
    scene = bpy.context.scene
    scene.render.engine = "NEUMESH"
    scene.render.resolution_x = scene.render.resolution_y = int(size)
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    engine = importlib.import_module(module + ".render.engine")
    render = importlib.import_module(module + ".render.field_cache")
    camera = importlib.import_module(module + ".scene.camera")
    nm = addon.runtime.core.get()
    addon.runtime.prefs.get_prefs().torch_threads = int(threads)
    import torch

    def core_in_blender():
        with addon.runtime.core.torch_work():   # as the engine renders: the preference's threads, jemalloc retains
            return core_render(nm, field, inp)

    def f12():
        t = time.perf_counter()
        bpy.ops.render.render()
        dt = time.perf_counter() - t
        if engine.LAST_ERROR["message"]:
            raise RuntimeError(engine.LAST_ERROR["message"])
        return {"seconds": dt, "phases": dict(engine.LAST_RENDER)}

    first = f12()   # warm-up: loads the field, poses it
    dg = bpy.context.evaluated_depsgraph_get()
    items = render.collect(dg, for_render=True)
    assert len(items) == 1, items
    K, c2w, W, H = camera.camera_K_c2w(cam, scene, dg)
    transparent = bool(scene.render.film_transparent)
    inp = {"vertices": items[0].vertices, "K": K, "c2w": c2w, "width": W, "height": H,
           "supersample": int(scene.neumesh.render_samples),
           "background": np.zeros(3) if transparent else np.ones(3)}
    np.savez(inputs_path, **inp)
    field = render.get_field(items[0].key, items[0].path)
    say(ready=True, first_f12=first, blender=bpy.app.version_string, python=sys.version.split()[0],
        torch=torch.__version__, threads_main=torch.get_num_threads(), malloc=addon.runtime.malloc.report(),
        supersample=inp["supersample"], transparent=transparent,
        env={k: os.environ.get(k) for k in ("LD_PRELOAD", "MALLOC_CONF", "OMP_NUM_THREADS")})
    commands({"f12": f12, "core": core_in_blender})


def main():
    a = args()
    if a[0] == "core":
        run_core(a[1], a[2], int(a[3]) if len(a) > 3 else 0)
    elif a[0] == "blender":
        run_blender(a[1], a[2], a[3], int(a[4]), int(a[5]) if len(a) > 5 else 0)
    else:
        raise SystemExit(f"unknown worker kind {a[0]!r}")


main()
