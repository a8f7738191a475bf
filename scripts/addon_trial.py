"""The add-on tried as a new user would, on a real capture, in Debian's Blender in a real window (Xvfb):
the install steps, Import Cameras, Import Mesh, Load Field, F12 with the background on and off, a shell
batch render with the window still open, ARAP (the handle Empty selected, a real G drag, a real Ctrl+Z),
Paint on view + Apply into the Edits folder, a real Texture Paint stroke and F12, then what an artist
does next: the Rendered viewport until its finest pass (Field & Render says which pass it shows), Save
paint (twice) and Close painting, Select by click on a field without semantic codes (a real click; the
error names the panel button that makes them) and a real Ctrl+S (the saved .blend's field paths read
back by a second ``blender -b``). Not a test: it needs a capture and a field trained on it.

    python scripts/addon_trial.py --capture DIR --field F.neumesh --scaffold S.ply --out OUT [--percent 25]

builds the add-on zip (build_addon.py), starts ``blender`` with a new user's empty preferences under
``xvfb-run`` (no event simulation: xdotool's real X input reaches it) with this file as its script, and
prints what each step showed. Inside Blender (``-- window ARGS``) a timer runs the steps; the buttons are
pressed through their operators (in the sidebar's context, the panels each step looks at alone in the
sidebar, open), the keys, the click and the drags are real X input (xdotool). OUT gets
trial.blend, trial_neumesh/ (the Edits folder), the frames, window screenshots (shot_*.png) and
trial.json (every step's time and report). The screenshots show the capture's photos nowhere (camera
background images off); they stay in OUT unless copied by hand.
"""
import argparse
import json
import os
import subprocess
import sys
import time
import traceback

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "blender_tests"))   # real_blender_common: shared with the tests
WINDOW = (1280, 900)


# ------------------------------------------------------------------------------------------ outside
def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--capture", required=True)
    ap.add_argument("--field", required=True)
    ap.add_argument("--scaffold", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--percent", type=int, default=25, help="render resolution percentage")
    ap.add_argument("--torch", default=os.path.join(ROOT, ".blender_torch"),
                    help="the folder set as Existing environment")
    ap.add_argument("--timeout", type=int, default=1800)
    a = ap.parse_args()
    out = os.path.abspath(a.out)
    os.makedirs(out, exist_ok=True)
    zip_path = os.path.join(out, "dist", "neumesh.zip")
    subprocess.run([sys.executable, os.path.join(ROOT, "build_addon.py"), "--out", zip_path], check=True)
    user = os.path.join(out, "user")
    env = {k: v for k, v in os.environ.items() if k not in ("NEUMESH_PYTHONPATH", "BLENDER_USER_RESOURCES")}
    env.update({"BLENDER_USER_CONFIG": os.path.join(user, "config"),
                "BLENDER_USER_SCRIPTS": os.path.join(user, "scripts"),
                "BLENDER_USER_DATAFILES": os.path.join(user, "datafiles"), "HOME": os.path.join(user, "home"),
                "XDG_CACHE_HOME": os.path.join(user, "cache"), "TMPDIR": os.path.join(user, "tmp"),
                "PYTHONNOUSERSITE": "1"})
    for k in ("HOME", "TMPDIR"):
        os.makedirs(env[k], exist_ok=True)
    cmd = ["xvfb-run", "-a", "-s", "-screen 0 %dx%dx24" % WINDOW, "blender", "--python", os.path.abspath(__file__),
           "--", "window", zip_path, os.path.abspath(a.torch), os.path.abspath(a.capture),
           os.path.abspath(a.scaffold), os.path.abspath(a.field), out, str(a.percent)]
    t0 = time.time()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=a.timeout)
    with open(os.path.join(out, "blender.log"), "w") as fh:
        fh.write(r.stdout + r.stderr)
    print(f"blender exited {r.returncode} after {time.time() - t0:.0f} s; log: {out}/blender.log")
    path = os.path.join(out, "trial.json")
    if os.path.exists(path):
        print(json.dumps(json.load(open(path)), indent=1)[:20000])
    return r.returncode


# ------------------------------------------------------------------------------------------ inside Blender
def window_steps(zip_path, torch_dir, capture, scaffold, field, out, percent):
    """A generator: each ``yield`` gives the seconds until the timer calls it again."""
    import addon_utils  # noqa: F401 - Blender's own
    import bpy

    R = TRIAL
    prefs = bpy.context.preferences

    def win():
        return bpy.context.window_manager.windows[0]

    def view3d():
        w = win()
        area = max((a for a in w.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.width * a.height)
        return w, area, {r.type: r for r in area.regions}

    def shot(name):
        w = win()
        area = w.screen.areas[0]
        path = os.path.join(out, name)
        with override(window=w, area=area):
            bpy.ops.screen.screenshot(filepath=path)
        R.setdefault("shots", []).append(name)
        return path

    def reports(since=0):
        """The Info log's lines (what the status bar and the Info editor show), from ``since`` on."""
        w = win()
        area = next(a for a in w.screen.areas if a.type != "VIEW_3D")
        old = area.type
        area.type = "INFO"
        try:
            with override(window=w, area=area, region=area.regions[-1]):
                bpy.ops.info.select_all(action="SELECT")
                bpy.ops.info.report_copy()
        finally:
            area.type = old
        lines = bpy.context.window_manager.clipboard.splitlines()
        return lines[since:], len(lines)

    def step(name, **kw):
        R["steps"].append(dict(step=name, t=round(time.time() - T0, 1), **kw))
        write()
        print("TRIAL", json.dumps(R["steps"][-1], default=str), flush=True)

    def xdo(*args):
        cmd = ["xdotool"] + [str(a) for a in args]
        return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def to_x(w, bx, by):
        return int(round(bx)), int(round(w.height - 1 - by))

    def timed(fn):
        t = time.time()
        res = fn()
        return res, round(time.time() - t, 1)

    n_rep = 0
    p = xdo("mousemove", 640, 880, "sleep", "0.3", "key", "Escape")   # the new user's splash screen goes
    while p.poll() is None:
        yield 0.2
    # 1. Install…, the tick, Existing environment (what the buttons run); saved at once?
    res_i = bpy.ops.preferences.addon_install(filepath=zip_path, overwrite=True)
    res_e = bpy.ops.preferences.addon_enable(module="neumesh")
    yield 2.0
    nm_addon = sys.modules["neumesh"]
    userpref = os.path.join(os.environ["BLENDER_USER_CONFIG"], "userpref.blend")
    step("install", install=sorted(res_i), enable=sorted(res_e), persist=nm_addon.runtime.persist.LAST["result"],
         userpref_written=os.path.exists(userpref), dirty=prefs.is_dirty)
    prefs.addons["neumesh"].preferences.env_path = torch_dir
    yield 2.0
    step("existing environment", persist=nm_addon.runtime.persist.LAST["result"], dirty=prefs.is_dirty,
         note=nm_addon.runtime.persist.unsaved_note())
    res, dt = timed(lambda: bpy.ops.neumesh.check_dependencies())
    w, area, _ = view3d()
    area.type = "PREFERENCES"
    prefs.active_section = "ADDONS"
    bpy.context.window_manager.addon_search = "NeuMesh"
    try:
        import addon_utils as au
        au.modules(refresh=False)
        au.module_bl_info(au.addons_fake_modules["neumesh"])["show_expanded"] = True
    except Exception:  # noqa: BLE001
        R["errors"].append(traceback.format_exc())
    yield 1.5
    shot("shot_prefs.png")
    R["prefs_area"] = [area.x, area.y, area.width, area.height]
    area.type = "VIEW_3D"
    lines, n_rep = reports()
    step("check dependencies", result=sorted(res), seconds=dt, reports=lines,
         numpy_on_path=any(p.startswith(torch_dir) for p in sys.path))
    if torch_dir not in sys.path:
        sys.path.append(torch_dir)
    import numpy as np

    # 2. a new scene saved beside the output; Import Cameras of the capture
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob, do_unlink=True)
    blend = os.path.join(out, "trial.blend")
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    w, area, _ = view3d()
    with override(window=w, area=area):
        res, dt = timed(lambda: bpy.ops.neumesh.import_dataset(directory=capture, background_images=False))
    yield 1.0
    lines, n_rep = reports(n_rep)
    cams = [o for o in bpy.data.objects if o.type == "CAMERA"]
    held = [o.name for o in cams if o.get("neumesh_held_out")]
    step("import cameras", result=sorted(res), seconds=dt, cameras=len(cams), held_out=len(held), reports=lines,
         objects=sorted(o.name for o in bpy.data.objects if o.type != "CAMERA"))
    for c in cams:   # the photos never show in the screenshots
        c.data.show_background_images = False

    # 3. Import Mesh (the scaffold), 4. Load Field on it: as the file browser's button runs them (modal
    # jobs, their reports in the status bar and the Info log)
    jobs = nm_addon.runtime.jobs

    def run_job(op, **props):
        w_, area_, regs_ = view3d()
        label = getattr(bpy.types, op.idname()).bl_label
        t = time.time()
        with override(window=w_, area=area_, region=regs_["WINDOW"]):
            res = op("INVOKE_DEFAULT", run=True, **props)
        seen = []
        while True:
            yield 0.25
            job = jobs.active(label)
            if job is not None:
                seen.append(f"{100 * job.fraction:.0f}% {job.message}")
            elif time.time() - t > 1.0:
                break
        R["last_job"] = dict(result=sorted(res), seconds=round(time.time() - t, 1), progress=seen[::4][-8:])

    yield from run_job(bpy.ops.neumesh.import_mesh, filepath=scaffold)
    obj = bpy.context.view_layer.objects.active
    step("import mesh", object=obj.name, vertices=len(obj.data.vertices), **R["last_job"])
    yield from run_job(bpy.ops.neumesh.load_field, filepath=field)
    step("load field", field_path=obj.neumesh.field_path, **R["last_job"])
    w, area, _ = view3d()
    area.type = "INFO"
    yield 1.5
    shot("shot_reports.png")
    R["info_area"] = [area.x, area.y, area.width, area.height]
    area.type = "VIEW_3D"
    yield 0.5

    # 5. F12, background on and off, at a low resolution percentage through a held-out camera
    scene = bpy.context.scene
    scene.render.engine = "NEUMESH"
    scene.camera = next((c for c in cams if c.get("neumesh_held_out")), cams[0])
    scene.render.resolution_percentage = percent
    frames = {}
    for bg in (True, False):
        scene.neumesh.render_background = bg
        res, dt = timed(lambda: bpy.ops.render.render())
        img = bpy.data.images["Render Result"]
        path = os.path.join(out, "f12_%s.png" % ("bg" if bg else "nobg"))
        img.save_render(path)
        frames[bg] = path
        yield 0.5
        lines, n_rep = reports(n_rep)
        step("F12", background=bg, result=sorted(res), seconds=dt, file=os.path.basename(path), reports=lines,
             size=[scene.render.resolution_x * percent // 100, scene.render.resolution_y * percent // 100])
    scene.neumesh.render_background = True
    bpy.ops.wm.save_mainfile()

    # 6. a shell batch render, this window still open (torch from the saved Existing environment)
    env = {k: v for k, v in os.environ.items() if k != "NEUMESH_PYTHONPATH"}
    cmd = [bpy.app.binary_path, "-b", blend, "-E", "NEUMESH", "-o", os.path.join(out, "batch_####"), "-f", "1"]
    t = time.time()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
    batch = os.path.join(out, "batch_0001.png")
    diff = None
    if os.path.exists(batch):
        a_ = np.asarray(bpy.data.images.load(batch).pixels[:], np.float32)
        b_ = np.asarray(bpy.data.images.load(frames[True]).pixels[:], np.float32)
        diff = float(np.abs(a_ - b_).max()) * 255 if a_.shape == b_.shape else f"shapes {a_.shape} {b_.shape}"
    step("batch render", rc=r.returncode, seconds=round(time.time() - t, 1), frame=os.path.exists(batch),
         max_diff_to_f12_in_255=diff, log_tail=(r.stdout + r.stderr)[-600:])
    yield 0.5

    # 7. ARAP: Anchor (lowest fifth of the mesh along the camera's up) and Handle (highest tenth)
    V = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.vertices.foreach_get("co", V)
    V = V.reshape(-1, 3)
    up = np.asarray(scene.camera.matrix_world.to_3x3().col[1], np.float32)
    h = V @ up
    lo, hi = np.quantile(h, [0.2, 0.9])
    for name, idx in (("Anchor", np.nonzero(h < lo)[0]), ("Handle", np.nonzero(h > hi)[0])):
        obj.vertex_groups.new(name=name).add([int(i) for i in idx], 1.0, "REPLACE")
    bpy.context.view_layer.objects.active = obj
    with override(window=w, area=area, active_object=obj, object=obj):
        res, dt = timed(lambda: bpy.ops.neumesh.arap_add())
    yield 1.0
    lines, n_rep = reports(n_rep)
    empty = next(o for o in bpy.data.objects if o.type == "EMPTY" and o.parent == obj)
    for o in bpy.context.selected_objects:
        o.select_set(False)
    empty.select_set(True)
    bpy.context.view_layer.objects.active = empty
    with override(window=w, area=area):
        # the undo step a click on the button pushes (operators called from Python push none)
        bpy.ops.ed.undo_push(message="Add ARAP deform")
    step("ARAP add", result=sorted(res), seconds=dt, empty=empty.name, reports=lines)
    open_edit_panels(bpy)
    # the sidebar's NeuMesh tab: real Ctrl+Wheel over the tab strip until the Edit field panel draws
    w, area, regs = view3d()
    area.spaces.active.show_region_ui = True
    space = area.spaces.active
    space.region_3d.view_perspective = "CAMERA"
    space.shading.type = "SOLID"
    yield 1.0
    w, area, regs = view3d()
    side = regs["UI"]
    for _ in range(12):
        if DRAWN.get("NEUMESH_PT_edit"):
            break
        x, y = to_x(w, side.x + side.width - 8, side.y + 20)
        p = xdo("mousemove", x, y, "keydown", "ctrl", "click", "5", "keyup", "ctrl")
        while p.poll() is None:
            yield 0.2
        yield 1.0
    yield 1.0
    shot("shot_arap_panel.png")
    R["sidebar"] = [side.x, side.y, side.width, side.height, w.height]
    step("ARAP panel with the Empty selected", edit_panel_drawn=DRAWN.get("NEUMESH_PT_edit", 0),
         arap_panel_drawn=DRAWN.get("NEUMESH_PT_arap", 0), drawn=dict(DRAWN))

    key = obj.data.shape_keys.key_blocks.get("NeuMesh ARAP")

    obj_name, empty_name = obj.name, empty.name

    def key_co():   # by name: an undo step makes new Python objects
        k = bpy.data.objects[obj_name].data.shape_keys.key_blocks.get("NeuMesh ARAP")
        a_ = np.empty(len(k.data) * 3, np.float32)
        k.data.foreach_get("co", a_)
        return a_.reshape(-1, 3)

    before = key_co() if key is not None else None
    e_before = tuple(empty.matrix_world.translation)
    main_r = regs["WINDOW"]
    cx, cy = to_x(w, main_r.x + main_r.width // 2, main_r.y + main_r.height // 2)
    t = time.time()
    p = xdo("mousemove", cx, cy, "sleep", "0.3", "key", "g", "sleep", "0.3", "mousemove", cx + 20, cy - 20,
            "sleep", "0.3", "mousemove", cx + 60, cy - 60, "sleep", "1.0", "click", "1")
    while p.poll() is None:
        yield 0.2
    yield 8.0
    moved = key_co()
    step("ARAP G drag", seconds=round(time.time() - t, 1), empty_moved=float(np.linalg.norm(
        np.subtract(empty.matrix_world.translation, e_before))),
         key_moved_max=float(np.abs(moved - before).max()) if before is not None else None,
         vertices_moved=int((np.abs(moved - before).max(1) > 1e-6).sum()) if before is not None else None)
    shot("shot_arap_moved.png")
    p = xdo("mousemove", cx, cy, "sleep", "0.3", "key", "ctrl+z")
    while p.poll() is None:
        yield 0.2
    yield 5.0
    after = key_co()
    obj = bpy.data.objects[obj_name]
    empty = bpy.data.objects[empty_name]
    step("ARAP Ctrl+Z", empty_back=float(np.linalg.norm(np.subtract(empty.matrix_world.translation, e_before))),
         key_residue_max=float(np.abs(after - before).max()) if before is not None else None,
         vertices_not_back=int((np.abs(after - before).max(1) > 1e-6).sum()) if before is not None else None)

    # 8. Paint on view + Apply: the edit goes to the Edits folder beside trial.blend
    for o in bpy.context.selected_objects:
        o.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    with override(window=w, area=area, active_object=obj, object=obj):
        res, dt = timed(lambda: bpy.ops.neumesh.paint_view())
    yield 1.0
    lines, n_rep = reports(n_rep)
    step("paint on view", result=sorted(res), seconds=dt, reports=lines)
    img = bpy.data.images.get("NeuMesh Paint")
    if img is not None:
        px = np.asarray(img.pixels[:], np.float32).reshape(img.size[1], img.size[0], 4)
        hh, ww = px.shape[:2]
        px[hh * 2 // 5:hh * 3 // 5, ww * 2 // 5:ww * 3 // 5, :3] = (1.0, 0.0, 1.0)   # a magenta square mid-frame
        img.pixels.foreach_set(px.ravel())
        img.update()
        w, area, _ = view3d()
        with override(window=w, area=area, active_object=obj, object=obj):
            res, dt = timed(lambda: bpy.ops.neumesh.apply_paint())
        yield 1.0
        lines, n_rep = reports(n_rep)
        edits = os.path.join(out, "trial_neumesh")
        files = sorted(os.listdir(edits)) if os.path.isdir(edits) else []
        step("apply painting", result=sorted(res), seconds=dt, reports=lines, edits_folder=files,
             field_path=obj.neumesh.field_path,
             field_folder_untouched=sorted(os.listdir(os.path.dirname(field))))
        yield 2.0
        shot("shot_edits.png")

    # 9. Texture Paint: a real stroke (xdotool drag) with a cyan brush across the middle of the view, then F12
    from real_blender_common import paint_brush

    tp = nm_addon.edit.texture_paint
    scene = bpy.context.scene   # an undo step makes new Python objects
    w, area, regs = view3d()
    obj = bpy.data.objects[obj_name]
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    with override(window=w, area=area, region=regs["WINDOW"], active_object=obj, object=obj):
        res, dt = timed(lambda: bpy.ops.neumesh.texture_paint())
        bpy.ops.ed.undo_push(message="Texture Paint")
    ip = scene.tool_settings.image_paint
    paint_brush(scene)
    step("texture paint", result=sorted(res), seconds=dt, mode=obj.mode, canvas=getattr(ip.canvas, "name", None))
    yield 2.0
    pushes0 = tp.STATS["pushes"]
    main_r = regs["WINDOW"]
    cx, cy = to_x(w, main_r.x + main_r.width // 2, main_r.y + main_r.height // 2)
    moves = []
    for i in range(13):
        moves += ["mousemove", cx - 60 + 10 * i, cy + (i % 2) * 4, "sleep", "0.05"]
    t = time.time()
    p = xdo("mousemove", cx - 60, cy, "sleep", "0.3", "mousedown", "1", *moves, "mouseup", "1", "sleep", "0.3",
            "mousemove", cx + 80, cy + 60)   # the pointer moves on after the stroke, as a hand does
    while p.poll() is None:
        yield 0.2
    while tp.STATS["pushes"] == pushes0 and time.time() - t < 60:
        yield 0.25
    pushed = round(time.time() - t, 1)
    # F12 as an artist presses it: once the stroke has ended (the watcher saw an event after it; on a
    # big scaffold Blender handles the stroke's events well after xdotool sent them) and the image settled
    ps = nm_addon.edit.paint_sync
    while (ps.stroke_running() or ps.WATCH["pending"]) and time.time() - t < 60:
        yield 0.25
    step("texture paint stroke", seconds_to_push=pushed, seconds_to_end=round(time.time() - t, 1),
         pushes=tp.STATS["pushes"] - pushes0, texels=tp.STATS.get("texels"), stroke_running=ps.stroke_running())
    shot("shot_texture_paint.png")
    res, dt = timed(lambda: bpy.ops.render.render())
    path = os.path.join(out, "f12_texture_paint.png")
    bpy.data.images["Render Result"].save_render(path)
    f12 = np.asarray(bpy.data.images.load(path).pixels[:], np.float32).reshape(-1, 4)
    base = np.asarray(bpy.data.images.load(frames[True]).pixels[:], np.float32).reshape(-1, 4)
    cyan = (f12[:, 0] < 0.35) & (f12[:, 1] > 0.55) & (f12[:, 2] > 0.55)
    step("F12 after the stroke", seconds=dt, cyan_pixels=int(cyan.sum()),
         cyan_pixels_before=int(((base[:, 0] < 0.35) & (base[:, 1] > 0.55) & (base[:, 2] > 0.55)).sum()),
         black_pixels=int((f12[:, :3].max(1) < 0.03).sum()), black_before=int((base[:, :3].max(1) < 0.03).sum()))
    yield 0.5
    step("before saving in Texture Paint mode")
    bpy.ops.wm.save_mainfile()
    step("saved in Texture Paint mode", blend=os.path.exists(blend))
    yield 2.0
    w, area, regs = view3d()
    with override(window=w, area=area, region=regs["WINDOW"]):
        bpy.ops.object.mode_set(mode="OBJECT")
    step("Object Mode")
    yield 2.0
    bpy.ops.wm.save_mainfile()
    step("saved", blend=os.path.exists(blend))
    yield from after_painting(bpy, nm_addon, R, out, blend, obj_name, view3d, win, shot, reports, step, xdo, to_x)


def after_painting(bpy, nm_addon, R, out, blend, obj_name, view3d, win, shot, reports, step, xdo, to_x):
    """Steps 10-13 (a generator, as :func:`window_steps`): the Rendered viewport, Save paint and Close
    painting, Select by click on a field without semantic codes, a real Ctrl+S.  From the Rendered
    viewport on, the preview thread runs Python: operators under a context override go through
    ``overridden`` (the add-on's workers held, as the add-on's own overridden calls do)."""
    from real_blender_common import overridden, preview_done

    eng = nm_addon.render.engine
    panels = nm_addon.ui.panels
    _, n_rep = reports()

    def level_text():
        return panels.viewport_level_text(eng.viewport_progress())

    def until_drawn(name, seconds=6.0):
        """Wait until panel ``name`` (the add-on's class name) is drawn again."""
        n0, t_ = DRAWN.get(name, 0), time.time()
        while DRAWN.get(name, 0) == n0 and time.time() - t_ < seconds:
            for r in view3d()[1].regions:
                if r.type == "UI":
                    r.tag_redraw()
            yield 0.25
        yield 0.5

    # 10. the Rendered viewport: its progressive passes until the finest is drawn (or 90 s); Field &
    # Render says which pass it shows
    w, area, regs = view3d()
    show_panels(bpy, ["NEUMESH_PT_field"], "_s10")
    area.spaces.active.shading.type = "RENDERED"
    t = time.time()
    labels = []
    while time.time() - t < 90 and not preview_done():
        text_ = level_text()
        if text_ and (not labels or labels[-1][1] != text_):
            labels.append((round(time.time() - t, 1), text_))
        yield 0.5
    done = preview_done()
    yield from until_drawn("NEUMESH_PT_field")
    shot("shot_viewport_level.png")
    w, area, regs = view3d()
    pv = next((getattr(e, "_preview", None) for e in eng._PollRedraw._engines), None)
    R["viewport"] = [regs["WINDOW"].width, regs["WINDOW"].height]
    R["sidebar_s10"] = [regs["UI"].x, regs["UI"].y, regs["UI"].width, regs["UI"].height, w.height]
    step("Rendered viewport", seconds=round(time.time() - t, 1), finest_drawn=done, label=level_text(),
         labels=labels, field_panel_drawn=DRAWN.get("NEUMESH_PT_field", 0),
         levels=None if pv is None else [[d, round(s, 1)] for d, s in pv.timings],
         divisors=None if pv is None else list(pv.divisors), error=None if pv is None else pv.error,
         viewport=R["viewport"])

    # 11. Save paint (Texture Paint panel), pressed again, then Close painting (Paint texture panel)
    tp, pe = nm_addon.edit.texture_paint, nm_addon.edit.paint

    def paint_states():
        """What the two panels draw (their own predicates): enabled buttons, texts, labels."""
        o = bpy.data.objects[obj_name]
        img = bpy.data.images.get(pe.PAINT_IMAGE)
        has_tp = tp.paint_image(o) is not None
        pending = pe.paint_pending(img)
        return dict(save_paint_enabled=has_tp, unsaved_texels=tp.unsaved_texels(o) if has_tp else 0,
                    apply_painting_enabled=pending, close_enabled=pe.is_paint_image(img),
                    close_text=pe.cancel_text(img), applied_label=pe.applied(img) and not pending,
                    image_editors=sum(a.type == "IMAGE_EDITOR" for a in win().screen.areas),
                    field_path=o.neumesh.field_path)

    def edits():
        folder = os.path.join(out, "trial_neumesh")
        return sorted(os.listdir(folder)) if os.path.isdir(folder) else []

    def press(op, message, **props):
        """A sidebar button: the operator in the sidebar's context, then the undo step a click pushes.
        Returns (result, seconds, its reports): an operator called from Python reports to stdout, not
        to the status bar and the Info log as a click's would; the reports are taken from there."""
        import contextlib
        import io

        w_, area_, regs_ = view3d()
        o = bpy.data.objects[obj_name]
        t_ = time.time()
        buf = io.StringIO()
        with overridden(window=w_, area=area_, region=regs_["UI"], active_object=o, object=o):
            with contextlib.redirect_stdout(buf):
                res_ = op(**props)
            if "FINISHED" in res_ and message:
                bpy.ops.ed.undo_push(message=message)
        sys.stdout.write(buf.getvalue())
        said = [x for x in buf.getvalue().splitlines() if x.split(":", 1)[0] in ("Info", "Warning", "Error")]
        return sorted(res_), round(time.time() - t_, 1), said

    show_panels(bpy, ["NEUMESH_PT_edit", "NEUMESH_PT_texture_paint", "NEUMESH_PT_paint"], "_s11")
    yield from until_drawn("NEUMESH_PT_texture_paint")
    shot("shot_paint_before_save.png")
    step("paint panels", states=paint_states(), drawn={k: DRAWN.get(k, 0) for k in (
        "NEUMESH_PT_edit", "NEUMESH_PT_texture_paint", "NEUMESH_PT_paint")})
    res, dt, said = press(bpy.ops.neumesh.save_paint, "Save paint")
    yield 1.0
    lines, n_rep = reports(n_rep)
    step("save paint", result=res, seconds=dt, said=said, reports=lines, states=paint_states(), edits_folder=edits())
    res, dt, said = press(bpy.ops.neumesh.save_paint, "Save paint")
    yield 1.0
    lines, n_rep = reports(n_rep)
    step("save paint again", result=res, seconds=dt, said=said, reports=lines, edits_folder=edits())
    res, dt, said = press(bpy.ops.neumesh.cancel_paint, "")
    yield 1.0
    lines, n_rep = reports(n_rep)
    step("close painting", result=res, seconds=dt, said=said, reports=lines, states=paint_states(),
         areas=[a.type for a in win().screen.areas])
    yield from until_drawn("NEUMESH_PT_paint")
    shot("shot_paint_closed.png")
    w, area, regs = view3d()
    R["sidebar_s11"] = [regs["UI"].x, regs["UI"].y, regs["UI"].width, regs["UI"].height, w.height]
    yield from info_shot("shot_paint_reports.png", "info_s11")

    # 12. Select by click (Semantics panel) on a field without semantic codes: a real click in the view
    show_panels(bpy, ["NEUMESH_PT_edit", "NEUMESH_PT_semantics"], "_s12")
    yield from until_drawn("NEUMESH_PT_semantics")
    w, area, regs = view3d()
    obj = bpy.data.objects[obj_name]
    with overridden(window=w, area=area, region=regs["UI"], active_object=obj, object=obj):
        res = bpy.ops.neumesh.select_by_click("INVOKE_DEFAULT", group_name="NeuMesh selection")
    yield 0.5
    main_r = regs["WINDOW"]
    cx, cy = to_x(w, main_r.x + main_r.width // 2, main_r.y + main_r.height // 2)
    t = time.time()
    p = xdo("mousemove", cx, cy, "sleep", "0.3", "click", "1")
    while p.poll() is None:
        yield 0.2
    yield 2.0
    lines, n_rep = reports(n_rep)
    errors = [x for x in lines if x.startswith("NeuMesh")]
    yield from until_drawn("NEUMESH_PT_semantics")
    shot("shot_select_by_click.png")
    w, area, regs = view3d()
    R["sidebar_s12"] = [regs["UI"].x, regs["UI"].y, regs["UI"].width, regs["UI"].height, w.height]
    msg = errors[-1] if errors else ""
    modal = [op.bl_idname for op in getattr(win(), "modal_operators", ())]   # Blender 4.2+
    step("select by click", invoke=sorted(res), seconds=round(time.time() - t, 1), reports=lines, modal=modal,
         message=msg, names_button="Distill semantics" in msg,
         names_command="neumesh semantics" in msg or "--field" in msg,
         group=[g.name for g in bpy.data.objects[obj_name].vertex_groups if g.name == "NeuMesh selection"])
    yield from info_shot("shot_select_reports.png", "info_s12")

    # 13. File > Save with a real Ctrl+S over the 3D View; where the saved .blend's field paths lead
    show_panels(bpy, ["NEUMESH_PT_edit"], "_s13")
    yield from until_drawn("NEUMESH_PT_edit")
    mtime = os.path.getmtime(blend)
    w, area, regs = view3d()
    main_r = regs["WINDOW"]
    cx, cy = to_x(w, main_r.x + main_r.width // 2, main_r.y + main_r.height // 3)
    t = time.time()
    p = xdo("mousemove", cx, cy, "sleep", "0.3", "key", "ctrl+s")
    while p.poll() is None:
        yield 0.2
    while os.path.getmtime(blend) == mtime and time.time() - t < 60:
        yield 0.25
    yield 1.0
    lines, n_rep = reports(n_rep)
    shot("shot_saved.png")
    R["sidebar_s13"] = [regs["UI"].x, regs["UI"].y, regs["UI"].width, regs["UI"].height, w.height]
    o = bpy.data.objects[obj_name]
    expr = ("import bpy, json; print('NEUMESH_SAVED ' + json.dumps({o.name: dict(o['neumesh']) for o in "
            "bpy.data.objects if o.get('neumesh', {}).get('field_path')}, default=str))")
    r = subprocess.run([bpy.app.binary_path, "-b", "--factory-startup", blend, "--python-expr", expr],
                       capture_output=True, text=True, timeout=120)
    saved = next((json.loads(x.split(" ", 1)[1]) for x in r.stdout.splitlines() if x.startswith("NEUMESH_SAVED ")),
                 None)
    step("Ctrl+S", seconds=round(time.time() - t, 1), written=os.path.getmtime(blend) != mtime, reports=lines,
         dirty=bpy.data.is_dirty, field_path=o.neumesh.field_path, edits_folder=edits(),
         blend_folder=sorted(os.listdir(out)), saved_file=saved,
         saved_path_resolves=None if not saved else {
             k: os.path.isfile(bpy.path.abspath(v.get("field_path", ""), start=out)) for k, v in saved.items()})


def info_shot(name, key):
    """The Info editor in the largest 3D View's place for a moment (the reports in full), screenshot."""
    import bpy

    w = bpy.context.window_manager.windows[0]
    area = max((a for a in w.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.width * a.height)
    area.type = "INFO"
    yield 1.5
    path = os.path.join(TRIAL["out"], name)
    from real_blender_common import overridden

    with overridden(window=w, area=w.screen.areas[0]):
        bpy.ops.screen.screenshot(filepath=path)
    TRIAL.setdefault("shots", []).append(name)
    TRIAL[key] = [area.x, area.y, area.width, area.height]
    area.type = "VIEW_3D"
    yield 1.0


TRIAL = {"steps": [], "errors": []}
DRAWN: dict = {}
T0 = time.time()


def write():
    out = TRIAL.get("out")
    if out:
        with open(os.path.join(out, "trial.json"), "w") as fh:
            json.dump(TRIAL, fh, indent=1, default=str)


def override(**kw):
    """``bpy.context.temp_override(**kw)`` with the add-on's threads held (``real_blender_common.overridden``):
    Blender 3.4 corrupts Python's heap when an operator runs under an override beside a running Python
    thread (the Rendered viewport's preview, a job)."""
    from real_blender_common import overridden

    return overridden(**kw)


ORIGINALS: dict = {}   # panel name -> the add-on's sidebar panel class, unregistered (copies are shown)
SHOWN: list = []       # the names of the copies registered now, parents first


def open_edit_panels(bpy):
    """The Edit field panels open and at the top of the sidebar (they are closed by default, below the
    workflow panels): the workflow panels go, the Edit field panel and its children are registered again
    under new names (<name>_open), Edit field, ARAP and painting open."""
    for name in ("NEUMESH_PT_data", "NEUMESH_PT_scaffold", "NEUMESH_PT_train", "NEUMESH_PT_field"):
        ORIGINALS[name] = getattr(bpy.types, name)
        bpy.utils.unregister_class(ORIGINALS[name])

    def parent(cls):
        return next((c.__dict__["bl_parent_id"] for c in cls.__mro__ if "bl_parent_id" in c.__dict__), "")

    classes = [getattr(bpy.types, "NEUMESH_PT_edit")]
    for n in sorted(dir(bpy.types)):
        if n.startswith("NEUMESH_PT") and parent(getattr(bpy.types, n)) == "NEUMESH_PT_edit":
            classes.append(getattr(bpy.types, n))
    for cls in reversed(classes):
        ORIGINALS[cls.__name__] = cls
        bpy.utils.unregister_class(cls)
    opened = {"NEUMESH_PT_edit", "NEUMESH_PT_arap", "NEUMESH_PT_paint"}
    show_panels(bpy, [c.__name__ for c in classes], "_open", opened)


def show_panels(bpy, names, suffix, opened=None):
    """Only the panels ``names`` (the add-on's class names, parents first, in the sidebar's order) in the
    sidebar, as copies named <name><suffix>: a new suffix gives panels Blender has not drawn yet, so
    ``opened`` (default: all of them) are open whatever was folded before."""
    from real_blender_common import register_open_copy

    for name in reversed(SHOWN):
        bpy.utils.unregister_class(getattr(bpy.types, name))
    SHOWN.clear()
    for name in names:
        register_open_copy(ORIGINALS[name], suffix, opened=opened is None or name in opened)
        SHOWN.append(name + suffix)


def _wrap_panels(bpy):
    def wrapper(name, original):
        def draw(panel, context):
            original(panel, context)
            DRAWN[name] = DRAWN.get(name, 0) + 1

        return draw

    for name in [n for n in dir(bpy.types) if n.startswith("NEUMESH_PT")]:
        cls = getattr(bpy.types, name)
        cls.draw = wrapper(name, cls.draw)


def in_blender(args):
    import bpy

    zip_path, torch_dir, capture, scaffold, field, out, percent = args
    TRIAL["out"] = out
    gen = window_steps(zip_path, torch_dir, capture, scaffold, field, out, int(percent))
    state = {"wrapped": False}

    def tick():
        try:
            if not state["wrapped"] and "neumesh" in sys.modules:
                _wrap_panels(bpy)
                state["wrapped"] = True
            return next(gen)
        except StopIteration:
            pass
        except Exception:  # noqa: BLE001 - recorded; the trial stops there
            TRIAL["errors"].append(traceback.format_exc())
            print(traceback.format_exc(), flush=True)
        write()
        bpy.context.preferences.view.use_save_prompt = False
        bpy.ops.wm.quit_blender()
        return None

    bpy.app.timers.register(tick, first_interval=2.0)


if "--" in sys.argv and sys.argv[sys.argv.index("--") + 1:][:1] == ["window"]:
    in_blender(sys.argv[sys.argv.index("--") + 2:])
elif __name__ == "__main__":
    sys.exit(main())
