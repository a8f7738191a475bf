"""Shared by the edit tests: a camera on the built-in blob, and which pixels' rays touch a region."""
import numpy as np
import torch

import neumesh_core as nm
from neumesh_core.metrics import psnr
from neumesh_core.render.renderer import RenderSettings, default_step
from neumesh_core.sampling.marcher import march_rays

SIZE = 48


def camera(azimuth_deg: float = 0.0, size: int = SIZE, distance: float = 3.5):
    """K, c2w (OpenCV) of a camera on a circle around the blob, looking at its centre."""
    from neumesh_core.data.synthetic import look_at_opencv

    a = np.radians(azimuth_deg)
    pos = distance * np.array([np.sin(a), -np.cos(a), 0.35])
    K = np.array([[0.9 * size, 0, size / 2], [0, 0.9 * size, size / 2], [0, 0, 1]], np.float32)
    return K, look_at_opencv(pos).astype(np.float32)


def render(field, view=0.0):
    K, c2w = camera(view)
    return nm.render_camera(field, K, c2w, SIZE, SIZE)


def _samples(field, K, c2w, size):
    o, d = nm.pixel_rays(K, c2w, size, size)
    return march_rays(o, d, field.grid, field.sigma_fn, default_step(field, RenderSettings()))


def _per_pixel(size, rays, flags):
    out = torch.zeros(size * size, dtype=torch.bool)
    out[rays[flags]] = True
    return out.view(size, size).numpy()


def touched_pixels(field, vertices, view=0.0, cam=None, size=SIZE) -> np.ndarray:
    """(H,W) bool: pixels whose rendered samples look up any of ``vertices`` (texture edits leave the
    densities alone, so the same samples are taken before and after an edit).  ``cam``: (K, c2w)
    instead of the view angle."""
    K, c2w = cam if cam is not None else camera(view)
    s = _samples(field, K, c2w, size)
    hit = torch.zeros(field.num_vertices, dtype=torch.bool)
    hit[torch.as_tensor(np.asarray(vertices))] = True
    return _per_pixel(size, s.ray_indices, (hit[s.aux.idx] & s.aux.valid).any(1))


def only_touching(field, vertices, view=0.0, cam=None, size=SIZE) -> np.ndarray:
    """(H,W) bool: pixels with samples whose every neighbour lies in ``vertices``, and no other samples."""
    K, c2w = cam if cam is not None else camera(view)
    s = _samples(field, K, c2w, size)
    inside = torch.zeros(field.num_vertices, dtype=torch.bool)
    inside[torch.as_tensor(np.asarray(vertices))] = True
    pure = (inside[s.aux.idx] | ~s.aux.valid).all(1)
    any_ = _per_pixel(size, s.ray_indices, torch.ones_like(pure))
    return any_ & ~_per_pixel(size, s.ray_indices, ~pure)


def masked_psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    return float(psnr(a[mask], b[mask]))
