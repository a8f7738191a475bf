"""`neumesh bake`: a field baked into a UV-textured mesh (OBJ + MTL + PNG + GLB)."""
from __future__ import annotations

import os
import sys

import numpy as np

from .common import _add_device_option, _device


def cmd_bake(args) -> int:
    import neumesh_core as nm
    from ..bake import bake_texture, save_bake

    field = nm.load_field(args.field, device=_device(args))
    name = args.name or os.path.splitext(os.path.basename(args.field))[0]

    def progress(frac):
        print(f"\rbaking {100 * frac:5.1f}%", end="", file=sys.stderr, flush=True)
        return True

    mesh = None
    if args.mesh:
        mesh = nm.load_mesh(args.mesh)
    if args.decimate < 1.0:
        from ..bake import decimate

        src = mesh if mesh is not None else nm.Mesh(np.asarray(field.vertices), field.faces.cpu().numpy())
        mesh = nm.Mesh(*decimate(src.vertices, src.faces, args.decimate))
        print(f"decimated {len(src.faces)} -> {len(mesh.faces)} faces", file=sys.stderr)
    res = bake_texture(field, resolution=args.resolution, padding=args.padding, directions=args.directions,
                       offset=args.offset, progress=progress, mesh=mesh)
    print(file=sys.stderr)
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
    p.add_argument("--decimate", type=float, default=1.0,
                   help="bake onto a quadric-decimated copy of the scaffold (or of --mesh) with about this "
                        "fraction of its faces, e.g. 0.1 (needs the fast-simplification package; "
                        "default 1 = no decimation)")
    p.add_argument("--offset", type=float, default=1.0,
                   help="texel rays start this many field radii out along the mesh's normal and look back "
                        "through twice that (default 1; raise it for a --mesh farther from the field's surface)")
    p.add_argument("--no-glb", dest="glb", action="store_false", help="skip the .glb (trimesh)")
    _add_device_option(p)
    p.set_defaults(func=cmd_bake)
