"""Pinhole cameras and ray generation.

Convention (one for the whole project): ``c2w`` is camera-to-world in the **OpenCV** convention
(x right, y down, z forward).  Blender / NeRF-synthetic cameras (OpenGL: y up, -z forward) are
converted on read with :func:`opengl_to_opencv`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0]).astype(np.float32)


def opengl_to_opencv(c2w_gl: np.ndarray) -> np.ndarray:
    """Convert camera-to-world matrices (...,4,4) from OpenGL/Blender to OpenCV convention."""
    return (np.asarray(c2w_gl, dtype=np.float32) @ _GL_TO_CV).astype(np.float32)


def opencv_to_opengl(c2w_cv: np.ndarray) -> np.ndarray:
    """Inverse of :func:`opengl_to_opencv`."""
    return (np.asarray(c2w_cv, dtype=np.float32) @ _GL_TO_CV).astype(np.float32)


def intrinsics_from_fov(fov_x: float, width: int, height: int) -> np.ndarray:
    """3x3 K for a horizontal field of view (radians), principal point at the image centre."""
    f = 0.5 * width / np.tan(0.5 * fov_x)
    return np.array([[f, 0, width / 2.0], [0, f, height / 2.0], [0, 0, 1]], dtype=np.float32)


@dataclass
class Cameras:
    """N pinhole cameras sharing one image size.

    K: (N,3,3) float32 intrinsics in pixels. c2w: (N,4,4) float32 camera-to-world, OpenCV convention.
    """

    K: np.ndarray
    c2w: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float32).reshape(-1, 3, 3)
        self.c2w = np.asarray(self.c2w, dtype=np.float32).reshape(-1, 4, 4)
        if len(self.K) == 1 and len(self.c2w) > 1:
            self.K = np.repeat(self.K, len(self.c2w), axis=0)
        if len(self.K) != len(self.c2w):
            raise ValueError(f"Cameras: {len(self.K)} intrinsics but {len(self.c2w)} poses")
        if not (np.isfinite(self.K).all() and np.isfinite(self.c2w).all()):
            raise ValueError("Cameras: intrinsics or poses contain NaN/inf; check the camera file")
        self.width = int(self.width)
        self.height = int(self.height)

    def __len__(self) -> int:
        return len(self.c2w)

    def subset(self, idx) -> "Cameras":
        idx = np.atleast_1d(np.asarray(idx))
        return Cameras(self.K[idx], self.c2w[idx], self.width, self.height)

    def scaled(self, factor: float) -> "Cameras":
        """Cameras for images resized by ``factor`` (e.g. 0.5 halves the resolution)."""
        K = self.K.copy()
        K[:, :2, :] *= factor
        return Cameras(K, self.c2w.copy(), int(round(self.width * factor)), int(round(self.height * factor)))

    @property
    def centres(self) -> np.ndarray:
        return self.c2w[:, :3, 3]


def pixel_rays(K, c2w, width: int, height: int, device="cpu", pixels: torch.Tensor | None = None,
               offset: tuple = (0.5, 0.5)):
    """Rays through pixel centres of one camera.

    Returns ``(origins, directions)`` as float32 tensors of shape (H*W,3) (row-major, y then x), or
    (P,3) when ``pixels`` (P,2) integer (x, y) coordinates are given. Directions are unit length.
    ``offset``: where in each pixel the rays pass, (x, y) in [0, 1) (the centre by default); sub-pixel
    offsets give the rays of a supersampled render.
    """
    K = torch.as_tensor(np.asarray(K), dtype=torch.float32, device=device)
    c2w = torch.as_tensor(np.asarray(c2w), dtype=torch.float32, device=device)
    if pixels is None:
        ys, xs = torch.meshgrid(
            torch.arange(height, device=device, dtype=torch.float32),
            torch.arange(width, device=device, dtype=torch.float32),
            indexing="ij",
        )
        xs, ys = xs.reshape(-1), ys.reshape(-1)
    else:
        xs, ys = pixels[:, 0].to(device, torch.float32), pixels[:, 1].to(device, torch.float32)
    y = (ys + float(offset[1]) - K[1, 2]) / K[1, 1]
    x = (xs + float(offset[0]) - K[0, 2] - K[0, 1] * y) / K[0, 0]  # K[0,1] is the skew (0 for most cameras)
    d_cam = torch.stack([x, y, torch.ones_like(x)], -1)
    d = d_cam @ c2w[:3, :3].T
    d = d / d.norm(dim=-1, keepdim=True)
    o = c2w[:3, 3].expand_as(d).contiguous()
    return o, d


def ray_to_axis_factor(K, width: int, height: int) -> np.ndarray:
    """(H,W) float32: for the ray through each pixel centre, the camera-axis (z) component of its unit
    direction, so that ``z = t * factor`` turns a distance ``t`` along the ray into the distance along
    the camera's viewing axis (Blender's / OpenGL's Z pass convention)."""
    K = np.asarray(K, np.float64)
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64) + 0.5
    y = (ys - K[1, 2]) / K[1, 1]
    x = (xs - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return (1.0 / np.sqrt(x * x + y * y + 1.0)).astype(np.float32)


def ray_to_axis_depth(depth, K) -> np.ndarray:
    """Distance along each pixel's ray (H,W) (``RenderOutput.depth``; inf where empty) -> distance
    along the camera axis (H,W) (the Z of Blender's Cycles/EEVEE Depth pass; inf stays inf)."""
    depth = np.asarray(depth, np.float32)
    h, w = depth.shape
    return depth * ray_to_axis_factor(K, w, h)


def axis_to_ray_depth(z, K) -> np.ndarray:
    """Inverse of :func:`ray_to_axis_depth`: camera-axis distance (H,W) -> distance along each ray."""
    z = np.asarray(z, np.float32)
    h, w = z.shape
    return z / ray_to_axis_factor(K, w, h)


def batch_pixel_rays(K: torch.Tensor, c2w: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor):
    """Rays for a batch of pixels, each from its own camera: K (B,3,3), c2w (B,4,4), xs/ys (B,)
    pixel indices (centres at +0.5).  Returns unit-direction rays (origins (B,3), dirs (B,3))."""
    y = (ys.float() + 0.5 - K[:, 1, 2]) / K[:, 1, 1]
    x = (xs.float() + 0.5 - K[:, 0, 2] - K[:, 0, 1] * y) / K[:, 0, 0]
    d_cam = torch.stack([x, y, torch.ones_like(x)], -1)
    d = torch.einsum("bij,bj->bi", c2w[:, :3, :3], d_cam)
    d = d / d.norm(dim=-1, keepdim=True)
    return c2w[:, :3, 3].contiguous(), d
