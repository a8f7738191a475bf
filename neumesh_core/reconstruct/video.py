"""Frames of a video clip for pose recovery: the sharpest frame of every 1/fps seconds (OpenCV),
written as JPEGs; a clip too blurry to reconstruct is refused with what to do."""
from __future__ import annotations

import os
from typing import Callable, Optional

import numpy as np

from .poses import PosesError


def sharpness(grey: np.ndarray) -> float:
    """Variance of the Laplacian of a grey uint8 image reduced to at most 960 px (higher = sharper)."""
    import cv2

    h, w = grey.shape[:2]
    s = 960.0 / max(h, w)
    if s < 1:
        grey = cv2.resize(grey, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def frames_from_video(video: str, out_dir: str, fps: float = 2.0, min_sharpness: float = 20.0,
                      progress: Callable[[float], Optional[bool]] | None = None, *,
                      callback: Callable[[float], Optional[bool]] | None = None) -> list:
    """Write the sharpest frame of every 1/fps seconds of ``video`` as out_dir/frame_00001.jpg ...
    Returns the paths. PosesError when the video cannot be read, is too short, or most kept frames are
    blurrier than ``min_sharpness`` (variance of the Laplacian). ``progress(fraction) -> False`` cancels
    (``callback``: the same, the name older scripts pass)."""
    progress = progress or callback
    import cv2

    from ..errors import Cancelled

    if fps <= 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if not os.path.isfile(video):
        raise PosesError(f"video not found: {video}")
    cap = cv2.VideoCapture(video)
    if not cap.isOpened():
        raise PosesError(f"could not open the video {video}; convert it to an .mp4 (H.264) and try again")
    try:
        src_fps = cap.get(cv2.CAP_PROP_FPS) or 30.0
        total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        step = max(1, int(round(src_fps / fps)))
        os.makedirs(out_dir, exist_ok=True)
        for old in os.listdir(out_dir):  # frames of an earlier run would mix in
            if old.startswith("frame_") and old.endswith(".jpg"):
                os.remove(os.path.join(out_dir, old))
        kept, best, i = [], None, 0  # kept: (sharpness, path); frames go to disk as they are chosen

        def keep(b):
            p = os.path.join(out_dir, f"frame_{len(kept) + 1:05d}.jpg")
            cv2.imwrite(p, b[1], [cv2.IMWRITE_JPEG_QUALITY, 95])
            kept.append((b[0], p))

        while True:
            ok, frame = cap.read()
            if not ok:
                break
            sc = sharpness(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
            if best is None or sc > best[0]:
                best = (sc, frame)
            i += 1
            if i % step == 0:
                keep(best)
                best = None
                if progress is not None and total and progress(min(i / total, 1.0)) is False:
                    raise Cancelled("frame extraction cancelled")
        if best is not None and (not kept or i % step > step // 2):
            keep(best)
    finally:
        cap.release()
    if i == 0:
        raise PosesError(f"no frames could be read from {video}; the file is empty or its codec is not supported "
                         "(convert it to an .mp4, H.264)")
    scores = np.array([k[0] for k in kept])
    if len(kept) < 3 or np.median(scores) < min_sharpness:
        for _, p in kept:
            os.remove(p)
        if len(kept) < 3:
            raise PosesError(f"{video} gives only {len(kept)} frames at {fps:g} fps; use a longer clip or a "
                             "higher --fps")
        raise PosesError(f"the video {video} is too blurry to recover poses (median sharpness {np.median(scores):.1f} "
                         f"< {min_sharpness:g}): film more slowly, with more light, or take photos instead")
    paths = []
    for sc, p in kept:
        if sc < 0.3 * np.median(scores):
            os.remove(p)  # a blurred moment: its neighbours cover it
        else:
            paths.append(p)
    return paths
