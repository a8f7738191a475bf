"""`neumesh scaffold`: posed images -> mesh scaffold (.ply) + JSON report next to it.

``neumesh_core/cli/__init__.py`` calls :func:`add_commands` with its subparsers object.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

from ..reconstruct.build import ScaffoldConfig
from ..reconstruct.config import METHODS
from .common import Progress


def _positive_int(s: str) -> int:
    v = int(s)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {v}")
    return v


def _int_list(s: str) -> tuple:
    try:
        vals = tuple(int(x) for x in s.replace(" ", "").split(",") if x)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {s!r}") from exc
    if not vals or min(vals) <= 0:
        raise argparse.ArgumentTypeError(f"expected positive integers, got {s!r}")
    return vals


def add_scaffold_options(p: argparse.ArgumentParser) -> None:
    """Options shared by `scaffold` (and usable by `fit`)."""
    g = p.add_argument_group("scaffold")
    g.add_argument("--method", choices=list(METHODS), default="auto",
                   help="auto (default): hull+mvs when the data has masks/alpha, fusion when it has none; "
                        "fusion: a density grid fitted with a background model inside the object box, its "
                        "per-view depths fused into one surface (photos without masks); "
                        "hull: visual hull only (fastest, no concavities, needs masks); "
                        "hull+mvs: hull, then plane-sweep stereo carves concavities and one-sided depth "
                        "(textureless parts keep the hull); "
                        "hull+density: hull then a volume-rendered density grid (slower); density: "
                        "photometric only (needs the scene bounding box)")
    g.add_argument("--vertices", type=_positive_int, default=200_000,
                   help="target vertex count of the scaffold (default 200000; the paper uses 100k-300k; "
                        "reached within ~12%%; 0 keeps the marching-cubes count of the grid)")
    g.add_argument("--max-grid", type=_positive_int, default=None,
                   help="cap on the grid the mesh is re-extracted on to reach --vertices (about this^3 "
                        f"nodes; default {ScaffoldConfig.max_mesh_grid}; on DTU scan24, 640 gives ~2M vertices "
                        "at 3.2 GB peak); raise it for more vertices")
    g.add_argument("--max-faces", type=_positive_int, default=None,
                   help=f"refuse scaffolds with more faces than this (default {ScaffoldConfig.max_faces}; "
                        "about 2 faces per vertex)")
    g.add_argument("--resolution", type=int, default=256,
                   help="visual-hull grid cells along the longest side of the object box (default 256); "
                        "raise it for very thin parts, lower it for speed")
    g.add_argument("--tolerance", type=int, default=0,
                   help="views allowed to disagree that a point is inside the mask (default 0; raise it "
                        "for hand-made masks that cut off parts of the object in some views)")
    g.add_argument("--dilate", type=float, default=-1.0,
                   help="grow the hull by this many pixels to protect thin parts (default -1 = auto: "
                        "0.5 px at 400 px images)")
    g.add_argument("--min-view-fraction", type=float, default=0.6,
                   help="the cameras must share a volume that this fraction of the views sees (default 0.6)")
    g.add_argument("--reconstruct-view-fraction", type=float, default=0.1,
                   help="reconstruct points in frame in at least this fraction of the views (default 0.1; "
                        "close-up captures cut the object at the frame in most views)")
    g.add_argument("--iters", type=_int_list, default=(300, 300),
                   help="density-grid iterations per coarse-to-fine stage, comma separated (default "
                        "300,300; used by hull+density and density)")
    g.add_argument("--density-resolutions", type=_int_list, default=(64, 128),
                   help="density-grid cells along the longest side per stage (default 64,128)")
    g.add_argument("--iso-alpha", type=float, default=0.1,
                   help="density iso level as the opacity of one voxel (default 0.1; lower keeps more)")
    g.add_argument("--iou-views", type=int, default=0,
                   help="training views used for the silhouette IoU figure (default 0 = all)")
    g.add_argument("--no-metrics", action="store_true",
                   help="skip the silhouette IoU / Chamfer figures (saves time on big scenes)")


def config_from_args(args):
    caps = {k: v for k, v in (("max_mesh_grid", args.max_grid), ("max_faces", args.max_faces)) if v is not None}
    return ScaffoldConfig(
        method=args.method, target_vertices=args.vertices, hull_resolution=args.resolution,
        mask_tolerance=args.tolerance, hull_dilate_px=args.dilate, min_view_fraction=args.min_view_fraction,
        reconstruct_view_fraction=args.reconstruct_view_fraction,
        density_iters=tuple(args.iters), density_resolutions=tuple(args.density_resolutions),
        density_iso_alpha=args.iso_alpha, iou_views=args.iou_views,
        compute_iou=not args.no_metrics, chamfer_samples=0 if args.no_metrics else 100_000, **caps)


def report_path_for(mesh_path: str) -> str:
    return os.path.splitext(mesh_path)[0] + ".scaffold.json"


def run_scaffold(args) -> int:
    """Entry point of `neumesh scaffold` (args from the parser built by :func:`add_commands`)."""
    from ..data.frame import parse_box
    from ..data.loader import load_scene
    from ..fit import capture_box
    from ..mesh import save_mesh
    from ..reconstruct.build import build_scaffold

    t0 = time.perf_counter()
    progress = Progress()
    progress.say(f"loading {args.data} (downscale {args.downscale}) ...")
    scene = load_scene(args.data, downscale=args.downscale, background=args.background)
    tr = scene.split("train")
    progress.say(f"  {len(tr)} training views {tr.cameras.width}x{tr.cameras.height}, "
                 f"masks: {'yes' if tr.masks is not None else 'no'} ({time.perf_counter() - t0:.1f}s)")
    verbose = getattr(args, "verbose", False)
    box = capture_box(scene, parse_box(args.box) if getattr(args, "box", None) else None,
                      log=lambda s: progress.say("  " + s))
    mesh, rep = build_scaffold(scene, config_from_args(args), progress=progress.scaffold,
                               log=(lambda s: progress.say("  " + s)) if verbose else None, box=box)
    progress.end()
    rep.timings["load"] = time.perf_counter() - t0 - rep.timings.get("total", 0.0)
    save_mesh(mesh, args.out)
    jpath = args.report or report_path_for(args.out)
    rep.save(jpath)
    print(rep.summary())
    print(f"wrote {args.out} and {jpath}")
    return 0


def add_commands(subparsers) -> None:
    """Register `scaffold` on the lead's subparsers object."""
    p = subparsers.add_parser(
        "scaffold", help="reconstruct a mesh scaffold from posed images (visual hull / density grid)",
        description="Build the triangle-mesh scaffold a field is trained on, from posed images alone: "
                    "visual hull carved from the masks (alpha for Blender data, mask/ for DTU), optional "
                    "density-grid refinement, marching cubes, floater removal, resampling to --vertices. "
                    "Prints progress per stage and a report (vertices, time per stage, silhouette IoU on "
                    "the training masks, Chamfer distance when the dataset ships mesh.ply); the report "
                    "is also written as JSON next to the mesh.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--data", required=True, help="dataset folder (NeRF-synthetic/Blender or DTU/NeuS; "
                                                 "format auto-detected)")
    p.add_argument("--out", required=True, help="mesh file to write (.ply recommended)")
    p.add_argument("--downscale", type=float, default=1,
                   help="load images downscaled by this factor (2 halves the resolution; faster)")
    p.add_argument("--background", choices=["white", "black"], default="white",
                   help="background colour Blender images are composited on")
    p.add_argument("--report", default=None,
                   help="JSON report path (default: <out without extension>.scaffold.json)")
    p.add_argument("--box", default=None, metavar="CX,CY,CZ,SX,SY,SZ",
                   help="object box: centre and half-sizes in world units (default: automatic for photos "
                        "without masks, found from their sparse points, as `neumesh fit` does)")
    p.add_argument("--verbose", action="store_true", help="print details of every stage")
    add_scaffold_options(p)
    p.set_defaults(func=run_scaffold)


def main(argv=None) -> int:
    """Stand-alone entry (python -m neumesh_core.cli.scaffold scaffold ...)."""
    from ..errors import NeuMeshError

    ap = argparse.ArgumentParser(prog="neumesh")
    add_commands(ap.add_subparsers(dest="command", required=True))
    args = ap.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except NeuMeshError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
