"""Baking a field into a UV-textured mesh: how close the baked asset's render is to the field's own.

    python benchmarks/bench/bench_bake.py --field runs/blob.neumesh                # the built-in scene
    python benchmarks/bench/bench_bake.py --field runs/lego_field.neumesh --data ../shared/data/nerf_synthetic/lego \
        --split val --views 4 --resolutions 1024,2048 --directions 1 --decimate 0.05 --threads 1 --cycles

For each texture size (``--resolutions``) and rays per texel (``--directions``: 1 = along -normal; 5 =
-normal and four rays tilted 30 degrees) the field is baked, and the baked mesh is rendered with the
core's numpy rasteriser (z-buffer, bilinear texture, 2x2 supersampled) on held-out views (``--split``,
default ``test``) and compared with the field's render of the same views (PSNR), and both with the
photos.  ``--mesh FILE`` bakes onto that mesh, ``--decimate R`` onto a quadric-decimated copy (about R x
the faces) of the scaffold (or of --mesh); ``--target field`` onto a mesh extracted from the field's own
density (marching cubes at a calibrated level, decimated to --decimate x the scaffold's faces).
``--colours views`` takes the texel colours from the field's renders on virtual cameras (``--proj-views`` of
``--proj-size`` pixels) instead of a ray along each texel's normal. Two comparisons: ``psnr_vs_field`` (the
field's render with one ray per pixel centre against the raster's 2x2 supersampled one) and
``psnr_vs_field_ss2`` (both 2x2 supersampled: the same anti-aliasing on both sides, as a photo and Cycles
have; the headline figure). Writes bake_<name>.json to benchmarks/results/log (or ``--results-dir``) and, with
``--figure``, field render | baked render pictures (``--figure-views`` views, one row each).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
import neumesh_core as nm  # noqa: E402
from neumesh_core.bake import ExtractConfig, ProjectConfig, SurfaceFitConfig, bake_texture  # noqa: E402
from neumesh_core.metrics import psnr  # noqa: E402
from neumesh_core.render.raster import render_textured_mesh  # noqa: E402
from benchmarks._results import add_options, use_threads, write_results  # noqa: E402


def cycles_renders(args, best, cams, views, refs, bg) -> dict:
    """Render ``best``'s bake with Cycles (Blender in a subprocess) on ``views``; PSNR vs the field."""
    import json
    import subprocess
    import tempfile

    from neumesh_core.imageio import read_image

    row, imgs, b = best
    worker = os.path.join(ROOT, "benchmarks", "workers", "bake_cycles_worker.py")
    with tempfile.TemporaryDirectory(prefix="neumesh_cycles_") as tmp:
        tex = os.path.join(tmp, "texture.png")
        nm.save_image(tex, b.texture)
        job = os.path.join(tmp, "job.npz")
        np.savez(job, vertices=b.vertices, faces=b.faces, uvs=b.uvs, texture_path=tex,
                 K=np.stack([cams.K[i] for i in views]), c2w=np.stack([cams.c2w[i] for i in views]),
                 width=int(cams.width), height=int(cams.height), background=bg,
                 samples=int(args.cycles_samples), threads=int(args.threads or 1))
        env = dict(os.environ)
        home = os.path.join(tmp, "home")
        os.makedirs(home)
        env.update(BLENDER_USER_RESOURCES=home, XDG_CACHE_HOME=home, XDG_CONFIG_HOME=home, HOME=home,
                   NEUMESH_PYTHONPATH=os.path.abspath(args.blender_python_path))
        t0 = time.perf_counter()
        proc = subprocess.run([args.blender, "-b", "--factory-startup", "--python-exit-code", "1", "--python",
                               worker, "--", job, tmp], env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            print(proc.stdout[-3000:], proc.stderr[-3000:])
            raise SystemExit(f"blender failed ({proc.returncode})")
        with open(os.path.join(tmp, "cycles.json")) as fh:
            info = json.load(fh)
        renders = [read_image(os.path.join(tmp, f"cycles_{k}.png"))[..., :3] for k in range(len(views))]
        if args.figure:
            stem, ext = os.path.splitext(args.figure)
            k = 0
            nm.save_image(f"{stem}_cycles{ext}", np.concatenate([refs[k], imgs[k], renders[k]], 1))
    per_view = [psnr(renders[k], refs[k]) for k in range(len(views))]
    out = {"resolution": row["resolution"], "directions": row["directions"], "samples": int(args.cycles_samples),
           "psnr_vs_field": float(np.mean(per_view)), "psnr_vs_field_views": per_view,
           "psnr_vs_raster": float(np.mean([psnr(renders[k], imgs[k]) for k in range(len(views))])),
           "seconds_per_view": round(float(np.mean(info["seconds_per_view"])), 2),
           "blender_wall_s": round(wall, 1), "blender": info["blender"]}
    print("cycles:", {k: v for k, v in out.items() if k != "psnr_vs_field_views"})
    return out


def depth_vs_field(b, cams, views, field_depths, radius) -> dict:
    """How far the baked mesh lies from the field's depth on the views: over the pixels both cover,
    |mesh depth - field depth| (ray distances; the field's where its opacity >= 0.5) median / mean /
    90th percentile in world units and field radii; and the share of pixels where they show another
    surface (one empty, or depths more than a radius apart)."""
    from neumesh_core.data.cameras import axis_to_ray_depth
    from neumesh_core.render.raster import depth_buffer

    diffs, wrong, total = [], 0, 0
    for k, i in enumerate(views):
        z = axis_to_ray_depth(depth_buffer(b.vertices, b.faces, cams.K[i], cams.c2w[i], cams.width, cams.height),
                              cams.K[i])
        ref = field_depths[k]
        a, f = np.isfinite(z), np.isfinite(ref)
        both = a & f
        d = np.abs(z[both] - ref[both])
        diffs.append(d)
        wrong += int((a ^ f).sum() + (d > radius).sum())
        total += z.size
    d = np.concatenate(diffs)
    out = {"pixels_both": int(d.size), "other_surface_share": wrong / max(1, total)}
    for key, val in (("median", np.median(d)), ("mean", d.mean()), ("p90", np.percentile(d, 90))):
        out[key] = float(val)
        out[f"{key}_radii"] = float(val / radius)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "field", "data", "name", "mesh", "threads", "results_dir", field=dict(required=True),
                data=dict(help="dataset (default: the built-in scene)"),
                name=dict(help="results name (default: blob, or the data folder's name)"),
                mesh=dict(help="bake onto this mesh instead of the scaffold (world space, near the surface)"))
    ap.add_argument("--split", default="test")
    ap.add_argument("--views", type=int, default=8, help="held-out views used (default 8)")
    ap.add_argument("--downscale", type=float, default=1)
    ap.add_argument("--resolutions", default="512,1024")
    ap.add_argument("--directions", default="1,5")
    ap.add_argument("--decimate", type=float, default=1.0,
                    help="bake onto a decimated copy with about this fraction of the faces (default 1: none)")
    ap.add_argument("--target", default="scaffold", choices=("scaffold", "field"),
                    help="bake onto the (decimated) scaffold or --mesh (default), or 'field': a mesh extracted "
                         "from the field's density, decimated to --decimate x the scaffold's faces")
    ap.add_argument("--voxel", type=float, default=0.35, help="--target field: grid spacing in radii")
    ap.add_argument("--colours", default="rays", choices=("rays", "views"),
                    help="texel colours: a ray along each texel's normal, or the field's renders projected")
    ap.add_argument("--proj-views", type=int, default=48)
    ap.add_argument("--proj-size", type=int, default=512)
    ap.add_argument("--no-fit", action="store_true",
                    help="bake onto the mesh where it is (default: first move it onto the field's surface)")
    ap.add_argument("--level", type=float, default=None,
                    help="opacity level of the field's surface for the fit (default: calibrated per field)")
    ap.add_argument("--offset", type=float, default=None, help="texel ray start, field radii (default: the bake's)")
    ap.add_argument("--fit-search", type=float, default=1.5, help="fit: field radii searched each side (default 1.5)")
    ap.add_argument("--fit-smoothness", type=float, default=0.3, help="fit: edge smoothness weight (default 0.3)")
    ap.add_argument("--figure", help="write field | baked pictures here (PNG)")
    ap.add_argument("--figure-views", type=int, default=2, help="views (rows) in the figure (default 2)")
    ap.add_argument("--cycles", action="store_true",
                    help="also render the best bake with Cycles in `blender -b` "
                         "(benchmarks/workers/bake_cycles_worker.py) "
                         "on the same views and compare it with the field's render")
    ap.add_argument("--cycles-samples", type=int, default=16)
    ap.add_argument("--blender", default="blender", help="Blender binary for --cycles (default: blender)")
    ap.add_argument("--blender-python-path", default=os.environ.get("NEUMESH_BLENDER_TORCH", os.path.join(
        ROOT, ".blender_torch")),
                    help="folder with numpy for Blender's Python (default: .blender_torch, see setup_blender.sh)")
    args = ap.parse_args(argv)
    use_threads(args.threads or None)
    extract_info = None
    data = args.data or nm.default_scene_dir()
    name = args.name or ("blob" if not args.data else os.path.basename(os.path.normpath(args.data)))
    scene = nm.load_scene(data, downscale=args.downscale)
    split = scene.split(args.split)
    cams = split.cameras
    views = list(range(min(args.views, len(split))))
    field = nm.load_field(args.field)
    field.eval()
    bg = np.asarray(scene.background, np.float32)
    mesh, decimate_s = None, 0.0
    if args.mesh:
        mesh = nm.load_mesh(args.mesh)
    extract = None
    if args.target == "field":
        if args.mesh:
            raise SystemExit("--target field extracts the mesh from the field: leave out --mesh")
        extract = ExtractConfig(voxel=args.voxel, faces=int(round(min(1.0, args.decimate) * len(field.faces)))
                                if args.decimate < 1.0 else 0)
        mesh = "field"
    elif args.decimate < 1.0:
        from neumesh_core.bake import decimate

        src = mesh if mesh is not None else nm.Mesh(np.asarray(field.vertices), field.faces.cpu().numpy())
        t0 = time.perf_counter()
        mesh = nm.Mesh(*decimate(src.vertices, src.faces, args.decimate))
        decimate_s = time.perf_counter() - t0
        print(f"decimated {len(src.faces)} -> {len(mesh.faces)} faces in {decimate_s:.1f} s")
    t0 = time.perf_counter()
    outs = [nm.render_camera(field, cams.K[i], cams.c2w[i], cams.width, cams.height, background=tuple(bg))
            for i in views]
    refs = [np.clip(o.rgb, 0, 1) for o in outs]
    # the same views with 2x2 rays per pixel: anti-aliased like the raster (supersample 2) and Cycles
    refs_ss2 = [np.clip(nm.render_camera(field, cams.K[i], cams.c2w[i], cams.width, cams.height, background=tuple(bg),
                                         settings=nm.RenderSettings(supersample=2)).rgb, 0, 1) for i in views]
    field_depths = [np.where(o.opacity >= 0.5, o.depth, np.inf) for o in outs]
    field_render_s = (time.perf_counter() - t0) / len(views)
    field_vs_photo = float(np.mean([psnr(refs[k], split.float_view(i)) for k, i in enumerate(views)]))
    print(f"field vs photos: {field_vs_photo:.2f} dB ({field_render_s:.2f} s per view)")
    runs = []
    best = None
    for res in [int(r) for r in args.resolutions.split(",")]:
        for dirs in [int(d) for d in args.directions.split(",")]:
            fit = False if args.no_fit or args.target == "field" else SurfaceFitConfig(
                level=args.level, search=args.fit_search, smoothness=args.fit_smoothness)
            b = bake_texture(field, resolution=res, directions=dirs, mesh=mesh, fit=fit, offset=args.offset,
                             colours=args.colours, extract=extract,
                             project=ProjectConfig(views=args.proj_views, size=args.proj_size))
            if isinstance(mesh, str):     # extracted once: the next bakes reuse the mesh
                extract_info = b.info["extract"]
                vm = np.zeros((int(b.vertex_index.max()) + 1, 3), np.float32)
                vm[b.vertex_index] = b.vertices
                mesh = (vm, b.vertex_index[b.faces])
            imgs = []
            t1 = time.perf_counter()
            for k, i in enumerate(views):
                img, _ = render_textured_mesh(b.vertices, b.faces, b.uvs, b.texture, cams.K[i], cams.c2w[i],
                                              cams.width, cams.height, background=bg, supersample=2)
                imgs.append(img)
            raster_s = (time.perf_counter() - t1) / len(views)
            per_view = [psnr(imgs[k], refs[k]) for k in range(len(views))]
            per_view_ss2 = [psnr(imgs[k], refs_ss2[k]) for k in range(len(views))]
            row = {"resolution": res, "directions": dirs, "bake_s": round(b.seconds, 2),
                   "unwrap_s": round(b.info["unwrap_s"], 2), "charts": b.info["charts"],
                   "texels": b.info["texels"], "padding_texels": round(b.info["padding_texels"], 2),
                   "mesh_vertices": b.info["mesh_vertices"], "mesh_faces": b.info["mesh_faces"],
                   "missed_texels": b.info["missed_texels"],
                   "psnr_vs_field": float(np.mean(per_view)), "psnr_vs_field_views": per_view,
                   "psnr_vs_field_ss2": float(np.mean(per_view_ss2)), "psnr_vs_field_ss2_views": per_view_ss2,
                   "colours": args.colours, "texels_unseen": b.info.get("texels_unseen"),
                   "project_s": round(b.info.get("project_s", 0.0), 2),
                   "psnr_vs_photos": float(np.mean([psnr(imgs[k], split.float_view(i)) for k, i in enumerate(views)])),
                   "raster_s_per_view": round(raster_s, 3),
                   "fit_s": round(b.info.get("fit_s", 0.0), 2),
                   "fit_level": b.info["fit"]["level"] if "fit" in b.info else None,
                   "surface_offset": b.info.get("surface_offset"),
                   "depth_vs_field": depth_vs_field(b, cams, views, field_depths, field.radius)}
            if "fit" in b.info:
                row["fit"] = {k: b.info["fit"][k] for k in ("before", "after", "level_scores", "iterations",
                                                            "before_render_disagreement") if k in b.info["fit"]}
            print({k: v for k, v in row.items() if k not in ("psnr_vs_field_views", "psnr_vs_field_ss2_views", "fit")},
                  flush=True)
            runs.append(row)
            if best is None or row["psnr_vs_field_ss2"] > best[0]["psnr_vs_field_ss2"]:
                best = (row, imgs, b)
    if args.figure:
        pick = views[:max(1, args.figure_views)]
        rows = [np.concatenate([refs[k], best[1][k]], 1) for k in range(len(pick))]
        nm.save_image(args.figure, np.concatenate(rows, 0))
        print(f"wrote {args.figure} (left: field render, right: baked mesh, {best[0]['resolution']} px, "
              f"{best[0]['directions']} direction(s))")
    result = {"field": args.field, "data": data, "split": args.split, "views": len(views),
              "image_size": [int(cams.width), int(cams.height)], "vertices": int(field.num_vertices),
              "faces": int(len(field.faces)), "field_vs_photos": field_vs_photo,
              "mesh": args.mesh, "decimate": args.decimate, "decimate_s": round(decimate_s, 2),
              "fit": None if args.no_fit else {"level": args.level, "search": args.fit_search,
                                               "smoothness": args.fit_smoothness},
              "downscale": args.downscale,
              "field_render_s_per_view": round(field_render_s, 3), "runs": runs,
              "target": args.target, "extract": extract_info, "colours": args.colours,
              "projection": {"views": args.proj_views, "size": args.proj_size} if args.colours == "views" else None,
              "best": {k: v for k, v in best[0].items() if k not in ("psnr_vs_field_views", "psnr_vs_field_ss2_views",
                                                                      "fit")},
              "machine": {"note": "2 CPU cores shared with other developers' jobs: times are upper bounds"}}
    if args.cycles:
        result["cycles"] = cycles_renders(args, best, cams, views, refs, bg)
    write_results(result, f"bake_{name}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
