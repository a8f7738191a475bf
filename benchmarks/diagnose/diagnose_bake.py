"""Where a bake's error against its field lies: per-pixel error maps split by region, and
oracles that separate the mesh's geometry from the texture's colour.

For each held-out view: the field's render (rgb, opacity, depth) and the baked mesh's raster; the
squared error summed over
* ``silhouette``: pixels where the field's opacity is between 0.02 and 0.98 or the mesh's coverage
  disagrees with it (one covers the pixel, the other does not);
* ``edge``: inside both, within 1 pixel of a jump of the field's depth by more than a field radius
  (occlusion edges between parts);
* ``interior``: the rest;
and three oracles on the same views:
* ``hard_field``: the field's own colour where its opacity >= 0.5, background elsewhere (what a hard
  edged surface at the field's exact silhouette loses, before any texture);
* ``mesh_oracle``: the mesh's geometry with, at every pixel it covers, the field volume-rendered along
  the camera ray within ``window`` radii of the mesh's depth (a perfect view-dependent texture on
  this mesh): the loss due to the mesh's geometry alone;
* ``bake``: the baked texture.

Writes ``benchmarks/results/log/bake_diagnose_<name>.json`` and, with ``--figure``, field | bake | error x4 per view.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

import neumesh_core as nm  # noqa: E402
from neumesh_core.bake import bake_texture, decimate  # noqa: E402
from neumesh_core.render.raster import depth_buffer, render_textured_mesh  # noqa: E402

from benchmarks._results import add_options, use_threads, write_results  # noqa: E402


def psnr(a, b) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float(10 * np.log10(1.0 / max(mse, 1e-12)))


def regions(opac, cov, depth, radius):
    """(silhouette, edge, interior) boolean masks of a view."""
    sil = ((opac > 0.02) & (opac < 0.98)) | ((opac >= 0.5) != (cov >= 0.5))
    d = np.where(np.isfinite(depth), depth, 1e3)
    jump = np.zeros_like(sil)
    jump[:, 1:] |= np.abs(d[:, 1:] - d[:, :-1]) > radius
    jump[1:, :] |= np.abs(d[1:, :] - d[:-1, :]) > radius
    grown = jump.copy()
    grown[1:] |= jump[:-1]
    grown[:-1] |= jump[1:]
    grown[:, 1:] |= jump[:, :-1]
    grown[:, :-1] |= jump[:, 1:]
    edge = grown & ~sil
    return sil, edge, ~(sil | edge)


@torch.no_grad()
def mesh_oracle(field, vertices, faces, K, c2w, w, h, bg, window):
    """The field rendered along each camera ray within ``window`` radii of the mesh's depth."""
    from neumesh_core.data.cameras import axis_to_ray_depth, pixel_rays

    t = axis_to_ray_depth(depth_buffer(vertices, faces, K, c2w, w, h), K).reshape(-1)
    hit = np.isfinite(t)
    img = np.tile(np.asarray(bg, np.float32), (w * h, 1))
    o, d = pixel_rays(K, c2w, w, h)
    idx = torch.as_tensor(np.nonzero(hit)[0])
    tt = torch.as_tensor(t[hit], dtype=torch.float32)
    r = float(field.radius) * window
    out = nm.render_rays(field, o[idx], d[idx], background=None, ranges=[(tt - r, tt + r)])
    op = out["opacity"].clamp_min(1e-6)[:, None]
    col = torch.where(op > 1e-3, out["rgb"] / op, torch.zeros_like(out["rgb"]))
    img[hit] = col.clamp(0, 1).numpy()
    return img.reshape(h, w, 3)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "field", "data", "name", "threads", "results_dir", field=dict(required=True),
                data=dict(required=True), name=dict(default="lego", help="results name (default lego)"),
                threads=dict(default=1, help="torch threads (default 1)"))
    ap.add_argument("--split", default="val")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--downscale", type=float, default=2)
    ap.add_argument("--resolution", type=int, default=1024)
    ap.add_argument("--decimate", type=float, default=0.05)
    ap.add_argument("--mesh", help="bake onto this mesh (world space) instead of the decimated scaffold; "
                    "'field': extracted from the field's density, decimated to --decimate x the scaffold's faces")
    ap.add_argument("--no-fit", action="store_true")
    ap.add_argument("--colours", default="rays", choices=("rays", "views"))
    ap.add_argument("--proj-views", type=int, default=48)
    ap.add_argument("--proj-size", type=int, default=512)
    ap.add_argument("--voxel", type=float, default=0.35)
    ap.add_argument("--tolerance", type=float, default=0.5)
    ap.add_argument("--window", type=float, default=1.0, help="mesh oracle: radii each side of the mesh depth")
    ap.add_argument("--figure")
    args = ap.parse_args(argv)
    use_threads(args.threads)
    scene = nm.load_scene(args.data, downscale=args.downscale)
    split = scene.split(args.split)
    cams = split.cameras
    views = list(range(min(args.views, len(split))))
    field = nm.load_field(args.field)
    field.eval()
    bg = np.asarray(scene.background, np.float32)
    from neumesh_core.bake import ExtractConfig, ProjectConfig

    extract = ExtractConfig(voxel=args.voxel, faces=int(round(args.decimate * len(field.faces))))
    if args.mesh == "field":
        mesh = "field"
    elif args.mesh:
        m = nm.load_mesh(args.mesh)
        mesh = (m.vertices, m.faces)
    else:
        mesh = decimate(np.asarray(field.vertices), field.faces.cpu().numpy(), args.decimate)
    t0 = time.perf_counter()
    b = bake_texture(field, resolution=args.resolution, mesh=mesh, fit=False if args.no_fit else None,
                     colours=args.colours, extract=extract,
                     project=ProjectConfig(views=args.proj_views, size=args.proj_size, tolerance=args.tolerance))
    print({k: v for k, v in b.info.items() if k not in ("fit",)}, flush=True)
    bake_s = time.perf_counter() - t0
    W, H = int(cams.width), int(cams.height)
    rows, per = [], []
    tot = {"silhouette": 0.0, "edge": 0.0, "interior": 0.0}
    counts = dict.fromkeys(tot, 0)
    for i in views:
        o = nm.render_camera(field, cams.K[i], cams.c2w[i], W, H, background=tuple(bg))
        ref = np.clip(o.rgb, 0, 1)
        img, cov = render_textured_mesh(b.vertices, b.faces, b.uvs, b.texture, cams.K[i], cams.c2w[i], W, H,
                                        background=bg, supersample=2)
        hard = np.where((o.opacity >= 0.5)[..., None], np.clip(o.rgb + (1 - o.opacity[..., None]) * 0, 0, 1), bg)
        # the field's colour where it is opaque enough, un-premultiplied against the background
        op = np.clip(o.opacity, 1e-6, 1)[..., None]
        hard = np.where((o.opacity >= 0.5)[..., None], np.clip((ref - (1 - op) * bg) / op, 0, 1), bg)
        orc = mesh_oracle(field, b.vertices, b.faces, cams.K[i], cams.c2w[i], W, H, bg, args.window)
        err = ((img - ref) ** 2).sum(-1)
        sil, edge, inter = regions(o.opacity, cov, np.where(o.opacity >= 0.5, o.depth, np.inf), field.radius)
        for k, m in (("silhouette", sil), ("edge", edge), ("interior", inter)):
            tot[k] += float(err[m].sum())
            counts[k] += int(m.sum())
        img1, _ = render_textured_mesh(b.vertices, b.faces, b.uvs, b.texture, cams.K[i], cams.c2w[i], W, H,
                                       background=bg, supersample=1)
        o2 = nm.render_camera(field, cams.K[i], cams.c2w[i], W, H, background=tuple(bg),
                              settings=nm.RenderSettings(supersample=2))
        per.append({"view": i, "bake": psnr(img, ref), "bake_ss1_vs_field_ss1": psnr(img1, ref),
                    "bake_ss2_vs_field_ss2": psnr(img, np.clip(o2.rgb, 0, 1)), "hard_field": psnr(hard, ref),
                    "mesh_oracle": psnr(orc, ref),
                    "bake_interior_only": psnr(np.where(inter[..., None], img, ref), ref),
                    "bake_without_silhouette": psnr(np.where(sil[..., None], ref, img), ref)})
        print(per[-1], flush=True)
        if args.figure and len(rows) < 2:
            e = np.clip(np.sqrt(err / 3) * 4, 0, 1)
            rows.append(np.concatenate([ref, img, orc, np.repeat(e[..., None], 3, -1)], 1))
    total = sum(tot.values())
    share = {k: v / max(total, 1e-12) for k, v in tot.items()}
    pix = {k: v / max(1, sum(counts.values())) for k, v in counts.items()}
    keys = ("bake", "bake_ss1_vs_field_ss1", "bake_ss2_vs_field_ss2", "hard_field", "mesh_oracle", "bake_interior_only",
            "bake_without_silhouette")
    result = {"field": args.field, "data": args.data, "split": args.split, "views": len(views),
              "image_size": [W, H], "resolution": args.resolution, "decimate": None if args.mesh else args.decimate,
              "mesh": args.mesh, "fit": not args.no_fit, "window_radii": args.window, "colours": args.colours,
              "projection": {"views": args.proj_views, "size": args.proj_size} if args.colours == "views" else None,
              "extract": b.info.get("extract"),
              "mesh_faces": b.info["mesh_faces"], "bake_s": round(bake_s, 2),
              "mean": {k: float(np.mean([p[k] for p in per])) for k in keys},
              "squared_error_share": share, "pixel_share": pix, "per_view": per,
              "machine": {"note": "2 shared, loaded CPU cores"}}
    print(result["mean"], share, pix)
    if args.figure:
        nm.save_image(args.figure, np.concatenate(rows, 0))
    write_results(result, f"bake_diagnose_{args.name}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
