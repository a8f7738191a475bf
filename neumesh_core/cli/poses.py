"""`neumesh poses`: camera poses from plain photos or a video (pycolmap on the CPU)."""
from __future__ import annotations

import os
import sys

from .common import Progress


def recover_poses(out: str, *, images: str | None = None, video: str | None = None, fps: float = 2.0,
                  min_sharpness: float = 20.0, config=None, progress: Progress | None = None, say=print):
    """Poses for photos (``images``, read in place) or a video's sharp frames (written to OUT/images):
    a COLMAP model in ``out`` that ``--data out`` loads. Progress through ``progress`` (stderr), the
    summary through ``say`` (stdout); returns the report."""
    from ..reconstruct.poses import PosesConfig, PosesError, estimate_poses
    from ..reconstruct.video import frames_from_video

    progress = progress or Progress()
    cfg = config or PosesConfig()
    sequential = False
    if video:
        images = os.path.join(out, "images")
        progress.say(f"extracting frames at {fps:g} fps from {video} into {images} ...")
        paths = frames_from_video(video, images, fps=fps, min_sharpness=min_sharpness)
        progress.say(f"{len(paths)} frames kept")
        sequential = True
    try:
        rep = estimate_poses(images, out, cfg, progress=progress.poses, sequential=sequential)
    except PosesError as exc:
        if cfg.colmap_log:
            raise
        raise PosesError(f"{exc} (--colmap-log shows COLMAP's own log lines)") from exc
    finally:
        progress.end()
    say(f"registered {rep.registered} of {rep.num_images} photos, mean reprojection error "
        f"{rep.mean_reprojection_error:.2f} px, {rep.num_points} points, {rep.seconds:.0f}s "
        f"(features {rep.stage_seconds.get('extract', 0):.0f}s, matching {rep.stage_seconds.get('match', 0):.0f}s, "
        f"mapping {rep.stage_seconds.get('map', 0):.0f}s)")
    if rep.unregistered:
        say(f"not placed: {', '.join(rep.unregistered[:10])}" + (" ..." if len(rep.unregistered) > 10 else ""))
    return rep


def add_colmap_log_option(p) -> None:
    p.add_argument("--colmap-log", action="store_true",
                   help="show pycolmap's own log lines (COLMAP's details of each step, on stderr); by default "
                        "only its errors show beside NeuMesh's progress")


def cmd_poses(args) -> int:
    from ..reconstruct.poses import PosesConfig

    if bool(args.images) == bool(args.video):
        print("error: give either --images DIR (photos) or --video clip.mp4", file=sys.stderr)
        return 2
    cfg = PosesConfig(matcher=args.matcher, max_image_size=args.max_image_size, camera_model=args.camera_model,
                      single_camera=not args.per_image_camera, num_threads=args.threads or -1,
                      colmap_log=args.colmap_log)
    rep = recover_poses(args.out, images=args.images, video=args.video, fps=args.fps,
                        min_sharpness=args.min_sharpness, config=cfg)
    print(f"model: {rep.model_dir}; train with: neumesh fit --data {args.out} --out DIR")
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser("poses", help="camera poses from plain photos or a video (COLMAP via pycolmap, CPU)",
                       description="Find features, match the photos and place the cameras (pycolmap incremental "
                                   "mapping). Writes OUT/sparse/0 (a COLMAP model that --data OUT loads; the "
                                   "photos stay where they are), OUT/database.db and OUT/poses_report.json. "
                                   "Ctrl-C stops.")
    p.add_argument("--images", help="folder of photos (.jpg/.png), read in place")
    p.add_argument("--video", help="a video clip instead of photos; frames go to OUT/images")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--fps", type=float, default=2.0, help="frames per second taken from --video (default 2)")
    p.add_argument("--min-sharpness", type=float, default=20.0,
                   help="refuse a video whose frames are blurrier than this (variance of the Laplacian; default 20)")
    p.add_argument("--matcher", choices=["auto", "exhaustive", "sequential"], default="auto",
                   help="auto: sequential for video, exhaustive for up to 300 photos (default)")
    p.add_argument("--max-image-size", type=int, default=1600,
                   help="features are found on photos reduced to this long side in px (default 1600)")
    p.add_argument("--camera-model", default="OPENCV",
                   help="COLMAP camera model to estimate (default OPENCV; SIMPLE_RADIAL for few photos)")
    p.add_argument("--per-image-camera", action="store_true",
                   help="one camera per photo (photos from different cameras or zoom levels)")
    p.add_argument("--threads", type=int, default=None, help="CPU threads (default: all)")
    add_colmap_log_option(p)
    p.set_defaults(func=cmd_poses)
