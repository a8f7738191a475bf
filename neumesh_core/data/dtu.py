"""Reader for DTU scans in the NeuS / IDR format.

Layout::

    root/cameras_sphere.npz   world_mat_i (4x4, K[R|t] projection) and scale_mat_i (4x4, maps the unit
                              sphere onto the object region) for every image i
    root/image/ or images/    000000.png ... (sorted; png or jpg)
    root/mask/                000.png ...    (optional; grey or 3-channel; thresholded to {0,1})

The projection of the normalised scene is ``P = world_mat @ scale_mat``; decomposing ``P[:3,:4]``
gives intrinsics K (K[2,2] = 1) and an OpenCV camera-to-world pose, so the object lies inside the
unit sphere and ``bbox = [-1,1]^3``.  NeuS puts pixel centres at integer coordinates; the loader
shifts the principal point by half a pixel to this project's convention (pixel i spans [i, i+1)).
"""
from __future__ import annotations

import os
import re
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.linalg

from ..errors import DataError
from ..imageio import read_image, resize_image
from .cameras import Cameras
from .scene import ImageSet, Scene

_EXTS = (".png", ".jpg", ".jpeg")


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a 3x4 (or 4x4) projection matrix ``P ~ K [R | t]`` into K (3x3, K[2,2]=1, positive focal
    lengths) and a 4x4 camera-to-world pose in the OpenCV convention (float64).

    Same result as NeuS' ``load_K_Rt_from_P`` (which uses ``cv2.decomposeProjectionMatrix``), without
    OpenCV: an RQ decomposition of the left 3x3 block with the signs fixed so that diag(K) > 0 and
    det(R) = +1.
    """
    P = np.asarray(P, dtype=np.float64)[:3, :4]
    M = P[:, :3]
    if abs(np.linalg.det(M)) < 1e-12 * max(1.0, np.abs(M).max() ** 3):
        raise DataError("projection matrix is singular (its left 3x3 block has no inverse); the camera file is broken")
    if np.linalg.det(M) < 0:  # P is defined up to scale; choose the sign that makes det(R)=+1
        P = -P
        M = P[:, :3]
    K, R = scipy.linalg.rq(M)
    signs = np.sign(np.diag(K))
    signs[signs == 0] = 1.0
    D = np.diag(signs)
    K = K @ D
    R = D @ R
    centre = -np.linalg.solve(M, P[:, 3])  # camera centre: P @ [C,1] = 0
    K = K / K[2, 2]
    c2w = np.eye(4)
    c2w[:3, :3] = R.T
    c2w[:3, 3] = centre
    return K, c2w


def _list_images(folder: str) -> list[str]:
    names = [f for f in os.listdir(folder) if os.path.splitext(f)[1].lower() in _EXTS and not f.startswith(".")]

    def key(name):  # natural sort: 2.png < 10.png
        return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]

    return [os.path.join(folder, f) for f in sorted(names, key=key)]


def _read_scaled(path: str, downscale: float) -> np.ndarray:
    if float(downscale).is_integer():
        return read_image(path, reduce=int(downscale))  # fast PIL box reduce
    return resize_image(read_image(path), 1.0 / downscale, premultiplied_alpha=True)


def _load_rgb(path: str, downscale: float) -> np.ndarray:
    img = _read_scaled(path, downscale)
    if img.shape[2] in (1, 2):
        img = np.repeat(img[..., :1], 3, axis=2)
    # stored as uint8 (a quarter of float32's memory; exact for 8-bit photos, ImageSet.float_view converts)
    return np.ascontiguousarray(np.clip(np.rint(img[..., :3] * 255.0), 0, 255).astype(np.uint8))


def _load_mask(path: str, downscale: float, threshold: float) -> np.ndarray:
    m = _read_scaled(path, downscale)
    if m.shape[2] == 4:
        m = m[..., :3]
    elif m.shape[2] == 2:
        m = m[..., :1]
    m = m.mean(axis=2)  # grey or 3-channel (DTU masks are 3 identical channels)
    return m > threshold  # bool: ImageSet.float_mask gives {0, 1}


def _camera_matrices(cams: dict, img_paths: list) -> tuple:
    """Intrinsics and camera-to-world matrices (OpenCV) of each image from ``cameras_sphere.npz``'s
    ``world_mat_i @ scale_mat_i``."""
    Ks, c2ws = [], []
    for i in range(len(img_paths)):
        key = f"world_mat_{i}"
        if key not in cams:
            raise DataError(
                f"cameras_sphere.npz has no {key} for image {os.path.basename(img_paths[i])}; "
                "world matrices must be numbered 0..N-1 in image order"
            )
        world = np.asarray(cams[key], dtype=np.float64)
        scale = np.asarray(cams.get(f"scale_mat_{i}", np.eye(4)), dtype=np.float64)
        if world.shape not in ((4, 4), (3, 4)) or scale.shape != (4, 4):
            raise DataError(f"cameras_sphere.npz: {key} must be 4x4 (or 3x4) and scale_mat_{i} 4x4")
        if world.shape == (3, 4):
            world = np.vstack([world, [0, 0, 0, 1]])
        K, c2w = decompose_projection((world @ scale)[:3, :4])
        Ks.append(K)
        c2ws.append(c2w)
    return Ks, c2ws


def _holdout_splits(full: ImageSet, holdout_every: int, root: str) -> dict:
    """'val': views 0, holdout_every, 2*holdout_every, ...; 'train': the others (0: all, no 'val')."""
    idx = np.arange(len(full))
    if holdout_every:
        val_idx = idx[idx % holdout_every == 0]
        train_idx = idx[idx % holdout_every != 0]
    else:
        val_idx, train_idx = idx[:0], idx
    if len(train_idx) == 0:
        raise DataError(f"{root}: holdout_every={holdout_every} leaves no training views; use a larger value or 0")
    splits = {"train": full.subset(train_idx)}
    if len(val_idx):
        splits["val"] = full.subset(val_idx)
    return splits


def load_dtu(root: str, downscale: float = 1, holdout_every: int = 10, mask_threshold: float = 0.5,
             num_workers: int | None = None) -> Scene:
    """Load a NeuS/IDR-format DTU scan into a :class:`Scene`.

    Splits: 'val' holds views 0, holdout_every, 2*holdout_every, ...; 'train' holds the others
    (``holdout_every=0``: every view in 'train', no 'val'). Images are not composited
    (``background=None``). Masks are optional; without a ``mask/`` folder ``masks`` is None and
    ``scene.notes`` says so.
    """
    root = os.fspath(root)
    if not os.path.isdir(root):
        raise DataError(f"dataset folder not found: {root}")
    if downscale <= 0:
        raise ValueError(f"downscale must be > 0, got {downscale}")
    if holdout_every < 0:
        raise ValueError(f"holdout_every must be >= 0, got {holdout_every}")
    npz_path = os.path.join(root, "cameras_sphere.npz")
    if not os.path.isfile(npz_path):
        raise DataError(
            f"{root} has no cameras_sphere.npz; a NeuS/IDR DTU scan needs cameras_sphere.npz "
            "(world_mat_i, scale_mat_i) plus image/ and optionally mask/"
        )
    img_dir = next((os.path.join(root, d) for d in ("image", "images") if os.path.isdir(os.path.join(root, d))), None)
    if img_dir is None:
        raise DataError(f"{root} has no image/ or images/ folder; put the scan's images there")
    img_paths = _list_images(img_dir)
    if not img_paths:
        raise DataError(f"{img_dir} contains no .png/.jpg images")
    try:
        cams = dict(np.load(npz_path))
    except Exception as exc:
        raise DataError(f"could not read {npz_path}: {exc}; the file is corrupt") from exc
    n = len(img_paths)
    n_cams = len([k for k in cams if re.fullmatch(r"world_mat_\d+", k)])
    if n_cams != n:
        raise DataError(
            f"{root}: {n} images in {os.path.basename(img_dir)}/ but {n_cams} cameras (world_mat_i) in "
            "cameras_sphere.npz; the counts must match"
        )
    Ks, c2ws = _camera_matrices(cams, img_paths)

    mask_dir = os.path.join(root, "mask")
    if not os.path.isdir(mask_dir):
        mask_dir = os.path.join(root, "masks") if os.path.isdir(os.path.join(root, "masks")) else None
    mask_paths = _list_images(mask_dir) if mask_dir else []
    if mask_dir and mask_paths and len(mask_paths) != n:
        raise DataError(
            f"{root}: {len(mask_paths)} masks in {os.path.basename(mask_dir)}/ but {n} images; "
            "provide one mask per image or remove the mask folder"
        )
    workers = num_workers or min(8, (os.cpu_count() or 2) * 2)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        images = list(pool.map(lambda p: _load_rgb(p, downscale), img_paths))
        masks = list(pool.map(lambda p: _load_mask(p, downscale, mask_threshold), mask_paths)) if mask_paths else None
    shapes = {im.shape[:2] for im in images}
    if len(shapes) != 1:
        raise DataError(f"{img_dir}: images have different sizes {sorted(shapes)}; all must match")
    h, w = images[0].shape[:2]
    if masks is not None and any(m.shape != (h, w) for m in masks):
        raise DataError(f"{mask_dir}: mask size differs from the image size {w}x{h}")
    from PIL import Image

    with Image.open(img_paths[0]) as im0:  # stored size (K refers to it)
        W0, H0 = im0.size
    K = np.stack(Ks)
    # NeuS/IDR put pixel centres at integer coordinates; here pixel i spans [i, i+1) (centre i + 0.5)
    K[:, 0, 2] += 0.5
    K[:, 1, 2] += 0.5
    K[:, 0, :] *= w / W0
    K[:, 1, :] *= h / H0
    cams_all = Cameras(K.astype(np.float32), np.stack(c2ws).astype(np.float32), w, h)
    images_arr = np.stack(images)
    masks_arr = np.stack(masks) if masks is not None else None
    names = [os.path.relpath(p, root) for p in img_paths]
    full = ImageSet(cams_all, images_arr, masks_arr, names)
    scene = Scene(
        splits=_holdout_splits(full, holdout_every, root),
        background=None,
        bbox=np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], dtype=np.float32),
        source=os.path.abspath(root),
        kind="dtu",
        mesh_path=None,
        notes=[] if masks is not None else ["no mask/ folder: masks are None (foreground metrics unavailable)"],
    )
    return scene
