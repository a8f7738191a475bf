"""docs/images/composite_cycles.png: a NeuMesh field standing in an ordinary Blender scene, rendered with
Cycles through "Composite with Scene" (the add-on's compositor set-up: the field in a companion
NEUMESH scene, Z-combined with the main scene's Cycles render).

    OMP_NUM_THREADS=1 .venv/bin/python scripts/composite_picture.py [--field /work/runs/lego_field.neumesh]

Runs in Blender's Python (the bpy module from PyPI, in the venv), with the add-on built from this
checkout and installed into a temporary Blender user folder. The scene: the field (the NeRF-synthetic
lego by default, in its world units) on a grey plane at the bottom of its scaffold, a blue column
behind it and an orange ball in front of one corner; a sun and a sky-grey world; the camera looks
down at it. The field hides part of the column and the plane, the ball hides part of the field.

Also measures how the field's Depth pass agrees with Cycles' Z of the field's own scaffold mesh at a
quarter of the size (pixels where the field is opaque, > 0.9, and the scaffold is hit), and writes the
figures and timings to benchmarks/results/figures/composite.json.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "blender_tests"))
import user_dirs  # noqa: E402
from benchmarks._results import FIGURES_DIR, write_results  # noqa: E402

_BASE = user_dirs.redirect("neumesh_composite_")

import bpy  # noqa: E402
import numpy as np  # noqa: E402

import build_addon  # noqa: E402
from helpers import add_camera, cycles_fast, exact_colour_settings, render_pass  # noqa: E402

MODULE = "bl_ext.user_default.neumesh"


def install_addon():
    import addon_utils

    zip_path = build_addon.build(os.path.join(_BASE, "neumesh.zip"))
    assert bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default",
                                                    enable_on_install=True, overwrite=True) == {"FINISHED"}
    addon_utils.enable(MODULE, default_set=True)
    return sys.modules[MODULE]


def material(name, rgb):
    mat = bpy.data.materials.new(name)
    mat.diffuse_color = (*rgb, 1.0)
    if mat.node_tree is None:
        mat.use_nodes = True
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (*rgb, 1.0)
    bsdf.inputs["Roughness"].default_value = 0.6
    return mat


def add(kind, name, rgb, **kw):
    getattr(bpy.ops.mesh, f"primitive_{kind}_add")(**kw)
    ob = bpy.context.active_object
    ob.name = name
    ob.data.materials.append(material(name, rgb))
    if hasattr(ob.data, "polygons"):
        for p in ob.data.polygons:
            p.use_smooth = kind != "plane"
    return ob


def build_scene(field_path, width, height, samples):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    import addon_utils

    addon_utils.enable(MODULE, default_set=True)
    assert bpy.ops.neumesh.load_field(filepath=field_path, new_object=True) == {"FINISHED"}
    field_ob = bpy.context.active_object
    v = np.array([tuple(p.co) for p in field_ob.data.vertices], np.float64)
    lo, hi = v.min(0), v.max(0)
    centre = (lo + hi) / 2
    size = float((hi - lo)[:2].max())
    add("plane", "floor", (0.42, 0.42, 0.40), size=size * 5, location=(centre[0], centre[1], lo[2] - 0.002))
    tall = float(hi[2] - lo[2])
    add("cylinder", "column", (0.15, 0.3, 0.75), radius=size * 0.13, depth=tall * 1.25,
        location=(centre[0] - size * 0.25, centre[1] + size * 0.55, lo[2] + tall * 0.625))
    add("uv_sphere", "ball", (0.9, 0.45, 0.1), radius=size * 0.13, segments=48, ring_count=24,
        location=(centre[0] + size * 0.3, centre[1] - size * 0.62, lo[2] + size * 0.13))
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 2.5
    sun.data.angle = math.radians(8)
    sun.rotation_euler = (math.radians(35), math.radians(10), math.radians(30))
    bpy.context.scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("sky")
    if world.node_tree is None:
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.55, 0.62, 0.72, 1.0)
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.7
    scene = bpy.context.scene
    scene.world = world
    eye = centre + np.array([size * 1.55, -size * 2.1, size * 1.25])
    add_camera(tuple(eye), look_at=tuple(centre + np.array([0.0, 0.0, -(hi[2] - lo[2]) * 0.1])), lens=48.0)
    exact_colour_settings(scene, width, height)
    cycles_fast(scene, samples=samples)
    scene.cycles.filter_width = 1.5
    scene.cycles.max_bounces = 4
    return scene, field_ob


def depth_agreement(addon, scene, field_ob, width, height, out_dir):
    """Median / 90th percentile |field Z - Cycles Z of the scaffold| where the field is opaque."""
    saved = {k: getattr(scene.render, k) for k in ("resolution_x", "resolution_y")}
    scene.render.resolution_x, scene.render.resolution_y = width, height
    bpy.context.view_layer.use_pass_z = True
    others = [o for o in scene.objects if o.type == "MESH" and o is not field_ob]
    for o in others:
        o.hide_render = True
    engine, samples = scene.render.engine, scene.cycles.samples
    scene.cycles.samples = 1
    zc = render_pass(addon.render.composite, scene, "Depth", os.path.join(out_dir, "zc.exr"))[..., 0]
    scene.render.engine = "NEUMESH"
    scene.render.film_transparent = True
    zf = render_pass(addon.render.composite, scene, "Depth", os.path.join(out_dir, "zf.exr"))[..., 0]
    af = render_pass(addon.render.composite, scene, "Alpha", os.path.join(out_dir, "af.exr"))[..., 0]
    scene.render.engine, scene.cycles.samples = engine, samples
    scene.render.film_transparent = False
    for o in others:
        o.hide_render = False
    for k, val in saved.items():
        setattr(scene.render, k, val)
    both = (af > 0.9) & (zc < 1e9)
    dz = np.abs(zf - zc)[both]
    signed = (zf - zc)[both]
    return {"size": [width, height], "pixels": int(both.sum()), "median_abs_dz": float(np.median(dz)),
            "p90_abs_dz": float(np.percentile(dz, 90)), "median_signed_dz": float(np.median(signed)),
            "median_z": float(np.median(zc[both]))}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--field", default="/work/runs/lego_field.neumesh")
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "images", "composite_cycles.png"))
    ap.add_argument("--results", default=os.path.join(FIGURES_DIR, "composite.json"))
    ap.add_argument("--size", type=int, nargs=2, default=(480, 360))
    ap.add_argument("--samples", type=int, default=24)
    a = ap.parse_args()
    addon = install_addon()
    addon.runtime.prefs.get_prefs().torch_threads = int(os.environ.get("OMP_NUM_THREADS", "0") or 0)
    w, h = a.size
    scene, field_ob = build_scene(os.path.abspath(a.field), w, h, a.samples)
    out_dir = os.environ["TMPDIR"]
    t0 = time.perf_counter()
    agree = depth_agreement(addon, scene, field_ob, w // 4, h // 4, out_dir)
    t1 = time.perf_counter()
    assert bpy.ops.neumesh.composite_with_scene() == {"FINISHED"}
    scene.render.filepath = os.path.abspath(a.out)
    scene.render.image_settings.color_depth = "8"
    scene.render.image_settings.color_mode = "RGB"
    t2 = time.perf_counter()
    bpy.ops.render.render(write_still=True, scene=scene.name)
    t3 = time.perf_counter()
    facts = {"field": os.path.basename(a.field), "vertices": len(field_ob.data.vertices), "picture": [w, h],
             "cycles_samples": a.samples, "depth_vs_cycles_scaffold": agree,
             "seconds": {"depth_check": round(t1 - t0, 1), "composite_render": round(t3 - t2, 1)},
             "threads": int(os.environ.get("OMP_NUM_THREADS", "0") or 0)}
    path = os.path.abspath(a.results)
    write_results(facts, os.path.basename(path), os.path.dirname(path))
    print(json.dumps(facts, indent=2))


if __name__ == "__main__":
    main()
