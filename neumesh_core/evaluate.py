"""Evaluate a field over a split: PSNR, SSIM (masked variants when masks exist), LPIPS if available."""
from __future__ import annotations

import json
import os
from typing import Callable, Optional

import numpy as np

from .data.cameras import Cameras, pixel_rays
from .data.scene import ImageSet
from .render.renderer import RenderSettings, render_camera


def evaluate(field, images: ImageSet, background=(1.0, 1.0, 1.0), masked: bool = False,
             out_dir: Optional[str] = None, lpips_cache: Optional[str] = None,
             settings: Optional[RenderSettings] = None,
             progress: Optional[Callable[[int, int], Optional[bool]]] = None) -> dict:
    """Render every camera of ``images`` and compare with its image.

    ``masked``: also report foreground metrics (pixels with mask > 0.5; DTU convention) and use them
    as the headline figures. ``background``: what the ground-truth images were composited on (None for
    real backgrounds, e.g. DTU: the render is then composited on black and only masked metrics mean
    much).  ``out_dir``: write renders as PNG.  Returns a dict with per-view and mean figures;
    ``lpips`` is None when its weights are not present locally (never faked).
    """
    from . import metrics
    from .imageio import save_image

    lp_ok = metrics.lpips_available(lpips_cache)
    rows = []
    for i in range(len(images)):
        cam = images.cameras
        out = render_camera(field, cam.K[i], cam.c2w[i], cam.width, cam.height,
                            background=background if background is not None else (0.0, 0.0, 0.0),
                            settings=settings)
        gt = images.float_view(i)
        pred = np.clip(out.rgb, 0.0, 1.0)
        row = {"view": images.names[i] if images.names else str(i), "psnr": metrics.psnr(pred, gt),
               "ssim": metrics.ssim(pred, gt), "render_s": out.seconds}
        if lp_ok:
            row["lpips"] = metrics.compute_lpips(pred, gt, cache_dir=lpips_cache)
        if masked and images.masks is not None:
            mf = images.float_mask(i)
            m = mf > 0.5
            row["psnr_fg"] = metrics.masked_psnr(pred, gt, mf)
            row["ssim_fg"] = metrics.ssim(pred, gt, mask=m)
        rows.append(row)
        if out_dir:
            save_image(os.path.join(out_dir, f"{row['view'].replace('/', '_')}.png"), pred)
        if progress is not None and progress(i + 1, len(images)) is False:
            break
    keys = [k for k in rows[0] if k != "view"] if rows else []
    mean = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    result = {"n_views": len(rows), "mean": mean, "views": rows,
              "lpips_available": lp_ok,
              "headline": {"psnr": mean.get("psnr_fg", mean.get("psnr")),
                           "ssim": mean.get("ssim_fg", mean.get("ssim")),
                           "lpips": mean.get("lpips")}}
    return result


def surface_points(K, c2w, depth: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """World points (P,3) where the rays through ``pixels`` (P,2) integer (x, y) of one camera meet a
    rendered ``depth`` map (H,W; distance along the ray, as :class:`RenderOutput` gives it)."""
    import torch

    o, d = pixel_rays(K, c2w, depth.shape[1], depth.shape[0], pixels=torch.as_tensor(pixels))
    t = depth[pixels[:, 1], pixels[:, 0]]
    return o.numpy() + d.numpy() * t[:, None]


def view_coverage(points: np.ndarray, cameras: Cameras, depths: np.ndarray, rel_tol: float = 0.01) -> np.ndarray:
    """How many of ``cameras`` see each world point (P,3) unoccluded: in front, in frame, and within
    ``rel_tol`` (relative) of that camera's depth map.  ``depths`` (N,H,W) are rendered distances along
    the ray at the cameras' resolution (inf where empty).  Returns (P,) int counts."""
    import torch

    from .data.views import ViewStack

    if depths.shape != (len(cameras), cameras.height, cameras.width):
        raise ValueError(f"depths must be (N,H,W) = ({len(cameras)},{cameras.height},{cameras.width}), "
                         f"got {depths.shape}")
    views = ViewStack.from_cameras(cameras)
    points = np.asarray(points, dtype=np.float32)
    pts = torch.from_numpy(points)
    counts = np.zeros(len(points), np.int64)
    for i in range(len(cameras)):
        u, v, z = (a.numpy() for a in views.project_view(i, pts))
        # pixel i spans [i, i+1): in frame is 0 <= u < width (ViewStack.in_frame also admits u == width)
        seen = (z > 1e-6) & (u >= 0) & (u < cameras.width) & (v >= 0) & (v < cameras.height)
        ui = np.clip(u.astype(np.int64), 0, cameras.width - 1)
        vi = np.clip(v.astype(np.int64), 0, cameras.height - 1)
        dist = np.linalg.norm(points - cameras.c2w[i, :3, 3], axis=1)
        seen &= np.abs(depths[i][vi, ui] - dist) <= rel_tol * dist
        counts += seen
    return counts


def write_json(obj, path: str) -> None:
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    tmp = path + ".tmp"
    with open(tmp, "w") as fh:
        json.dump(obj, fh, indent=2, default=float)
    os.replace(tmp, path)
