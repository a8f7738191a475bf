"""A render in Texture Paint mode around a real brush stroke, in a real `blender` window, driven by
test_real_blender_redo.py after real_blender_ui.py's setup step made OUT_DIR/ui.blend:

    blender OUT_DIR/ui.blend --python real_blender_tpaint_render.py -- tpf12 OUT_DIR HOW ENGINE [arap]

(no --enable-event-simulate: xdotool's real X input has to reach Blender).  From a timer: ENGINE
(NEUMESH, BLENDER_WORKBENCH or BLENDER_EEVEE) through the scene camera, Solid shading; with ``arap``
first ARAP deform on the field object and its handle Empty moved (the live key then holds a drag's
solve, so the next frame change, a render's included, solves again from rest and writes the key);
*Texture Paint* on the object; a real stroke (xdotool) with a cyan brush across the object; a render:
HOW ``midstroke`` calls ``bpy.ops.render.render()`` from the timer while the button is still down
(the stroke goes on after the render and ends a few seconds later), ``timer`` calls it after the
stroke, ``key`` presses a real F12 over the 3D view after the stroke (the render job).  The window
then runs on for a few seconds of redraws and events (a crash shows there), the Render Result is read
and the facts printed (NEUMESH_FACTS): the render's result and frame changes, whether a stroke ran at
the render, what ARAP wrote afterwards, cyan pixels in the render.

Blender's projection paint reads the painted object's evaluated mesh through pointers it took when the
stroke began; a shape key written during the stroke frees that mesh under it (a segfault at the next
dab once the freed memory is reused).  The test runs Blender with jemalloc filling freed memory
(``MALLOC_CONF=junk:true``), so a read of freed memory crashes at once instead of now and then.
"""
import os
import subprocess
import sys
import time
import traceback

import bpy
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from real_blender_common import addon_module, facts, overridden, paint_brush, script_args  # noqa: E402

ARGS = script_args()
RUN: dict = {"facts": {"errors": []}}


def stroke_moves(x0, y0, dx, n=13):
    out = []
    for i in range(n):
        out += ["mousemove", x0 + dx * i, y0 + (i % 2) * 4, "sleep", "0.05"]
    return out


def add_arap(obj, win, area, f):
    """ARAP deform on ``obj`` (Anchor: its lowest fifth, Handle: its highest tenth), the handle Empty
    then moved up; yields until the drag's solve is written."""
    arap = addon_module().deform.arap
    V = np.array([v.co[:] for v in obj.data.vertices])
    lo, hi = np.quantile(V[:, 2], [0.2, 0.9])
    for name, idx in (("Anchor", np.nonzero(V[:, 2] < lo)[0]), ("Handle", np.nonzero(V[:, 2] > hi)[0])):
        obj.vertex_groups.new(name=name).add([int(i) for i in idx], 1.0, "REPLACE")
    with overridden(window=win, area=area, active_object=obj, object=obj):
        f["arap_add"] = sorted(bpy.ops.neumesh.arap_add())
    yield 1.0
    empty = next(o for o in bpy.data.objects if o.type == "EMPTY" and o.parent == obj)
    empty.location.z += 0.15
    bpy.context.view_layer.update()
    t = time.time()
    while time.time() - t < 1.0 or (bpy.app.timers.is_registered(arap._apply_drags) and time.time() - t < 30):
        yield 0.2
    f["arap_before"] = arap.TIMINGS.get(obj.name_full, {}).get("mode")


def steps(out_dir, how, engine_name, with_arap):
    f = RUN["facts"]
    f.update(how=how, engine=engine_name, arap=with_arap)
    tp, ps = addon_module().edit.texture_paint, addon_module().edit.paint_sync
    arap = addon_module().deform.arap
    scene = bpy.context.scene

    def view3d():
        win = bpy.context.window_manager.windows[0]
        area = max((a for a in win.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.width * a.height)
        return win, area, {r.type: r for r in area.regions}

    def xdo(*args):
        p = subprocess.Popen(["xdotool"] + [str(a) for a in args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
        while p.poll() is None:
            yield 0.1
        if p.returncode:
            f["errors"].append("xdotool: " + p.stderr.read())

    win, area, regs = view3d()
    scene.render.engine = engine_name
    scene.render.resolution_percentage = 50
    space = area.spaces.active
    space.region_3d.view_perspective = "CAMERA"
    space.shading.type = "SOLID"
    obj = bpy.data.objects["blob"]
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    if with_arap:
        yield from add_arap(obj, win, area, f)
        bpy.context.view_layer.objects.active = obj
        obj.select_set(True)
    with overridden(window=win, area=area, region=regs["WINDOW"], active_object=obj, object=obj):
        f["texture_paint"] = sorted(bpy.ops.neumesh.texture_paint(resolution=1024))
        bpy.ops.ed.undo_push(message="Texture Paint")
    paint_brush(scene)
    f["mode"] = obj.mode
    yield 2.0
    pushes0 = tp.STATS["pushes"]
    main = regs["WINDOW"]
    cx, cy = int(main.x + main.width // 2), int(win.height - 1 - (main.y + main.height // 2))
    press = ["mousemove", cx - 60, cy, "sleep", "0.3", "mousedown", "1"] + stroke_moves(cx - 60, cy, 10)
    t = time.time()
    stroke = None
    if how == "midstroke":   # the button stays down through the render; the stroke goes on after it
        stroke = subprocess.Popen(["xdotool"] + [str(a) for a in press + ["sleep", "4"]
                                                 + stroke_moves(cx + 60, cy + 20, -10) + ["mouseup", "1"]])
    else:
        yield from xdo(*press, "mouseup", "1")
    while tp.STATS["pushes"] == pushes0 and time.time() - t < 60:
        yield 0.05
    f["pushes"] = tp.STATS["pushes"] - pushes0
    if how != "midstroke":
        yield 1.0
    f["stroke_at_render"] = bool(ps.WATCH["running"] and ps.WATCH.get("stroke"))   # the watcher's view
    solves0 = dict(arap.TIMINGS.get(obj.name_full, {}))
    frames = []

    def on_frame(scene, depsgraph=None):
        frames.append(scene.frame_current)

    bpy.app.handlers.frame_change_post.append(on_frame)
    print("NEUMESH_STATE render", flush=True)
    t = time.time()
    if how in ("timer", "midstroke"):
        f["render"] = sorted(bpy.ops.render.render())
    else:
        yield from xdo("mousemove", cx, cy, "sleep", "0.3", "key", "F12")
    f["render_call_s"] = round(time.time() - t, 2)
    print("NEUMESH_STATE rendered", flush=True)
    while time.time() - t < 120 and getattr(bpy.app, "is_job_running", lambda _kind: False)("RENDER"):
        yield 0.25
    f["frame_changes_in_render"] = len(frames)
    if stroke is not None:   # the stroke ends; the pointer moves on, as a hand does
        while stroke.poll() is None and time.time() - t < 60:
            yield 0.1
        yield from xdo("mousemove", cx + 80, cy + 60)
    end = time.time() + 6.0
    while time.time() < end:
        yield 0.25
    now = arap.TIMINGS.get(obj.name_full, {})
    f["arap_after"] = now.get("mode") if now != solves0 else None
    f["stroke_after"] = bool(ps.WATCH["running"] and ps.WATCH.get("stroke"))
    img = bpy.data.images.get("Render Result")
    if img is not None:
        path = os.path.join(out_dir, "tpf12.png")
        img.save_render(path)
        px = np.asarray(bpy.data.images.load(path).pixels[:], np.float32).reshape(-1, 4)
        f["cyan_pixels"] = int(((px[:, 0] < 0.35) & (px[:, 1] > 0.55) & (px[:, 2] > 0.55)).sum())
    f["mode_after"] = obj.mode


def start(out_dir, how, engine_name, with_arap):
    gen = steps(out_dir, how, engine_name, with_arap)

    def tick():
        try:
            return next(gen)
        except StopIteration:
            pass
        except Exception:  # noqa: BLE001 - recorded
            RUN["facts"]["errors"].append(traceback.format_exc())
        facts(version=list(bpy.app.version), **RUN["facts"])
        bpy.context.preferences.view.use_save_prompt = False
        bpy.ops.wm.quit_blender()
        return None

    bpy.app.timers.register(tick, first_interval=1.0)


if ARGS and ARGS[0] == "tpf12":
    start(ARGS[1], ARGS[2], ARGS[3], "arap" in ARGS[4:])
