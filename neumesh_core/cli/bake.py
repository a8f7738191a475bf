"""`neumesh bake`: a field baked into a UV-textured mesh (OBJ + MTL + PNG + GLB)."""
from __future__ import annotations

import os
import sys

import numpy as np

from .common import Progress, _add_device_option, _device


def cmd_bake(args) -> int:
    import neumesh_core as nm
    from ..bake import ProjectConfig, SurfaceFitConfig, bake_texture, save_bake

    field = nm.load_field(args.field, device=_device(args))
    name = args.name or os.path.splitext(os.path.basename(args.field))[0]

    printer = Progress()
    mesh = None
    extract = None
    if args.target is None:      # the field's surface, unless a mesh to bake onto is given
        args.target = "scaffold" if args.mesh else "field"
    if args.target == "field":
        if args.mesh:
            raise SystemExit("error: --target field extracts the mesh from the field's density; leave out --mesh "
                             "(or use --target scaffold to bake onto your mesh)")
        from ..bake import ExtractConfig

        ratio = 0.2 if args.decimate is None else args.decimate
        faces = int(round(ratio * len(field.faces))) if ratio < 1.0 else 0
        extract = ExtractConfig(faces=faces)
        mesh = "field"
    elif args.mesh:
        mesh = nm.load_mesh(args.mesh)
    if args.decimate is not None and args.decimate < 1.0 and extract is None:
        from ..bake import decimate

        src = mesh if mesh is not None else nm.Mesh(np.asarray(field.vertices), field.faces.cpu().numpy())
        mesh = nm.Mesh(*decimate(src.vertices, src.faces, args.decimate))
        print(f"decimated {len(src.faces)} -> {len(mesh.faces)} faces", file=sys.stderr)
    res = bake_texture(field, resolution=args.resolution, padding=args.padding, directions=args.directions,
                       offset=args.offset, progress=printer.fraction("baking"), mesh=mesh, extract=extract,
                       fit=False if args.no_fit or extract is not None else SurfaceFitConfig(level=args.level),
                       colours=args.colours, project=ProjectConfig(views=args.views, size=args.view_size))
    printer.end()
    if "surface_offset" in res.info and "median_radii" in res.info["surface_offset"]:
        so = res.info["surface_offset"]
        print(f"the baked mesh lies {so['median_radii']:.3f} field radii (median; 90%: {so['p90_radii']:.3f}) "
              "from the field's surface" + (f" (moved onto it, opacity level {res.info['fit']['level']:g})"
                                            if "fit" in res.info else "")
              + (f" (extracted from the field's density at opacity {res.info['extract']['level']:g} over a radius: "
                 f"{res.info['extract']['marching_cubes_faces']} faces, decimated to {res.info['mesh_faces']})"
                 if "extract" in res.info else ""), file=sys.stderr)
    if res.info.get("texels_unseen"):
        print(f"{res.info['texels_unseen']} texels were seen by none of the {args.views} views (inside or "
              "underneath): they took the colour along their normal", file=sys.stderr)
    paths = save_bake(res, args.out, name, glb=args.glb, protect=(args.field,))
    if res.info.get("missed_texels"):
        print(f"warning: {res.info['missed_texels']} texels lie farther than the field radius from the field's "
              "scaffold (no density there); they were filled from their neighbours", file=sys.stderr)
    print(f"baked {res.info['texels']} texels ({res.info['charts']} charts, {args.resolution}x{args.resolution}, "
          f"{res.info['mesh_vertices']} vertices, {res.info['mesh_faces']} faces) "
          f"in {res.seconds:.1f}s; wrote " + ", ".join(paths[k] for k in sorted(paths)))
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser("bake", help="bake a field (its current, edited and deformed state) into a UV-textured "
                                    "mesh: OBJ + MTL + PNG (+ GLB) for Blender, glTF viewers, game engines",
                       description="Unwrap the field's scaffold with xatlas and bake the colour the field shows "
                                   "looking straight at each texel's surface point into a texture (baked "
                                   "light: the photos' lighting is in it). Files are written atomically; the "
                                   "field file is never touched.")
    p.add_argument("--field", required=True, help="field file (.neumesh)")
    p.add_argument("--out", required=True, help="output folder for <name>.obj/.mtl/.png/.glb")
    p.add_argument("--name", help="file name stem (default: the field file's)")
    p.add_argument("--resolution", type=int, default=1024, help="texture size in texels (square; default 1024)")
    p.add_argument("--padding", type=int, default=4, help="texels between charts, dilated (default 4)")
    p.add_argument("--directions", type=int, default=1,
                   help="rays averaged per texel: 1 = along -normal (default); more average view-dependent "
                        "highlights over a 30-degree cone")
    p.add_argument("--mesh", help="bake onto this mesh (.ply/.obj/.glb, world space, lying near the field's "
                                  "surface: within the field radius) instead of the scaffold, e.g. a "
                                  "decimated copy")
    p.add_argument("--decimate", type=float, default=None,
                   help="bake onto a quadric-decimated copy of the scaffold (or of --mesh) with about this "
                        "fraction of its faces, e.g. 0.1 (needs the fast-simplification package; "
                        "default 0.2 with --target field, else 1 = no decimation)")
    p.add_argument("--offset", type=float, default=None,
                   help="texel rays start this many field radii out along the mesh's normal and look back "
                        "through twice that (default 0.5 after the fit, 1 with --no-fit; raise it for a --mesh "
                        "farther from the field's surface)")
    p.add_argument("--no-fit", action="store_true",
                   help="bake onto the mesh where it is (default: first move its vertices onto the surface the "
                        "field renders, within 1.5 field radii)")
    p.add_argument("--level", type=float, default=None,
                   help="opacity (0-1) along the normal at which the field's surface lies, for the fit "
                        "(default: calibrated against the field's own renders)")
    p.add_argument("--target", choices=("scaffold", "field"), default=None,
                   help="field (default without --mesh): onto a mesh extracted from the field's own density "
                        "(marching cubes), decimated to --decimate x the scaffold's faces (default 0.2): the "
                        "surface the field renders; scaffold (default with --mesh): onto the scaffold (or "
                        "--mesh), decimated with --decimate (default 1: none); quicker, part edges a little off")
    p.add_argument("--colours", choices=("rays", "views"), default="views",
                   help="views (default): from the field's renders on --views virtual cameras, projected onto "
                        "the texels they see (closer to the field's look); rays: each texel's colour from a "
                        "short ray along its normal (quicker)")
    p.add_argument("--views", type=int, default=48, help="--colours views: virtual cameras (default 48)")
    p.add_argument("--view-size", type=int, default=512, help="--colours views: their size in pixels (default 512)")
    p.add_argument("--no-glb", dest="glb", action="store_false", help="skip the .glb (trimesh)")
    _add_device_option(p)
    p.set_defaults(func=cmd_bake)
