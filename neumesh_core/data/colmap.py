"""Reader for COLMAP sparse models (binary or text), read with ``pycolmap``.

Layouts found (as COLMAP, gaussian-splatting's ``convert.py`` and ``neumesh poses`` leave them)::

    root/sparse/0/{cameras,images,points3D}.{bin,txt}   (or root/sparse/, or root/ itself)
    root/images/...                                    the photos, by the names in images.bin
    root/poses_report.json                             (``neumesh poses``: "images" = the photo folder,
                                                        so photos are read where they are)

Camera models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV, OPENCV_FISHEYE,
SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE (distortion removed on load). Only registered images are kept.
Splits named by the data: ``train_list.txt`` / ``val_list.txt`` / ``test_list.txt`` (one image
name a line) in root; else every 8th photo is held out.
"""
from __future__ import annotations

import json
import os
import warnings

import numpy as np

from ..errors import DataError
from .capture import Capture
from .undistort import Lens

_PARTS = ("cameras", "images", "points3D")
REPORT_NAME = "poses_report.json"


def _has_model(d: str) -> str | None:
    for ext in (".bin", ".txt"):
        if all(os.path.isfile(os.path.join(d, p + ext)) for p in _PARTS):
            return ext
    return None


def find_model(root: str) -> str | None:
    """The folder that holds the COLMAP model of ``root`` (sparse/0, else the other sparse/N in name
    order, sparse itself, or root), or None."""
    root = os.fspath(root)
    cands = [os.path.join(root, "sparse", "0"), os.path.join(root, "sparse"), root]
    sp = os.path.join(root, "sparse")
    if os.path.isdir(sp):
        subs = sorted(os.path.join(sp, d) for d in os.listdir(sp) if os.path.isdir(os.path.join(sp, d)))
        cands[1:1] = [s for s in subs if s not in cands]
    for c in cands:
        if os.path.isdir(c) and _has_model(c):
            return c
    return None


def _images_dir(root: str, model_dir: str, names: list) -> str:
    report = os.path.join(root, REPORT_NAME)
    cands = []
    if os.path.isfile(report):
        try:
            with open(report, "r", encoding="utf-8") as fh:
                img = json.load(fh).get("images")
            if img:
                cands.append(img if os.path.isabs(img) else os.path.join(root, img))
        except (OSError, ValueError):
            pass
    cands += [os.path.join(root, d) for d in ("images", "input", "image")]
    cands += [os.path.join(os.path.dirname(model_dir), "images")]
    for c in cands:
        if os.path.isdir(c) and any(os.path.isfile(os.path.join(c, n)) for n in names[:20]):
            return c
    tried = ", ".join(os.path.relpath(c, root) if not os.path.isabs(c) or c.startswith(root) else c for c in cands)
    raise DataError(f"{root}: the COLMAP model names photos like {names[0]!r} but none was found (looked in "
                    f"{tried}); put the photos in {os.path.join(root, 'images')}")


def read_model(model_dir: str):
    """``pycolmap.Reconstruction`` of a model folder with a clear DataError on bad files."""
    try:
        import pycolmap
    except ImportError as exc:  # pragma: no cover - a declared dependency
        raise DataError("reading COLMAP models needs pycolmap: pip install pycolmap") from exc
    ext = _has_model(model_dir)
    if ext is None:
        raise DataError(f"{model_dir} has no COLMAP model (cameras, images, points3D as .bin or .txt)")
    rec = pycolmap.Reconstruction()
    try:
        if ext == ".bin":
            rec.read_binary(model_dir)
        else:
            rec.read_text(model_dir)
    except Exception as exc:  # pycolmap raises ValueError/RuntimeError with COLMAP's message
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DataError(f"could not read the COLMAP model in {model_dir} ({first}); the files are truncated or "
                        "corrupt: export the model again (COLMAP: File > Export model)") from exc
    return rec


def _c2w(image) -> np.ndarray:
    cfw = image.cam_from_world
    cfw = cfw() if callable(cfw) else cfw
    m = np.eye(4)
    m[:3, :4] = np.asarray(cfw.inverse().matrix(), dtype=np.float64)
    return m


def _named_splits(root: str, names: list) -> dict | None:
    out = {}
    by_name = {n: i for i, n in enumerate(names)}
    by_base = {os.path.basename(n): i for i, n in enumerate(names)}
    for k in ("train", "val", "test"):
        p = os.path.join(root, f"{k}_list.txt")
        if os.path.isfile(p):
            with open(p, "r", encoding="utf-8") as fh:
                lines = [ln.strip().replace("\\", "/") for ln in fh if ln.strip()]
            out[k] = sorted({by_name.get(ln, by_base.get(os.path.basename(ln))) for ln in lines} - {None})
    return out or None


def read_colmap(root: str, images_dir: str | None = None, log=None) -> Capture:
    """Read a COLMAP capture folder as a :class:`Capture` (registered photos only, no pixels).
    Missing photos are said once through ``log(message)``, or as a Python warning without it."""
    root = os.path.abspath(os.fspath(root))
    if not os.path.isdir(root):
        raise DataError(f"dataset folder not found: {root}")
    model_dir = find_model(root)
    if model_dir is None:
        raise DataError(f"{root} has no COLMAP model: expected sparse/0/ with cameras, images and points3D "
                        "(.bin or .txt); run `neumesh poses --images DIR --out DIR` to make one from photos")
    rec = read_model(model_dir)
    imgs = [im for im in rec.images.values() if (im.has_pose if not callable(im.has_pose) else im.has_pose())]
    if not imgs:
        raise DataError(f"{model_dir}: the COLMAP model has no registered images; run the reconstruction again "
                        "with more overlapping photos")
    imgs.sort(key=lambda im: im.name)
    names = [im.name.replace("\\", "/") for im in imgs]
    img_dir = images_dir or _images_dir(root, model_dir, names)
    paths, kept, missing = [], [], []
    for im, n in zip(imgs, names):
        p = os.path.join(img_dir, n)
        if os.path.isfile(p):
            paths.append(p)
            kept.append(im)
        else:
            missing.append(n)
    notes = []
    if missing:
        msg = (f"{root}: {len(missing)} of {len(imgs)} registered photos are missing and were skipped "
               f"(e.g. {missing[0]})")
        if log is not None:
            log(msg)
        else:
            warnings.warn(msg, stacklevel=2)
        notes.append(msg)
    lenses, lens_of = [], {}
    for im in kept:
        if im.camera_id not in lens_of:
            cam = rec.cameras[im.camera_id]
            lens_of[im.camera_id] = Lens.from_colmap(cam.model.name, cam.width, cam.height, cam.params)
        lenses.append(lens_of[im.camera_id])
    c2w = np.stack([_c2w(im) for im in kept])
    pts = rec.points3D
    if len(pts):
        points = np.array([p.xyz for p in pts.values()], dtype=np.float32)
        colours = np.array([p.color for p in pts.values()], dtype=np.uint8)
    else:
        points = colours = None
    kept_names = [im.name.replace("\\", "/") for im in kept]
    return Capture("colmap", root, kept_names, paths, lenses, c2w, None, points, colours, None,
                   _named_splits(root, kept_names), missing, notes, {"model_dir": model_dir, "images_dir": img_dir})


def load_colmap(root: str, downscale: float | None = None, holdout_every: int = 8, images_dir: str | None = None,
                **kw):
    """Load a COLMAP capture as a :class:`Scene` (see ``capture.scene_from_capture``)."""
    from .capture import scene_from_capture

    from .capture import _stderr_log

    cap = read_colmap(root, images_dir, log=kw.get("log") or _stderr_log)
    return scene_from_capture(cap, downscale=downscale, holdout_every=holdout_every, **kw)
