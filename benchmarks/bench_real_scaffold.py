"""The scaffold of photos without masks: one surface where the photos see one, and the whole object.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_real_scaffold.py --data ../shared/data/real/fox \
        --scaffold OUT/scaffold.ply [--downscale 8] [--pictures DIR] [--name fox]
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/bench_real_scaffold.py --room [--pictures DIR]

Figures, all from the held-out photos' viewpoints (every 8th photo) and the capture's own sparse points:

* **layers**: of the pixels whose ray crosses the object box, the share whose ray crosses the scaffold
  more than twice (a single surface: at most in and out; a grid's iso-level of a room painted into the
  box: many), and the share it crosses at all;
* **object points**: the sparse points of the object (``data.frame.find_object``: all of them, those
  outside the box too) and their distance to the scaffold, in units of the box's diagonal: percentiles
  and the share within 1 % (the field reaches about that far from its vertices), and the share of them
  outside the box (the box cut the object there);
* **room scene** (``--room``): the built-in blob in a textured room, rendered without masks, has a true
  surface: the scaffold built as ``neumesh fit`` builds it (the box found the same way), and its
  distance to the truth both ways (accuracy: scaffold to truth; completeness: truth to scaffold).

``--pictures DIR``: per held-out view, the scaffold shaded (grey, lit from the camera) with the object
box's edges drawn in green and the object's sparse points that fall outside the box in red: our own
geometry only, no photo. Writes ``real_scaffold_<name>.json`` (benchmarks/results/log by default).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from benchmarks._results import add_options, use_threads, write_results  # noqa: E402

BOX_EDGES = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]


def box_corners(box) -> np.ndarray:
    s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
    return box.centre + (s * box.half_extents) @ np.asarray(box.rotation, np.float64).T


def box_pixels(box, K, c2w, width, height) -> np.ndarray:
    """(H,W) bool: the pixels whose ray crosses the box (its twelve triangles rasterised)."""
    from neumesh_core.render.raster import project_mesh, raster_triangles

    c = box_corners(box)
    quads = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    faces = np.array([t for q in quads for t in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))], np.int64)
    z, pix, fi = project_mesh(c, faces, K, c2w, 1e-6)
    out = np.zeros(width * height, bool)
    for _, px, _ in raster_triangles(pix[faces[fi]], width, height, eps=1e-9):
        out[px] = True
    return out.reshape(height, width)


def crossings_and_shading(vertices, faces, K, c2w, width, height):
    """Per pixel: how many scaffold triangles its centre ray crosses (in front of the camera), and the
    nearest triangle's |cos| to the ray (0 where nothing), for the shaded picture."""
    from neumesh_core.render.raster import project_mesh, raster_triangles

    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    z, pix, fi = project_mesh(V, F, K, c2w, 1e-6)
    count = np.zeros(width * height, np.int64)
    best = np.full(width * height, np.inf)
    best_face = np.full(width * height, -1, np.int64)
    for ids, px, bary in raster_triangles(pix[F[fi]], width, height, eps=0.0):
        count += np.bincount(px, minlength=width * height)
        depth = 1.0 / (bary / z[F[fi[ids]]]).sum(1)
        order = np.lexsort((depth, px))   # per pixel, nearest first
        px_s, d_s, f_s = px[order], depth[order], fi[ids][order]
        first = np.r_[True, px_s[1:] != px_s[:-1]]
        px_s, d_s, f_s = px_s[first], d_s[first], f_s[first]
        closer = d_s < best[px_s]
        best[px_s[closer]] = d_s[closer]
        best_face[px_s[closer]] = f_s[closer]
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    shade = np.zeros(width * height)
    hit = best_face >= 0
    if hit.any():
        ys, xs = np.divmod(np.nonzero(hit)[0], width)
        rays = np.stack([(xs + 0.5 - K[0, 2]) / K[0, 0], (ys + 0.5 - K[1, 2]) / K[1, 1], np.ones(len(xs))], 1)
        rays = rays @ np.asarray(c2w, np.float64)[:3, :3].T
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        shade[hit] = np.abs((n[best_face[hit]] * rays).sum(1))
    return count.reshape(height, width), shade.reshape(height, width)


def _draw_line(img, a, b, colour):
    n = int(max(abs(b[0] - a[0]), abs(b[1] - a[1]), 1)) * 2
    t = np.linspace(0, 1, n)
    xs = np.round(a[0] + (b[0] - a[0]) * t).astype(int)
    ys = np.round(a[1] + (b[1] - a[1]) * t).astype(int)
    ok = (xs >= 0) & (xs < img.shape[1]) & (ys >= 0) & (ys < img.shape[0])
    img[ys[ok], xs[ok]] = colour


def picture(shade, box, points_outside, K, c2w) -> np.ndarray:
    """The shaded scaffold (grey) with the box's edges (green) and the object's points outside it (red)."""
    img = np.repeat((0.15 + 0.8 * shade)[..., None], 3, axis=2)
    img[shade == 0] = 0.05
    w2c = np.linalg.inv(np.asarray(c2w, np.float64))

    def project(p):
        cam = np.asarray(p, np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
        return (cam @ np.asarray(K, np.float64).T)[:, :2] / np.maximum(cam[:, 2:3], 1e-9), cam[:, 2]

    pc, zc = project(box_corners(box))
    for i, j in BOX_EDGES:
        if zc[i] > 0 and zc[j] > 0:
            _draw_line(img, pc[i], pc[j], (0.1, 0.9, 0.2))
    if len(points_outside):
        pp, zp = project(points_outside)
        for (x, y), z in zip(pp, zp):
            if z > 0 and 0 <= x < img.shape[1] and 0 <= y < img.shape[0]:
                img[max(int(y) - 1, 0):int(y) + 2, max(int(x) - 1, 0):int(x) + 2] = (0.95, 0.1, 0.1)
    return (img.clip(0, 1) * 255 + 0.5).astype(np.uint8)


def measure(scene, mesh, box, object_points, pictures=None, name="scene"):
    """The figures of the module docstring for ``mesh`` (world space) in ``scene``'s held-out views."""
    from scipy.spatial import cKDTree

    from neumesh_core.imageio import save_image

    val = scene.split("val")
    cams = val.cameras
    diag = float(2.0 * np.linalg.norm(box.half_extents))
    per_view, layered, crossed, boxed = [], 0, 0, 0
    outside = object_points[~box.contains(object_points)] if len(object_points) else object_points
    for i in range(len(cams)):
        K, c2w = cams.K[i].astype(np.float64), cams.c2w[i].astype(np.float64)
        inbox = box_pixels(box, K, c2w, cams.width, cams.height)
        count, shade = crossings_and_shading(mesh.vertices, mesh.faces, K, c2w, cams.width, cams.height)
        n_box = int(inbox.sum())
        more = int(((count > 2) & inbox).sum())
        some = int(((count > 0) & inbox).sum())
        per_view.append({"view": val.names[i] if val.names else i, "box_pixels": n_box,
                         "more_than_two": more / max(n_box, 1), "crossed": some / max(n_box, 1)})
        layered, crossed, boxed = layered + more, crossed + some, boxed + n_box
        if pictures:
            os.makedirs(pictures, exist_ok=True)
            stem = os.path.splitext(os.path.basename(str(per_view[-1]["view"])))[0]
            save_image(os.path.join(pictures, f"{name}_{stem}.png"), picture(shade, box, outside, K, c2w))
    out = {"held_out_views": len(cams), "box_pixels": boxed,
           "more_than_two_crossings": layered / max(boxed, 1), "crossed": crossed / max(boxed, 1),
           "per_view": per_view, "box_diagonal": diag, "scaffold_vertices": int(len(mesh.vertices))}
    if len(object_points):
        d, _ = cKDTree(np.asarray(mesh.vertices, np.float64)).query(np.asarray(object_points, np.float64))
        out["object_points"] = {"count": int(len(object_points)), "outside_box": int(len(outside)),
                                "distance_over_diagonal_p50_p90_p99": [float(x) for x in
                                                                       np.percentile(d / diag, [50, 90, 99])],
                                "within_1pc_of_diagonal": float((d / diag <= 0.01).mean())}
    return out


def room_figures(args) -> dict:
    """The built-in room scene: the scaffold built as `neumesh fit` builds it, against the true surface."""
    from scipy.spatial import cKDTree

    from neumesh_core.data.synthetic import default_mesh
    from neumesh_core.data.synthetic.room import make_room_scene
    from neumesh_core.fit import capture_box
    from neumesh_core.reconstruct.build import ScaffoldConfig, build_scaffold

    scene, _ = make_room_scene(resolution=args.room_resolution, n_train=24, n_val=3)
    truth = default_mesh(subdiv=5)   # the blob's true surface
    box = capture_box(scene, log=print)
    t0 = time.perf_counter()
    cfg = ScaffoldConfig(method="auto", target_vertices=args.vertices,
                         density_resolutions=tuple(args.room_density), density_iters=tuple(args.room_iters))
    mesh, rep = build_scaffold(scene, cfg, box=box, log=print)
    seconds = time.perf_counter() - t0
    T = np.asarray(truth.vertices, np.float64)
    S = np.asarray(mesh.vertices, np.float64)
    acc, _ = cKDTree(T).query(S)
    comp, _ = cKDTree(S).query(T)
    diag = float(2.0 * np.linalg.norm(box.half_extents))
    out = measure(scene, mesh, box, np.zeros((0, 3)), args.pictures, "room")
    out.update({"seconds": seconds, "density_resolutions": list(args.room_density),
                "density_iters": list(args.room_iters), "room_resolution": args.room_resolution,
                "accuracy_over_diagonal_p50_p90": [float(x) for x in np.percentile(acc / diag, [50, 90])],
                "completeness_over_diagonal_p50_p90": [float(x) for x in np.percentile(comp / diag, [50, 90])],
                "true_surface_within_1pc": float((comp / diag <= 0.01).mean())})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "data", "threads", "name", "results_dir")
    ap.add_argument("--scaffold", default=None, help="the scaffold .ply to measure (neumesh scaffold/fit wrote it)")
    ap.add_argument("--box", default=None, metavar="CX,CY,CZ,SX,SY,SZ",
                    help="the object box (default: found as neumesh fit finds it)")
    ap.add_argument("--downscale", type=float, default=8, help="held-out photos' size for the layer count")
    ap.add_argument("--room", action="store_true", help="the built-in room scene instead of --data")
    ap.add_argument("--room-resolution", type=int, default=64)
    ap.add_argument("--vertices", type=int, default=20_000, help="--room: the scaffold's target vertices")
    ap.add_argument("--room-density", type=lambda t: [int(x) for x in t.split(",")], default=[48, 96],
                    help="--room: the density grid's cells per stage (neumesh fit: 64,128)")
    ap.add_argument("--room-iters", type=lambda t: [int(x) for x in t.split(",")], default=[300, 300],
                    help="--room: the density grid's iterations per stage")
    ap.add_argument("--pictures", default=None, help="folder for the shaded scaffold of each held-out view")
    args = ap.parse_args(argv)
    threads = use_threads(args.threads)

    import neumesh_core as nm
    from neumesh_core.data.frame import find_object, parse_box
    from neumesh_core.reconstruct.points import capture_points

    if args.room:
        result = {"scene": "built-in room", **room_figures(args)}
        name = args.name or "room"
    else:
        if not args.data or not args.scaffold:
            ap.error("--data and --scaffold (or --room)")
        scene = nm.load_scene(args.data, downscale=args.downscale)
        mesh = nm.load_mesh(args.scaffold)
        pts = capture_points(scene.capture)
        found = find_object(scene.split("train").cameras.c2w, pts)
        box = parse_box(args.box) if args.box else found.box
        result = {"data": os.path.abspath(args.data), "scaffold": os.path.abspath(args.scaffold),
                  "downscale": args.downscale, "box": {"centre": box.centre.tolist(),
                                                       "half_extents": box.half_extents.tolist()},
                  **measure(scene, mesh, box, pts[found.object_points], args.pictures,
                            args.name or os.path.basename(os.path.normpath(args.data)))}
        name = args.name or os.path.basename(os.path.normpath(args.data))
    result["threads"] = threads
    for k in ("more_than_two_crossings", "crossed"):
        print(f"{k}: {result[k]:.3f}")
    for k in ("object_points", "accuracy_over_diagonal_p50_p90", "completeness_over_diagonal_p50_p90",
              "true_surface_within_1pc"):
        if k in result:
            print(f"{k}: {result[k]}")
    write_results(result, f"real_scaffold_{name}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
