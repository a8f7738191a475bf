"""Real captures (photos with poses from COLMAP, instant-ngp, nerfstudio, Polycam, Record3D ...).

Every reader of a real capture (``transforms.py``, ``colmap.py``) returns a :class:`Capture`: the raw
camera rig (one :class:`~.undistort.Lens` and one OpenCV camera-to-world pose per photo), the photo
paths where they are (nothing is renamed or moved), the sparse points in world space when the tool
wrote them, ``aabb_scale`` when given, and the splits the data names. Reading a capture touches no
pixels: it is what *Import Cameras* in Blender needs (``loader.read_capture``), and
:func:`undistorted_images` gives pinhole cameras plus image files without distortion (cached) for
backgrounds.

:func:`scene_from_capture` turns a capture into a :class:`~.scene.Scene`: photos read as uint8,
reduced (``downscale``; None picks the smallest integer factor that brings the long side to at most
1600 px), distortion removed once (cached), and kept as uint8 (``ImageSet.float_view`` converts). Held-out views: the
splits the data names, else every 8th photo in name order (the Mip-NeRF 360 convention) in 'val'.
Without masks, ``ImageSet.masks`` is None, ``scene.has_masks`` is False and ``scene.notes`` says so.
"""
from __future__ import annotations

import math
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from ..errors import DataError
from .cameras import Cameras
from .scene import ImageSet, Scene
from .undistort import Lens, default_cache_dir, read_uint8, undistorted_file

MAX_AUTO_SIDE = 1600  # long side of photos loaded with downscale=None
IMAGE_EXTS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")


@dataclass
class Capture:
    """A real capture without its pixels. ``c2w`` (N,4,4) float64 OpenCV camera-to-world; ``lenses[i]``
    the camera of photo i at the size stored on disk; ``points`` (P,3) float32 world-space sparse points
    (``point_colours`` (P,3) uint8) or None; ``splits``: name -> indices when the data names its splits."""

    kind: str
    source: str
    names: list
    image_paths: list
    lenses: list
    c2w: np.ndarray
    mask_paths: list = field(default_factory=list)
    points: Optional[np.ndarray] = None
    point_colours: Optional[np.ndarray] = None
    aabb_scale: Optional[float] = None
    splits: Optional[dict] = None
    skipped: list = field(default_factory=list)  # listed frames whose image is missing
    notes: list = field(default_factory=list)
    extra: dict = field(default_factory=dict)  # format-specific keys kept as read (e.g. transforms 'scale')

    def __post_init__(self) -> None:
        n = len(self.names)
        self.c2w = np.asarray(self.c2w, dtype=np.float64).reshape(-1, 4, 4)
        if not (len(self.image_paths) == len(self.lenses) == len(self.c2w) == n):
            raise ValueError("Capture: names, image_paths, lenses and c2w must have one entry per photo")
        if not self.mask_paths:
            self.mask_paths = [None] * n
        if n == 0:
            raise DataError(f"{self.source}: the capture has no photos with poses; nothing to load")

    def __len__(self) -> int:
        return len(self.names)

    @property
    def has_masks(self) -> bool:
        return all(p is not None for p in self.mask_paths)

    @property
    def is_distorted(self) -> bool:
        return any(not lens.is_pinhole for lens in self.lenses)

    def subset(self, idx) -> "Capture":
        idx = [int(i) for i in np.atleast_1d(idx)]
        return Capture(self.kind, self.source, [self.names[i] for i in idx], [self.image_paths[i] for i in idx],
                       [self.lenses[i] for i in idx], self.c2w[idx], [self.mask_paths[i] for i in idx],
                       self.points, self.point_colours, self.aabb_scale, None, list(self.skipped),
                       list(self.notes), dict(self.extra))


def _stderr_log(msg: str) -> None:
    print(f"neumesh: {msg}", file=sys.stderr, flush=True)


def auto_downscale(width: int, height: int, max_side: int = MAX_AUTO_SIDE) -> int:
    """Smallest integer factor that brings the long side to at most ``max_side`` pixels."""
    return max(1, math.ceil(max(width, height) / float(max_side)))


def _physical_memory() -> int:
    """Bytes of RAM (0 when unknown)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 0


def reduced_size(width: int, height: int, downscale: float) -> tuple:
    """(w, h) of an image of width x height read with ``downscale`` (as ``undistort.read_uint8`` does)."""
    if float(downscale).is_integer():
        n = int(downscale)
        return -(-width // n), -(-height // n)
    return max(1, round(width / downscale)), max(1, round(height / downscale))


def undistorted_images(capture: Capture, cache_dir: str | None = None,
                       progress: Callable[[float], object] | None = None) -> tuple[list, list]:
    """Pinhole intrinsics (list of 3x3 float64 for the full-size images) and paths of images without
    lens distortion: the photos themselves for pinhole cameras, else undistorted copies in the cache
    (made on the first call). ``progress(fraction) -> False`` cancels (nm.Cancelled)."""
    from ..errors import Cancelled

    cache_dir = cache_dir or default_cache_dir()
    Ks, paths = [], []
    for i, (p, lens) in enumerate(zip(capture.image_paths, capture.lenses)):
        if lens.is_pinhole:
            Ks.append(lens.K)
            paths.append(p)
        else:
            _, K, _, cached = undistorted_file(p, lens, 1, cache_dir, fmt="png")
            Ks.append(K)
            paths.append(cached)
        if progress is not None and progress((i + 1) / len(capture)) is False:
            raise Cancelled("undistortion cancelled; the images done so far stay in the cache")
    return Ks, paths


def _bbox(capture: Capture, c2w: np.ndarray) -> tuple[np.ndarray, str]:
    """Provisional bounds until the object box of part 2: the sparse points' 2-98 % box, else the
    instant-ngp unit cube (``scale``/``offset``, default 0.33 / 0.5) times aabb_scale, else the cameras'."""
    if capture.points is not None and len(capture.points) >= 8:
        lo, hi = np.percentile(capture.points, [2, 98], axis=0)
        pad = 0.05 * (hi - lo)
        return np.stack([lo - pad, hi + pad]).astype(np.float32), "the sparse points (2-98 %)"
    if capture.kind == "transforms":
        scale = float(capture.extra.get("scale", 0.33))
        off = np.broadcast_to(np.asarray(capture.extra.get("offset", 0.5), dtype=np.float64), (3,))
        a = float(capture.aabb_scale or 1.0)
        lo = ((0.5 - 0.5 * a) - off) / scale
        hi = ((0.5 + 0.5 * a) - off) / scale
        return np.stack([lo, hi]).astype(np.float32), f"instant-ngp's unit cube x aabb_scale {a:g}"
    c = c2w[:, :3, 3]
    lo, hi = c.min(0), c.max(0)
    return np.stack([lo, hi]).astype(np.float32), "the camera positions"


def capture_object_box(capture: Capture, points: Optional[np.ndarray] = None, holdout_every: int = 8):
    """The object box of ``capture`` (:func:`.frame.object_box` of its training cameras and ``points``,
    else the capture's own sparse points): the box ``neumesh fit`` finds for the scene loaded from
    it, without reading a photo (the add-on's Import Cameras). A capture without points (instant-ngp's
    transforms.json) gets its points from ``nm.capture_points`` (triangulated from the photos)."""
    from .frame import object_box

    pts = capture.points if points is None else points
    return object_box(training_photos(capture, holdout_every).c2w, pts)


def training_photos(capture: Capture, holdout_every: int = 8) -> Capture:
    """The photos of ``capture`` that train a field: its 'train' split, else all but every
    ``holdout_every``-th photo (what :func:`scene_from_capture` holds out)."""
    return capture.subset(_split_indices(capture, holdout_every)["train"])


def _split_indices(capture: Capture, holdout_every: int) -> dict:
    n = len(capture)
    if capture.splits:
        out = {k: np.asarray(v, dtype=np.int64) for k, v in capture.splits.items() if len(v)}
        if "train" not in out:
            held = set(int(i) for k, v in out.items() for i in v)
            out["train"] = np.array([i for i in range(n) if i not in held], dtype=np.int64)
        return out
    idx = np.arange(n)
    if holdout_every and n > 1:
        return {"train": idx[idx % holdout_every != 0], "val": idx[idx % holdout_every == 0]}
    return {"train": idx}


def scene_from_capture(capture: Capture, downscale: float | None = None, holdout_every: int = 8,
                       cache_dir: str | None = None, num_workers: int | None = None,
                       log: Callable[[str], None] | None = None) -> Scene:
    """Load the photos of ``capture`` into a :class:`Scene` (see the module docstring).

    ``downscale``: 2 halves the resolution; None (default) = 1 up to 1600 px, else the smallest
    integer factor that reaches it (said through ``log``, default stderr). ``holdout_every``: every
    n-th photo (0, n, 2n ...) goes to 'val' unless the data names its splits (0: all in 'train').
    """
    log = log or _stderr_log
    if holdout_every < 0:
        raise ValueError(f"holdout_every must be >= 0, got {holdout_every}")
    notes = list(capture.notes)
    sizes = {(lens.width, lens.height) for lens in capture.lenses}
    if len(sizes) != 1:
        raise DataError(f"{capture.source}: the photos have different sizes {sorted(sizes)}; NeuMesh trains on "
                        "photos of one size: resize them to one size (and their cameras) or drop the odd ones")
    W0, H0 = sizes.pop()
    if downscale is None:
        downscale = auto_downscale(W0, H0)
        if downscale > 1:
            msg = (f"photos are {W0}x{H0}: loading them at downscale {downscale} "
                   f"({round(W0 / downscale)}x{round(H0 / downscale)}); pass --downscale 1 for full size")
            log(msg)
            notes.append(msg)
    if downscale <= 0:
        raise ValueError(f"downscale must be > 0, got {downscale}")
    cache_dir = cache_dir or default_cache_dir()
    n = len(capture)
    w, h = reduced_size(W0, H0, downscale)
    gib = n * h * w * (3 + capture.has_masks) / 2**30
    log(f"loading {n} photos at {w}x{h} ({gib:.2f} GiB as uint8)"
        + (", removing lens distortion (cached in " + cache_dir + ")" if capture.is_distorted else ""))
    total = _physical_memory()
    if total and gib * 2**30 > 0.8 * total:
        fit = next((f for f in range(int(downscale) + 1, 64) if n * (-(-H0 // f)) * (-(-W0 // f)) * 4 < 0.5 * total),
                   64)
        raise DataError(f"{n} photos at {w}x{h} need {gib:.1f} GiB but this machine has "
                        f"{total / 2**30:.1f} GiB; load them with --downscale {fit} (or fewer photos)")
    idx = _split_indices(capture, holdout_every)
    if len(idx["train"]) == 0:
        raise DataError(f"{capture.source}: no training views are left after the held-out split; "
                        "use holdout_every=0 or name fewer held-out views")
    use_masks = capture.has_masks
    # each split's arrays are filled in place (no full-capture copy: peak memory = the images once)
    where = {}
    arrays = {}
    try:
        for name, ids in idx.items():
            arrays[name] = (np.empty((len(ids), h, w, 3), dtype=np.uint8),
                            np.empty((len(ids), h, w), dtype=np.uint8) if use_masks else None)
            for row, i in enumerate(ids):
                where.setdefault(int(i), []).append((name, row))
    except MemoryError as exc:
        raise DataError(f"{n} photos at {w}x{h} need {gib:.1f} GiB; load them with a larger --downscale") from exc
    Ks = np.empty((n, 3, 3), dtype=np.float64)
    hits = [False] * n

    def one(i):
        if i not in where:
            return
        img, K, hit, _ = undistorted_file(capture.image_paths[i], capture.lenses[i], downscale, cache_dir)
        if img.shape[:2] != (h, w):
            raise DataError(f"{capture.image_paths[i]} is {img.shape[1]}x{img.shape[0]} after downscale {downscale:g}, "
                            f"its camera says {w}x{h}; the camera file does not describe these photos (all must "
                            "have the size the cameras give)")
        Ks[i], hits[i] = K, hit
        m = None
        if use_masks:
            m, _, _, _ = undistorted_file(capture.mask_paths[i], capture.lenses[i], downscale, cache_dir, grey=True)
            if m.shape[:2] != (h, w):
                raise DataError(f"mask {capture.mask_paths[i]} does not match its photo's size {w}x{h}")
        for name, row in where[i]:
            arrays[name][0][row] = img
            if m is not None:
                arrays[name][1][row] = m

    workers = num_workers or min(4, os.cpu_count() or 2)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        list(pool.map(one, range(n)))
    used = sorted(where)
    if capture.is_distorted:
        notes.append(f"lens distortion removed ({sum(hits[i] for i in used)} of {len(used)} photos from the cache "
                     f"{cache_dir})")
    if not use_masks:
        some = sum(p is not None for p in capture.mask_paths)
        notes.append("no masks: ImageSet.masks is None (training fits whole photos, background included; "
                     "foreground metrics unavailable)" + (f"; masks given for only {some} of {n} photos were ignored"
                                                          if some else ""))
    splits = {}
    for name, ids in idx.items():
        cams = Cameras(Ks[ids].astype(np.float32), capture.c2w[ids].astype(np.float32), w, h)
        splits[name] = ImageSet(cams, arrays[name][0], arrays[name][1], [capture.names[i] for i in ids])
    bbox, how = _bbox(capture, capture.c2w)
    notes.append(f"bbox from {how} (provisional: the object box comes with the background model)")
    return Scene(splits=splits, background=None, bbox=bbox, source=os.path.abspath(capture.source),
                 kind=capture.kind, mesh_path=None, notes=notes, capture=capture)


def list_images(folder: str) -> list:
    """Image files in ``folder`` (not recursive), natural name order."""
    import re

    names = [f for f in os.listdir(folder)
             if os.path.splitext(f)[1].lower() in IMAGE_EXTS and not f.startswith(".")]

    def key(name):
        return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]

    return sorted(names, key=key)


__all__ = ["Capture", "Lens", "auto_downscale", "list_images", "scene_from_capture",
           "undistorted_images", "read_uint8"]
