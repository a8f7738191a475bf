"""Scaffold of a real capture without masks: how much of the object the held-out photos see
lies within the field's reach of the scaffold.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_real_scaffold.py --data ../shared/data/real/fox \
        --sparse OUT/poses --field FIELD.neumesh [--scaffold SCAFFOLD.ply] [--downscale 4] [--name fox]

Without masks there is no silhouette to compare with (``bench_scaffold.py``'s IoU), so the reference is
independent of the scaffold: the sparse points of a COLMAP model of the same photos (``neumesh poses``),
moved onto the capture's cameras by a similarity (Umeyama on the camera centres shared by name). For
every held-out photo (every 8th), the points its own keypoints triangulated (the point's track names
that photo) that lie inside the field's object box are the object that photo sees; **coverage** is the
fraction of them within the field's query radius of a scaffold vertex (farther, the field holds nothing
there: K nearest vertices within the radius).  Also the distance percentiles in radii, and the same over
all points in the box.  Writes benchmarks/results/real_scaffold_<name>.json.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from benchmarks._results import write_results  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="/work/shared/data/real/fox")
    ap.add_argument("--sparse", required=True, help="a COLMAP model folder of the same photos (neumesh poses --out)")
    ap.add_argument("--field", required=True, help="the trained field (its box, radius and, without --scaffold, "
                                                   "its scaffold's vertices)")
    ap.add_argument("--scaffold", default=None, help="a scaffold .ply (default: the field's rest vertices)")
    ap.add_argument("--downscale", type=float, default=4)
    ap.add_argument("--name", default=None)
    args = ap.parse_args(argv)

    import pycolmap
    from scipy.spatial import cKDTree

    import neumesh_core as nm
    from neumesh_core.data.colmap import find_model, read_colmap
    from neumesh_core.edit.align import umeyama

    scene = nm.load_scene(args.data, downscale=args.downscale)
    field = nm.load_field(args.field)
    box = getattr(field, "object_box", None)
    if box is None:
        raise SystemExit(f"{args.field} has no object box (a field of a capture without masks has one)")
    radius = float(field.config.radius)
    verts = (nm.load_mesh(args.scaffold).vertices if args.scaffold
             else field.rest_vertices.detach().cpu().numpy()).astype(np.float64)

    # the reference model, moved onto the loaded scene's cameras (same photo names)
    est = read_colmap(args.sparse)
    names, c2w = [], []
    for split in ("train", "val"):
        s = scene.split(split)
        names += [os.path.basename(n) for n in s.names]
        c2w.append(s.cameras.c2w)
    c2w = np.concatenate(c2w)
    by_name = {n: i for i, n in enumerate(names)}
    pairs = [(i, by_name[os.path.basename(n)]) for i, n in enumerate(est.names) if os.path.basename(n) in by_name]
    if len(pairs) < 3:
        raise SystemExit(f"{args.sparse} and {args.data} share {len(pairs)} photo names; at least 3 are needed")
    ei, ri = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
    sim = umeyama(est.c2w[ei, :3, 3], c2w[ri, :3, 3], with_scale=True)
    resid = np.linalg.norm(sim.apply(est.c2w[ei, :3, 3]) - c2w[ri, :3, 3], axis=1)
    rig = np.linalg.norm(c2w[:, :3, 3] - c2w[:, :3, 3].mean(0), axis=1).mean()

    rec = pycolmap.Reconstruction(find_model(args.sparse))
    img_name = {iid: os.path.basename(im.name) for iid, im in rec.images.items()}
    pid = list(rec.point3D_ids())
    xyz = sim.apply(np.array([rec.points3D[p].xyz for p in pid], np.float64))
    seen_by = [{img_name[el.image_id] for el in rec.points3D[p].track.elements} for p in pid]
    inside = box.contains(xyz)
    dist, _ = cKDTree(verts).query(xyz[inside])
    d_in = dist / radius

    def stats(d):
        return {"points": int(d.size), "coverage": float((d <= 1.0).mean()) if d.size else None,
                "distance_radii_p50": float(np.percentile(d, 50)) if d.size else None,
                "distance_radii_p95": float(np.percentile(d, 95)) if d.size else None}

    idx_inside = np.flatnonzero(inside)
    views = []
    for n in scene.split("val").names:
        b = os.path.basename(n)
        m = np.array([b in seen_by[i] for i in idx_inside], bool)
        views.append(dict(stats(d_in[m]), view=b))
    valid = [v for v in views if v["points"]]
    res = {"data": os.path.abspath(args.data), "sparse": os.path.abspath(args.sparse),
           "field": os.path.abspath(args.field), "scaffold_vertices": int(len(verts)), "radius": radius,
           "alignment": {"shared_photos": len(pairs), "scale": float(sim.scale),
                         "centre_residual_rel_median": float(np.median(resid) / rig)},
           "points_total": len(pid), "points_in_box": int(inside.sum()),
           "all_in_box": stats(d_in), "held_out_views": views,
           "held_out_mean_coverage": float(np.mean([v["coverage"] for v in valid])) if valid else None}
    print(f"{len(pid)} sparse points, {int(inside.sum())} in the box; coverage within the radius "
          f"({radius:.4f}): all {res['all_in_box']['coverage']:.3f}, held-out views mean "
          f"{res['held_out_mean_coverage']:.3f} ({', '.join(str(v['points']) for v in views)} points)")
    name = args.name or os.path.basename(os.path.normpath(args.data))
    write_results(res, f"real_scaffold_{name}.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
