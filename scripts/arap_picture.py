"""docs/images/arap_lego.png: lego's bucket lifted by an ARAP handle, the body anchored.

    python scripts/arap_picture.py --field /work/runs/lego/field.neumesh

The bucket is picked by a box in lego's scaffold coordinates (the NeRF-synthetic lego: the arm reaches
towards -y, the bucket is its high end), the anchors are the body (y > -0.1) and the base plate
(z < -0.3); the arm between them bends.  The handle is lifted by ``--lift`` and tilted by ``--tilt``
degrees about its centre; ``nm.deform.arap`` solves from rest.  The field at rest (left) and deformed
(right) from one camera; the solve's figures go to benchmarks/results/log/arap_picture_lego.json.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
import neumesh_core as nm  # noqa: E402
from benchmarks._results import use_threads, write_results  # noqa: E402
from neumesh_core.data.synthetic import look_at_opencv  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", default="/work/runs/lego/field.neumesh")
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "images", "arap_lego.png"))
    ap.add_argument("--size", type=int, default=240)
    ap.add_argument("--lift", type=float, default=0.3)
    ap.add_argument("--tilt", type=float, default=-20.0)
    ap.add_argument("--cage", type=int, default=0, help="solve on a cage of this many vertices (0: full)")
    args = ap.parse_args(argv)
    use_threads(max(1, int(os.environ.get("OMP_NUM_THREADS", "1"))))
    field = nm.load_field(args.field)
    v = field.rest_vertices.numpy().astype(np.float64)
    y, z = v[:, 1], v[:, 2]
    handles = np.nonzero((y < -0.62) & (z > 0.42))[0]
    anchors = np.nonzero((y > -0.1) | (z < -0.3))[0]
    c = v[handles].mean(0)
    a = np.radians(args.tilt)
    R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = c - R @ c + np.array([0.0, 0.0, args.lift])
    t0 = time.perf_counter()
    res = nm.deform.arap(field, anchors, handles, M,
                         nm.deform.ArapConfig(iterations=30, cage_vertices=args.cage))
    solve_s = time.perf_counter() - t0
    print(f"{len(v)} vertices, {len(anchors)} anchors, {len(handles)} handles; ARAP {res.iterations} iterations "
          f"in {solve_s:.1f} s (incl. set_vertices)")
    K = nm.intrinsics_from_fov(0.69, args.size, args.size)
    c2w = look_at_opencv(np.array([3.2, -1.6, 1.6]), target=(0.0, -0.2, 0.2)).astype(np.float32)
    imgs = []
    for V in (v, res.vertices):
        field.set_vertices(V.astype(np.float32))
        out = nm.render_camera(field, K, c2w, args.size, args.size, background=(1, 1, 1))
        imgs.append(np.clip(out.rgb, 0, 1))
    field.reset_vertices()
    sheet = np.concatenate([imgs[0], np.ones((args.size, 6, 3)), imgs[1]], 1)
    nm.save_image(args.out, sheet)
    print(f"wrote {args.out}")
    write_results({"field": args.field, "vertices": int(len(v)), "anchors": int(len(anchors)),
                   "handles": int(len(handles)), "lift": args.lift, "tilt_deg": args.tilt, "cage": args.cage,
                   "iterations": int(res.iterations), "solve_and_set_vertices_s": round(solve_s, 2)},
                  "arap_picture_lego.json")


if __name__ == "__main__":
    main()
