"""The built-in blob in a textured room, rendered without masks (tests of real-capture training).

The room is an inverted sphere of radius ``ROOM_RADIUS`` around the blob, coloured by a checker
pattern of its direction (longitude x latitude cells) and lit by nothing (emissive), so the
background has texture a background model must learn.  :func:`render_in_room` composites the
ground-truth tracer's blob (its anti-aliased alpha) over the room; :func:`make_room_scene` gives a
:class:`~neumesh_core.data.scene.Scene` with ``masks`` None and ``background`` None, as a phone
capture would be (the true alpha is returned apart for checks).
"""
from __future__ import annotations

import math

import numpy as np

from .scene import CAMERA_ANGLE_X, CAMERA_RADIUS, camera_positions, look_at_opencv
from .shape import _torch_single_thread
from .tracer import _render_unpremultiplied

ROOM_RADIUS = 10.0


def room_colour(origins: np.ndarray, dirs: np.ndarray, radius: float = ROOM_RADIUS) -> np.ndarray:
    """(R,3) colour where rays (origins inside the room) meet the textured inverted sphere."""
    o, d = np.asarray(origins, np.float64), np.asarray(dirs, np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    b = (o * d).sum(-1)
    c = (o * o).sum(-1) - radius ** 2
    t = -b + np.sqrt(np.maximum(b * b - c, 0.0))
    p = (o + t[:, None] * d) / radius
    lon = np.arctan2(p[:, 1], p[:, 0])
    lat = np.arcsin(np.clip(p[:, 2], -1, 1))
    cell = (np.floor(lon / (2 * math.pi) * 12) + np.floor(lat / math.pi * 6)).astype(np.int64) % 2
    base = np.stack([0.55 + 0.35 * np.cos(lon), 0.45 + 0.3 * np.sin(2 * lat), 0.5 + 0.3 * np.sin(lon)], -1)
    return np.clip(base * (0.6 + 0.4 * cell[:, None]), 0, 1)


def render_in_room(K, c2w, width: int, height: int, spp: int = 1, seed: int = 0):
    """(rgb (H,W,3) float32: blob over the room, object alpha (H,W) float32)."""
    K = np.asarray(K, np.float64)
    c2w = np.asarray(c2w, np.float64)
    with _torch_single_thread():
        obj, alpha = _render_unpremultiplied(K, c2w, int(width), int(height), spp=spp, seed=seed)
    ys, xs = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    d_cam = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1).reshape(-1, 3)
    d = d_cam @ c2w[:3, :3].T
    room = room_colour(np.broadcast_to(c2w[:3, 3], d.shape), d).reshape(height, width, 3)
    rgb = alpha[..., None] * obj + (1 - alpha[..., None]) * room
    return rgb.astype(np.float32), alpha.astype(np.float32)


def make_room_scene(resolution: int = 48, n_train: int = 24, n_val: int = 3, seed: int = 0):
    """(Scene without masks: 'train' and 'val' splits, kind 'synthetic-room'; true alphas {split: (N,H,W)})."""
    from ..cameras import Cameras
    from ..scene import ImageSet, Scene

    pos = camera_positions(n_train, n_val, 0, radius=CAMERA_RADIUS, seed=seed)
    f = 0.5 * resolution / math.tan(0.5 * CAMERA_ANGLE_X)
    K = np.array([[f, 0, resolution / 2], [0, f, resolution / 2], [0, 0, 1]], np.float32)
    splits, alphas = {}, {}
    for name in ("train", "val"):
        if len(pos[name]) == 0:
            continue
        c2w = np.stack([look_at_opencv(p) for p in pos[name]]).astype(np.float32)
        imgs, als = zip(*(render_in_room(K, c, resolution, resolution, seed=seed + i) for i, c in enumerate(c2w)))
        cams = Cameras(np.repeat(K[None], len(c2w), 0), c2w, resolution, resolution)
        splits[name] = ImageSet(cams, np.stack(imgs), None, [f"{name}_{i:03d}" for i in range(len(c2w))])
        alphas[name] = np.stack(als)
    return Scene(splits=splits, background=None, bbox=None, source="built-in room", kind="synthetic-room"), alphas
