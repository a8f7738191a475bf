"""Reader for instant-ngp / nerfstudio ``transforms.json`` captures (one file for all photos).

Layout (what instant-ngp's ``colmap2nerf.py``, nerfstudio's ``ns-process-data``, Polycam and
Record3D exports write)::

    root/transforms.json   {"fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_model",
                            "k1".."k4", "p1", "p2", "aabb_scale", "frames": [{"file_path",
                            "transform_matrix" (4x4 OpenGL camera-to-world), optional per-frame
                            intrinsics, "mask_path"}, ...], optional "train_filenames" /
                            "val_filenames" / "test_filenames"}
    root/images/...        the photos (paths relative to the json; Windows separators work)

``camera_model``: PINHOLE, OPENCV (k1, k2, p1, p2[, k3]) or OPENCV_FISHEYE (k1..k4); without it,
``is_fisheye`` selects the fisheye model and any k/p coefficient selects OPENCV. Frames whose image
is missing are skipped with one warning that counts them.
"""
from __future__ import annotations

import json
import os
import warnings

import numpy as np

from ..errors import DataError
from .capture import Capture
from .undistort import Lens

_DIST_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_FILE = "transforms.json"


def _resolve(root: str, rel: str) -> str | None:
    rel = str(rel).replace("\\", "/")
    base = rel if os.path.isabs(rel) else os.path.normpath(os.path.join(root, rel))
    if os.path.isfile(base):
        return base
    stem, ext = os.path.splitext(base)
    stems = (stem,) if ext.lower() in (".png", ".jpg", ".jpeg") else (base,)  # "./train/r_0" has no extension
    for s in stems:
        for e in (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG"):
            if os.path.isfile(s + e):
                return s + e
    return None


def _lens(meta: dict, frame: dict, where: str, image_path: str) -> Lens:
    def get(key):
        v = frame.get(key, meta.get(key))
        return None if v is None else float(v)

    w, h = get("w"), get("h")
    if w is None or h is None:  # not written by every tool: the photo's header has it
        from PIL import Image

        try:
            with Image.open(image_path) as im:
                w, h = (float(v) for v in im.size)
        except Exception as exc:
            raise DataError(f"{where}: could not read the size of {image_path} ({exc}); add 'w' and 'h' "
                            "(pixels) to transforms.json or replace the photo") from exc
    fl_x, fl_y = get("fl_x"), get("fl_y")
    if fl_x is None and get("camera_angle_x") is not None:
        fl_x = 0.5 * w / np.tan(0.5 * get("camera_angle_x"))
    if fl_y is None and get("camera_angle_y") is not None:
        fl_y = 0.5 * h / np.tan(0.5 * get("camera_angle_y"))
    if fl_x is None and fl_y is None:
        raise DataError(f"{where} has no intrinsics: add 'fl_x' (and 'fl_y', 'cx', 'cy') or 'camera_angle_x' "
                        "at the top level or per frame")
    fl_x = fl_y if fl_x is None else fl_x
    fl_y = fl_x if fl_y is None else fl_y
    cx = get("cx") if get("cx") is not None else w / 2.0
    cy = get("cy") if get("cy") is not None else h / 2.0
    dist = {k: get(k) for k in _DIST_KEYS if get(k) is not None}
    model = frame.get("camera_model", meta.get("camera_model"))
    fisheye = bool(frame.get("is_fisheye", meta.get("is_fisheye", False)))
    if model is None:
        model = "OPENCV_FISHEYE" if fisheye else ("OPENCV" if any(dist.values()) else "PINHOLE")
    model = str(model).upper()
    if model == "OPENCV_FISHEYE":
        dist = {k: v for k, v in dist.items() if k in ("k1", "k2", "k3", "k4")}
    elif model == "OPENCV":
        if dist.get("k4"):
            raise DataError(f"{where}: an OPENCV camera with k4 (an r^8 term) cannot be undistorted here; "
                            "re-export the poses with k1-k3 or as OPENCV_FISHEYE")
        dist.pop("k4", None)
    elif model == "PINHOLE":
        if any(dist.values()):
            raise DataError(f"{where}: camera_model PINHOLE but distortion coefficients are given; "
                            "set camera_model to OPENCV (or OPENCV_FISHEYE) or remove the coefficients")
        dist = {}
    else:
        raise DataError(f"{where}: camera_model {model} is not supported (PINHOLE, OPENCV, OPENCV_FISHEYE)")
    return Lens(model, int(round(w)), int(round(h)), fl_x, fl_y, cx, cy, dist)


def read_transforms(root: str, json_name: str = _FILE, log=None) -> Capture:
    """Read ``root/transforms.json`` as a :class:`Capture` (cameras, photo paths; no pixels).
    Skipped frames are said once through ``log(message)``, or as a Python warning without it."""
    root = os.fspath(root)
    path = os.path.join(root, json_name) if os.path.isdir(root) else root
    root = os.path.dirname(os.path.abspath(path))
    try:
        with open(path, "r", encoding="utf-8") as fh:
            meta = json.load(fh)
    except FileNotFoundError as exc:
        raise DataError(f"{path} not found; a transforms.json capture needs it next to the photos") from exc
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"could not parse {path}: {exc}; the file must be valid JSON") from exc
    if not isinstance(meta, dict):
        raise DataError(f"{path} must hold a JSON object with a 'frames' list")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DataError(f"{path} has no 'frames' list (or it is empty); it must list the photos and their poses")
    rows, missing = [], []
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise DataError(f"{path}: frame {i} needs 'file_path' and 'transform_matrix'")
        img = _resolve(root, fr["file_path"])
        if img is None:
            missing.append(str(fr["file_path"]))
            continue
        m = np.asarray(fr["transform_matrix"], dtype=np.float64)
        if m.shape == (3, 4):
            m = np.vstack([m, [0, 0, 0, 1]])
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise DataError(f"{path}: frame {i} transform_matrix must be a finite 4x4 matrix, got shape {m.shape}")
        lens = _lens(meta, fr, f"{path} (frame {i})", img)
        mask = None
        if fr.get("mask_path"):
            mask = _resolve(root, fr["mask_path"])
            if mask is None:
                raise DataError(f"{path}: frame {i} mask_path '{fr['mask_path']}' not found; add it or remove the key")
        rel = os.path.relpath(img, root).replace("\\", "/")
        rows.append((rel, img, lens, m, mask))
    if not rows:
        raise DataError(f"{path} lists {len(frames)} frames but none of their images exists (e.g. "
                        f"{missing[0]}); put the photos where file_path points (relative to {root})")
    notes = []
    if missing:
        msg = (f"{path}: {len(missing)} of {len(frames)} frames have no image and were skipped "
               f"(e.g. {', '.join(missing[:3])})")
        if log is not None:
            log(msg)
        else:
            warnings.warn(msg, stacklevel=2)
        notes.append(msg)
    rows.sort(key=lambda r: r[0])
    names = [r[0] for r in rows]
    c2w = np.stack([r[3] for r in rows]) @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL -> OpenCV, kept float64
    splits = None
    named = {k: meta.get(f"{k}_filenames") for k in ("train", "val", "test")}
    if any(isinstance(v, list) and v for v in named.values()):
        by_name = {n: i for i, n in enumerate(names)}
        by_stem = {os.path.basename(n): i for i, n in enumerate(names)}
        splits = {}
        for k, lst in named.items():
            if isinstance(lst, list) and lst:
                ids = []
                for f in lst:
                    f = str(f).replace("\\", "/")
                    j = by_name.get(os.path.relpath(os.path.normpath(os.path.join(root, f)), root).replace("\\", "/"),
                                    by_stem.get(os.path.basename(f)))
                    if j is not None:
                        ids.append(j)
                splits[k] = sorted(set(ids))
    extra = {k: meta[k] for k in ("scale", "offset", "aabb", "scene_bbox", "applied_transform", "ply_file_path")
             if k in meta}
    points = colours = None
    ply = meta.get("ply_file_path")
    if ply:  # nerfstudio writes the COLMAP points as a PLY beside the json
        ply_path = os.path.join(root, str(ply).replace("\\", "/"))
        if os.path.isfile(ply_path):
            points, colours = _read_points_ply(ply_path)
    aabb = meta.get("aabb_scale")
    return Capture("transforms", root, names, [r[1] for r in rows], [r[2] for r in rows], c2w,
                   [r[4] for r in rows], points, colours, float(aabb) if aabb is not None else None, splits,
                   missing, notes, extra)


def _read_points_ply(path: str):
    try:
        import trimesh

        pc = trimesh.load(path, process=False)
        pts = np.asarray(pc.vertices, dtype=np.float32)
        cols = getattr(pc, "colors", None)
        cols = None if cols is None or len(cols) != len(pts) else np.asarray(cols)[:, :3].astype(np.uint8)
        return pts, cols
    except Exception:  # the points are a convenience; a bad PLY must not stop the photos loading
        return None, None


def load_transforms(root: str, downscale: float | None = None, holdout_every: int = 8, **kw):
    """Load a transforms.json capture as a :class:`Scene` (see ``capture.scene_from_capture``)."""
    from .capture import scene_from_capture

    from .capture import _stderr_log

    cap = read_transforms(root, log=kw.get("log") or _stderr_log)
    return scene_from_capture(cap, downscale=downscale, holdout_every=holdout_every, **kw)
