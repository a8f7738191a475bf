"""Sparse points of a capture whose poses are known (instant-ngp's transforms.json has none): SIFT
features, each photo matched with the photos that look at the same part (its nearest views), and
points triangulated with the given poses held fixed (pycolmap), on the CPU, with progress and cancel.

The points are what the object box is found from (``data.frame.find_object``). They are kept in a
cache folder (``$NEUMESH_CACHE`` or ``~/.cache/neumesh``, ``points/`` inside) keyed by the photos (path,
size, time), their lenses and poses and the settings, so the next run of the same capture reads them
back; the dataset folder is never written.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from typing import Callable, Optional

import numpy as np

from ..data.capture import Capture
from ..data.undistort import cache_folder
from .colmap_run import _is_cancelled, _run_stage, colmap_log, import_pycolmap
from .poses import PosesError

_CACHE_VERSION = 1


@dataclass
class PointsConfig:
    """max_image_size: SIFT runs on photos reduced to this long side (px). neighbours: each photo is
    matched with this many views nearest to it (position and viewing direction). A point is kept when
    at least ``min_track_length`` photos see it with a mean reprojection error up to
    ``max_reprojection_error`` px. num_threads -1: all cores."""

    max_image_size: int = 1000
    max_num_features: int = 4096
    neighbours: int = 12
    min_track_length: int = 3
    max_reprojection_error: float = 2.0
    num_threads: int = -1


@dataclass
class SparsePoints:
    """World-space points (P,3) float32 with their colours (P,3) uint8, mean reprojection errors (P,)
    in pixels and track lengths (P,): how many photos see each one."""

    points: np.ndarray
    colours: np.ndarray
    errors: np.ndarray
    track_lengths: np.ndarray
    seconds: float = 0.0
    cached: bool = False

    def __len__(self) -> int:
        return len(self.points)


def cache_dir() -> str:
    return cache_folder("points")


def _cache_key(capture: Capture, cfg: PointsConfig) -> str:
    files = []
    for p in capture.image_paths:
        st = os.stat(p)
        files.append([os.path.abspath(p), st.st_size, st.st_mtime_ns])
    blob = json.dumps([_CACHE_VERSION, files, [lens.to_dict() for lens in capture.lenses],
                       np.round(capture.c2w, 9).tolist(), asdict(cfg)], sort_keys=True)
    return hashlib.sha1(blob.encode()).hexdigest()


def view_pairs(c2w: np.ndarray, neighbours: int) -> list:
    """Pairs (i, j), i < j, of each camera with its ``neighbours`` nearest: the distance of the centres
    (in units of the rig's median spread) plus 1 - the cosine between the viewing directions."""
    c2w = np.asarray(c2w, np.float64).reshape(-1, 4, 4)
    C, D = c2w[:, :3, 3], c2w[:, :3, 2]
    D = D / np.linalg.norm(D, axis=1, keepdims=True)
    spread = max(float(np.median(np.linalg.norm(C - C.mean(0), axis=1))), 1e-12)
    n = len(C)
    pairs = set()
    for i in range(n):
        score = np.linalg.norm(C - C[i], axis=1) / spread + (1.0 - D @ D[i])
        score[i] = np.inf
        for j in np.argsort(score)[:min(neighbours, n - 1)]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def _colmap_params(lens) -> list:
    from ..data.undistort import _COLMAP_PARAMS

    values = {"f": 0.5 * (lens.fx + lens.fy), "fx": lens.fx, "fy": lens.fy, "cx": lens.cx, "cy": lens.cy}
    return [values[k] if k in values else lens.dist.get(k, 0.0) for k in _COLMAP_PARAMS[lens.model]]


def triangulate_capture(capture: Capture, config: Optional[PointsConfig] = None,
                        progress: Optional[Callable[[float], object]] = None, use_cache: bool = True,
                        log: Optional[Callable[[str], None]] = None) -> SparsePoints:
    """Sparse points of ``capture`` triangulated with its poses held fixed (cached; see the module).

    ``progress(fraction)`` about four times a second; False cancels (raises ``nm.Cancelled``).
    Raises :class:`~.poses.PosesError` (with what to do) when the photos give too few points."""
    cfg = config or PointsConfig()
    say = log or (lambda m: None)
    key = _cache_key(capture, cfg)
    path = os.path.join(cache_dir(), key + ".npz")
    if use_cache and os.path.isfile(path):
        with np.load(path) as z:
            colours = z["colours"] if "colours" in z else z["colors"]   # caches written under the older name
            pts = SparsePoints(z["points"], colours, z["errors"], z["track_lengths"], float(z["seconds"]), True)
        say(f"sparse points: {len(pts)} read back from the cache ({path})")
        if progress is not None:
            progress(1.0)
        return pts
    pycolmap = import_pycolmap()
    t0 = time.perf_counter()
    folder = os.path.commonpath([os.path.dirname(os.path.abspath(p)) for p in capture.image_paths])
    names = [os.path.relpath(os.path.abspath(p), folder) for p in capture.image_paths]
    work = tempfile.mkdtemp(prefix="neumesh_points_")
    token = pycolmap.CancellationToken()
    state = {"base": 0.0, "span": 0.0, "done": 0.0}

    def report():
        if progress is None:
            return None
        return progress(min(state["base"] + state["span"] * state["done"], 0.999))

    def stage(base: float, span: float, fn):
        state.update(base=base, span=span, done=0.0)
        return _run_stage(fn, token, report)

    try:
        with colmap_log(show=False):
            out, pairs = _triangulate(pycolmap, capture, cfg, folder, names, work, token, stage, state)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    pts = _kept_points(out, cfg)
    pts.seconds = time.perf_counter() - t0
    if len(pts) < 30:
        raise PosesError(f"only {len(pts)} sparse points could be triangulated from the {len(capture)} photos with "
                         "their poses; check that the poses belong to these photos (and their convention), or give "
                         "the object box with --box")
    say(f"sparse points: {len(pts)} triangulated from {len(capture)} photos with their poses held fixed "
        f"({len(pairs)} photo pairs, {pts.seconds:.0f}s)")
    if use_cache:
        os.makedirs(cache_dir(), exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".tmp_", suffix=".npz", dir=cache_dir())
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, points=pts.points, colours=pts.colours, errors=pts.errors,
                     track_lengths=pts.track_lengths, seconds=pts.seconds)
        os.replace(tmp, path)
    if progress is not None:
        progress(1.0)
    return pts


def _triangulate(pycolmap, capture: Capture, cfg: PointsConfig, folder: str, names: list, work: str, token, stage,
                 state: dict):
    """Features, matching of the nearest views and triangulation into ``work``: (reconstruction, pairs).
    ``stage(base, span, fn)`` runs ``fn`` reporting progress, ``state["done"]`` its fraction."""
    db = os.path.join(work, "database.db")
    lenses = {}
    for i, lens in enumerate(capture.lenses):
        lenses.setdefault(json.dumps(lens.to_dict(), sort_keys=True), []).append(i)
    ext = pycolmap.FeatureExtractionOptions()
    ext.max_image_size = int(cfg.max_image_size)
    ext.num_threads = int(cfg.num_threads)
    ext.sift.max_num_features = int(cfg.max_num_features)
    groups = list(lenses.values())
    n = len(names)

    def extract():   # one camera per distinct lens, its parameters as given (no refinement)
        done = 0
        for members in groups:
            lens = capture.lenses[members[0]]
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = lens.model
            reader.camera_params = ",".join(repr(float(v)) for v in _colmap_params(lens))
            chunk = max(1, int(np.ceil(n / 20)))
            for k in range(0, len(members), chunk):
                pycolmap.extract_features(db, folder, image_names=[names[i] for i in members[k:k + chunk]],
                                          camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                          extraction_options=ext, device=pycolmap.Device.cpu,
                                          cancellation_token=token)
                done += len(members[k:k + chunk])
                state["done"] = done / n
                if _is_cancelled(token):
                    return

    stage(0.0, 0.6, extract)
    pairs = view_pairs(capture.c2w, cfg.neighbours)
    mopt = pycolmap.FeatureMatchingOptions()
    mopt.num_threads = int(cfg.num_threads)
    pairs_file = os.path.join(work, "pairs.txt")

    def match():
        step = max(1, int(np.ceil(len(pairs) / 20)))
        for k in range(0, len(pairs), step):
            with open(pairs_file, "w", encoding="utf-8") as fh:
                fh.writelines(f"{names[i]} {names[j]}\n" for i, j in pairs[k:k + step])
            imp = pycolmap.ImportedPairingOptions()
            imp.match_list_path = pairs_file
            pycolmap.match_image_pairs(db, matching_options=mopt, pairing_options=imp,
                                       device=pycolmap.Device.cpu, cancellation_token=token)
            state["done"] = min(len(pairs), k + step) / len(pairs)
            if _is_cancelled(token):
                return

    if any(" " in nm_ for nm_ in names):
        raise PosesError(f"photo names with spaces in {folder} cannot be paired for matching; rename them")
    stage(0.6, 0.35, match)
    rec = _posed_reconstruction(pycolmap, db, capture, names)
    model = os.path.join(work, "model")
    os.makedirs(model)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = int(cfg.num_threads)
    out = stage(0.95, 0.05, lambda: pycolmap.triangulate_points(rec, db, folder, model, options=opts,
                                                                cancellation_token=token))
    return out, pairs


def _posed_reconstruction(pycolmap, db_path: str, capture: Capture, names: list):
    """A pycolmap Reconstruction of the database's cameras and images, every image registered at its
    given pose (OpenCV camera-to-world -> COLMAP's cam_from_world)."""
    db = pycolmap.Database.open(db_path)
    try:
        cams, imgs = db.read_all_cameras(), db.read_all_images()
    finally:
        db.close()
    rec = pycolmap.Reconstruction()
    for cam in cams:
        rec.add_camera_with_trivial_rig(cam)
    index = {nm_: i for i, nm_ in enumerate(names)}
    for im in imgs:
        w2c = np.linalg.inv(capture.c2w[index[im.name]])
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
        rec.add_image_with_trivial_frame(pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=im.image_id),
                                         pose)
    return rec


def _kept_points(rec, cfg: PointsConfig) -> SparsePoints:
    pts = list(rec.points3D.values()) if rec is not None else []
    P = np.array([p.xyz for p in pts], np.float64).reshape(-1, 3)
    col = np.array([p.color for p in pts], np.uint8).reshape(-1, 3)
    err = np.array([p.error for p in pts], np.float64)
    tl = np.array([p.track.length() for p in pts], np.int64)
    keep = (tl >= cfg.min_track_length) & (err <= cfg.max_reprojection_error) & np.isfinite(P).all(1)
    return SparsePoints(P[keep].astype(np.float32), col[keep], err[keep].astype(np.float32), tl[keep])


def capture_points(capture: Capture, progress: Optional[Callable[[float], object]] = None,
                   log: Optional[Callable[[str], None]] = None, cached_only: bool = False) -> Optional[np.ndarray]:
    """The sparse points the object box of ``capture`` is found from: the capture's own (COLMAP, a
    transforms.json with a point cloud), else those triangulated from its training photos with their
    poses (:func:`triangulate_capture`, cached). ``cached_only``: never triangulate (None when the
    cache has nothing yet: e.g. an interface that must answer at once)."""
    from ..data.capture import training_photos

    if capture.points is not None and len(capture.points):
        return np.asarray(capture.points, np.float32)
    train = training_photos(capture)
    if cached_only:
        path = os.path.join(cache_dir(), _cache_key(train, PointsConfig()) + ".npz")
        if not os.path.isfile(path):
            return None
    return triangulate_capture(train, progress=progress, log=log).points
