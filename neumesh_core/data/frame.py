"""Scene frame and object box of a real capture (issue 49).

A phone capture has the object somewhere in a room.  :func:`scene_frame` finds where the cameras look
(the least-squares point closest to every optical axis), how far they are (the scale) and which way
is up (the mean of the cameras' up vectors); the world coordinates are never changed (Blender's
cameras stay where they are): the frame only sizes the background model's contracted space.
:func:`object_box` puts an :class:`ObjectBox` around what the cameras look at: the sparse points
near the focus point (robust 5-95 % percentiles), or without points a cube sized from the camera
distance.  ``parse_box`` reads ``--box cx,cy,cz,sx,sy,sz`` (centre and half-extents).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np


@dataclass
class ObjectBox:
    """An oriented box: ``centre`` (3,), ``half_extents`` (3,) along the box axes, ``rotation`` (3,3)
    whose columns are the box axes in world space (identity: axis-aligned).  The mesh field holds
    what is inside; the background model holds the rest."""

    centre: np.ndarray
    half_extents: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    #: how it was found (said to the user; not saved): see :func:`object_box`
    source: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        self.centre = np.asarray(self.centre, np.float64).reshape(3)
        self.half_extents = np.asarray(self.half_extents, np.float64).reshape(3)
        self.rotation = np.asarray(self.rotation, np.float64).reshape(3, 3)
        if not (np.isfinite(self.centre).all() and np.isfinite(self.half_extents).all()
                and np.isfinite(self.rotation).all()):
            raise ValueError("ObjectBox: centre, half_extents and rotation must be finite numbers")
        if (self.half_extents <= 0).any():
            raise ValueError(f"ObjectBox: half_extents must be > 0, got {self.half_extents.tolist()}")
        if not np.allclose(self.rotation.T @ self.rotation, np.eye(3), atol=1e-4):
            raise ValueError("ObjectBox: rotation must be a rotation matrix (orthonormal columns); remove "
                             "shear/scale from the box object and put the size in half_extents")

    def corners(self) -> np.ndarray:
        s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
        return self.centre + (s * self.half_extents) @ self.rotation.T

    def aabb(self) -> np.ndarray:
        """(2,3) float32 world-space axis-aligned bounds of the box (min, max)."""
        c = self.corners()
        return np.stack([c.min(0), c.max(0)]).astype(np.float32)

    def contains(self, points: np.ndarray) -> np.ndarray:
        local = (np.asarray(points, np.float64) - self.centre) @ self.rotation
        return (np.abs(local) <= self.half_extents).all(-1)

    def to_dict(self) -> dict:
        return {"centre": self.centre.tolist(), "half_extents": self.half_extents.tolist(),
                "rotation": self.rotation.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "ObjectBox":
        return cls(d["centre"], d["half_extents"], d.get("rotation", np.eye(3)))

    @classmethod
    def from_aabb(cls, bbox) -> "ObjectBox":
        b = np.asarray(bbox, np.float64).reshape(2, 3)
        return cls(0.5 * (b[0] + b[1]), np.maximum(0.5 * (b[1] - b[0]), 1e-6))


@dataclass
class SceneFrame:
    """Where the cameras look (``centre``), how far they are (``radius``: the largest camera distance
    from the centre) and which way is up (``up``, unit; the mean of the cameras' up vectors)."""

    centre: np.ndarray
    radius: float
    up: np.ndarray

    def to_dict(self) -> dict:
        return {"centre": np.asarray(self.centre).tolist(), "radius": float(self.radius),
                "up": np.asarray(self.up).tolist()}


def focus_point(c2w: np.ndarray) -> np.ndarray:
    """The point closest (least squares) to every camera's optical axis (OpenCV: +z forward)."""
    c2w = np.asarray(c2w, np.float64).reshape(-1, 4, 4)
    o = c2w[:, :3, 3]
    d = c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]   # projector orthogonal to each axis
    A = P.sum(0)
    b = np.einsum("nij,nj->i", P, o)
    if len(c2w) < 2 or np.linalg.cond(A) > 1e8:   # one camera or parallel axes: a point ahead of them
        return o.mean(0) + d.mean(0)
    return np.linalg.solve(A, b)


def scene_frame(c2w: np.ndarray, points: Optional[np.ndarray] = None) -> SceneFrame:
    """The capture's frame from its cameras (and sparse points, which widen the radius to the room)."""
    c2w = np.asarray(c2w, np.float64).reshape(-1, 4, 4)
    centre = focus_point(c2w)
    dist = np.linalg.norm(c2w[:, :3, 3] - centre, axis=1)
    radius = float(dist.max()) if len(dist) else 1.0
    if points is not None and len(points) >= 8:
        radius = max(radius, float(np.percentile(np.linalg.norm(points - centre, axis=1), 50)))
    up = -c2w[:, :3, 1].mean(0)   # OpenCV y points down
    n = np.linalg.norm(up)
    up = up / n if n > 1e-8 else np.array([0.0, 0.0, 1.0])
    return SceneFrame(centre, max(radius, 1e-6), up)


def object_box(c2w: np.ndarray, points: Optional[np.ndarray] = None, pad: float = 0.1,
               lo_pct: float = 5.0, hi_pct: float = 95.0) -> ObjectBox:
    """An axis-aligned box around what the cameras look at.

    With sparse points: the points within half the median camera distance of the focus point, their
    ``lo_pct``-``hi_pct`` percentiles per axis, padded by ``pad`` of the size.  Without (or with too few
    near points): a cube centred on the focus point with half-size 0.3 x the median camera distance."""
    c2w = np.asarray(c2w, np.float64).reshape(-1, 4, 4)
    centre = focus_point(c2w)
    med = float(np.median(np.linalg.norm(c2w[:, :3, 3] - centre, axis=1)))
    if points is not None and len(points) >= 8:
        pts = np.asarray(points, np.float64)
        near = pts[np.linalg.norm(pts - centre, axis=1) <= 0.5 * med]
        if len(near) >= 8:
            lo, hi = np.percentile(near, [lo_pct, hi_pct], axis=0)
            size = np.maximum(hi - lo, 1e-3 * med)
            return ObjectBox(0.5 * (lo + hi), 0.5 * size * (1 + 2 * pad),
                             source=f"sparse points near the cameras' focus ({lo_pct:g}-{hi_pct:g} %)")
    return ObjectBox(centre, np.full(3, 0.3 * med), source="the cameras' common look-at point")


def parse_box(text: str) -> ObjectBox:
    """``"cx,cy,cz,sx,sy,sz"`` (centre, half-extents; world units) -> :class:`ObjectBox`."""
    try:
        v = [float(x) for x in str(text).replace(" ", "").split(",")]
    except ValueError:
        v = []
    if len(v) != 6:
        raise ValueError(f"--box wants six numbers cx,cy,cz,sx,sy,sz (centre and half-sizes), got {text!r}")
    return ObjectBox(v[:3], v[3:])
