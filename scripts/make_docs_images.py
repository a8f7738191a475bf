"""The README's and docs' pictures, re-runnable: renders of the built-in scene and screenshots of the
add-on's real panels.  Every picture shows our own built-in scene (the procedural "bumpy blob" of
``nm.default_scene_dir()``: 128 px, 60 training views, its 10,242-vertex true mesh as scaffold).

    .venv/bin/python scripts/make_docs_images.py                  # everything (a few minutes on 2 cores)
    .venv/bin/python scripts/make_docs_images.py --skip-blender   # the renders only

1. Trains a field on the built-in scene (``--steps``, default 600; reused from ``--field`` when that
   file exists, so a second run skips training) and writes, under ``--out`` (docs/images):

   * ``demo.png``: held-out test views, the ground-truth ray tracer's image (top) above the field's
     render (bottom), as ``neumesh demo`` draws its comparison figure;
   * ``hero.png``: one view of the field as trained, deformed (twisted through ``field.set_vertices``)
     and edited (a painted stroke through ``nm.paint_texture``), side by side;
   * ``deform.png``: the field as trained, bent, twisted and squashed, all through
     ``field.set_vertices`` with the same camera; no retraining.

   Their figures (test PSNR/SSIM, training time, the paint edit's size) go to ``--results``
   (benchmarks/results/figures/docs_images.json, the file the docs cite).

2. Screenshots of the add-on in Debian's ``blender`` (3.4) in a virtual X display (Xvfb), taken by the
   machinery of ``blender_tests/test_real_blender_ui.py``: ``real_blender_ui.py setup`` installs the
   add-on zip, imports the dataset's cameras and loads the field; ``real_blender_ui.py gui OUT docs``
   opens the window, shows the NeuMesh sidebar, renders the viewport, and takes the screenshots.
   Writes ``addon_panels.png`` (the sidebar's Dataset / Scaffold / Training / Field & Render panels
   beside the rendered viewport), ``addon_deform.png`` (a Simple Deform twist: the viewport renders
   the field through it), ``addon_edit.png`` (the Edit field panels: swap, fill, paint, semantics) and
   ``addon_prefs.png`` (the add-on's preferences with its dependency list).  Needs ``blender``,
   ``xvfb-run`` and torch for Blender's Python (``bash scripts/setup_blender.sh``; the folder is
   ``$NEUMESH_BLENDER_TORCH`` or ``<repo>/.blender_torch``).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
import neumesh_core as nm  # noqa: E402
from benchmarks._results import FIGURES_DIR, use_threads, write_results  # noqa: E402

SIZE = 160          # side of the renders in hero.png / deform.png (the field was trained at 128 px)
WINDOW = (1280, 1000)  # taller than the test's 900: the open Edit field panels fit


# ------------------------------------------------------------------------------------ the field
def trained_field(scene, path: str, steps: int) -> tuple:
    """The field on the built-in scene's mesh: loaded from ``path`` if it exists, else trained and saved."""
    if os.path.exists(path):
        print(f"field: reusing {path}", file=sys.stderr)
        info_path = path + ".json"
        info = json.load(open(info_path)) if os.path.exists(info_path) else {}
        return nm.load_field(path), info
    mesh = nm.load_mesh(scene.mesh_path)
    field = nm.create_field(mesh, nm.FieldConfig())
    print(f"field: training {steps} steps on the built-in scene ({mesh.num_vertices} vertices)...", file=sys.stderr)
    last = [0.0]

    def cb(p):
        if time.time() - last[0] > 10 or p.step == p.total_steps:
            last[0] = time.time()
            print(f"  step {p.step}/{p.total_steps} PSNR {p.psnr:.2f} ({p.elapsed_s:.0f} s)", file=sys.stderr)
        return True

    res = nm.train(field, scene, nm.TrainConfig(steps=steps), progress=cb)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    nm.save_field(field, path)
    info = {"steps": res.steps_done, "train_s": round(res.seconds, 1)}
    with open(path + ".json", "w") as fh:
        json.dump(info, fh)
    return field, info


def render(field, K, c2w, w, h):
    out = nm.render_camera(field, K, c2w, w, h, background=(1, 1, 1))
    return np.clip(out.rgb, 0, 1)


def camera(size=SIZE, azimuth_deg=-60.0, elevation_deg=20.0, radius=4.0):
    from neumesh_core.data.synthetic import CAMERA_ANGLE_X, look_at_opencv

    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    pos = radius * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
    return nm.intrinsics_from_fov(CAMERA_ANGLE_X, size, size), look_at_opencv(pos).astype(np.float32)


# ------------------------------------------------------------------------------------ deformations
def twist(v, turns_per_unit=0.45):
    """Rotate about the z axis by an angle proportional to z (a Simple Deform 'twist')."""
    a = 2 * np.pi * turns_per_unit * v[:, 2] / 2.0
    c, s = np.cos(a), np.sin(a)
    return np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]], 1)


def bend(v, radius=1.6):
    """Bend the z axis into an arc of ``radius`` in the x-z plane (a Simple Deform 'bend')."""
    th = v[:, 2] / radius
    r = radius - v[:, 0]
    return np.stack([radius - r * np.cos(th), v[:, 1], r * np.sin(th)], 1)


def squash(v):
    """Flatten along z and widen in x and y, keeping the volume (a stretch/squash)."""
    return v * np.array([1.25, 1.25, 0.64])


def deformed(field, fn):
    rest = field.rest_vertices.numpy()
    field.set_vertices(fn(rest.astype(np.float64)).astype(np.float32))


def restore(field):
    field.set_vertices(field.rest_vertices.numpy())


# ------------------------------------------------------------------------------------ sheets
def sheet(images, labels, path, cols=None):
    """Images (H,W,3) in [0,1] in a grid with a caption under each -> one PNG."""
    from PIL import Image, ImageDraw

    cols = cols or len(images)
    rows = (len(images) + cols - 1) // cols
    h, w = images[0].shape[:2]
    pad = 18 if labels else 0
    canvas = Image.new("RGB", (w * cols, (h + pad) * rows), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for i, img in enumerate(images):
        r, c = divmod(i, cols)
        canvas.paste(Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)), (c * w, r * (h + pad)))
        if labels:
            text = labels[i]
            tw = draw.textlength(text) if hasattr(draw, "textlength") else 6 * len(text)
            draw.text((c * w + (w - tw) / 2, r * (h + pad) + h + 3), text, fill=(40, 40, 40))
    canvas.save(path, optimize=True)
    return path


def demo_picture(field, scene, out_dir, n=4):
    split = scene.split("test")
    with tempfile.TemporaryDirectory() as renders:
        r = nm.evaluate(field, split, background=scene.background, out_dir=renders)
        from neumesh_core.cli.demo import _comparison_figure

        _comparison_figure(split, renders, r, os.path.join(out_dir, "demo.png"), n=n)
    return {"split": "test", "n_views": len(split), "psnr": round(float(r["mean"]["psnr"]), 2),
            "ssim": round(float(r["mean"]["ssim"]), 3)}


def paint_stroke(size):
    """(H,W,4) straight-alpha paint layer: a magenta ring with a cyan dot in its middle."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) + 0.5
    cx, cy = 0.5 * size, 0.46 * size
    d = np.hypot(xx - cx, yy - cy)
    rgba = np.zeros((size, size, 4), np.float32)
    ring = np.abs(d - 0.17 * size) < 0.035 * size
    dot = d < 0.06 * size
    rgba[ring] = (0.9, 0.1, 0.8, 1.0)
    rgba[dot] = (0.1, 0.8, 0.9, 1.0)
    return rgba


def render_pictures(field, scene, out_dir):
    facts = {}
    t = time.time()
    facts["demo"] = demo_picture(field, scene, out_dir)
    K, c2w = camera()
    original = render(field, K, c2w, SIZE, SIZE)

    views = [original]
    for fn in (bend, twist, squash):
        deformed(field, fn)
        views.append(render(field, K, c2w, SIZE, SIZE))
    restore(field)
    sheet(views, ["as trained", "bent", "twisted", "squashed"], os.path.join(out_dir, "deform.png"))

    rec = nm.paint_texture(field, K, c2w, SIZE, SIZE, paint_stroke(SIZE))
    painted = render(field, K, c2w, SIZE, SIZE)
    K2, c2w2 = camera(azimuth_deg=-25.0)
    painted_side = render(field, K2, c2w2, SIZE, SIZE)
    rec.undo(field)
    facts["paint"] = {"vertices_changed": int(len(rec.vertices)),
                      "seconds": round(float(rec.info.get("seconds", 0.0)), 2) if "seconds" in rec.info else None}
    sheet([original, views[2], painted, painted_side],
          ["original", "deformed (twist)", "edited (painted)", "painted, other view"],
          os.path.join(out_dir, "hero.png"))
    facts["render_pictures_s"] = round(time.time() - t, 1)
    return facts


# ------------------------------------------------------------------------------------ Blender
def _facts(log):
    lines = [line for line in log.splitlines() if line.startswith("NEUMESH_FACTS ")]
    if not lines:
        raise RuntimeError("the Blender script printed no facts:\n" + log[-4000:])
    return json.loads(lines[-1][len("NEUMESH_FACTS "):])


def _trim(img, bg_tol=6.0, margin=8):
    """Cut the bottom rows that only hold the panel background (uniform colour)."""
    a = np.asarray(img.convert("RGB"), np.float32)
    body = a[:, : max(1, a.shape[1] - 30)]  # leave out the tab strip at the right edge
    busy = np.nonzero(body.std(axis=(1, 2)) > bg_tol)[0]
    if len(busy) == 0:
        return img
    return img.crop((0, 0, img.width, min(img.height, int(busy[-1]) + margin)))


def _small(img, path, max_width=None):
    from PIL import Image

    if max_width and img.width > max_width:
        img = img.resize((max_width, round(img.height * max_width / img.width)), Image.LANCZOS)
    img.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(path, optimize=True)
    return path


def blender_pictures(field_path, dataset, out_dir, keep=None):
    sys.path.insert(0, os.path.join(ROOT, "blender_tests"))
    sys.path.insert(0, ROOT)
    from PIL import Image

    import build_addon
    from test_real_blender import BLENDER, TORCH_DIR, _env

    xvfb = shutil.which("xvfb-run")
    if not os.path.exists(BLENDER) or xvfb is None:
        raise RuntimeError("needs `blender` and `xvfb-run`: run scripts/setup_blender.sh")
    if not os.path.isdir(os.path.join(TORCH_DIR, "torch")):
        raise RuntimeError(f"no torch for Blender's Python in {TORCH_DIR}: run scripts/setup_blender.sh "
                           "(or set NEUMESH_BLENDER_TORCH)")
    from pathlib import Path

    tmp = Path(tempfile.mkdtemp(prefix="neumesh_docs_ui."))
    try:
        zip_path = build_addon.build(str(tmp / "neumesh.zip"))
        env = _env(tmp)
        script = os.path.join(ROOT, "blender_tests", "real_blender_ui.py")
        shots = tmp / "ui"
        r = subprocess.run([BLENDER, "-b", "--factory-startup", "--python", script, "--", "setup", zip_path,
                            field_path, dataset, str(shots)], env=env, capture_output=True, text=True, timeout=300)
        if r.returncode != 0:
            raise RuntimeError("Blender setup failed:\n" + (r.stdout + r.stderr)[-4000:])
        t = time.time()
        r = subprocess.run([xvfb, "-a", "-s", "-screen 0 %dx%dx24" % WINDOW, BLENDER, str(shots / "ui.blend"),
                            "--enable-event-simulate", "--python", script, "--", "gui", str(shots), "docs"],
                           env=env, capture_output=True, text=True, timeout=500)
        f = _facts(r.stdout)
        if r.returncode != 0 or f.get("errors"):
            raise RuntimeError(f"Blender window run failed (rc {r.returncode}): {f.get('errors')}\n"
                               + (r.stdout + r.stderr)[-4000:])
        H = WINDOW[1]
        x, y, w, h = f["sidebar"]
        window = Image.open(shots / "window.png").convert("RGB")
        written = {}
        # the sidebar beside the rendered viewport (the whole 3D View)
        vx = f["viewport"][0]
        panels = window.crop((vx, H - (y + h) - 40, x + w + 10, H - y))
        written["addon_panels.png"] = _small(panels, os.path.join(out_dir, "addon_panels.png"), max_width=900)
        if (shots / "edit.png").exists():
            edit = Image.open(shots / "edit.png").convert("RGB").crop((x, H - (y + h) - 40, x + w + 10, H - y))
            written["addon_edit.png"] = _small(_trim(edit), os.path.join(out_dir, "addon_edit.png"))
        if (shots / "deform.png").exists():
            deform = Image.open(shots / "deform.png").convert("RGB")
            vx, vy, vw, vh = f["viewport"]
            left = vx  # the whole 3D View, its sidebar, and the Properties editor with the modifier
            right = deform.width
            if "properties" in f:
                px, py, pw, ph = f["properties"]
                right = px + pw
            crop = deform.crop((left, 0, right, H))
            written["addon_deform.png"] = _small(crop, os.path.join(out_dir, "addon_deform.png"), max_width=960)
        if (shots / "prefs.png").exists():
            vx, vy, vw, vh = f["viewport"]
            prefs = Image.open(shots / "prefs.png").convert("RGB")
            prefs = prefs.crop((0, H - (vy + vh) - 30, x + w, H - vy))
            written["addon_prefs.png"] = _small(_trim(prefs), os.path.join(out_dir, "addon_prefs.png"), max_width=960)
        if keep:
            os.makedirs(keep, exist_ok=True)
            for p in shots.glob("*.png"):
                shutil.copy(p, os.path.join(keep, p.name))
        return {"blender": f.get("version"), "window_run_s": round(time.time() - t, 1),
                "pictures": sorted(written)}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# ------------------------------------------------------------------------------------ main
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "images"), help="picture folder")
    ap.add_argument("--results", default=os.path.join(FIGURES_DIR, "docs_images.json"),
                    help="JSON with the pictures' figures (default: the one the docs cite)")
    ap.add_argument("--field", default=os.path.join(ROOT, "runs", "docs_images", "blob.neumesh"),
                    help="field of the built-in scene: trained and saved here, or reused when it exists")
    ap.add_argument("--steps", type=int, default=600, help="training steps when the field is trained (default 600)")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = torch's default)")
    ap.add_argument("--skip-renders", action="store_true", help="only the Blender screenshots")
    ap.add_argument("--skip-blender", action="store_true", help="only the renders")
    ap.add_argument("--keep-screenshots", help="also copy Blender's full-window screenshots to this folder")
    args = ap.parse_args(argv)
    use_threads(args.threads or None)
    os.makedirs(args.out, exist_ok=True)
    t0 = time.time()
    data = nm.default_scene_dir()
    scene = nm.load_scene(data)
    field, info = trained_field(scene, args.field, args.steps)
    facts = {"scene": "built-in default scene (nm.default_scene_dir(): 128 px, 60 training views, 8 test views)",
             "vertices": int(field.num_vertices), "command": "python scripts/make_docs_images.py", **info}
    if os.path.exists(args.results):
        old = json.load(open(args.results))
        facts = {**old, **facts}
    if not args.skip_renders:
        facts.update(render_pictures(field, scene, args.out))
    if not args.skip_blender:
        facts["blender_pictures"] = blender_pictures(os.path.abspath(args.field), data, args.out,
                                                     args.keep_screenshots)
    facts["seconds"] = round(time.time() - t0, 1)
    path = os.path.abspath(args.results)
    write_results(facts, os.path.basename(path), os.path.dirname(path))
    print(json.dumps(facts, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
