"""`neumesh edit swap|fill|paint`: edits of a field file, written to a new file beside it."""
from __future__ import annotations

import json
import os

from .common import Progress


def _load(path, device):
    import neumesh_core as nm

    return nm.load_field(path, device=device)


def _report(record, out: str, progress: Progress) -> None:
    from ..edit.edited_files import _jsonable

    progress.end()
    print(json.dumps({"op": record.op, "vertices_changed": record.num_changed, "out": out,
                      **_jsonable(record.info)}, indent=1))


def _target_and_other(args, other_path):
    """Check the output path, then load the field to edit and the other field (source / template; the
    same object when ``other_path`` is empty or the field itself)."""
    from ..edit.edited_files import check_out_path

    check_out_path(args.field, args.out)   # before the work, not only when saving
    target = _load(args.field, args.device)
    same = not other_path or os.path.abspath(other_path) == os.path.abspath(args.field)
    return target, target if same else _load(other_path, args.device)


def _save(field, parent, record, out):
    from ..edit.edited_files import save_edited

    return save_edited(field, parent, record, out_path=out)


def cmd_swap(args) -> int:
    from ..edit.inputs import read_pairs, read_region
    from ..edit.swap import SwapConfig, swap_texture

    target, source = _target_and_other(args, args.source)
    region = read_region(args.region, target.num_vertices)
    src_region = read_region(args.source_region, source.num_vertices) if args.source_region else region
    pairs = read_pairs(args.pairs) if args.pairs else None
    cfg = SwapConfig(nonrigid=not args.rigid, nonrigid_iterations=args.iterations,
                     match_orientation=not args.no_frames, with_scale=not args.no_scale,
                     check_fit=not args.no_check)
    progress = Progress()
    rec = swap_texture(target, region, source, src_region, pairs=pairs, config=cfg,
                       progress=progress.fraction("swap"))
    out = _save(target, args.field, rec, args.out)
    _report(rec, out, progress)
    return 0


def cmd_fill(args) -> int:
    from ..errors import EditError
    from ..edit.fill import fill_texture
    from ..edit.inputs import read_region, read_uvs

    target, template = _target_and_other(args, args.template)
    region = read_region(args.region, target.num_vertices)
    uv = read_uvs(args.uv, target.num_vertices)
    if args.template_uv is None and template is not target:
        raise EditError("--template-uv is needed when the template is another field")
    t_region = read_region(args.template_region, template.num_vertices)
    t_uv = read_uvs(args.template_uv, template.num_vertices) if args.template_uv else uv
    progress = Progress()
    rec = fill_texture(target, region, uv, template, t_region, t_uv, scale=args.scale,
                       progress=progress.fraction("fill"))
    out = _save(target, args.field, rec, args.out)
    _report(rec, out, progress)
    return 0


def _paint_camera(args, field):
    """(K, c2w, width, height) from --camera JSON or --data/--split/--view."""
    import numpy as np

    from ..errors import EditError

    if args.camera:
        try:
            with open(args.camera, encoding="utf-8") as fh:
                c = json.load(fh)
            K, c2w = np.asarray(c["K"], np.float32), np.asarray(c["c2w"], np.float32)
            w, h = int(c["width"]), int(c["height"])
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise EditError(f"camera file {args.camera}: expected JSON with K (3x3), c2w (4x4, OpenCV), width "
                            f"and height ({exc})") from exc
        if K.shape != (3, 3) or c2w.shape != (4, 4):
            raise EditError(f"camera file {args.camera}: K must be 3x3 and c2w 4x4")
        return K, c2w, w, h
    if not args.data:
        raise EditError("give the view: --camera cam.json, or --data DIR with --view N (and --split)")
    import neumesh_core as nm

    cams = nm.load_scene(args.data, downscale=args.downscale).split(args.split).cameras
    if not 0 <= args.view < len(cams):
        raise EditError(f"--view {args.view}: the '{args.split}' split has {len(cams)} cameras")
    return cams.K[args.view], cams.c2w[args.view], cams.width, cams.height


def cmd_paint(args) -> int:
    import numpy as np

    import neumesh_core as nm

    from ..errors import EditError
    from ..edit.edited_files import check_out_path
    from ..edit.paint import paint_layer, paint_texture

    if not args.save_render:
        check_out_path(args.field, args.out)
    field = _load(args.field, args.device)
    K, c2w, w, h = _paint_camera(args, field)
    if args.save_render:
        out = nm.render_camera(field, K, c2w, w, h, background=(1.0, 1.0, 1.0))
        nm.save_image(args.save_render, np.concatenate([np.clip(out.rgb, 0, 1), np.ones((h, w, 1), np.float32)], -1))
        print(f"wrote {args.save_render} ({w}x{h}): paint on it, then run this command with --painted "
              f"PAINTED.png --original {args.save_render}")
        return 0
    if args.paint:
        layer = nm.read_image(args.paint)
        if layer.shape[2] != 4:
            raise EditError(f"--paint {args.paint} has no alpha channel; give an RGBA layer (alpha > 0 marks paint) "
                            "or --painted with --original")
    elif args.painted and args.original:
        layer = paint_layer(nm.read_image(args.painted)[..., :3], nm.read_image(args.original)[..., :3])
    else:
        raise EditError("give the paint: --paint LAYER.png (RGBA), or --painted IMAGE.png with --original RENDER.png")
    progress = Progress()
    rec = paint_texture(field, K, c2w, w, h, layer, progress=progress.fraction("paint"))
    out = _save(field, args.field, rec, args.out)
    _report(rec, out, progress)
    return 0


_REGION_HELP = ("vertex indices: .npy (indices or a boolean mask) or text (whole numbers separated by "
                "spaces, commas or new lines)")


def add_commands(sub) -> None:
    """Register ``neumesh edit ...`` on the top-level subparsers."""
    p = sub.add_parser("edit", help="edit a field without retraining (texture swap, fill, paint); writes a new "
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
    q.add_argument("--iterations", type=int, default=12, help="non-rigid ICP iterations (default 12)")
    q.add_argument("--no-scale", action="store_true", help="rigid alignment without scaling")
    q.add_argument("--no-check", action="store_true", help="apply the swap even when the aligned source "
                   "does not cover the target (docs/editing.md: when the alignment fails)")
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

    q = esub.add_parser("paint", help="paint on one rendered view; the paint appears on the surface in "
                                      "every view",
                        description="Texture painting: the painted pixels' surface points select the "
                                    "vertices near them; only their modification colours change, solved "
                                    "so that the view shows the paint and every other pixel keeps its "
                                    "colour. Workflow: --save-render view.png, paint on it, then "
                                    "--painted painted.png --original view.png.")
    q.add_argument("--field", required=True, help="field file to edit (.neumesh); never overwritten")
    q.add_argument("--out", help="output field file (default: the next <name>.edit-NNN.neumesh beside "
                                 "--field)")
    q.add_argument("--device", default="cpu", help="torch device (default cpu)")
    q.add_argument("--camera", help="view as JSON: K (3x3), c2w (4x4, OpenCV), width, height")
    q.add_argument("--data", help="dataset whose camera --view is the view (instead of --camera)")
    q.add_argument("--split", default="val", help="dataset split of --view (default val)")
    q.add_argument("--view", type=int, default=0, help="camera index in --split (default 0)")
    q.add_argument("--downscale", type=float, default=1, help="downscale of the dataset cameras")
    q.add_argument("--save-render", metavar="PNG", help="only render the view to this PNG (to paint on) and exit")
    q.add_argument("--paint", help="paint layer: RGBA PNG of the view's size; alpha > 0 marks painted pixels")
    q.add_argument("--painted", help="the view's render with paint on it (with --original)")
    q.add_argument("--original", help="the unpainted render (--save-render's output); pixels that differ are paint")
    q.set_defaults(func=cmd_paint)
