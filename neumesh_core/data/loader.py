"""``load_scene``: one entry point for every supported dataset format (auto-detected)."""
from __future__ import annotations

import os

from ..errors import DataError
from .scene import Scene

_KINDS = ("auto", "blender", "dtu", "transforms", "colmap")


def detect_kind(path: str) -> str:
    """'blender' (transforms_train.json), 'dtu' (cameras_sphere.npz), 'transforms' (instant-ngp /
    nerfstudio transforms.json) or 'colmap' (sparse/0 or a COLMAP model); DataError otherwise."""
    path = os.fspath(path)
    if not os.path.isdir(path):
        raise DataError(f"dataset folder not found: {path}")
    if os.path.isfile(os.path.join(path, "transforms_train.json")):
        return "blender"
    if os.path.isfile(os.path.join(path, "cameras_sphere.npz")):
        return "dtu"
    if os.path.isfile(os.path.join(path, "transforms.json")):
        return "transforms"
    from .colmap import find_model

    if find_model(path) is not None:
        return "colmap"
    try:
        listing = sorted(os.listdir(path))
    except OSError:
        listing = []
    shown = ", ".join(listing[:12]) + (" ..." if len(listing) > 12 else "") if listing else "nothing"
    raise DataError(
        f"could not recognise the dataset format of {path} (it contains: {shown}). Expected either "
        "NeRF-synthetic/Blender (transforms_train.json [+ transforms_val.json, transforms_test.json] and "
        "the images they list), NeuS/IDR DTU (cameras_sphere.npz, image/ or images/, optional mask/), "
        "instant-ngp/nerfstudio (transforms.json and the photos it lists) or COLMAP (sparse/0/ with cameras, "
        "images, points3D and images/). Photos without poses: run `neumesh poses --images DIR --out DIR` first"
    )


def load_scene(path: str, kind: str = "auto", downscale: float | None = None, background="white", **kw) -> Scene:
    """Load a dataset folder as a :class:`Scene`.

    kind: 'auto' (detect from the files), 'blender', 'dtu', 'transforms' or 'colmap'. ``downscale``
    None: 1, except photos of real captures over 1600 px, which are reduced by the smallest integer
    factor that brings them to 1600 (said on stderr and in ``scene.notes``). ``background`` applies to
    Blender data (DTU and real captures have a real background and are never composited). Extra keyword
    arguments go to the reader: Blender: ``splits``, ``num_workers``; DTU: ``holdout_every``,
    ``mask_threshold``, ``num_workers``; real captures: ``holdout_every`` (8), ``cache_dir``,
    ``num_workers``, ``log``; COLMAP also ``images_dir``.
    """
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {_KINDS}, got {kind!r}")
    if kind == "auto":
        kind = detect_kind(path)
    if kind in ("transforms", "colmap"):
        if kind == "transforms":
            from .transforms import load_transforms as reader
        else:
            from .colmap import load_colmap as reader
        return reader(path, downscale=downscale, **kw)
    downscale = 1 if downscale is None else downscale
    if kind == "blender":
        from .blender import load_blender

        return load_blender(path, downscale=downscale, background=background, **kw)
    from .dtu import load_dtu

    return load_dtu(path, downscale=downscale, **kw)


def read_capture(path: str, kind: str = "auto"):
    """Cameras, photo paths and sparse points of a real capture folder (COLMAP or transforms.json) as a
    :class:`~.capture.Capture`, no pixels read. ``kind``: 'auto', 'transforms' or 'colmap'. The core
    call behind Import Cameras."""
    kind = detect_kind(path) if kind == "auto" else kind
    if kind == "transforms":
        from .transforms import read_transforms

        return read_transforms(path)
    if kind == "colmap":
        from .colmap import read_colmap

        return read_colmap(path)
    raise DataError(f"{path} is a '{kind}' dataset, not a real capture (COLMAP or transforms.json)")
