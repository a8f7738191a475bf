#!/usr/bin/env python3
"""Topology edits in Blender (bpy==5.0.1 in the venv): what the vertex-identity mapping costs.

1. Sync per frame (depsgraph update excluded): ``render.collect`` (evaluated vertices, and the identity
   attributes where the mesh has them) plus ``set_vertices`` for an armature-deformed ~300k-vertex
   sphere, in three states: without identity attributes (the strict same-order path), with them and
   the mesh whole (the field itself renders it), and after deleting a few vertices (a remapped field,
   built once and reused while only positions change).  Target: the attribute paths within 20% of the
   strict path.
2. Separate / Join round trip: Separate (P) half of the mesh, the first render sync of the two objects
   (each builds its remapped field), Join (Ctrl+J), the first sync of the joined object.

The field is untrained (timings do not depend on training).  Prints figures and writes
benchmarks/results/log/topology.json.

    .venv/bin/python benchmarks/bench/bench_topology.py [--vertices 300000] [--frames 5]
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

from bench_addon import _BASE, MODULE, ROOT, sphere_grid  # noqa: F401  (sets up a private Blender home)

import bpy  # noqa: E402  (first: the bpy module provides bmesh)
import bmesh  # noqa: E402, I001
import numpy as np  # noqa: E402

import build_addon  # noqa: E402
from benchmarks._results import add_options, write_results  # noqa: E402


def _sync_frames(addon, arm, frames: int) -> list:
    pb = arm.pose.bones["tip"]
    out = []
    for i in range(frames + 1):
        pb.rotation_euler = (0.0, math.radians(10 + 7 * i), 0.0)
        dg = bpy.context.evaluated_depsgraph_get()
        dg.update()
        t = time.perf_counter()
        items = addon.render.field_cache.collect(dg, for_render=False)
        with addon.render.field_cache._LOCK:
            for it in items:
                if it.field is None:
                    addon.render.field_cache.get_field(it.key, it.path)
                addon.render.field_cache._apply_vertices(it)
        if i:   # the first frame may (re)build a remapped field
            out.append(time.perf_counter() - t)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vertices", type=int, default=300_000)
    ap.add_argument("--frames", type=int, default=5)
    add_options(ap, "results_dir")
    a = ap.parse_args(argv)

    zip_path = build_addon.build(os.path.join(_BASE, "neumesh.zip"))
    bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    import addon_utils

    addon_utils.enable(MODULE, default_set=True)
    addon = sys.modules[MODULE]
    sys.path.insert(0, os.path.join(ROOT, "blender_tests"))
    from helpers import add_armature_bend

    nm = addon.runtime.core.get()
    V, F = sphere_grid(a.vertices)
    fpath = os.path.join(_BASE, "big.neumesh")
    nm.save_field(nm.create_field(nm.Mesh(V, F), nm.FieldConfig()), fpath)
    assert bpy.ops.neumesh.load_field(filepath=fpath, new_object=True) == {"FINISHED"}
    obj = bpy.context.active_object
    arm, _, _ = add_armature_bend(obj, split_x=0.3, angle_deg=0.0)
    bpy.context.scene.render.engine = "NEUMESH"
    n = len(obj.data.vertices)
    print(f"sphere: {n:,} vertices, {len(F):,} triangles")

    res = {"vertices": n, "frames": a.frames}
    for name in addon.scene.identity.ATTRS:
        obj.data.attributes.remove(obj.data.attributes[name])
    strict = _sync_frames(addon, arm, a.frames)
    path = addon.scene.props.field_abspath(obj)
    addon.scene.identity.write(obj, addon.render.field_cache.get_field(obj.name_full, path))
    whole = _sync_frames(addon, arm, a.frames)
    bm = bmesh.new()
    bm.from_mesh(obj.data)
    bm.verts.ensure_lookup_table()
    bmesh.ops.delete(bm, geom=[bm.verts[i] for i in range(0, 40)], context="VERTS")
    bm.to_mesh(obj.data)
    bm.free()
    t = time.perf_counter()
    _sync_frames(addon, arm, 0)
    first_remap_s = time.perf_counter() - t
    remapped = _sync_frames(addon, arm, a.frames)
    med = {k: float(np.median(v)) for k, v in (("strict", strict), ("attributes_whole", whole),
                                                ("attributes_remapped", remapped))}
    res["sync_per_frame_s"] = med
    res["sync_runs_s"] = {"strict": strict, "attributes_whole": whole, "attributes_remapped": remapped}
    res["first_remap_s"] = first_remap_s
    res["ratio_to_strict"] = {k: med[k] / med["strict"] for k in med}
    print("sync per frame (collect + set_vertices, median): strict {strict:.3f} s, with ids {attributes_whole:.3f} s, "
          "remapped {attributes_remapped:.3f} s".format(**med))
    print(f"  ratios to strict: {res['ratio_to_strict']['attributes_whole']:.2f}, "
          f"{res['ratio_to_strict']['attributes_remapped']:.2f} (target <= 1.2); first remap {first_remap_s:.2f} s")

    # separate / join round trip
    obj.modifiers.clear()
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    t0 = time.perf_counter()
    bpy.ops.object.mode_set(mode="EDIT")
    bme = bmesh.from_edit_mesh(obj.data)
    for v in bme.verts:
        v.select = v.co.z > 0.0
    bme.select_flush(True)
    bmesh.update_edit_mesh(obj.data)
    bpy.ops.mesh.separate(type="SELECTED")
    bpy.ops.object.mode_set(mode="OBJECT")
    t1 = time.perf_counter()
    dg = bpy.context.evaluated_depsgraph_get()
    items = addon.render.field_cache.collect(dg, for_render=False)
    t2 = time.perf_counter()
    meshes = [o for o in bpy.context.scene.objects if o.type == "MESH"]
    for o in bpy.context.view_layer.objects:
        o.select_set(o in meshes)
    bpy.context.view_layer.objects.active = meshes[0]
    bpy.ops.object.join()
    t3 = time.perf_counter()
    dg = bpy.context.evaluated_depsgraph_get()
    items2 = addon.render.field_cache.collect(dg, for_render=False)
    t4 = time.perf_counter()
    res["separate_join_s"] = {"separate": t1 - t0, "first_sync_after_separate": t2 - t1, "join": t3 - t2,
                              "first_sync_after_join": t4 - t3, "total": t4 - t0,
                              "objects_after_separate": len(items), "items_after_join": len(items2)}
    print("separate {separate:.2f} s + first sync {first_sync_after_separate:.2f} s; join {join:.2f} s + first "
          "sync {first_sync_after_join:.2f} s; round trip {total:.2f} s".format(**res["separate_join_s"]))
    write_results(res, "topology.json", a.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
