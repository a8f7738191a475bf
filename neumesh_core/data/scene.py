"""The common structure every dataset reader returns."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .cameras import Cameras


def as_float(a):
    """Pixels as float32 in [0,1]: uint8 (0..255) divided by 255, bool as 0/1, float as is (float32).
    Works on numpy arrays and torch tensors (any shape): the one conversion every image reader uses."""
    if a is None:
        return None
    try:
        import torch

        if isinstance(a, torch.Tensor):
            if a.dtype == torch.uint8:
                return a.to(torch.float32).mul_(1.0 / 255.0)
            return a.to(torch.float32)
    except ImportError:  # pragma: no cover - torch is a core dependency
        pass
    a = np.asarray(a)
    if a.dtype == np.uint8:
        out = a.astype(np.float32)
        out *= np.float32(1.0 / 255.0)
        return out
    return a.astype(np.float32, copy=False)


@dataclass
class ImageSet:
    """Images of one split with their cameras.

    images: (N,H,W,3) uint8 (photos as read: a quarter of float32's memory) or float32 in [0,1]
    (renders), already composited on the scene background where alpha exists.
    masks: optional (N,H,W) uint8 (0..255), bool or float32 in [0,1] (alpha for Blender data,
    thresholded {0,1} for DTU).
    Read pixels through :meth:`float_view` / :meth:`float_mask` (one view) or :meth:`float_images` /
    :meth:`float_masks` (several), which give float32 in [0,1] whatever the storage; the trainer's
    batcher gathers from the stored arrays and converts each batch with :func:`as_float`.
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
        if self.images.dtype != np.uint8 and self.images.dtype.kind != "f":
            raise ValueError(f"ImageSet: images must be uint8 or float in [0,1], got {self.images.dtype}")
        if self.masks is not None and self.masks.dtype not in (np.uint8, np.bool_) and self.masks.dtype.kind != "f":
            raise ValueError(f"ImageSet: masks must be uint8, bool or float in [0,1], got {self.masks.dtype}")

    def __len__(self) -> int:
        return len(self.images)

    def float_view(self, i: int) -> np.ndarray:
        """Image ``i`` as (H,W,3) float32 in [0,1] (a converted copy when stored as uint8)."""
        return as_float(self.images[int(i)])

    def float_mask(self, i: int) -> Optional[np.ndarray]:
        """Mask ``i`` as (H,W) float32 in [0,1], or None without masks."""
        return None if self.masks is None else as_float(self.masks[int(i)])

    def float_images(self, idx=None) -> np.ndarray:
        """Images ``idx`` (default all) as (n,H,W,3) float32 in [0,1]; with uint8 storage this is a
        float copy (4x the stored bytes): prefer :meth:`float_view` one image at a time."""
        return as_float(self.images if idx is None else self.images[np.atleast_1d(np.asarray(idx))])

    def float_masks(self, idx=None) -> Optional[np.ndarray]:
        """Masks ``idx`` (default all) as (n,H,W) float32 in [0,1], or None without masks."""
        if self.masks is None:
            return None
        return as_float(self.masks if idx is None else self.masks[np.atleast_1d(np.asarray(idx))])

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
    mesh_path: the true mesh shipped with the scene, when there is one (the built-in scene has it).
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
