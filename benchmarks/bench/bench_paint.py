"""Texture painting speed and quality on a trained field: a stroke of ~5,000 pixels on one 400^2 view.

    python benchmarks/bench/bench_paint.py --field runs/lego/field.neumesh --data ../shared/data/nerf_synthetic/lego
    python benchmarks/bench/bench_paint.py                               # the built-in scene, trained briefly

The stroke is a band of rows through the middle of the object in the chosen view, cut to the object's
pixels (opacity > 0.95) and to ``--pixels`` pixels, painted in a saturated colour.  Prints the apply
time and its split (render: the painted pixels and the box around them; surface: the affected
vertices; weights: how the box's rays depend on their modification colours; solve), the PSNR inside
the stroke afterwards, how many pixels outside the stroke changed, how wide the stroke's edge is, and
writes benchmarks/results/log/paint_<name>_atlas.json (``--target atlas``, the default: texel paint in a
paint atlas, made first and timed apart) or paint_<name>.json (``--target colours``: the per-vertex
modification colours).  ``--figure``: the stroke before/after/another view, and a thin line with
lettering painted both ways.
"""
from __future__ import annotations

import argparse
import copy
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
import neumesh_core as nm  # noqa: E402
from neumesh_core.metrics import psnr  # noqa: E402
from benchmarks._results import add_options, use_threads, write_results  # noqa: E402


def stroke_mask(opacity: np.ndarray, pixels: int) -> np.ndarray:
    """A horizontal band through the object's middle rows, on opaque pixels, about ``pixels`` big."""
    solid = opacity > 0.95
    rows = np.nonzero(solid.any(1))[0]
    mid = int(np.median(rows))
    mask = np.zeros_like(solid)
    half = 1
    while True:
        band = np.zeros_like(solid)
        band[max(0, mid - half):mid + half + 1] = True
        mask = band & solid
        if mask.sum() >= pixels or half > opacity.shape[0]:
            break
        half += 1
    ys, xs = np.nonzero(mask)
    keep = np.argsort(np.abs(xs - np.median(xs)), kind="stable")[:pixels]   # the middle of the band
    out = np.zeros_like(mask)
    out[ys[keep], xs[keep]] = True
    return out


def edge_width(before: np.ndarray, after: np.ndarray, mask: np.ndarray, colour: np.ndarray) -> dict:
    """How sharp the stroke's edge is: each pixel's painted fraction f (the change along the
    render -> paint colour direction), the pixels with 0.1 < f < 0.9 within 3 px of the stroke's
    boundary, per boundary pixel (a stroke pixel with a 4-neighbour outside): ~0 for an edge as sharp
    as the painted pixels, ~the blur radius for a soft one."""
    from scipy.ndimage import binary_dilation, binary_erosion

    target = np.broadcast_to(colour, before.shape)
    d = target - before
    f = ((after - before) * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-6)
    boundary = mask & ~binary_erosion(mask)
    band = binary_dilation(boundary, iterations=3)
    partial = band & (f > 0.1) & (f < 0.9) & ((d * d).sum(-1) > 0.01)
    nb = int(boundary.sum())
    return {"boundary_pixels": nb, "partial_pixels": int(partial.sum()),
            "width_px": float(partial.sum()) / max(1, nb)}


def lettering_layer(W: int, H: int, opacity: np.ndarray, colour) -> np.ndarray:
    """A thin one-pixel line and the word NeuMesh (OpenCV's Hershey font, 1-2 px strokes) over the
    object's middle, as an RGBA layer."""
    import cv2

    solid = opacity > 0.95
    ys, xs = np.nonzero(solid)
    cy, cx = int(np.median(ys)), int(np.median(xs))
    m = np.zeros((H, W), np.uint8)
    cv2.line(m, (cx - W // 6, cy - H // 12), (cx + W // 6, cy - H // 12), 255, 1)
    scale = W / 600.0
    (tw, th), _ = cv2.getTextSize("NeuMesh", cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    cv2.putText(m, "NeuMesh", (cx - tw // 2, cy + th // 2 + H // 40), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, 1,
                cv2.LINE_8)
    mask = (m > 0) & solid
    layer = np.zeros((H, W, 4), np.float32)
    layer[mask, :3] = colour
    layer[mask, 3] = 1.0
    return layer


def figure(args, field, edited, K, c2w, W, H, before, after, cams) -> dict:
    """Row 1: before | the stroke painted | another view.  Row 2: a thin line and lettering painted on a
    copy of the field into a paint atlas: the painted view | another view | the painted view zoomed 3x;
    row 3: the same painted into the per-vertex colours."""
    n = len(cams.c2w)
    painted = next(k for k in range(n) if np.allclose(cams.c2w[k], c2w))
    other = (painted + 1) % n
    K2, c22 = cams.K[other], cams.c2w[other]
    row1 = [before.rgb, after.rgb, nm.render_camera(edited, K2, c22, W, H).rgb]
    colour = np.array([0.05, 0.05, 0.05], np.float32)
    layer = lettering_layer(W, H, before.opacity, colour)
    out = {"lettering_pixels": int((layer[..., 3] > 0).sum())}
    rows = [np.concatenate(row1, 1)]
    for target in ("atlas", "colours"):
        f = copy.deepcopy(field)
        if target == "atlas":
            from neumesh_core.edit.paint import create_paint_atlas

            create_paint_atlas(f, resolution=args.atlas_resolution or (4096 if len(f.faces) > 50_000 else 2048),
                               method=args.atlas_method)
        t = time.perf_counter()
        nm.paint_texture(f, K, c2w, W, H, layer, target=target, surface=before if target == "atlas" else None)
        out[f"lettering_{target}_s"] = time.perf_counter() - t
        a = nm.render_camera(f, K, c2w, W, H).rgb
        m = layer[..., 3] > 0
        out[f"lettering_{target}_psnr_db"] = float(psnr(np.clip(a[m], 0, 1),
                                                        np.broadcast_to(colour, (int(m.sum()), 3))))
        m_ys, m_xs = np.nonzero(m)
        cy, cx = int(np.median(m_ys)), int(np.median(m_xs))
        y0, x0 = max(0, min(H - H // 3, cy - H // 6)), max(0, min(W - W // 3, cx - W // 6))
        zoom = np.repeat(np.repeat(a[y0:y0 + H // 3, x0:x0 + W // 3], 3, 0), 3, 1)[:H, :W]
        zoom = np.pad(zoom, ((0, H - zoom.shape[0]), (0, W - zoom.shape[1]), (0, 0)), constant_values=1.0)
        rows.append(np.concatenate([a, nm.render_camera(f, K2, c22, W, H).rgb, zoom], 1))
    nm.save_image(args.figure, np.clip(np.concatenate(rows, 0), 0, 1))
    print(f"wrote {args.figure}: row 1 stroke (before | after | other view); rows 2-3 line + lettering "
          f"(atlas {out['lettering_atlas_psnr_db']:.1f} dB, vertex colours {out['lettering_colours_psnr_db']:.1f} dB)")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "field", "data", "threads", "name", "results_dir",
                field=dict(help="trained field (.neumesh); default: the built-in scene trained 1500 steps"),
                data=dict(help="dataset whose camera is painted on (default: a turntable view)"))
    ap.add_argument("--split", default="val")
    ap.add_argument("--view", type=int, default=0)
    ap.add_argument("--resolution", type=int, default=400, help="view size without --data (square)")
    ap.add_argument("--pixels", type=int, default=5000, help="stroke size in pixels (default 5,000)")
    ap.add_argument("--colour", default="1,0,0.8", help="paint colour r,g,b in [0,1] (default magenta)")
    ap.add_argument("--target", choices=("atlas", "colours"), default="atlas",
                    help="paint into the texel paint atlas (default) or the per-vertex modification colours")
    ap.add_argument("--atlas-resolution", type=int, default=None,
                    help="paint atlas size (default 2048; 4096 for a grid atlas of a big scaffold)")
    ap.add_argument("--atlas-method", default="auto", choices=("auto", "xatlas", "grid"))
    ap.add_argument("--no-surface", action="store_true",
                    help="atlas: render the painted pixels again instead of passing the render painted on")
    ap.add_argument("--figure", help="write before | after | another view, and a thin line + lettering, here (PNG)")
    args = ap.parse_args(argv)
    use_threads(args.threads or None)
    if args.field:
        field = nm.load_field(args.field)
        name = args.name or os.path.basename(os.path.dirname(os.path.abspath(args.field)))
    else:
        scene = nm.load_scene(nm.default_scene_dir())
        field = nm.create_field(nm.load_mesh(scene.mesh_path))
        nm.train(field, scene, nm.TrainConfig(steps=1500))
        name = args.name or "default_scene"
    field.eval()
    if args.data:
        cams = nm.load_scene(args.data).split(args.split).cameras
        K, c2w, W, H = cams.K[args.view], cams.c2w[args.view], cams.width, cams.height
    else:
        from neumesh_core.cli import turntable_cameras

        bb = field.grid.aabb.cpu().numpy()
        cams = turntable_cameras(bb.mean(0), float(np.linalg.norm(bb[1] - bb[0])) * 1.1, 8, args.resolution,
                                 args.resolution)
        K, c2w, W, H = cams.K[1], cams.c2w[1], cams.width, cams.height
    before = nm.render_camera(field, K, c2w, W, H)
    mask = stroke_mask(before.opacity, args.pixels)
    colour = np.array([float(x) for x in args.colour.split(",")], np.float32)
    layer = np.zeros((H, W, 4), np.float32)
    layer[mask, :3] = colour
    layer[mask, 3] = 1.0
    edited = copy.deepcopy(field)
    atlas_s, atlas_info = 0.0, None
    if args.target == "atlas":
        from neumesh_core.edit.paint import create_paint_atlas

        res = args.atlas_resolution or (4096 if args.atlas_method == "grid" or
                                        (args.atlas_method == "auto" and len(field.faces) > 50_000) else 2048)
        t = time.perf_counter()
        atlas = create_paint_atlas(edited, resolution=res, method=args.atlas_method)
        atlas_s = time.perf_counter() - t
        atlas_info = {"source": atlas.source, "resolution": res, "cell_texels": atlas.cell, "seconds": atlas_s}
        print(f"paint atlas: {atlas.source}, {res}^2 texels, {atlas_s:.2f} s")
    t = time.perf_counter()
    load_before = os.getloadavg()
    surface = before if args.target == "atlas" and not args.no_surface else None
    rec = nm.paint_texture(edited, K, c2w, W, H, layer, target=args.target, surface=surface)
    apply_s = time.perf_counter() - t
    after = nm.render_camera(edited, K, c2w, W, H)
    p_in = float(psnr(np.clip(after.rgb[mask], 0, 1), np.broadcast_to(colour, (int(mask.sum()), 3))))
    delta = np.abs(after.rgb - before.rgb).max(-1)
    from scipy.ndimage import binary_dilation

    outside = ~binary_dilation(mask, iterations=2)
    i = rec.info
    edge = edge_width(before.rgb, after.rgb, mask, colour)
    print(f"{name}: {field.num_vertices:,} vertices, {W}x{H} view, stroke {int(mask.sum())} px")
    if args.target == "atlas":
        split = {k: i[k] for k in ("render_s", "surface_s", "texels_s", "write_s")}
        if i.get("surface_given"):
            print("surface points from the render painted on (render_camera of this view): no render in apply")
        print(f"apply {apply_s:.2f} s: " + ", ".join(f"{k[:-2]} {v:.2f}" for k, v in split.items()) +
              f" ({i['painted_texels']:,} texels, {i['candidate_faces']:,} faces, {i['box_pixels']:,} box pixels)")
    else:
        split = {k: i[k] for k in ("render_s", "surface_s", "weights_s", "solve_s")}
        print(f"apply {apply_s:.2f} s: render {i['render_s']:.2f}, surface {i['surface_s']:.2f}, weights "
              f"{i['weights_s']:.2f}, solve {i['solve_s']:.2f} ({i['affected_vertices']:,} vertices, "
              f"{i['ring_pixels']:,} ring pixels, {i['box_pixels']:,} box pixels)")
    print(f"stroke edge: {edge['partial_pixels']} pixels between 10% and 90% painted along "
          f"{edge['boundary_pixels']} boundary pixels: {edge['width_px']:.2f} px wide")
    print(f"stroke PSNR {p_in:.2f} dB; pixels changed > 1/255 farther than 2 px from the stroke: "
          f"{int((delta[outside] > 1 / 255).sum())} (max {delta[outside].max():.4f})")
    result = {"field": args.field or "default scene (1500 steps)", "vertices": field.num_vertices,
              "view": {"data": args.data, "split": args.split, "index": args.view, "width": W, "height": H},
              "stroke_pixels": int(mask.sum()), "colour": colour.tolist(), "apply_s": apply_s,
              "target": args.target, "atlas": atlas_info, "split_s": split,
              "affected_vertices": i.get("affected_vertices"), "ring_pixels": i.get("ring_pixels"),
              "painted_texels": i.get("painted_texels"), "edge": edge,
              "stroke_psnr_db": p_in, "changed_outside_2px": int((delta[outside] > 1 / 255).sum()),
              "max_change_outside_2px": float(delta[outside].max()), "target_apply_s": 2.0,
              "target_stroke_psnr_db": 30.0,
              "surface_given": i.get("surface_given"),
              "machine": {"loadavg_before_apply": list(load_before),
                          "note": "2 cores shared by six developers' jobs: timings are upper bounds"}}
    if args.figure:
        result["figure"] = figure(args, field, edited, K, c2w, W, H, before, after, cams)
    # the per-vertex colours keep their file name (paint_<name>.json); texel paint: paint_<name>_atlas.json
    write_results(result, f"paint_{name}{'_atlas' if args.target == 'atlas' else ''}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
