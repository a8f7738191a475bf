"""The painted view, shared by the two kinds of paint (edit/paint.py: modification colours at the vertex
spacing; edit/paint_atlas.py: texels of the paint atlas): its configuration, the layer a painter made,
the rays of its painted pixels and their render, the render it was painted on."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import EditError



@dataclass
class PaintConfig:
    """Parameters of :func:`paint_texture`."""

    ring_weight: float = 1.0      # weight of "keep the original colour" on the ring around the stroke
    damping: float = 1e-3         # pull of each changed modification colour towards its current value
    hit_opacity: float = 0.5      # a painted pixel paints the surface where the render is this opaque
    facing: bool = True           # only vertices whose normal faces the camera take paint
    chunk_rays: int = 16384

    def __post_init__(self) -> None:
        if self.ring_weight < 0 or self.damping <= 0:
            raise EditError("ring_weight must be >= 0 and damping > 0")
        if not 0 < self.hit_opacity <= 1:
            raise EditError("hit_opacity must lie in (0, 1]")


def _checked_layer(paint_rgba, width: int, height: int) -> np.ndarray:
    """The painted view as float32 (H,W,4), or an EditError that says what went wrong."""
    layer = np.asarray(paint_rgba, np.float32)
    if layer.ndim != 3 or layer.shape[:2] != (height, width) or layer.shape[2] != 4:
        raise EditError(f"the paint layer must be ({height}, {width}, 4) RGBA for this {width}x{height} view, "
                        f"got {layer.shape}; was the camera or the image size changed since the render?")
    if not np.isfinite(layer).all():
        raise EditError("the paint layer holds NaN/inf values")
    return layer


def paint_layer(painted: np.ndarray, original: np.ndarray, threshold: float = 1.5 / 255) -> np.ndarray:
    """(H,W,4) straight-alpha paint layer from a painted image and the render it was painted on: alpha
    is 1 where any channel differs by more than ``threshold`` (a pixel quantised to 8 bits and back
    differs by at most 0.5/255), and the colour is the painted one."""
    p = np.asarray(painted, np.float32)[..., :3]
    o = np.asarray(original, np.float32)[..., :3]
    if p.shape != o.shape:
        raise EditError(f"the painted image is {p.shape[1]}x{p.shape[0]} but the render it was painted on is "
                        f"{o.shape[1]}x{o.shape[0]}; paint on the render of this view (Paint on view)")
    alpha = (np.abs(p - o).max(-1) > threshold).astype(np.float32)
    return np.concatenate([p, alpha[..., None]], -1)


def _cancel(progress, fraction):
    if progress is not None and progress(float(fraction)) is False:
        from ..render.renderer import Cancelled

        raise Cancelled("painting cancelled; the field is unchanged")


def _rays(K, c2w, width, height, pixels: np.ndarray, device):
    from ..data.cameras import pixel_rays

    px = torch.as_tensor(np.stack([pixels % width, pixels // width], 1), dtype=torch.long)
    return pixel_rays(K, c2w, width, height, device=device, pixels=px)


def _render(fields, o, d, settings, chunk):
    from ..render.renderer import render_rays

    outs = []
    with torch.no_grad():
        for s in range(0, len(o), chunk):
            r = render_rays(fields, o[s:s + chunk], d[s:s + chunk], None, settings)
            outs.append((r["rgb"].cpu(), r["opacity"].cpu(), r["depth"].cpu()))
    if not outs:
        z = torch.zeros(0)
        return torch.zeros(0, 3), z, z
    return tuple(torch.cat(x) for x in zip(*outs))


def _checked_surface(surface, width: int, height: int):
    """(opacity, depth) flat float arrays of the render a layer was painted on, or an EditError."""
    try:
        if isinstance(surface, (tuple, list)):
            op, depth = surface
        else:
            op, depth = surface.opacity, surface.depth
        op, depth = np.asarray(op, np.float32), np.asarray(depth, np.float32)
    except (TypeError, ValueError, AttributeError) as exc:
        raise EditError("surface must be the render the layer was painted on (render_camera's result, or "
                        "(opacity, depth) arrays)") from exc
    if op.shape != (height, width) or depth.shape != (height, width):
        raise EditError(f"the render painted on is {op.shape[::-1]} / {depth.shape[::-1]}, not this {width}x{height} "
                        "view; pass the render of this view, or none (the painted pixels are rendered again)")
    return op.reshape(-1), depth.reshape(-1)


def _render_pixels(field, K, c2w, width: int, height: int, pixels: np.ndarray, settings, chunk: int):
    """(opacity, depth) of some pixels of a view, rendered as :func:`render_camera` renders them (the
    same per-pixel ray ranges, so the same samples and the same expected depths)."""
    K32, c2w32 = K.astype(np.float32), c2w.astype(np.float32)
    device = field.rest_vertices.device
    op = np.zeros(len(pixels), np.float32)
    depth = np.full(len(pixels), np.inf, np.float32)
    ranges = field.grid.camera_ranges(K32, c2w32, width, height, settings.empty_tile) if settings.skip_empty \
        else None
    rows = np.arange(len(pixels))
    if ranges is not None:
        pt = torch.as_tensor(pixels, device=ranges[0].device)
        near, far = ranges[0][pt], ranges[1][pt]
        live = (near <= far).cpu().numpy()
        rows = rows[live]
        near, far = near[torch.as_tensor(live, device=near.device)], far[torch.as_tensor(live, device=near.device)]
    if len(rows) == 0:
        return op, depth
    o, d = _rays(K32, c2w32, width, height, pixels[rows], device)
    from ..render.renderer import render_rays

    with torch.no_grad():
        for s in range(0, len(rows), chunk):
            e = min(len(rows), s + chunk)
            r = render_rays([field], o[s:e], d[s:e], None, settings, train=False,
                            ranges=None if ranges is None else [(near[s:e], far[s:e])])
            op[rows[s:e]] = r["opacity"].cpu().numpy()
            depth[rows[s:e]] = r["depth"].cpu().numpy()
    return op, depth


__all__ = ["PaintConfig", "paint_layer"]
