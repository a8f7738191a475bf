#!/usr/bin/env python3
"""Semantic distillation and one-click selection: timings, pictures, and IoU where labels exist.

1. Distillation of a trained field with the weight-free extractor ("colour-texture", or --extractor):
   time per stage (2D features, marching the ray bank, training).
2. Selection from one click per --click NAME:VIEW:X:Y (VIEW indexes --split; X, Y pixels from the
   top-left): seconds from the click to the vertex indices, the first click with the selection context
   built (vertex features + neighbour graph: what the add-on's first click pays), later clicks with it
   cached (the add-on keeps it), and the redo slider (another threshold, cached context).
   With --blender the same clicks also go through the add-on's Select by click operator in bpy (click
   to vertex group and edit-mode selection).
3. A picture per click: the view as the field renders it with the click marked, and the selection
   tinted magenta and the rest darkened (--pictures PNG, one row per click).
4. On the built-in multi-part scene (the data folder holds part_labels.npy) the clicks are chosen from
   the ground truth when none are given, and the IoU per part is reported.  --make-multipart writes
   the small multi-part scene to --data (--same-colour: one texture on every part) and trains the
   field to --field (200 steps, as the tests) when they do not exist yet.
5. The geometric features (neumesh_core.semantics.geometry): their time on the field's scaffold, and
   with --scaffold PLY [--subdivide N] on any mesh (e.g. lego's 200k-vertex scaffold); --scaffold
   without --field times only that, and with --data and --click it selects on the bare scaffold with
   shape alone (a field whose semantic features are the same everywhere; the click's surface point
   from the scaffold's z-buffer), --pictures showing each selection on the shaded scaffold.

    nice -n 10 .venv/bin/python benchmarks/bench/bench_semantics.py --field F --data DIR \\
        [--click bucket:0:120:200 ...] [--pictures docs/semantics_lego.png] [--save F_sem.neumesh]
    .venv/bin/python benchmarks/bench/bench_semantics.py --make-multipart --same-colour --data /tmp/mp_same \\
        --field /tmp/mp_same.neumesh --steps 300 --rays-per-view 1024 --name semantics_multipart_same.json
    .venv/bin/python benchmarks/bench/bench_semantics.py --scaffold /work/runs/lego/scaffold.ply

Writes benchmarks/results/log/<--name> (default semantics_<field stem>.json).
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
from benchmarks._results import add_options, use_threads, write_results  # noqa: E402


def parse_click(s: str):
    try:
        name, view, x, y = s.split(":")
        return name, int(view), (float(x), float(y))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--click wants NAME:VIEW:X:Y, got {s!r}") from exc


def label_clicks(data: str, split: str):
    """One click per part of the multi-part scene: the pixel deepest inside the part, over the views."""
    from scipy.ndimage import distance_transform_edt

    import neumesh_core as nm
    from neumesh_core.data import multipart as mp

    cams = nm.load_scene(data).split(split).cameras
    best = {}
    for i in range(len(cams)):
        lab = mp.label_image(cams.K[i], cams.c2w[i], cams.width, cams.height)
        for p, name in enumerate(mp.PART_NAMES):
            dt = distance_transform_edt(lab == p)
            if name not in best or dt.max() > best[name][0]:
                y, x = np.unravel_index(dt.argmax(), dt.shape)
                best[name] = (dt.max(), i, (x + 0.5, y + 0.5), p)
    return [(name, i, xy, p) for name, (_, i, xy, p) in best.items()]


def make_multipart(data: str, field_path: str, same_colour: bool) -> dict:
    """The small multi-part scene (as the tests use it) at ``data`` and a field trained on it 200 steps
    at ``field_path``, each made only when missing."""
    import torch

    import neumesh_core as nm
    from neumesh_core.data.multipart import SMALL_KWARGS, make_multipart_scene

    out = {"same_colour": same_colour}
    if not os.path.isfile(os.path.join(data, "scene.json")):
        t = time.perf_counter()
        make_multipart_scene(data, same_colour=same_colour, **SMALL_KWARGS)
        out["scene_s"] = time.perf_counter() - t
    if not os.path.isfile(field_path):
        t = time.perf_counter()
        torch.manual_seed(0)
        field = nm.create_field(nm.load_mesh(os.path.join(data, "mesh.ply")), nm.FieldConfig(interpolation="early"))
        res = nm.train(field, nm.load_scene(data), nm.TrainConfig(steps=200, rays_per_batch=1024, log_every=50))
        nm.save_field(field, field_path)
        out.update({"train_s": time.perf_counter() - t, "train_psnr": res.final_psnr})
    return out


def subdivide(vertices: np.ndarray, faces: np.ndarray):
    """One midpoint subdivision (each triangle into four)."""
    from neumesh_core.mesh import unique_edges

    e = unique_edges(faces)
    n = len(vertices)
    key = e[:, 0] * n + e[:, 1]
    mid = (vertices[e[:, 0]] + vertices[e[:, 1]]) / 2

    def m(a, b):
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        return n + np.searchsorted(key, lo * n + hi)

    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    ab, bc, ca = m(a, b), m(b, c), m(c, a)
    f = np.concatenate([np.stack(x, 1) for x in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return np.concatenate([vertices, mid]), f


def scaffold_features(path: str, times: int) -> dict:
    """Seconds of the geometric features of the mesh at ``path`` (subdivided ``times`` times)."""
    import neumesh_core as nm
    from neumesh_core.semantics.geometry import compute_geometric_features

    if path.startswith("multipart:"):   # the built-in multi-part mesh at this marching-cubes grid
        from neumesh_core.data.multipart import multipart_mesh

        mesh, _ = multipart_mesh(int(path.split(":")[1]))
    else:
        mesh = nm.load_mesh(path)
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    for _ in range(times):
        v, f = subdivide(v, f)
    t = time.perf_counter()
    feats = compute_geometric_features(v.astype(np.float32), f)
    dt = time.perf_counter() - t
    print(f"geometric features of {path} ({len(v)} vertices, {len(f)} faces): {dt:.2f}s "
          f"({', '.join(f'{k} {x:.2f}' for k, x in feats.timings.items() if k.endswith('_s'))})")
    return {"mesh": path, "subdivided": times, "vertices": int(len(v)), "faces": int(len(f)), "seconds": dt,
            "load_average_after": list(os.getloadavg()), **feats.timings}


def _face_buffer(V, F, K, c2w, w: int, h: int):
    """(H*W,) index of the nearest face at each pixel centre (-1: none)."""
    from neumesh_core.render.raster import _project, raster_triangles

    z, pix, fi = _project(V, F, K, c2w, 1e-6)
    best = np.full(w * h, np.inf)
    face = np.full(w * h, -1, np.int64)
    for ids, px, bary in raster_triangles(pix[F[fi]], w, h, eps=1e-9):
        d = 1.0 / (bary / z[F[fi[ids]]]).sum(1)
        order = np.lexsort((d, px))
        px, d, ids = px[order], d[order], ids[order]
        first = np.r_[True, px[1:] != px[:-1]]
        px, d, ids = px[first], d[first], ids[first]
        upd = d < best[px]
        best[px[upd]] = d[upd]
        face[px[upd]] = fi[ids[upd]]
    return face


def scaffold_clicks(path: str, data: str, split: str, clicks, threshold: float, pictures, size: int):
    """Shape alone: one click per --click on the bare scaffold, through a field whose semantic features
    are the same on every vertex (so only the geometric features and the creases separate parts)."""
    import torch

    import neumesh_core as nm
    from neumesh_core.semantics import SelectConfig, SelectionContext, select_at_point

    mesh = nm.load_mesh(path)
    V, F = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    cams = nm.load_scene(data).split(split).cameras
    field = nm.create_field(mesh, nm.FieldConfig())
    field.enable_semantics(8, 16)
    with torch.no_grad():
        field.sem_codes.copy_(field.sem_codes[:1].expand_as(field.sem_codes))
    t = time.perf_counter()
    ctx = SelectionContext(field).prepare()
    out = {"context_s": time.perf_counter() - t, "clicks": []}
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-12)
    tiles = []
    for name, view, xy in clicks:
        K, c2w, w, h = cams.K[view], cams.c2w[view], cams.width, cams.height
        face = _face_buffer(V, F, K, c2w, w, h)
        x, y = int(xy[0]), int(xy[1])
        if face[y * w + x] < 0:
            print(f"  {name}: pixel {x},{y} misses the scaffold")
            continue
        p = V[F[face[y * w + x]]].mean(0)
        t = time.perf_counter()
        sel = select_at_point(field, p, SelectConfig(threshold=threshold), context=ctx)
        dt = time.perf_counter() - t
        out["clicks"].append({"name": name, "view": view, "pixel": [x, y], "vertices": int(len(sel.vertices)),
                              "seconds": dt})
        print(f"  shape alone, {name}: {len(sel.vertices)} vertices in {dt:.2f}s")
        if pictures:
            insel = np.zeros(len(V), bool)
            insel[sel.vertices] = True
            img = np.ones((h * w, 3))
            ok = face >= 0
            shade = 0.3 + 0.7 * np.abs(fn[face[ok]] @ c2w[:3, 2])
            col = np.where(insel[F[face[ok]]].mean(1, keepdims=True) > 0.5, [1.0, 0.15, 1.0], [0.8, 0.8, 0.8])
            img[ok] = col * shade[:, None]
            tiles.append(_mark(img.reshape(h, w, 3).astype(np.float32), xy, r=6, colour=(0.0, 0.7, 0.0)))
    if tiles:
        from skimage.transform import resize

        ink = np.any(np.stack([(t < 0.99).any(-1) for t in tiles]), 0)   # crop to what any tile shows
        ys, xs = np.nonzero(ink)
        pad = 8
        y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, ink.shape[0])
        x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, ink.shape[1])
        s = size / max(y1 - y0, x1 - x0)
        tiles = [resize(t[y0:y1, x0:x1], (int((y1 - y0) * s), int((x1 - x0) * s), 3), anti_aliasing=True)
                 for t in tiles]
        cols = 2 if len(tiles) > 2 else len(tiles)
        tiles += [np.ones_like(tiles[0])] * (-len(tiles) % cols)
        rows = [np.concatenate(tiles[i:i + cols], 1) for i in range(0, len(tiles), cols)]
        nm.save_image(pictures, np.concatenate(rows, 0))
        print(f"wrote {pictures}")
        out["pictures"] = pictures
    return out


def tinted_render(field, K, c2w, w, h, vertices, tint=(1.0, 0.0, 1.0), amount=0.8, dim=0.35):
    """The field's render with the selected vertices' modification colours pulled towards ``tint`` and
    every other vertex darkened by ``dim`` (a temporary change, undone before returning)."""
    import torch

    import neumesh_core as nm

    idx = torch.as_tensor(np.asarray(vertices, np.int64))
    old = field.mod_colours.detach().clone()
    try:
        with torch.no_grad():
            field.mod_colours.sub_(dim)
            field.mod_colours[idx] = old[idx] + amount * (torch.tensor(tint) - 0.5)
        return nm.render_camera(field, K, c2w, w, h, background=(1, 1, 1)).rgb
    finally:
        with torch.no_grad():
            field.mod_colours.copy_(old)


def _mark(img, xy, r=4, colour=(1.0, 0.0, 1.0)):
    out = img.copy()
    h, w = img.shape[:2]
    x, y = int(xy[0]), int(xy[1])
    for dx in range(-r, r + 1):
        for px, py in ((x + dx, y), (x, y + dx)):
            if 0 <= px < w and 0 <= py < h:
                out[py, px] = colour
    return out


def _viewport_matrices(K, c2w, w: int, h: int):
    """(view matrix, window matrix), flattened, of a 3D viewport that sees what camera (K, c2w OpenCV)
    sees: an OpenGL projection with Blender's conventions for K (camera.k_from_projection inverted)."""
    flat_view = np.linalg.inv(c2w @ np.diag([1.0, -1.0, -1.0, 1.0])).reshape(-1).tolist()
    P = np.zeros((4, 4))
    P[0, 0], P[0, 2] = 2 * K[0, 0] / w, 1 - 2 * K[0, 2] / w
    P[1, 1], P[1, 2] = 2 * K[1, 1] / h, 2 * K[1, 2] / h - 1
    P[2, 2], P[2, 3], P[3, 2] = -1.0, -0.02, -1.0
    return flat_view, P.reshape(-1).tolist()


def blender_clicks(field_path: str, cams, clicks, threshold: float):
    """Seconds per click through the add-on operator (bpy), first and later clicks."""
    sys.path.insert(0, os.path.join(ROOT, "blender_tests"))
    import user_dirs

    base = user_dirs.redirect("neumesh_bench_sem_")
    import bpy
    import addon_utils

    import build_addon

    zip_path = build_addon.build(os.path.join(base, "neumesh.zip"))
    bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    addon_utils.enable("bl_ext.user_default.neumesh", default_set=True)
    addon = sys.modules["bl_ext.user_default.neumesh"]
    assert bpy.ops.neumesh.load_field(filepath=field_path, new_object=True) == {"FINISHED"}
    scene = bpy.context.scene
    out = []
    for name, view, xy, *_ in clicks:
        K = cams.K[view]
        c2w = cams.c2w[view]
        w, h = cams.width, cams.height
        flat_view, flat_proj = _viewport_matrices(K, c2w, w, h)
        t = time.perf_counter()
        res = bpy.ops.neumesh.select_by_click(view_matrix=flat_view, window_matrix=flat_proj,
                                              view_size=(w, h), pixel=xy, group_name=name, threshold=threshold)
        dt = time.perf_counter() - t
        obj = bpy.context.active_object
        n = sum(1 for v in obj.data.vertices if v.select)
        out.append({"name": name, "seconds": dt, "result": sorted(res), "vertices_selected": n})
        print(f"  blender click {name}: {dt:.2f}s, {n} vertices selected")
    if clicks:
        # the interactive operator starts building the selection context (features, KD-tree, graph)
        # when it starts waiting for the click; time that, then the first click again on top of it
        name, view, xy, *_ = clicks[0]
        addon.semantics.select._CONTEXTS.clear()
        obj = bpy.context.active_object
        t = time.perf_counter()
        job = addon.semantics.select.prepare_selection(obj, bpy.context)
        if job is not None:
            job.join()
        prep = time.perf_counter() - t
        w, h = cams.width, cams.height
        flat_view, flat_proj = _viewport_matrices(cams.K[view], cams.c2w[view], w, h)
        t = time.perf_counter()
        res = bpy.ops.neumesh.select_by_click(view_matrix=flat_view, window_matrix=flat_proj,
                                              view_size=(w, h), pixel=xy, group_name=name, threshold=threshold)
        dt = time.perf_counter() - t
        out.append({"name": name, "prepared": True, "prepare_s": prep, "seconds": dt, "result": sorted(res)})
        print(f"  blender click {name} after the context was prepared while aiming ({prep:.2f}s): {dt:.2f}s")
    del scene, addon
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "field", "data",
                field=dict(help="trained field (.neumesh); with --skip-distill, one with semantics"),
                data=dict(help="its dataset"))
    ap.add_argument("--make-multipart", action="store_true",
                    help="write the small multi-part scene to --data and train --field on it when missing")
    ap.add_argument("--same-colour", action="store_true", help="with --make-multipart: one texture on every part")
    ap.add_argument("--geometry", type=float, default=None, help="weight of the geometric similarity (default: "
                    "SelectConfig's; 0: semantic features only)")
    ap.add_argument("--no-creases", action="store_true", help="let the growth cross concave creases")
    ap.add_argument("--semantic-tolerance", type=float, default=None,
                    help="feature distance counted as alike (default: SelectConfig's; 0: cosine only)")
    ap.add_argument("--scaffold", help="also time the geometric features on this mesh (.ply/.obj; multipart:GRID: "
                    "the built-in multi-part mesh)")
    ap.add_argument("--subdivide", type=int, default=0, help="midpoint-subdivide --scaffold this many times first")
    ap.add_argument("--split", default="val", help="split whose cameras the clicks index (default val)")
    ap.add_argument("--click", action="append", type=parse_click, default=[], metavar="NAME:VIEW:X:Y")
    ap.add_argument("--extractor", default=None, help="2D features (default colour-texture)")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--rays-per-view", type=int, default=4096)
    ap.add_argument("--threshold", type=float, default=0.75, help="selection similarity (default 0.75)")
    ap.add_argument("--skip-distill", action="store_true", help="use the field's own semantic codes")
    ap.add_argument("--save", help="write the distilled field here (reuse it with --skip-distill)")
    ap.add_argument("--pictures", help="PNG with one row per click (view | selection)")
    ap.add_argument("--picture-size", type=int, default=256, help="tile size in the picture (default 256)")
    ap.add_argument("--blender", action="store_true", help="also time the clicks through the add-on in bpy")
    add_options(ap, "threads", "results_dir")
    ap.add_argument("--name", default=None, help="results file name (default semantics_<field stem>.json)")
    args = ap.parse_args(argv)

    import neumesh_core as nm
    from neumesh_core.semantics import (DistillConfig, SelectConfig, SelectionContext, distill_semantics,
                                        make_extractor, select_region)

    use_threads(args.threads or None)
    result = {}
    if args.scaffold:
        result["scaffold_features"] = scaffold_features(args.scaffold, args.subdivide)
    if not args.field:
        if not args.scaffold:
            ap.error("give --field and --data, or --scaffold")
        if args.data and args.click:
            result["scaffold_clicks"] = scaffold_clicks(args.scaffold, args.data, args.split, args.click,
                                                        args.threshold, args.pictures, args.picture_size)
        write_results(result, args.name or "semantics_geometry_scaffold.json", args.results_dir)
        return 0
    if not args.data:
        ap.error("--field needs --data")
    if args.make_multipart:
        result["made"] = make_multipart(args.data, args.field, args.same_colour)
    field = nm.load_field(args.field)
    scene = nm.load_scene(args.data)
    result.update({"field": args.field, "data": args.data, "vertices": field.num_vertices})
    print(f"field {args.field}: {field.num_vertices} vertices")
    if not args.skip_distill:
        ex = make_extractor(args.extractor)
        cfg = DistillConfig(steps=args.steps, rays_per_view=args.rays_per_view, log_every=100)

        def cb(p):
            if p.stage == "train" and p.step % 500 == 0:
                print(f"  train {p.step}/{p.total} loss {p.loss:.4f} ({p.elapsed_s:.0f}s)", flush=True)

        res = distill_semantics(field, scene, ex, cfg, progress=cb)
        result["distill"] = {"extractor": ex.name, "steps": res.steps_done, "loss": res.final_loss,
                             "seconds": res.seconds, "bank_rays": res.bank_rays, "bank_samples": res.bank_samples,
                             "views": len(scene.split(cfg.split)), **res.timings}
        print(f"distillation ({ex.name}): {res.seconds:.1f}s = features {res.timings['features_s']:.1f}s + rays "
              f"{res.timings['rays_s']:.1f}s + training {res.timings['train_s']:.1f}s ({res.steps_done} steps, "
              f"loss {res.final_loss:.4f}, {res.bank_rays} rays)")
        if args.save:
            nm.save_field(field, args.save)
            print(f"saved {args.save}")
    cams = scene.split(args.split).cameras
    labels_path = os.path.join(args.data, "part_labels.npy")
    labels = np.load(labels_path) if os.path.isfile(labels_path) else None
    clicks = [(n, v, xy, None) for n, v, xy in args.click]
    if not clicks and labels is not None:
        clicks = label_clicks(args.data, args.split)
    if not clicks:
        print("no --click given and no part labels: nothing to select")
    sel_kw = {"creases": not args.no_creases}
    if args.geometry is not None:
        sel_kw["geometry"] = args.geometry
    if args.semantic_tolerance is not None:
        sel_kw["semantic_tolerance"] = args.semantic_tolerance
    cfg = SelectConfig(threshold=args.threshold, **sel_kw)
    result["select_config"] = {"threshold": cfg.threshold, "geometry": cfg.geometry, "creases": cfg.creases,
                               "semantic_tolerance": cfg.semantic_tolerance,
                               "geometry_config": dataclasses.asdict(cfg.geometry_config)}
    from neumesh_core.semantics import geometry as geo_mod

    geo_mod._MEMO.clear()   # time the features of this scaffold from scratch
    t = time.perf_counter()
    gf = geo_mod.geometric_features(field, cfg.geometry_config)
    result["geometry"] = {"seconds": time.perf_counter() - t, **gf.timings}
    print(f"geometric features of the field's scaffold: {result['geometry']['seconds']:.2f}s "
          f"({', '.join(f'{k} {v:.2f}' for k, v in gf.timings.items() if k.endswith('_s'))})")
    rows, tiles = [], []
    ctx = None
    for name, view, xy, part in clicks:
        K, c2w, w, h = cams.K[view], cams.c2w[view], cams.width, cams.height
        t = time.perf_counter()
        cold = ctx is None
        ctx = ctx if ctx is not None else SelectionContext(field, cfg)
        sel = select_region(field, (K, c2w, w, h), xy, cfg, context=ctx)
        dt = time.perf_counter() - t
        t = time.perf_counter()
        redo = select_region(field, (K, c2w, w, h), xy,
                             SelectConfig(threshold=min(0.95, args.threshold + 0.1), **sel_kw), context=ctx)
        dt_redo = time.perf_counter() - t
        row = {"name": name, "view": view, "pixel": list(xy), "seconds": dt, "context_built": cold,
               "redo_seconds": dt_redo, "vertices": int(len(sel.vertices)), "redo_vertices": int(len(redo.vertices)),
               "info": {k: v for k, v in sel.info.items() if isinstance(v, (int, float))}}
        if labels is not None and part is not None:
            gt = np.nonzero(labels == part)[0]
            row["iou"] = len(np.intersect1d(sel.vertices, gt)) / len(np.union1d(sel.vertices, gt))
        rows.append(row)
        print(f"click {name} (view {view}, pixel {xy[0]:.0f},{xy[1]:.0f}): {len(sel.vertices)} vertices in {dt:.2f}s"
              f"{' (context built)' if cold else ''}; redo at {min(0.95, args.threshold + 0.1):.2f}: {dt_redo:.2f}s"
              + (f"; IoU {row['iou']:.3f}" if "iou" in row else ""))
        if args.pictures:
            base = nm.render_camera(field, K, c2w, w, h, background=(1, 1, 1)).rgb
            tint = tinted_render(field, K, c2w, w, h, sel.vertices)
            tiles.append(np.concatenate([_mark(np.clip(base, 0, 1), xy), np.clip(tint, 0, 1)], 1))
    result["clicks"] = rows
    if rows:
        result["click_seconds"] = {"first": rows[0]["seconds"],
                                   "max_later": max([r["seconds"] for r in rows[1:]] or [0]),
                                   "max_redo": max(r["redo_seconds"] for r in rows)}
    if tiles:
        from skimage.transform import resize

        s = args.picture_size
        rows_img = [resize(t, (s, 2 * s, 3), anti_aliasing=True) for t in tiles]
        nm.save_image(args.pictures, np.concatenate(rows_img, 0))
        print(f"wrote {args.pictures} ({os.path.getsize(args.pictures) // 1024} KB)")
        result["pictures"] = args.pictures
    if args.blender and clicks:
        path = args.field
        if not args.skip_distill:   # the add-on reads the distilled field from a file
            path = args.save or os.path.join(os.environ.get("TMPDIR", "/tmp"), "bench_semantics_field.neumesh")
            if not args.save:
                nm.save_field(field, path)
        result["blender_clicks"] = blender_clicks(path, cams, clicks, args.threshold)
    name = args.name or "semantics_" + os.path.splitext(os.path.basename(args.field))[0] + ".json"
    write_results(result, name, args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
