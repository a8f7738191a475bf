"""`neumesh` command line: train, render, eval, demo (+ scaffold, fit, edit, semantics, bake)."""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np


def _fmt_time(s: float) -> str:
    s = int(max(0, s))
    return f"{s // 3600:d}:{s % 3600 // 60:02d}:{s % 60:02d}"


class ProgressBar:
    """Terminal consumer of the training callback (one line, refreshed in place)."""

    def __init__(self, stream=None):
        self._stream = stream  # None: whatever sys.stderr is at write time (it can be swapped)
        self.tty = self.stream.isatty()

    @property
    def stream(self):
        return self._stream if self._stream is not None else sys.stderr

    def __call__(self, p) -> None:
        frac = p.step / max(1, p.total_steps)
        bar = "#" * int(30 * frac) + "-" * (30 - int(30 * frac))
        line = (f"[{bar}] {p.step}/{p.total_steps} loss {p.loss:.4f} psnr {p.psnr:5.2f} "
                f"{p.rays_per_sec / 1000:6.1f}k rays/s {p.samples_per_ray:4.1f} smp/ray "
                f"elapsed {_fmt_time(p.elapsed_s)} eta {_fmt_time(p.eta_s)}")
        self.stream.write(("\r" + line) if self.tty else (line + "\n"))
        if self.tty and p.step >= p.total_steps:
            self.stream.write("\n")
        self.stream.flush()


def _add_field_options(ap):
    g = ap.add_argument_group("field")
    g.add_argument("--interpolation", choices=["post", "early"], default="post",
                   help="post: decode each of the K neighbours then average (the paper's default, best "
                        "quality); early: average codes first and decode once (~3x faster, ~0.15 dB worse)")
    g.add_argument("--radius-scale", type=float, default=2.5,
                   help="neighbour search radius = this x the mean edge length of the scaffold (default 2.5)")
    g.add_argument("--radius", type=float, default=0.0,
                   help="absolute neighbour search radius in scene units (overrides --radius-scale)")
    g.add_argument("--grid-res", type=int, default=128,
                   help="occupancy grid cells along the longest axis (default 128)")


def _add_train_options(ap):
    g = ap.add_argument_group("training")
    g.add_argument("--steps", type=int, default=3000, help="optimisation steps (default 3000)")
    g.add_argument("--rays", type=int, default=4096, help="rays per step (default 4096)")
    g.add_argument("--lr-codes", type=float, default=1e-2, help="Adam learning rate of vertex codes")
    g.add_argument("--lr-decoders", type=float, default=2e-3, help="Adam learning rate of the decoders")
    g.add_argument("--tv", type=float, default=1e-3, help="weight of the total-variation loss on codes")
    g.add_argument("--tv-vertices", choices=["random", "batch"], default="random",
                   help="TV over random vertices each step (default) or over the vertices each batch looked up")
    g.add_argument("--lr-final", type=float, default=0.1,
                   help="learning rate at the end of the budget, as a fraction of the start (default 0.1)")
    g.add_argument("--average-from", type=float, default=None, metavar="FRACTION",
                   help="average the weights over the end of training, from this fraction of the budget "
                        "(e.g. 0.5; default off): sharper on new views, free at render time")
    g.add_argument("--code-levels", type=int, default=None, metavar="N",
                   help="coarse code levels while training (each 4x sparser; baked into the vertex codes at "
                        "the end, so the field stays a plain per-vertex field): surfaces that few views see "
                        "inherit their surroundings' appearance. 0 = off (default: TrainConfig's)")
    g.add_argument("--code-levels-until", type=float, default=None, metavar="FRACTION",
                   help="with --code-levels: bake the levels into the vertex codes at this fraction of the "
                        "budget (e.g. 0.3) and train plain per-vertex codes from there (default: to the end)")
    g.add_argument("--mask-weight", type=float, default=0.05,
                   help="weight of the mask BCE (used only when the data has alpha/masks)")
    g.add_argument("--max-minutes", type=float, default=None,
                   help="stop after this many minutes of training (a checkpoint is written)")
    g.add_argument("--checkpoint-every", type=int, default=500, help="steps between checkpoints")
    g.add_argument("--threads", type=int, default=None, help="CPU threads for torch (default: all)")
    g.add_argument("--seed", type=int, default=0, help="random seed")


def _add_data_options(ap, required=True):
    g = ap.add_argument_group("data")
    g.add_argument("--data", required=required,
                   help="dataset folder: NeRF-synthetic/Blender (transforms_*.json) or NeuS/DTU "
                        "(cameras_sphere.npz + image(s)/ + mask/)")
    g.add_argument("--downscale", type=float, default=1,
                   help="image downscale factor (2 = half resolution); cameras are scaled to match")
    g.add_argument("--background", choices=["white", "black"], default="white",
                   help="background colour that Blender-format RGBA images are composited on")


def _train_config(args, checkpoint_path):
    import neumesh_core as nm

    extra = {k: v for k, v in (("code_levels", args.code_levels), ("code_levels_until", args.code_levels_until))
             if v is not None}
    try:
        return nm.TrainConfig(steps=args.steps, rays_per_batch=args.rays, lr_codes=args.lr_codes,
                              lr_decoders=args.lr_decoders, weight_tv=args.tv, tv_vertices=args.tv_vertices,
                              weight_mask=args.mask_weight,
                              lr_final_factor=args.lr_final, average_from=args.average_from,
                              max_seconds=None if args.max_minutes is None else args.max_minutes * 60,
                              checkpoint_path=checkpoint_path, checkpoint_every=args.checkpoint_every,
                              threads=args.threads, seed=args.seed, **extra)
    except ValueError as exc:   # a config check: say it as an option error, not a traceback
        raise nm.NeuMeshError(f"training options: {exc}") from exc


def _field_config(args):
    import neumesh_core as nm

    return nm.FieldConfig(interpolation=args.interpolation, radius_scale=args.radius_scale,
                          radius=args.radius, grid_resolution=args.grid_res)


def _add_render_options(ap) -> None:
    ap.add_argument("--supersample", type=int, default=1,
                    help="S x S rays per pixel, averaged (anti-aliasing; S^2 times slower; default 1)")
    ap.add_argument("--step-scale", type=float, default=None,
                    help="marching step / field radius (default: the step the field was trained with; "
                         "half of it renders finer, twice as slowly)")


def _add_device_option(ap) -> None:
    from .device import DEVICE_CHOICES

    ap.add_argument("--device", default="cpu", metavar="|".join(DEVICE_CHOICES),
                    help="torch device to train/render on: cpu (default), cuda, cuda:N, or auto "
                         "(CUDA when torch sees a GPU)")


def _device(args):
    from .device import resolve_device

    return resolve_device(getattr(args, "device", "cpu"))


def _render_settings(args):
    import neumesh_core as nm

    return nm.RenderSettings(supersample=args.supersample, step_scale=args.step_scale)


def _scene_background(scene):
    return scene.background if scene.background is not None else (0.0, 0.0, 0.0)


def cmd_train(args) -> int:
    import neumesh_core as nm

    device = _device(args)
    scene = nm.load_scene(args.data, downscale=args.downscale, background=args.background)
    if args.resume and os.path.exists(args.out):
        field = nm.load_field(args.out, device=device)
        done = field._checkpoint_meta.get("train_state", {}).get("step", 0)
        print(f"resuming {args.out} from step {done}", file=sys.stderr)
    else:
        mesh_path = args.mesh or scene.mesh_path
        if not mesh_path:
            print("error: no scaffold mesh. Pass --mesh MESH.ply, or build one with `neumesh scaffold "
                  "--data DIR --out mesh.ply` (or run `neumesh fit`, which does both).", file=sys.stderr)
            return 2
        mesh = nm.load_mesh(mesh_path)
        field = nm.create_field(mesh, _field_config(args), device=device)
        print(f"scaffold {mesh_path}: {mesh.num_vertices} vertices, radius {field.radius:.4g}",
              file=sys.stderr)
    res = nm.train(field, scene, _train_config(args, args.out), callback=ProgressBar())
    state = "interrupted (Ctrl-C)" if res.interrupted else ("stopped" if res.cancelled else "done")
    avg = f" (weights averaged over {res.averaged} snapshots)" if res.averaged else ""
    print(f"{state} at step {res.steps_done}: train psnr {res.final_psnr:.2f} in {res.seconds:.0f}s; "
          f"saved {args.out}{avg}", file=sys.stderr)
    if "val" in scene.splits and not res.interrupted and args.eval:
        r = nm.evaluate(field, scene.split("val"), background=scene.background,
                        masked=scene.kind == "dtu")
        _print_eval(r)
    return 130 if res.interrupted else 0


def _print_eval(r: dict) -> None:
    keys = [k for k in r["mean"] if k != "render_s"]
    print("view".ljust(24) + "".join(k.rjust(10) for k in keys))
    for row in r["views"]:
        print(str(row["view"])[-24:].ljust(24) + "".join(f"{row[k]:10.4f}" for k in keys))
    print("mean".ljust(24) + "".join(f"{r['mean'][k]:10.4f}" for k in keys))
    if not r["lpips_available"]:
        print("lpips: unavailable (no local weights; see README 'Metrics')")


def cmd_eval(args) -> int:
    import neumesh_core as nm
    from .evaluate import write_json

    field = nm.load_field(args.field, device=_device(args))
    scene = nm.load_scene(args.data, downscale=args.downscale, background=args.background)
    masked = scene.kind == "dtu" if args.masked == "auto" else args.masked == "yes"
    r = nm.evaluate(field, scene.split(args.split), background=scene.background, masked=masked,
                    out_dir=args.renders, settings=_render_settings(args))
    _print_eval(r)
    out = args.json or os.path.splitext(args.field)[0] + f"_eval_{args.split}.json"
    write_json({"field": args.field, "data": args.data, "split": args.split, **r}, out)
    print(f"wrote {out}")
    return 0


def turntable_cameras(center, radius: float, n: int, width: int, height: int, fov_deg: float = 40.0,
                      elevation_deg: float = 25.0):
    """n cameras on a circle around ``center`` (z up), OpenCV c2w."""
    import neumesh_core as nm
    from .data.synthetic import look_at_opencv

    K = nm.intrinsics_from_fov(np.radians(fov_deg), width, height)
    el = np.radians(elevation_deg)
    c2ws = []
    for i in range(n):
        az = 2 * np.pi * i / n
        pos = np.asarray(center) + radius * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        c2ws.append(look_at_opencv(pos, center))
    return nm.Cameras(np.repeat(K[None], n, 0), np.stack(c2ws), width, height)


def _render_cameras(field, cams, out_dir, background, settings=None, prefix="frame"):
    import neumesh_core as nm

    os.makedirs(out_dir, exist_ok=True)
    times = []
    for i in range(len(cams)):
        out = nm.render_camera(field, cams.K[i], cams.c2w[i], cams.width, cams.height, background=background,
                               settings=settings)
        nm.save_image(os.path.join(out_dir, f"{prefix}_{i:04d}.png"), out.rgba(background))
        times.append(out.seconds)
        print(f"\rrendered {i + 1}/{len(cams)} ({out.seconds:.2f}s)", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    return times


def cmd_render(args) -> int:
    import neumesh_core as nm

    field = nm.load_field(args.field, device=_device(args))
    bg = (1.0, 1.0, 1.0) if args.background == "white" else (0.0, 0.0, 0.0)
    if args.data:
        scene = nm.load_scene(args.data, downscale=args.downscale, background=args.background)
        cams = scene.split(args.split).cameras
    else:
        w, h = (int(v) for v in args.resolution.lower().split("x"))
        bb = field.grid.aabb.cpu().numpy()
        center = bb.mean(0)
        dist = float(np.linalg.norm(bb[1] - bb[0])) * 1.3
        cams = turntable_cameras(center, dist, args.frames, w, h)
    times = _render_cameras(field, cams, args.out, bg, _render_settings(args))
    print(f"wrote {len(times)} images to {args.out}; mean {np.mean(times):.2f}s per frame")
    return 0


def _comparison_figure(images, renders_dir, result, path, n=4):
    """Reference images (top row) above the field's renders (bottom row), PSNR per view in the log."""
    import neumesh_core as nm

    n = min(n, len(images))
    top = np.concatenate([images.images[i] for i in range(n)], 1)
    views = result["views"][:n]
    bottom = np.concatenate([nm.read_image(os.path.join(renders_dir, f"{v['view'].replace('/', '_')}.png"))[..., :3]
                             for v in views], 1)
    nm.save_image(path, np.concatenate([top, bottom], 0))


def cmd_demo(args) -> int:
    import neumesh_core as nm
    from .evaluate import write_json

    t0 = time.perf_counter()
    os.makedirs(args.out, exist_ok=True)
    print("1/4 making the built-in scene (procedural blob, reference ray tracer)...", file=sys.stderr)
    data = nm.default_scene_dir(small=args.small)
    scene = nm.load_scene(data)
    mesh = nm.load_mesh(scene.mesh_path)
    field = nm.create_field(mesh, nm.FieldConfig(interpolation=args.interpolation))
    print(f"2/4 training {args.steps} steps on {len(scene.split('train'))} views "
          f"({mesh.num_vertices} scaffold vertices)...", file=sys.stderr)
    path = os.path.join(args.out, "field.neumesh")
    cfg = nm.TrainConfig(steps=args.steps, rays_per_batch=args.rays, checkpoint_path=path)
    res = nm.train(field, scene, cfg, callback=ProgressBar())
    if res.interrupted:
        print(f"interrupted; the field so far is in {path}", file=sys.stderr)
        return 130
    print("3/4 evaluating on the held-out test views...", file=sys.stderr)
    split = "test" if "test" in scene.splits else "val"
    renders = os.path.join(args.out, "test_renders")
    r = nm.evaluate(field, scene.split(split), background=scene.background, out_dir=renders)
    _print_eval(r)
    fig = os.path.join(args.out, "comparison.png")
    _comparison_figure(scene.split(split), renders, r, fig)
    print(f"comparison figure (reference top, field bottom): {fig}", file=sys.stderr)
    write_json({"data": data, "split": split, "steps": res.steps_done, "train_s": res.seconds, **r},
               os.path.join(args.out, "eval.json"))
    print("4/4 rendering a turntable...", file=sys.stderr)
    cams = turntable_cameras((0, 0, 0), 4.0, args.frames, scene.split("train").cameras.width,
                             scene.split("train").cameras.height)
    _render_cameras(field, cams, os.path.join(args.out, "turntable"), scene.background)
    print(f"demo done in {time.perf_counter() - t0:.0f}s: test PSNR {r['mean']['psnr']:.2f} dB, "
          f"SSIM {r['mean']['ssim']:.4f}; field {path}; turntable in {args.out}/turntable")
    return 0


def cmd_fit(args) -> int:
    from .scaffold.cli import StageProgress, config_from_args
    from .scaffold.fit import fit

    print("stage 1/3: scaffold (skipped when OUT/scaffold.ply exists)", file=sys.stderr)
    bar = ProgressBar()

    def train_cb(p):
        if p.step == 1 or p.step % args.log_every == 0 or p.step >= p.total_steps:
            bar(p)
        return None

    tcfg = _train_config(args, os.path.join(args.out, "field.neumesh"))
    tcfg.log_every = 1
    summary = fit(args.data, args.out, downscale=args.downscale, background=args.background,
                  scaffold_config=config_from_args(args), field_config=_field_config(args), train_config=tcfg,
                  scaffold_progress=StageProgress(), train_callback=train_cb,
                  log=lambda m: print(m, file=sys.stderr), device=_device(args))
    ev = summary.get("eval")
    if ev:
        print("stage 3/3: evaluation: " + ", ".join(f"{k} {v:.4f}" for k, v in ev.items() if k != "render_s"))
    print(f"fit done in {summary['seconds']:.0f}s; outputs in {args.out}")
    return 0


def cmd_bake(args) -> int:
    import neumesh_core as nm
    from .bake import SurfaceFitConfig, bake_texture, save_bake

    field = nm.load_field(args.field, device=_device(args))
    name = args.name or os.path.splitext(os.path.basename(args.field))[0]

    def progress(frac):
        print(f"\rbaking {100 * frac:5.1f}%", end="", file=sys.stderr, flush=True)
        return True

    mesh = None
    if args.mesh:
        mesh = nm.load_mesh(args.mesh)
    if args.decimate < 1.0:
        from .bake import decimate

        src = mesh if mesh is not None else nm.Mesh(np.asarray(field.vertices), field.faces.cpu().numpy())
        mesh = nm.Mesh(*decimate(src.vertices, src.faces, args.decimate))
        print(f"decimated {len(src.faces)} -> {len(mesh.faces)} faces", file=sys.stderr)
    res = bake_texture(field, resolution=args.resolution, padding=args.padding, directions=args.directions,
                       offset=args.offset, progress=progress, mesh=mesh,
                       fit=False if args.no_fit else SurfaceFitConfig(level=args.level))
    print(file=sys.stderr)
    if "surface_offset" in res.info and "median_radii" in res.info["surface_offset"]:
        so = res.info["surface_offset"]
        print(f"the baked mesh lies {so['median_radii']:.3f} field radii (median; 90%: {so['p90_radii']:.3f}) "
              "from the field's surface" + (f" (moved onto it, opacity level {res.info['fit']['level']:g})"
                                            if "fit" in res.info else ""), file=sys.stderr)
    paths = save_bake(res, args.out, name, glb=args.glb, protect=(args.field,))
    if res.info.get("missed_texels"):
        print(f"warning: {res.info['missed_texels']} texels lie farther than the field radius from the field's "
              "scaffold (no density there); they were filled from their neighbours", file=sys.stderr)
    print(f"baked {res.info['texels']} texels ({res.info['charts']} charts, {args.resolution}x{args.resolution}, "
          f"{res.info['mesh_vertices']} vertices, {res.info['mesh_faces']} faces) "
          f"in {res.seconds:.1f}s; wrote " + ", ".join(paths[k] for k in sorted(paths)))
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="neumesh", description="NeuMesh++ editable neural radiance fields "
                                 "on mesh scaffolds (CPU-first).")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="train a field from posed images and a scaffold mesh",
                       description="Train a field. Progress shows loss, PSNR, rays/s and ETA. Ctrl-C "
                                   "saves the field and exits; --resume continues from it.")
    _add_data_options(p)
    p.add_argument("--mesh", help="scaffold mesh (.ply/.obj); default: the dataset's mesh.ply if present")
    p.add_argument("--out", required=True, help="field file to write (e.g. runs/lego.neumesh)")
    p.add_argument("--resume", action="store_true", help="continue training the field in --out")
    p.add_argument("--no-eval", dest="eval", action="store_false", help="skip evaluation on 'val'")
    _add_field_options(p)
    _add_train_options(p)
    _add_device_option(p)
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("render", help="render a field to PNG images (dataset cameras or a turntable)")
    p.add_argument("--field", required=True, help="field file (.neumesh)")
    p.add_argument("--out", required=True, help="output folder for RGBA PNGs")
    p.add_argument("--data", help="render the cameras of this dataset (else a turntable)")
    p.add_argument("--split", default="test", help="dataset split whose cameras to render (default test)")
    p.add_argument("--downscale", type=float, default=1, help="downscale of the dataset cameras")
    p.add_argument("--frames", type=int, default=36, help="turntable frames (default 36)")
    p.add_argument("--resolution", default="400x400", help="turntable image size WxH (default 400x400)")
    p.add_argument("--background", choices=["white", "black"], default="white", help="background colour")
    _add_render_options(p)
    _add_device_option(p)
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("eval", help="PSNR/SSIM(/LPIPS) of a field over a dataset split; prints a table, "
                                    "writes JSON")
    p.add_argument("--field", required=True, help="field file (.neumesh)")
    _add_data_options(p)
    p.add_argument("--split", default="val", help="split to evaluate (default val)")
    p.add_argument("--masked", choices=["auto", "yes", "no"], default="auto",
                   help="foreground (mask) metrics: auto = yes for DTU")
    p.add_argument("--json", help="JSON output path (default: next to the field)")
    p.add_argument("--renders", help="also write the rendered images to this folder")
    _add_render_options(p)
    _add_device_option(p)
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("demo", help="the main job on the built-in scene: make it, train, evaluate, render a "
                                    "turntable, print PSNR")
    p.add_argument("--out", default="outputs/demo", help="output folder (default outputs/demo)")
    p.add_argument("--steps", type=int, default=1500, help="training steps (default 1500)")
    p.add_argument("--rays", type=int, default=4096, help="rays per step (default 4096)")
    p.add_argument("--frames", type=int, default=24, help="turntable frames (default 24)")
    p.add_argument("--small", action="store_true", help="use the small (64 px) built-in scene")
    p.add_argument("--interpolation", choices=["post", "early"], default="post",
                   help="decoder interpolation (see `neumesh train --help`)")
    p.set_defaults(func=cmd_demo)

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
    p.add_argument("--no-glb", dest="glb", action="store_false", help="skip the .glb (trimesh)")
    _add_device_option(p)
    p.set_defaults(func=cmd_bake)

    from .edit.cli import add_commands as add_edit_commands
    from .scaffold.cli import add_commands, add_scaffold_options

    add_commands(sub)
    add_edit_commands(sub)

    from .semantics.cli import add_commands as add_semantics_commands

    add_semantics_commands(sub)
    p = sub.add_parser("fit", help="images alone -> scaffold -> trained field -> evaluation (resumable)",
                       description="Build the scaffold (skipped when OUT/scaffold.ply exists), train the "
                                   "field (resumes OUT/field.neumesh), evaluate on 'val'. Progress per stage.")
    _add_data_options(p)
    p.add_argument("--out", required=True, help="output folder: scaffold.ply, field.neumesh, fit.json")
    p.add_argument("--log-every", type=int, default=25, help="steps between progress lines")
    add_scaffold_options(p)
    _add_field_options(p)
    _add_train_options(p)
    _add_device_option(p)
    p.set_defaults(func=cmd_fit)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from .errors import NeuMeshError

    try:
        return int(args.func(args) or 0)
    except NeuMeshError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\ninterrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
