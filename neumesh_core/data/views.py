"""A stack of pinhole views as torch tensors: world -> pixel projection of many points at once.

Used by the scaffold builder (reconstruct/) and by evaluation (view coverage of surface points).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .cameras import Cameras


@dataclass
class ViewStack:
    """Per-view projection data as torch tensors (float32)."""

    R: torch.Tensor  # (N,3,3) world->camera rotation
    t: torch.Tensor  # (N,3)   world->camera translation
    K: torch.Tensor  # (N,3,3)
    width: int
    height: int
    sdf: torch.Tensor | None = None  # (N,1,H,W) signed distance to the mask boundary (pixels)

    @classmethod
    def from_cameras(cls, cams: Cameras) -> "ViewStack":
        c2w = torch.as_tensor(cams.c2w, dtype=torch.float64)
        R = c2w[:, :3, :3].transpose(1, 2)
        t = -(R @ c2w[:, :3, 3:4])[..., 0]
        return cls(R.float(), t.float(), torch.as_tensor(cams.K, dtype=torch.float32), cams.width, cams.height)

    def __len__(self) -> int:
        return len(self.R)

    def project(self, pts: torch.Tensor):
        """pts (P,3) -> u,v (N,P) pixel coordinates (pixel i spans [i, i+1)), z (N,P) depth."""
        pc = torch.einsum("nij,pj->npi", self.R, pts) + self.t[:, None, :]
        return _to_pixels(self.K[:, None], pc)

    def project_view(self, i: int, pts: torch.Tensor):
        """pts (...,3) -> u, v, z (...) in view ``i`` alone (same convention as :meth:`project`)."""
        return _to_pixels(self.K[i], pts @ self.R[i].T + self.t[i])

    def in_frame(self, u, v, z, margin: float = 0.0):
        return (z > 1e-6) & (u >= -margin) & (u <= self.width + margin) & (v >= -margin) & (v <= self.height + margin)

    def mean_focal(self) -> float:
        return float(0.5 * (self.K[:, 0, 0] + self.K[:, 1, 1]).mean())


def _to_pixels(K: torch.Tensor, pc: torch.Tensor):
    """Camera-space points pc (...,3) -> u, v, z with intrinsics K (...,3,3) broadcast against pc."""
    z = pc[..., 2]
    zs = torch.where(z.abs() < 1e-8, torch.full_like(z, 1e-8), z)
    x, y = pc[..., 0] / zs, pc[..., 1] / zs
    u = K[..., 0, 0] * x + K[..., 0, 1] * y + K[..., 0, 2]
    v = K[..., 1, 1] * y + K[..., 1, 2]
    return u, v, z
