"""The README's edit pictures, re-runnable: texture fill, texture swap and texture painting on lego.
The swap takes its texture from another trained field (the built-in scene by default), which only
renders right because that field's decoder travels with its codes.

    .venv/bin/neumesh train --data ~/.cache/neumesh/<default scene> --steps 1500 --out runs/blob.neumesh
    .venv/bin/python scripts/edit_pictures.py --lego runs/lego/field.neumesh \
        --lego-data ../shared/data/nerf_synthetic/lego --source runs/blob.neumesh --out docs/images

Regions are picked the way an artist would with a box select, here as boxes in each scene's
coordinates plus a colour test on the field's own decoded colour (lego's tracks are the dark brown
vertices in the tracks' box); the swap's source region is the cap of the source field around the
point its surface has in ``--source-dir`` from its centre (``--source-fraction`` of its vertices).  UVs for
the fill are planar projections (each region's two widest principal axes).  Writes edit_fill.png,
edit_swap.png and edit_paint.png (before on top, after below), and --results with the figures of
each edit.
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import neumesh_core as nm  # noqa: E402
from benchmarks._results import LOG_DIR, write_results  # noqa: E402
from neumesh_core.edit.fill import planar_uvs  # noqa: E402


def vertex_colours(field) -> np.ndarray:
    """(N,3) the field's colour at each vertex, seen along the vertex normal (for colour-based picks)."""
    v = field.rest_vertices
    n = field.rest_normals
    out = []
    with torch.no_grad():
        for s in range(0, len(v), 65536):
            x = v[s:s + 65536] + 0.3 * field.radius * n[s:s + 65536]
            _, rgb, _ = field.query(x, -n[s:s + 65536])
            out.append(rgb.clamp(0, 1))
    return torch.cat(out).numpy()


def lego_regions(field):
    v = field.rest_vertices.numpy()
    c = vertex_colours(field)
    bucket = np.nonzero((v[:, 1] < -0.62) & (v[:, 2] > 0.3))[0]
    box = (v[:, 2] > -0.36) & (v[:, 2] < 0.05) & (np.abs(v[:, 0]) > 0.36) & (v[:, 1] > -0.6) & (v[:, 1] < 0.75)
    brown = (c[:, 0] > c[:, 2] + 0.05) & (c.max(1) < 0.6)
    tracks = np.nonzero(box & brown)[0]
    plate = np.nonzero((v[:, 2] > -0.42) & (v[:, 2] < -0.3) & (np.abs(v[:, 0]) < 0.3) & (v[:, 1] > 0.3))[0]
    return {"bucket": bucket, "tracks": tracks, "plate": plate}


def best_views(field, region, cams, n=2):
    """Indices of the cameras that see the most of ``region`` head-on."""
    v = field.rest_vertices.numpy()[region]
    nrm = field.rest_normals.numpy()[region]
    score = []
    for i in range(len(cams)):
        c = cams.c2w[i][:3, 3]
        d = c[None] - v
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        score.append(float(np.clip((d * nrm).sum(1), 0, None).sum()))
    return list(np.argsort(score)[::-1][:n])


def render(field, cams, i):
    out = nm.render_camera(field, cams.K[i], cams.c2w[i], cams.width, cams.height)
    return np.clip(out.rgb, 0, 1)


def sheet(rows, path, labels=None):
    """Images (H,W,3) in rows -> one PNG; ``labels`` one string per row, drawn top-left."""
    from PIL import Image, ImageDraw

    h, w = rows[0][0].shape[:2]
    img = np.ones((h * len(rows), w * len(rows[0]), 3), np.float32)
    for r, row in enumerate(rows):
        for c, im in enumerate(row):
            img[r * h:(r + 1) * h, c * w:(c + 1) * w] = im
    pil = Image.fromarray((img * 255 + 0.5).astype(np.uint8))
    if labels:
        d = ImageDraw.Draw(pil)
        for r, text in enumerate(labels):
            d.text((6, r * h + 4), text, fill=(0, 0, 0))
    if pil.width > 900:   # small PNGs for the docs: 3/4 size, 256-colour palette
        pil = pil.resize((pil.width * 3 // 4, pil.height * 3 // 4), Image.LANCZOS)
    pil = pil.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    pil.save(path, optimize=True)
    print(f"wrote {path}")


def paint_layer_for(view_rgb: np.ndarray, opacity: np.ndarray) -> np.ndarray:
    """A wavy magenta stroke and a cyan dot over the object's middle (opaque pixels only)."""
    H, W = opacity.shape
    layer = np.zeros((H, W, 4), np.float32)
    ys, xs = np.nonzero(opacity > 0.95)
    cy, cx = int(np.median(ys)), int(np.median(xs))
    yy, xx = np.mgrid[0:H, 0:W]
    wave = np.abs(yy - (cy + 10 * np.sin((xx - cx) / 9.0))) < 3.5
    wave &= np.abs(xx - cx) < 70
    dot = (yy - (cy - 35)) ** 2 + (xx - cx) ** 2 < 12 ** 2
    for m, colour in ((wave, (0.9, 0.0, 0.7)), (dot, (0.0, 0.8, 0.9))):
        m = m & (opacity > 0.95)
        layer[m, :3] = colour
        layer[m, 3] = 1.0
    return layer


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lego", required=True, help="trained lego field")
    ap.add_argument("--lego-data", required=True, help="lego dataset (its val cameras are used)")
    ap.add_argument("--source", help="another trained field whose texture the bucket takes (the swap picture)")
    ap.add_argument("--source-dir", default="0,-1,0.3", help="where on the source to take it: a direction "
                                                           "from its centre (default 0,-1,0.3)")
    ap.add_argument("--source-fraction", type=float, default=0.15,
                    help="size of the source cap as a fraction of the source's vertices (default 0.15: a patch "
                         "whose pattern stays legible on the bucket; the built-in scene has only 10k vertices)")
    ap.add_argument("--results", default=os.path.join(LOG_DIR, "edit_pictures.json"),
                    help="figures of each edit (default benchmarks/results/log/edit_pictures.json)")
    ap.add_argument("--out", default="docs/images", help="output folder (default docs/images)")
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    figures = {}
    lego = nm.load_field(args.lego)
    lego.eval()
    cams = nm.load_scene(args.lego_data).split("val").cameras
    reg = lego_regions(lego)
    print({k: len(v) for k, v in reg.items()})

    # fill: the bucket takes the tracks' texture through planar UVs, tiled twice
    views = best_views(lego, reg["bucket"], cams)
    filled = copy.deepcopy(lego)
    v = lego.rest_vertices.numpy()
    rec = nm.fill_texture(filled, reg["bucket"], planar_uvs(v[reg["bucket"]]), filled, reg["tracks"],
                          planar_uvs(v[reg["tracks"]]), scale=2.0)
    figures["fill"] = {"target_vertices": int(len(rec.vertices)), "template_vertices": len(reg["tracks"]),
                       "seconds": rec.info["seconds"], "views": [int(i) for i in views]}
    sheet([[render(lego, cams, i) for i in views], [render(filled, cams, i) for i in views]],
          os.path.join(args.out, "edit_fill.png"), ["before", "fill: bucket <- tracks (UV, scale 2)"])

    # swap: the bucket takes the texture of a part of another field (another decoder)
    if args.source:
        src = nm.load_field(args.source)
        src.eval()
        sv = src.rest_vertices.numpy().astype(np.float64)
        direction = np.array([float(x) for x in args.source_dir.split(",")])
        direction /= np.linalg.norm(direction)
        c = sv.mean(0)
        tip = sv[np.argmax((sv - c) @ direction)]
        n_cap = max(4, min(len(reg["bucket"]), int(args.source_fraction * len(sv))))
        cap = np.argsort(np.linalg.norm(sv - tip, axis=1))[:n_cap]
        swapped = copy.deepcopy(lego)
        srec = nm.swap_texture(swapped, reg["bucket"], src, cap)
        bad = copy.deepcopy(swapped)
        with torch.no_grad():     # the same codes decoded by lego's own decoder
            bad.decoder_id.zero_()
        figures["swap"] = {k: srec.info[k] for k in ("residual_rigid", "residual", "scale", "align_s",
                                                       "nonrigid_s", "transfer_s", "seconds")}
        figures["swap"].update(target_vertices=int(len(srec.vertices)), source=args.source,
                               decoders=swapped.num_decoders)
        sheet([[render(lego, cams, i) for i in views], [render(swapped, cams, i) for i in views],
               [render(bad, cams, i) for i in views]],
              os.path.join(args.out, "edit_swap.png"),
              ["before", "swap: bucket <- another field (its decoder travels)", "the same codes on lego's decoder"])

    # paint on one view, seen from two others
    pv = best_views(lego, reg["bucket"], cams, n=1)[0]
    K, c2w, W, H = cams.K[pv], cams.c2w[pv], cams.width, cams.height
    base = nm.render_camera(lego, K, c2w, W, H)
    layer = paint_layer_for(base.rgb, base.opacity)
    painted = copy.deepcopy(lego)
    prec = nm.paint_texture(painted, K, c2w, W, H, layer)
    order = np.argsort([np.linalg.norm(cams.c2w[i][:3, 3] - c2w[:3, 3]) for i in range(len(cams))])
    novel = [int(order[3]), int(order[8])]
    shown = np.clip(base.rgb * (1 - layer[..., 3:]) + layer[..., :3] * layer[..., 3:], 0, 1)
    figures["paint"] = {k: prec.info[k] for k in ("painted_pixels", "affected_vertices", "ring_pixels",
                                                   "render_s", "surface_s", "weights_s", "solve_s", "seconds")}
    figures["paint"]["views"] = {"painted": int(pv), "novel": novel}
    sheet([[shown] + [render(lego, cams, i) for i in novel],
           [render(painted, cams, pv)] + [render(painted, cams, i) for i in novel]],
          os.path.join(args.out, "edit_paint.png"),
          ["the painted layer (left) and two other views, before", "after: the field, in all three views"])
    figures["lego_field"] = args.lego
    path = os.path.abspath(args.results)
    write_results(figures, os.path.basename(path), os.path.dirname(path), default=float)
    print(json.dumps(figures, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
