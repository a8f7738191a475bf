"""Poses from plain photos or a video: pycolmap feature extraction, matching and incremental mapping
on the CPU, with progress and cancel.

``estimate_poses(images_dir, out_dir)`` writes a COLMAP model that ``load_scene(out_dir)`` reads
(``out_dir/sparse/0/{cameras,images,points3D}.bin``), the feature database (``out_dir/database.db``)
and a short report (``out_dir/poses_report.json``: registered photos, mean reprojection error, times,
and the photo folder, so the photos are read where they are: nothing is renamed or moved).
Video clips: ``video.frames_from_video`` extracts frames to run this on.

Progress: ``progress(p: PosesProgress) -> False`` cancels (raises ``nm.Cancelled``); it is called
from the calling thread about four times a second while pycolmap works in a helper thread.

pycolmap's own log (COLMAP's glog lines, written by C++ straight to the process's stderr) is hidden
while it works unless ``PosesConfig.colmap_log``; errors still show (:func:`colmap_log`).
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Optional

import numpy as np

from ..errors import NeuMeshError
from .colmap_run import _is_cancelled, _run_stage, colmap_log, import_pycolmap

REPORT_NAME = "poses_report.json"
_STAGES = ("extract", "match", "map")


class PosesError(NeuMeshError):
    """Poses could not be recovered (too few photos registered, no images, blurry video ...)."""


@dataclass
class PosesConfig:
    """matcher: 'auto' (sequential for video frames, else exhaustive up to 300 photos, sequential
    (neighbours in name order) above), 'exhaustive' or 'sequential'. max_image_size: SIFT runs on photos reduced to
    this long side (px). camera_model: COLMAP model to estimate (OPENCV: k1,k2,p1,p2, what phones need;
    SIMPLE_RADIAL for few photos). single_camera: one camera shared by all photos (one phone, fixed zoom).
    min_registered_fraction: below it the run fails with advice. num_threads -1: all cores.
    colmap_log: show pycolmap's own log lines (COLMAP's progress and details, on stderr); off, only
    its errors show."""

    matcher: str = "auto"
    max_image_size: int = 1600
    max_num_features: int = 8192
    camera_model: str = "OPENCV"
    single_camera: bool = True
    min_registered_fraction: float = 0.5
    min_registered: int = 3
    num_threads: int = -1
    sequential_overlap: int = 10
    seed: int = 0
    colmap_log: bool = False


@dataclass
class PosesProgress:
    stage: str           # 'extract' | 'match' | 'map'
    fraction: float      # of the whole run, 0..1 (estimated)
    message: str         # what is done of the stage, in its units (photos, pairs, cameras)
    elapsed_s: float
    registered: int = 0  # images registered so far (mapping)
    stage_fraction: float = 0.0   # of this stage, 0..1


@dataclass
class PosesReport:
    images_dir: str
    model_dir: str
    num_images: int
    registered: int
    unregistered: list
    mean_reprojection_error: float
    num_points: int
    seconds: float
    stage_seconds: dict = field(default_factory=dict)
    matcher: str = ""
    camera_model: str = ""
    num_models: int = 1

    def to_json(self) -> dict:
        d = asdict(self)
        d["images"] = self.images_dir  # read by data/colmap.py to find the photos where they are
        return d


def _list_photos(images_dir: str) -> list:
    from ..data.capture import list_images

    if not os.path.isdir(images_dir):
        raise PosesError(f"photo folder not found: {images_dir}; pass the folder that holds the photos (--images DIR)")
    names = list_images(images_dir)
    if not names:
        raise PosesError(f"{images_dir} holds no photos (.jpg, .png, .tif ...); pass the folder that holds them, "
                         "or a video with --video clip.mp4")
    return names


def estimate_poses(images_dir: str, out_dir: str, config: PosesConfig | None = None,
                   progress: Callable[[PosesProgress], Optional[bool]] | None = None,
                   sequential: bool = False, *,
                   callback: Callable[[PosesProgress], Optional[bool]] | None = None) -> PosesReport:
    """Recover camera poses and sparse points of the photos in ``images_dir`` into ``out_dir``.

    ``sequential``: the photos are frames of one video in order (matcher 'auto' then matches each
    frame with its neighbours, not all pairs). Raises :class:`PosesError` with what to do when too few
    photos register, and ``nm.Cancelled`` when ``progress`` returns False (``callback``: the same, the
    name older scripts pass).
    """
    cfg = config or PosesConfig()
    with colmap_log(cfg.colmap_log):
        return _estimate_poses(images_dir, out_dir, cfg, progress or callback, sequential)


def _estimate_poses(images_dir: str, out_dir: str, cfg: PosesConfig, callback, sequential: bool) -> PosesReport:
    pycolmap = import_pycolmap()
    if cfg.matcher not in ("auto", "exhaustive", "sequential"):
        raise ValueError(f"matcher must be 'auto', 'exhaustive' or 'sequential', got {cfg.matcher!r}")
    images_dir = os.path.abspath(os.fspath(images_dir))
    out_dir = os.path.abspath(os.fspath(out_dir))
    names = _list_photos(images_dir)
    n = len(names)
    if n < 3:
        raise PosesError(f"{images_dir} holds {n} photo(s); poses need at least 3 (20-100 overlapping photos "
                         "taken around the object work best)")
    matcher = cfg.matcher
    if matcher == "auto":
        matcher = "sequential" if (sequential or n > 300) else "exhaustive"
    os.makedirs(out_dir, exist_ok=True)
    db = os.path.join(out_dir, "database.db")
    if os.path.exists(db):
        os.remove(db)  # a fresh run: stale features of other photos would mix in
    run = _Run(pycolmap, n, matcher, callback)
    # 1. features
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = cfg.camera_model
    ext = pycolmap.FeatureExtractionOptions()
    ext.max_image_size = int(cfg.max_image_size)
    ext.num_threads = int(cfg.num_threads)
    ext.sift.max_num_features = int(cfg.max_num_features)
    mode = pycolmap.CameraMode.SINGLE if cfg.single_camera else pycolmap.CameraMode.AUTO
    # in chunks, for progress: later chunks reuse the first chunk's camera when there is one camera
    chunk = max(1, int(np.ceil(n / 20)))

    def extract():
        for k in range(0, n, chunk):
            pycolmap.extract_features(db, images_dir, image_names=names[k:k + chunk], camera_mode=mode,
                                      reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu,
                                      cancellation_token=run.token)
            if _is_cancelled(run.token):
                return
            if k == 0 and cfg.single_camera:
                reader.existing_camera_id = _first_camera_id(pycolmap, db)
            run.done = min(n, k + chunk)

    run.stage("extract", extract, n)
    # 2. matching: the pairs (all, or each photo with its next neighbours) matched in chunks, for progress
    mopt = pycolmap.FeatureMatchingOptions()
    mopt.num_threads = int(cfg.num_threads)
    pairs = _exhaustive_pairs(n) if matcher == "exhaustive" else _sequential_pairs(n, cfg.sequential_overlap)
    own_pairing = any(" " in nm_ for nm_ in names)   # COLMAP's pair lists are space separated
    if own_pairing:   # its own pairing then, one call: no count of pairs done
        if matcher == "exhaustive":
            fn = lambda: pycolmap.match_exhaustive(db, matching_options=mopt,  # noqa: E731
                                                   device=pycolmap.Device.cpu, cancellation_token=run.token)
        else:
            pair = pycolmap.SequentialPairingOptions()
            pair.overlap = int(cfg.sequential_overlap)
            fn = lambda: pycolmap.match_sequential(db, matching_options=mopt, pairing_options=pair,  # noqa: E731
                                                   device=pycolmap.Device.cpu, cancellation_token=run.token)
    else:
        def fn():
            step = max(1, int(np.ceil(len(pairs) / 20)))
            for k in range(0, len(pairs), step):
                imp = pycolmap.ImportedPairingOptions()
                imp.match_list_path = _write_pairs(out_dir, names, pairs[k:k + step])
                pycolmap.match_image_pairs(db, matching_options=mopt, pairing_options=imp,
                                           device=pycolmap.Device.cpu, cancellation_token=run.token)
                if _is_cancelled(run.token):
                    return
                run.done = min(len(pairs), k + step)
    try:
        run.stage("match", fn, 0 if own_pairing else len(pairs))
    finally:
        if os.path.exists(os.path.join(out_dir, ".pairs.txt")):
            os.remove(os.path.join(out_dir, ".pairs.txt"))
    # 3. incremental mapping
    return _map(db, images_dir, out_dir, names, cfg, run)


def _first_camera_id(pycolmap, db_path: str) -> int:
    db = pycolmap.Database.open(db_path)
    try:
        cams = db.read_all_cameras()
    finally:
        db.close()
    return int(min(c.camera_id for c in cams))


def _exhaustive_pairs(n: int) -> list:
    return [(i, j) for i in range(n) for j in range(i + 1, n)]


def _sequential_pairs(n: int, overlap: int) -> list:
    """Each photo with its next ``overlap`` photos and with those 2^k ahead (COLMAP's quadratic overlap)."""
    out = set()
    for i in range(n):
        for k in range(1, overlap + 1):
            if i + k < n:
                out.add((i, i + k))
        k = 1
        while i + (1 << k) < n and k <= overlap:
            out.add((i, i + (1 << k)))
            k += 1
    return sorted(out)


def _write_pairs(out_dir: str, names: list, pairs: list) -> str:
    path = os.path.join(out_dir, ".pairs.txt")
    with open(path, "w", encoding="utf-8") as fh:
        fh.writelines(f"{names[i]} {names[j]}\n" for i, j in pairs)
    return path


class _Run:
    """State of one pose recovery: cancellation token, stage, work done of it (photos, pairs),
    registered count, progress reports."""

    _WEIGHTS = {"extract": (0.0, 0.3), "match": (0.3, 0.3), "map": (0.6, 0.4)}

    def __init__(self, pycolmap, n: int, matcher: str, callback):
        self.token = pycolmap.CancellationToken()
        self.n, self.matcher, self.callback = n, matcher, callback
        self.t_start = time.perf_counter()
        self.current, self.registered, self.done, self.total = "extract", 0, 0, 0
        self.seconds = {}

    def report(self):
        if self.callback is None:
            return None
        st = self.current
        lo, span = self._WEIGHTS[st]
        if st == "map":
            # pycolmap calls back once per registration attempt, across every model it tries (a second
            # start pair, re-registrations): the count can pass n before mapping ends, so it is shown
            # capped and the stage's fraction stays below its end until the mapping returns
            placed = min(self.registered, self.n)
            part = min(placed / self.n, 0.99)
            msg = f"{placed} of {self.n} cameras placed"
        else:
            placed = 0
            part = self.done / self.total if self.total else 0.0
            msg = (f"features in {self.done} of {self.n} photos" if st == "extract" else
                   f"{self.done} of {self.total} photo pairs matched ({self.matcher})" if self.total else
                   f"matching the photos ({self.matcher})")
        return self.callback(PosesProgress(st, min(lo + span * part, 1.0), msg, time.perf_counter() - self.t_start,
                                           placed, part))

    def stage(self, name: str, fn, total: int = 0):
        """Run stage ``name``; ``total``: its units of work (fn counts them in ``done``), 0 unknown."""
        self.current, self.done, self.total = name, 0, total
        t0 = time.perf_counter()
        out = _run_stage(fn, self.token, self.report)
        self.seconds[name] = time.perf_counter() - t0
        return out


def map_database(database: str, images_dir: str, out_dir: str, config: PosesConfig | None = None,
                 progress: Callable[[PosesProgress], Optional[bool]] | None = None, *,
                 callback: Callable[[PosesProgress], Optional[bool]] | None = None) -> PosesReport:
    """Stage 3 alone: incremental mapping of a COLMAP database whose features and matches exist
    (e.g. made by COLMAP's GUI), written like :func:`estimate_poses` writes it (``progress`` and
    ``callback`` as there)."""
    callback = progress or callback
    pycolmap = import_pycolmap()
    cfg = config or PosesConfig()
    with colmap_log(cfg.colmap_log):
        db = pycolmap.Database.open(database)
        try:
            names = sorted(im.name for im in db.read_all_images())
        finally:
            db.close()
        if not names:
            raise PosesError(f"{database} holds no images; run feature extraction first "
                             "(`neumesh poses --images DIR`)")
        os.makedirs(out_dir, exist_ok=True)
        return _map(database, os.path.abspath(images_dir), os.path.abspath(out_dir), names, cfg,
                    _Run(pycolmap, len(names), "existing", callback))


def _map(db: str, images_dir: str, out_dir: str, names: list, cfg: PosesConfig, run: _Run) -> PosesReport:
    pycolmap = import_pycolmap()
    n = len(names)
    popt = pycolmap.IncrementalPipelineOptions()
    popt.num_threads = int(cfg.num_threads)
    popt.random_seed = int(cfg.seed)
    popt.mapper.random_seed = int(cfg.seed)
    popt.triangulation.random_seed = int(cfg.seed)

    def next_image():
        run.registered += 1

    tmp_models = tempfile.mkdtemp(prefix=".models_", dir=out_dir)
    try:
        recs = run.stage("map", lambda: pycolmap.incremental_mapping(db, images_dir, tmp_models, options=popt,
                                                                     next_image_callback=next_image,
                                                                     cancellation_token=run.token))
    finally:
        shutil.rmtree(tmp_models, ignore_errors=True)
    recs = dict(recs or {})
    if not recs:
        raise PosesError(f"no two of the {n} photos in {images_dir} could be matched into a start pair; the photos "
                         "need more overlap (each part of the object in 3+ photos, ~70% overlap between neighbours), "
                         "texture, sharp focus and no moving parts")
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    model_dir = os.path.join(out_dir, "sparse", "0")
    _write_model(rec, model_dir)
    reg_names = {rec.images[i].name for i in rec.reg_image_ids()}
    unreg = [nm_ for nm_ in names if nm_ not in reg_names]
    registered = len(reg_names)
    rep = PosesReport(images_dir, model_dir, n, registered, unreg, float(rec.compute_mean_reprojection_error()),
                      int(rec.num_points3D()), time.perf_counter() - run.t_start, dict(run.seconds), run.matcher,
                      cfg.camera_model, len(recs))
    _write_report(os.path.join(out_dir, REPORT_NAME), rep)
    need = max(cfg.min_registered, int(np.ceil(cfg.min_registered_fraction * n)))
    if registered < need:
        raise PosesError(
            f"only {registered} of {n} photos could be placed (at least {need} needed; the partial model is in "
            f"{model_dir}). Take more photos with more overlap (~70% between neighbours, walk around the object "
            "at two heights), avoid blur, reflections and plain backgrounds"
            + (", or try --matcher exhaustive" if run.matcher == "sequential" else ""))
    if run.callback is not None:
        run.callback(PosesProgress("map", 1.0, f"{registered} of {n} cameras placed",
                                   time.perf_counter() - run.t_start, registered, 1.0))
    return rep


def _write_model(rec, model_dir: str) -> None:
    """Write a reconstruction into model_dir atomically (a temporary sibling folder, then renamed)."""
    parent = os.path.dirname(model_dir)
    os.makedirs(parent, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=".tmp_model_", dir=parent)
    try:
        rec.write_binary(tmp)
        if os.path.isdir(model_dir):
            shutil.rmtree(model_dir)
        os.replace(tmp, model_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _write_report(path: str, rep: PosesReport) -> None:
    fd, tmp = tempfile.mkstemp(prefix=".tmp_", suffix=".json", dir=os.path.dirname(path))
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        json.dump(rep.to_json(), fh, indent=1)
    os.replace(tmp, path)
