"""Reader for the NeRF-synthetic ("Blender") format.

Layout::

    root/transforms_train.json   {"camera_angle_x": ..., "frames": [{"file_path": "./train/r_0",
                                   "transform_matrix": 4x4 OpenGL camera-to-world}, ...]}
    root/transforms_val.json, root/transforms_test.json   (optional)
    root/train/r_0.png ...       RGBA PNGs (alpha becomes the mask)
    root/mesh.ply                (optional true mesh -> Scene.mesh_path)

Optional top-level (or per-frame) keys ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h`` override the
intrinsics derived from ``camera_angle_x``; ``aabb`` / ``scene_bbox`` override the default bounds.
"""
from __future__ import annotations

import json
import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..errors import DataError
from ..imageio import read_image, resize_image
from .cameras import Cameras, opengl_to_opencv
from .scene import ImageSet, Scene

_BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
_DEFAULT_BBOX = np.array([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]], dtype=np.float32)
_IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")


def parse_background(background):
    """'white' | 'black' | None | (r,g,b) in [0,1] -> tuple or None."""
    if background is None:
        return None
    if isinstance(background, str):
        key = background.strip().lower()
        if key in ("none", ""):
            return None
        if key not in _BACKGROUNDS:
            raise ValueError(f"background must be 'white', 'black', None or an (r,g,b) tuple, got {background!r}")
        return _BACKGROUNDS[key]
    bg = tuple(float(c) for c in background)
    if len(bg) != 3:
        raise ValueError(f"background must have 3 components (r,g,b), got {background!r}")
    return bg


def _resolve_image(root: str, file_path: str, json_path: str) -> str:
    rel = file_path.replace("\\", "/")
    base = os.path.normpath(os.path.join(root, rel))
    candidates = [base] if os.path.splitext(base)[1] in _IMAGE_EXTS else []
    candidates += [base + ext for ext in _IMAGE_EXTS]
    if os.path.splitext(base)[1] in _IMAGE_EXTS:
        stem = os.path.splitext(base)[0]
        candidates += [stem + ext for ext in _IMAGE_EXTS]
    for c in candidates:
        if os.path.isfile(c):
            return c
    raise DataError(
        f"{os.path.basename(json_path)} lists file_path '{file_path}' but no image was found "
        f"(tried {candidates[0]} and .png/.jpg variants); add the image or remove the frame"
    )


def _bbox_from_meta(meta: dict):
    for key in ("aabb", "scene_bbox", "bbox"):
        if key in meta:
            try:
                b = np.asarray(meta[key], dtype=np.float32).reshape(2, 3)
            except ValueError as exc:
                raise DataError(f"'{key}' must be [[xmin,ymin,zmin],[xmax,ymax,zmax]], got {meta[key]}") from exc
            return np.stack([b.min(0), b.max(0)]).astype(np.float32)
    return None


def _read_scaled(path: str, downscale: float) -> np.ndarray:
    """read_image + area downscale (fast PIL path for integer factors)."""
    if float(downscale).is_integer():
        return read_image(path, reduce=int(downscale))
    return resize_image(read_image(path), 1.0 / downscale, premultiplied_alpha=True)


def _stored_size(path: str) -> tuple:
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size  # (W, H), header only
    except Exception as exc:
        raise DataError(f"could not read image {path}: {exc}; the file is corrupt or not an image") from exc


def _load_one(path: str, downscale: float, bg) -> tuple:
    img = _read_scaled(path, downscale)
    c = img.shape[2]
    if c in (1, 2):  # grey (+alpha)
        rgb = np.repeat(img[..., :1], 3, axis=2)
        alpha = img[..., 1] if c == 2 else None
    else:
        rgb = img[..., :3]
        alpha = img[..., 3] if c == 4 else None
    if alpha is not None and bg is not None:
        a = alpha[..., None]
        rgb = rgb * a + np.asarray(bg, dtype=np.float32) * (1.0 - a)
    return np.ascontiguousarray(rgb, dtype=np.float32), alpha


def _intrinsics(meta: dict, frame: dict, stored_w: int, stored_h: int, json_path: str) -> np.ndarray:
    """K for the image size stored on disk. Per-frame keys override top-level ones."""

    def get(key):
        if key in frame:
            return float(frame[key])
        if key in meta:
            return float(meta[key])
        return None

    w0, h0 = get("w") or float(stored_w), get("h") or float(stored_h)
    # values in the json refer to its (w,h); rescale if the stored images differ from that
    sx, sy = stored_w / w0, stored_h / h0
    fl_x, fl_y = get("fl_x"), get("fl_y")
    angle_x, angle_y = get("camera_angle_x"), get("camera_angle_y")
    if fl_x is None and angle_x is not None:
        fl_x = 0.5 * w0 / np.tan(0.5 * angle_x)
    if fl_y is None and angle_y is not None:
        fl_y = 0.5 * h0 / np.tan(0.5 * angle_y)
    if fl_x is None and fl_y is None:
        raise DataError(f"{json_path} has neither 'camera_angle_x' nor 'fl_x'; add the field of view")
    fl_x = fl_y if fl_x is None else fl_x
    fl_y = fl_x if fl_y is None else fl_y
    cx, cy = get("cx"), get("cy")
    cx = cx * sx if cx is not None else stored_w / 2.0
    cy = cy * sy if cy is not None else stored_h / 2.0
    return np.array([[fl_x * sx, 0, cx], [0, fl_y * sy, cy], [0, 0, 1]], dtype=np.float64)


def _load_split(root: str, split: str, downscale: float, bg, pool) -> tuple:
    json_path = os.path.join(root, f"transforms_{split}.json")
    try:
        with open(json_path, "r", encoding="utf-8") as fh:
            meta = json.load(fh)
    except (OSError, json.JSONDecodeError) as exc:
        raise DataError(f"could not parse {json_path}: {exc}; the file must be valid JSON") from exc
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DataError(f"{json_path} has no 'frames' list (or it is empty); it must list the images")
    paths, poses = [], []
    for i, fr in enumerate(frames):
        if "file_path" not in fr or "transform_matrix" not in fr:
            raise DataError(f"{json_path}: frame {i} needs 'file_path' and 'transform_matrix'")
        paths.append(_resolve_image(root, str(fr["file_path"]), json_path))
        m = np.asarray(fr["transform_matrix"], dtype=np.float64)
        if m.shape == (3, 4):
            m = np.vstack([m, [0, 0, 0, 1]])
        if m.shape != (4, 4):
            raise DataError(f"{json_path}: frame {i} transform_matrix must be 4x4, got shape {m.shape}")
        poses.append(m)
    loaded = list(pool.map(lambda p: _load_one(p, downscale, bg), paths))
    shapes = {im.shape[:2] for im, _ in loaded}
    if len(shapes) != 1:
        bad = [os.path.basename(p) for p, (im, _) in zip(paths, loaded) if im.shape[:2] != loaded[0][0].shape[:2]]
        raise DataError(
            f"{json_path}: images have different sizes {sorted(shapes)} (e.g. {bad[:3]}); all must match"
        )
    h, w = loaded[0][0].shape[:2]
    W0, H0 = _stored_size(paths[0])
    images = np.stack([im for im, _ in loaded])
    masks = None
    if all(a is not None for _, a in loaded):
        masks = np.stack([a for _, a in loaded]).astype(np.float32)
    K = np.stack([_intrinsics(meta, fr, W0, H0, json_path) for fr in frames])
    K[:, 0, :] *= w / W0  # downscale: pixel units of the resized images
    K[:, 1, :] *= h / H0
    K = K.astype(np.float32)
    c2w = opengl_to_opencv(np.stack(poses).astype(np.float32))
    names = [os.path.relpath(p, root) for p in paths]
    return ImageSet(Cameras(K, c2w, w, h), images, masks, names), meta


def load_blender(root: str, splits=("train", "val", "test"), downscale: float = 1,
                 background="white", num_workers: int | None = None) -> Scene:
    """Load a NeRF-synthetic dataset folder into a :class:`Scene` (cameras in OpenCV convention).

    ``downscale`` 2 halves the resolution (area averaging). ``background``: 'white', 'black', an
    (r,g,b) tuple, or None (keep rgb as stored, no compositing). Alpha becomes ``ImageSet.masks``.
    Split files that are absent are skipped, but a train split is required.
    """
    root = os.fspath(root)
    if not os.path.isdir(root):
        raise DataError(f"dataset folder not found: {root}")
    if downscale <= 0:
        raise ValueError(f"downscale must be > 0, got {downscale}")
    if isinstance(splits, str):
        splits = (splits,)
    bg = parse_background(background)
    present = [s for s in splits if os.path.isfile(os.path.join(root, f"transforms_{s}.json"))]
    if "train" in splits and "train" not in present:
        found = sorted(f for f in os.listdir(root) if f.startswith("transforms") and f.endswith(".json"))
        raise DataError(
            f"{root} has no transforms_train.json (found: {found or 'no transforms_*.json files'}); "
            "a NeRF-synthetic dataset needs transforms_train.json next to train/ images"
        )
    if not present:
        raise DataError(f"{root}: none of the requested splits {list(splits)} has a transforms_<split>.json")
    workers = num_workers or min(8, (os.cpu_count() or 2) * 2)
    out, bbox = {}, None
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for s in present:
            out[s], meta = _load_split(root, s, downscale, bg, pool)
            if bbox is None:
                bbox = _bbox_from_meta(meta)
    mesh_path = os.path.join(root, "mesh.ply")
    return Scene(
        splits=out,
        background=bg,
        bbox=bbox if bbox is not None else _DEFAULT_BBOX.copy(),
        source=os.path.abspath(root),
        kind="blender",
        mesh_path=mesh_path if os.path.isfile(mesh_path) else None,
    )
