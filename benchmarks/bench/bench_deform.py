"""Deformation fidelity against ground truth: a built-in-scene field, deformed, against the mesh tracer.

    python benchmarks/bench/bench_deform.py --field runs/blob.neumesh  # a field of the built-in scene
    python benchmarks/bench/bench_deform.py                             # runs/blob.neumesh if present,
                                                                        # else trains --steps and saves it

Each deformation of ``neumesh_core.data.deformations.DEFORMATIONS`` (bend 35/70/140 deg, twist 90 deg,
stretch 1.3x/2x and squash 0.7x along z, two-bone creases with smooth weights: 45 deg blended over most
of the body, 60 deg with a narrow blend) is applied to
the field's rest vertices (``field.set_vertices``) and to the mesh that the ground truth traces
(``neumesh_core.data.mesh_truth.render_mesh_truth``: the rest-pose appearance carried with the
surface, view direction rotated into the rest pose).  Each is rendered from ``--views`` cameras at
``--size``^2 and scored (PSNR, SSIM) against its truth, beside the undeformed figure (the same field
and cameras against the mesh truth of the rest pose).  Writes benchmarks/results/log/deform_<name>.json
and, with ``--picture``, a sheet of the worst deformations (field vs truth).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
import neumesh_core as nm  # noqa: E402
from neumesh_core.data.deformations import DEFORMATIONS, inverted_fraction  # noqa: E402
from neumesh_core.data.mesh_truth import render_mesh_truth  # noqa: E402
from neumesh_core.data.synthetic import CAMERA_ANGLE_X, look_at_opencv, surface_radius  # noqa: E402
from neumesh_core.metrics import masked_psnr, psnr, ssim  # noqa: E402
from benchmarks._results import add_options, use_threads, write_results  # noqa: E402

# (azimuth, elevation) in degrees: four views around the blob, none a training view
VIEWS = [(-60.0, 20.0), (30.0, -10.0), (120.0, 35.0), (210.0, 5.0), (-150.0, -40.0), (75.0, 60.0)]


def cameras(n: int, size: int, radius: float = 4.0):
    K = nm.intrinsics_from_fov(CAMERA_ANGLE_X, size, size)
    out = []
    for az, el in VIEWS[:n]:
        a, e = math.radians(az), math.radians(el)
        pos = radius * np.array([math.cos(a) * math.cos(e), math.sin(a) * math.cos(e), math.sin(e)])
        out.append((K, look_at_opencv(pos)))
    return out


def check_builtin(field) -> None:
    rv = field.rest_vertices.cpu().numpy().astype(np.float64)
    off = np.abs(np.linalg.norm(rv, axis=1) - surface_radius(rv)).max()
    if off > 1e-4:
        raise SystemExit(f"the field's rest vertices are not on the built-in scene's surface (off by {off:.3g}): "
                         "the ground truth exists only for fields of the built-in scene")


def score(field, fn, cams, size: int, keep_images: bool = False) -> dict:
    """Render the field deformed by ``fn`` (None: rest pose) and its truth from ``cams``."""
    rest = field.rest_vertices.cpu().numpy().astype(np.float64)
    faces = field.faces.cpu().numpy()
    v = rest if fn is None else fn(rest)
    field.set_vertices(v.astype(np.float32))
    ps, fg, ss, imgs = [], [], [], []
    t0 = time.perf_counter()
    try:
        for K, c2w in cams:
            out = nm.render_camera(field, K, c2w.astype(np.float32), size, size, background=(1, 1, 1))
            pred = np.clip(out.rgb, 0, 1)
            gt, alpha = render_mesh_truth(K, c2w, size, size, v, faces, rest_vertices=rest)
            ps.append(psnr(pred, gt))
            fg.append(masked_psnr(pred, gt, np.maximum(alpha, out.opacity)))
            ss.append(ssim(pred, gt))
            if keep_images:
                imgs.append((pred, gt))
    finally:
        field.set_vertices(rest.astype(np.float32))
    res = {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "psnr_fg": float(np.mean(fg)),
           "psnr_views": [round(p, 3) for p in ps], "psnr_fg_views": [round(p, 3) for p in fg],
           "ssim_views": [round(s, 4) for s in ss], "seconds": round(time.perf_counter() - t0, 2)}
    if keep_images:
        res["images"] = imgs
    return res


def picture(rows, path: str) -> None:
    """rows: [(label, pred, gt)] -> one PNG, field (top) over truth (bottom) per column."""
    from PIL import Image, ImageDraw

    h, w = rows[0][1].shape[:2]
    pad, cap = 4, 16
    sheet = Image.new("RGB", (len(rows) * (w + pad) + pad, 2 * (h + cap) + pad), "white")
    draw = ImageDraw.Draw(sheet)
    for i, (label, pred, gt) in enumerate(rows):
        x = pad + i * (w + pad)
        for j, (img, name) in enumerate(((pred, "field"), (gt, "truth"))):
            y = j * (h + cap)
            sheet.paste(Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)), (x, y + cap))
            draw.text((x + 2, y + 2), f"{label}: {name}", fill=(0, 0, 0))
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    sheet.save(path)
    print(f"wrote {path}")


def trained_field(path: str, steps: int):
    if os.path.exists(path):
        return nm.load_field(path), False
    scene = nm.load_scene(nm.default_scene_dir())
    field = nm.create_field(nm.load_mesh(scene.mesh_path), nm.FieldConfig())
    print(f"training {steps} steps on the built-in scene...", file=sys.stderr)
    nm.train(field, scene, nm.TrainConfig(steps=steps))
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    nm.save_field(field, path)
    return field, True


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "field", "name", field=dict(default=os.path.join(ROOT, "runs", "blob.neumesh"),
                help="a field of the built-in scene (trained with --steps and saved there if missing)"),
                name=dict(default="blob", help="results name (default blob)"))
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--only", nargs="*", default=None, help="deformation names (default: all)")
    ap.add_argument("--picture", default=None, help="PNG of the worst deformations (field vs truth)")
    ap.add_argument("--worst", type=int, default=4)
    add_options(ap, "threads", "results_dir", threads=dict(default=max(1, int(os.environ.get("OMP_NUM_THREADS", "1"))),
                                                           help="torch threads (default: OMP_NUM_THREADS, else 1)"))
    args = ap.parse_args(argv)
    use_threads(args.threads)
    field, trained = trained_field(args.field, args.steps)
    check_builtin(field)
    cams = cameras(args.views, args.size)
    keep = args.picture is not None
    base = score(field, None, cams, args.size, keep)
    print(f"{'undeformed':12s} PSNR {base['psnr']:6.2f}  SSIM {base['ssim']:.4f}  fg PSNR {base['psnr_fg']:6.2f}")
    rows = {}
    for name, fn in DEFORMATIONS.items():
        if args.only and name not in args.only:
            continue
        r = score(field, fn, cams, args.size, keep)
        r["drop_db"] = base["psnr"] - r["psnr"]
        r["drop_fg_db"] = base["psnr_fg"] - r["psnr_fg"]
        r["inverted_fraction"] = round(inverted_fraction(fn, field.rest_vertices.cpu().numpy(),
                                                         field.faces.cpu().numpy()), 4)
        rows[name] = r
        print(f"{name:12s} PSNR {r['psnr']:6.2f}  SSIM {r['ssim']:.4f}  drop {r['drop_db']:5.2f} dB  "
              f"fg PSNR {r['psnr_fg']:6.2f} drop {r['drop_fg_db']:5.2f} dB  inverted {r['inverted_fraction']:.3f}  "
              f"views {r['psnr_views']}")
    if keep:
        worst = sorted(rows, key=lambda n: rows[n]["psnr"])[: args.worst]
        sel = [("undeformed", *base["images"][0])]
        for n in worst:
            i = int(np.argmin(rows[n]["psnr_views"]))
            sel.append((f"{n} {rows[n]['psnr_views'][i]:.1f}dB", *rows[n]["images"][i]))
        picture(sel, args.picture)
    for r in [base, *rows.values()]:
        r.pop("images", None)
    result = {
        "field": os.path.relpath(args.field, ROOT) if os.path.abspath(args.field).startswith(ROOT) else args.field,
        "trained_here": trained, "interpolation": field.config.interpolation,
        "vertices": int(field.num_vertices), "size": args.size, "views": VIEWS[: args.views],
        "truth": "mesh tracer: rest-pose appearance carried with the surface, view direction rotated "
                 "into the rest pose by each triangle's rest->deformed rotation",
        "undeformed": base, "deformed": rows,
    }
    write_results(result, f"deform_{args.name}.json", args.results_dir)
    return result


if __name__ == "__main__":
    main()
