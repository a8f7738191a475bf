"""The common structure every dataset reader returns."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .cameras import Cameras


@dataclass
class ImageSet:
    """Images of one split with their cameras.

    images: (N,H,W,3) float32 in [0,1], already composited on the scene background where alpha exists.
    masks: optional (N,H,W) float32 in [0,1] (alpha for Blender data, thresholded {0,1} for DTU).
    """

    cameras: Cameras
    images: np.ndarray
    masks: Optional[np.ndarray] = None
    names: list = field(default_factory=list)

    def __post_init__(self) -> None:
        if len(self.images) != len(self.cameras):
            raise ValueError(f"ImageSet: {len(self.images)} images but {len(self.cameras)} cameras")
        if self.images.shape[1:3] != (self.cameras.height, self.cameras.width):
            raise ValueError(
                f"ImageSet: images are {self.images.shape[2]}x{self.images.shape[1]} but cameras say "
                f"{self.cameras.width}x{self.cameras.height}"
            )
        if self.masks is not None and self.masks.shape != self.images.shape[:3]:
            raise ValueError("ImageSet: masks must have shape (N,H,W) matching the images")

    def __len__(self) -> int:
        return len(self.images)

    def subset(self, idx) -> "ImageSet":
        idx = np.atleast_1d(np.asarray(idx))
        return ImageSet(
            self.cameras.subset(idx),
            self.images[idx],
            None if self.masks is None else self.masks[idx],
            [self.names[i] for i in idx] if self.names else [],
        )


@dataclass
class Scene:
    """A dataset: named splits ('train', 'val', 'test'), background colour and bounds.

    background: RGB in [0,1] that images were composited on (None: images are not composited,
    e.g. DTU, whose background is real).  bbox: (2,3) float32 axis-aligned bounds of the object
    (min, max), used to place the occupancy grid / scaffold volume when no mesh is given.
    mesh_path: a reference mesh shipped with the scene (the built-in scene has its true mesh).
    """

    splits: dict
    background: Optional[tuple] = None
    bbox: Optional[np.ndarray] = None
    source: str = ""
    kind: str = ""  # "blender" | "dtu" | "transforms" | "colmap"
    mesh_path: Optional[str] = None
    notes: list = field(default_factory=list)  # reader remarks (e.g. "no masks found")
    capture: Optional[object] = None  # data.capture.Capture for real captures: raw rig, sparse points, aabb_scale

    @property
    def has_masks(self) -> bool:
        """True when every split has masks (object silhouettes). Real captures usually have none:
        training then fits the whole image (background included); see scene.notes."""
        return all(s.masks is not None for s in self.splits.values())

    def split(self, name: str) -> ImageSet:
        if name not in self.splits:
            raise KeyError(f"split '{name}' not in this scene; it has {sorted(self.splits)}")
        return self.splits[name]
