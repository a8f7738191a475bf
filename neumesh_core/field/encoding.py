"""Input encodings for the decoders (pure torch)."""
from __future__ import annotations

import math

import torch


def frequency_encoding(x: torch.Tensor, n_freqs: int) -> torch.Tensor:
    """x (...,) -> (..., 1 + 2*n_freqs): [x, sin(2^i pi x), cos(2^i pi x)]."""
    if n_freqs == 0:
        return x[..., None]
    freqs = (2.0 ** torch.arange(n_freqs, device=x.device, dtype=x.dtype)) * math.pi
    xb = x[..., None] * freqs
    if torch.is_grad_enabled() and x.requires_grad:
        return torch.cat([x[..., None], torch.sin(xb), torch.cos(xb)], -1)
    # written into one output (torch.cat along the last axis is ~3x slower than slice copies on the CPU)
    out = x.new_empty(*x.shape, 1 + 2 * n_freqs)
    out[..., 0] = x
    out[..., 1:1 + n_freqs] = torch.sin(xb)
    out[..., 1 + n_freqs:] = torch.cos(xb)
    return out


def sh_encoding(d: torch.Tensor, degree: int = 4) -> torch.Tensor:
    """Real spherical harmonics of unit directions d (...,3) up to ``degree`` (1..4) -> degree^2 values."""
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree > 1:
        out += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
    if degree > 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            1.0925484305920792 * xy,
            -1.0925484305920792 * yz,
            0.94617469575755997 * zz - 0.31539156525251999,
            -1.0925484305920792 * xz,
            0.54627421529603959 * (xx - yy),
        ]
    if degree > 3:
        out += [
            0.59004358992664352 * y * (-3.0 * xx + yy),
            2.8906114426405538 * xy * z,
            0.45704579946446572 * y * (1.0 - 5.0 * zz),
            0.3731763325901154 * z * (5.0 * zz - 3.0),
            0.45704579946446572 * x * (1.0 - 5.0 * zz),
            1.4453057213202769 * z * (xx - yy),
            0.59004358992664352 * x * (-xx + 3.0 * yy),
        ]
    if torch.is_grad_enabled() and d.requires_grad:
        return torch.stack(out, -1)
    res = d.new_empty(*x.shape, len(out))   # column writes: faster than stack along the last axis
    for i, c in enumerate(out):
        res[..., i] = c
    return res


_EXP_MAX = 15.0  # exp(15) = 3.3e6 per unit length: opaque at any step size, and never inf (inf-inf = nan)


class _TruncExp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x.clamp(max=_EXP_MAX))

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(max=_EXP_MAX))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    """exp with a clamped gradient (instant-NGP's density activation); the output saturates at
    exp(15), where the gradient stays that of exp(15) so a too-dense sample can still be lowered."""
    return _TruncExp.apply(x)
