"""`neumesh edit swap|fill`: edits of a field file, written to a new file beside it."""
from __future__ import annotations

import json
import os
import sys


def _progress(label):
    def cb(fraction):
        print(f"\r{label}: {100 * fraction:5.1f}%", end="", file=sys.stderr, flush=True)
        return True
    return cb


def _load(path, device):
    import neumesh_core as nm

    return nm.load_field(path, device=device)


def _report(record, out: str) -> None:
    from .files import _jsonable

    print(file=sys.stderr)
    print(json.dumps({"op": record.op, "vertices_changed": record.num_changed, "out": out,
                      **_jsonable(record.info)}, indent=1))


def _save(field, parent, record, out):
    from .files import save_edited

    return save_edited(field, parent, record, out_path=out)


def cmd_swap(args) -> int:
    from .files import check_out_path
    from .io import read_pairs, read_region
    from .swap import SwapConfig, swap_texture

    check_out_path(args.field, args.out)   # before the work, not only when saving
    target = _load(args.field, args.device)
    source = target if not args.source or os.path.abspath(args.source) == os.path.abspath(args.field) \
        else _load(args.source, args.device)
    region = read_region(args.region, target.num_vertices)
    src_region = read_region(args.source_region, source.num_vertices) if args.source_region else region
    pairs = read_pairs(args.pairs) if args.pairs else None
    cfg = SwapConfig(nonrigid=not args.rigid, nonrigid_iterations=args.iterations,
                     match_orientation=not args.no_frames, with_scale=not args.no_scale)
    rec = swap_texture(target, region, source, src_region, pairs=pairs, config=cfg,
                       progress=_progress("swap"))
    out = _save(target, args.field, rec, args.out)
    _report(rec, out)
    return 0


def cmd_fill(args) -> int:
    from ..errors import EditError
    from .files import check_out_path
    from .fill import fill_texture
    from .io import read_region, read_uvs

    check_out_path(args.field, args.out)   # before the work, not only when saving
    target = _load(args.field, args.device)
    template = target if not args.template or os.path.abspath(args.template) == os.path.abspath(args.field) \
        else _load(args.template, args.device)
    region = read_region(args.region, target.num_vertices)
    uv = read_uvs(args.uv, target.num_vertices)
    if args.template_uv is None and template is not target:
        raise EditError("--template-uv is needed when the template is another field")
    t_region = read_region(args.template_region, template.num_vertices)
    t_uv = read_uvs(args.template_uv, template.num_vertices) if args.template_uv else uv
    rec = fill_texture(target, region, uv, template, t_region, t_uv, scale=args.scale,
                       progress=_progress("fill"))
    out = _save(target, args.field, rec, args.out)
    _report(rec, out)
    return 0


_REGION_HELP = ("vertex indices: .npy (indices or a boolean mask) or text (whole numbers separated by "
                "spaces, commas or new lines)")


def add_commands(sub) -> None:
    """Register ``neumesh edit ...`` on the top-level subparsers."""
    p = sub.add_parser("edit", help="edit a field without retraining (texture swap, fill); writes a new "
                                    "file beside it",
                       description="Edit a trained field. The result is written to a new file beside the "
                                   "input (<name>.edit-NNN.neumesh, or --out); the input is never changed.")
    esub = p.add_subparsers(dest="edit_command", required=True)

    def common(q):
        q.add_argument("--field", required=True, help="field file to edit (.neumesh); never overwritten")
        q.add_argument("--region", required=True, help="target region: " + _REGION_HELP)
        q.add_argument("--out", help="output field file (default: the next <name>.edit-NNN.neumesh beside "
                                     "--field)")
        q.add_argument("--device", default="cpu", help="torch device (default cpu)")

    q = esub.add_parser("swap", help="give the region the texture of a source region (the same field or "
                                     "another), aligned automatically or from point pairs",
                        description="Texture swap: the source region is aligned onto the target region "
                                    "(similarity from --pairs or automatic, then ARAP non-rigid ICP), and "
                                    "each target vertex takes the inverse-distance-weighted texture codes "
                                    "and modification colours of its 4 nearest aligned source vertices, "
                                    "with the source's radiance decoder.")
    common(q)
    q.add_argument("--source", help="source field file (default: --field itself)")
    q.add_argument("--source-region", help="source region (default: the same indices as --region)")
    q.add_argument("--pairs", help="3 or more correspondences: rows 'source_vertex target_vertex' or "
                                   "six numbers 'sx sy sz tx ty tz' (.npy or text); default: automatic")
    q.add_argument("--rigid", action="store_true", help="skip the non-rigid refinement")
    q.add_argument("--iterations", type=int, default=20, help="non-rigid ICP iterations (default 20)")
    q.add_argument("--no-scale", action="store_true", help="rigid alignment without scaling")
    q.add_argument("--no-frames", action="store_true",
                   help="do not rotate normals/view directions into the source's orientation")
    q.set_defaults(func=cmd_swap)

    q = esub.add_parser("fill", help="tile a template region's texture over the region through UV maps",
                        description="Texture fill: the template's UV square is one tile, repeated --scale "
                                    "times across the target's UV square; each target UV takes the "
                                    "inverse-distance-weighted codes of its 4 nearest template UVs (tiles "
                                    "wrap). Vertices on UV seams average their UVs' lookups.")
    common(q)
    q.add_argument("--uv", required=True, help="UVs of the field: .obj with vt (the field's mesh, same "
                                               "vertex order) or .npy (num_vertices, 2)")
    q.add_argument("--template", help="template field file (default: --field itself)")
    q.add_argument("--template-region", required=True, help="template region: " + _REGION_HELP)
    q.add_argument("--template-uv", help="UVs of the template field (default: --uv, when the template is "
                                         "--field)")
    q.add_argument("--scale", type=float, default=1.0, help="tile scale: the template repeats this many "
                                                            "times across (default 1)")
    q.set_defaults(func=cmd_fill)
