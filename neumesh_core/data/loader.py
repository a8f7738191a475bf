"""``load_scene``: one entry point for every supported dataset format (auto-detected)."""
from __future__ import annotations

import os

from ..errors import DataError
from .scene import Scene

_KINDS = ("auto", "blender", "dtu")


def detect_kind(path: str) -> str:
    """'blender' (transforms_train.json) or 'dtu' (cameras_sphere.npz); DataError otherwise."""
    path = os.fspath(path)
    if not os.path.isdir(path):
        raise DataError(f"dataset folder not found: {path}")
    if os.path.isfile(os.path.join(path, "transforms_train.json")):
        return "blender"
    if os.path.isfile(os.path.join(path, "cameras_sphere.npz")):
        return "dtu"
    try:
        listing = sorted(os.listdir(path))
    except OSError:
        listing = []
    shown = ", ".join(listing[:12]) + (" ..." if len(listing) > 12 else "") if listing else "nothing"
    raise DataError(
        f"could not recognise the dataset format of {path} (it contains: {shown}). Expected either "
        "NeRF-synthetic/Blender (transforms_train.json [+ transforms_val.json, transforms_test.json] and "
        "the images they list) or NeuS/IDR DTU (cameras_sphere.npz, image/ or images/, optional mask/)"
    )


def load_scene(path: str, kind: str = "auto", downscale: float = 1, background="white", **kw) -> Scene:
    """Load a dataset folder as a :class:`Scene`.

    kind: 'auto' (detect from the files), 'blender' or 'dtu'. ``background`` applies to Blender data
    (DTU has a real background and is never composited). Extra keyword arguments go to the reader:
    Blender: ``splits``, ``num_workers``; DTU: ``holdout_every``, ``mask_threshold``, ``num_workers``.
    """
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {_KINDS}, got {kind!r}")
    if kind == "auto":
        kind = detect_kind(path)
    if kind == "blender":
        from .blender import load_blender

        return load_blender(path, downscale=downscale, background=background, **kw)
    from .dtu import load_dtu

    return load_dtu(path, downscale=downscale, **kw)
