"""Which path renders a call: the fused kernel alone, the torch path with the kernel marching, or the
torch path alone.  :func:`render_path` is the one place that decides; the renderer asks it once per
call (``render_rays``, ``render_camera``'s ray order, ``mod_colour_weights``).

``RenderSettings.backend``: "auto" (the kernel on CUDA when triton imports and covers the field, the
torch path otherwise, the CPU always), "torch" (the reference) or "triton" (the kernel, an error where
it cannot run).  The fused kernel renders a call alone only when the call asks for nothing it does
not compute (training with autograd, jitter, vertex ids, semantics, several fields composited
together); those calls take the torch path, which still marches each covered field with the kernel
(its MARCH variant, ``fused.march_rays_fused``) and decodes the samples with the torch decoders.

Nothing here imports triton on the CPU's default path.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch

BACKENDS = ("auto", "torch", "triton")


def supported(field) -> Optional[str]:
    """None when the fused kernel renders ``field`` exactly as the torch path does, else the reason
    it does not (the torch path then renders it)."""
    if len(field.rad_decoders) != 1:
        return "the field has several radiance decoders (decoder binding after a texture edit)"
    if field.tex_frame is not None:
        return "the field has texture frames (a swap or fill from a differently oriented surface)"
    if field.code_prior is not None:
        return "coarse code levels are attached (training)"
    if field.config.sh_degree > 4 or field.config.sh_degree < 1:
        return f"sh_degree {field.config.sh_degree} (the kernel encodes degrees 1-4)"
    if field.config.k > 32:
        return f"k={field.config.k} (the kernel keeps up to 32 neighbours)"
    if not math.isfinite(field.radius) or field.radius <= 0:
        return "the field's radius is not finite"
    return None


@dataclass(frozen=True)
class RenderPath:
    """What renders one call: ``fused`` (the fused kernel renders it alone, ``fused.render_rays_fused``)
    or, when not, per field whether the kernel marches it for the torch path (``march``)."""

    fused: bool
    march: tuple


def render_path(settings, fields, device, *, train: bool = False, jitter=None, vertex_ids: bool = False,
                semantics: bool = False, march_only: bool = False) -> RenderPath:
    """The path for rendering ``fields`` on ``device`` under ``settings.backend`` (see the module).
    ``train``, ``jitter``, ``vertex_ids``, ``semantics``: what the call asks for; ``march_only``: the
    caller marches and decodes itself (never the whole kernel).  Under "triton" a field the kernel
    cannot render, or a device it cannot run on, raises :class:`~neumesh_core.errors.NeuMeshError`."""
    backend = getattr(settings, "backend", "auto")
    if backend not in BACKENDS:
        raise ValueError(f"RenderSettings.backend must be one of {', '.join(BACKENDS)}, not {backend!r}")
    n = len(fields)
    if backend == "torch" or (backend == "auto" and torch.device(device).type != "cuda"):
        return RenderPath(False, (False,) * n)   # the CPU's default: triton is not even imported
    whole = not (march_only or train or jitter is not None or vertex_ids or semantics) and n == 1
    if backend == "auto":
        from .knn import triton_available

        covered = tuple(supported(f) is None and triton_available() for f in fields)
        return RenderPath(whole and covered[0], covered)
    for f in fields:   # "triton" asked for explicitly: every field must be covered
        _require_supported(f, device)
    return RenderPath(whole, (True,) * n)


def use_triton(settings, fields, device, *, train: bool = False, jitter=None, vertex_ids: bool = False,
               semantics: bool = False) -> bool:
    """Whether the fused kernel renders this call alone: ``render_path(...).fused``."""
    return render_path(settings, fields, device, train=train, jitter=jitter, vertex_ids=vertex_ids,
                       semantics=semantics).fused


def use_fused_march(settings, field, device) -> bool:
    """Whether the torch path marches ``field`` with the kernel: ``render_path(...).march``."""
    return render_path(settings, [field], device, march_only=True).march[0]


def _require_supported(field, device) -> None:
    from ..errors import NeuMeshError
    from .knn import require_triton

    require_triton(device)
    reason = supported(field)
    if reason is not None:
        raise NeuMeshError(f"the Triton renderer cannot render this: {reason}; use "
                           "RenderSettings(backend='auto') to fall back to the torch renderer")
