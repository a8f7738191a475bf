"""The background model of real captures (the paper's "unbounded scenes").

The mesh field holds the object inside its :class:`~neumesh_core.data.frame.ObjectBox`; everything
else (the room, the support the object stands on or hangs from) is a separate, cheap field in plain
torch: density + colour features in mip-NeRF 360's contracted space (``y = (x - centre) / radius``,
``|y| <= 1`` kept, beyond it ``(2 - 1/|y|) y/|y|``, so the whole world fits in a ball of radius 2),
read from K-Planes (or a dense grid), and a tiny MLP (features + view direction -> colour).

Sampling (``version`` 2, what ``neumesh fit`` trains): the space is the box's own (``y`` in the box's
axes, centred on the box), so a wall or table parallel to the box's faces lies in one plane of the
K-Planes; each ray is sampled at even steps of its length in the contracted space (even in distance
inside the ball, even in disparity beyond it) from the camera to far away, and the samples inside
the object box hold nothing. A ray just inside the box's outline and one just outside it are sampled
alike, so the box's edges leave no seam. The last interval reaches infinity (the background is
opaque: a photo has no holes). Version 1 (files written before it): world axes, each ray sampled
evenly in disparity from where it leaves the box (or, missing the box, from its closest approach to
the frame centre); such files render as they were trained.

The renderer composites it behind the mesh field by the mesh field's transmittance:
``rgb = rgb_field + (1 - opacity_field) * rgb_background`` (``render.renderer.render_rays``,
``background_model=``).  It never depends on the scaffold's vertices, so deformations and edits of
the object never move it.  Saved with the field (``field.io``: header entry ``background`` +
``param/background.*`` tensors); files without it load as fields without a background.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F


def contract(y: torch.Tensor) -> torch.Tensor:
    """mip-NeRF 360's contraction: identity inside the unit ball, ``(2 - 1/|y|) y/|y|`` outside."""
    n = y.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    return torch.where(n <= 1, y, (2 - 1 / n) * y / n)


def ray_box_exit(o: torch.Tensor, d: torch.Tensor, centre, half, rot):
    """(t_enter, t_exit) of rays against an oriented box (inf/-inf-free: t_enter > t_exit = miss)."""
    lo_ = (o - centre) @ rot          # ray in box coordinates
    ld = d @ rot
    inv = 1.0 / torch.where(ld.abs() < 1e-12, torch.full_like(ld, 1e-12), ld)
    t0 = (-half - lo_) * inv
    t1 = (half - lo_) * inv
    return torch.minimum(t0, t1).amax(-1), torch.maximum(t0, t1).amin(-1)


_PLANE_AXES = ((0, 1), (0, 2), (1, 2))   # the xy, xz and yz planes


def plane_features(z: torch.Tensor, planes) -> torch.Tensor:
    """K-Planes features of points ``z`` (S,3) in [-1,1]^3: per scale the product of the bilinear reads
    of its three planes (each (1, F, n, n): xy, xz, yz) -> (S, scales*F)."""
    feats = []
    for k in range(0, len(planes), 3):
        f = None
        for (a, b), plane in zip(_PLANE_AXES, planes[k:k + 3]):
            g = F.grid_sample(plane, z[:, (a, b)].view(1, -1, 1, 2), mode="bilinear", align_corners=True)
            g = g.view(plane.shape[1], -1).t()
            f = g if f is None else f * g
        feats.append(f)
    return torch.cat(feats, -1)


def bilinear_reference(uv: torch.Tensor, plane: torch.Tensor) -> torch.Tensor:
    """Reference of one plane read: ``plane`` (F, n, n) indexed [v, u], read bilinearly at ``uv`` (S,2) in
    [-1,1]^2 (corners at the ends: align_corners=True) by explicit corner gathers."""
    n = plane.shape[-1]
    p = (uv.clamp(-1, 1) + 1) * 0.5 * (n - 1)
    p0 = p.floor().clamp_max(n - 2)
    f = p - p0
    i0 = p0.long()
    out = 0
    for du in (0, 1):
        for dv in (0, 1):
            w = (f[:, 0] if du else 1 - f[:, 0]) * (f[:, 1] if dv else 1 - f[:, 1])
            out = out + w[:, None] * plane[:, i0[:, 1] + dv, i0[:, 0] + du].t()
    return out


class BackgroundModel(nn.Module):
    """Contracted-space features + MLP colour head.  ``planes`` empty: one dense grid (``resolution``^3
    x (1 + ``features``), read by grid_sample; the first version).  ``planes`` = resolutions (e.g. (128,
    512)): per resolution three feature planes (xy, xz, yz; ``plane_features`` channels) multiplied as in
    K-Planes, then a tiny density MLP: 512^2 per plane costs 3 x 0.26M x F numbers where a 512^3 grid
    would cost 134M x F, so a fine background stays cheap to train on the CPU."""

    def __init__(self, centre, radius: float, box=None, resolution: int = 64, features: int = 8,
                 hidden: int = 32, samples: int = 48, far_factor: float = 100.0, planes=(),
                 plane_features: int = 8, version: int = 1, support_samples: int = 0):
        super().__init__()
        planes = tuple(int(p) for p in planes)
        if resolution < 2 or features < 1 or samples < 2 or radius <= 0:
            raise ValueError("BackgroundModel: resolution >= 2, features >= 1, samples >= 2, radius > 0")
        if any(p < 2 for p in planes) or plane_features < 1:
            raise ValueError("BackgroundModel: plane resolutions >= 2 and plane_features >= 1")
        self.centre_np = np.asarray(centre, np.float64).reshape(3)
        self.radius = float(radius)
        self.box = box   # data.frame.ObjectBox or None (the whole ray is background)
        self.resolution, self.features, self.hidden = int(resolution), int(features), int(hidden)
        self.samples, self.far_factor = int(samples), float(far_factor)
        self.planes, self.plane_features = planes, int(plane_features)
        if int(version) not in (1, 2):
            raise ValueError(f"BackgroundModel: version 1 or 2, got {version}")
        self.version = int(version)
        if support_samples < 0:
            raise ValueError("BackgroundModel: support_samples >= 0")
        self.support_samples = int(support_samples)
        gen = torch.Generator().manual_seed(0)
        if not self.planes:
            r = self.resolution
            grid = torch.zeros(1, 1 + self.features, r, r, r)
            grid[:, 0] = -2.0   # low initial density: softplus(-2) ~ 0.13 per radius
            grid[:, 1:].normal_(0, 0.1, generator=gen)
            self.grid = nn.Parameter(grid)
        else:   # K-Planes' initialisation: products of values near 0.1..0.5
            self.plane_params = nn.ParameterList(
                [nn.Parameter(torch.empty(1, self.plane_features, p, p).uniform_(0.1, 0.5, generator=gen))
                 for p in self.planes for _ in range(3)])
            self.density_mlp = nn.Sequential(nn.Linear(len(self.planes) * self.plane_features, self.hidden),
                                             nn.ReLU(), nn.Linear(self.hidden, 1 + self.features))
        self.mlp = nn.Sequential(nn.Linear(self.features + 3, self.hidden), nn.ReLU(),
                                 nn.Linear(self.hidden, 3))

    # -- configuration (the file header holds it; the tensors are the parameters) --------------------
    def config(self) -> dict:
        return {"centre": self.centre_np.tolist(), "radius": self.radius,
                "box": None if self.box is None else self.box.to_dict(), "resolution": self.resolution,
                "features": self.features, "hidden": self.hidden, "samples": self.samples,
                "far_factor": self.far_factor, "planes": list(self.planes),
                "plane_features": self.plane_features, "version": self.version,
                "support_samples": self.support_samples}

    @classmethod
    def from_config(cls, cfg: dict) -> "BackgroundModel":
        from ..data.frame import ObjectBox

        box = None if cfg.get("box") is None else ObjectBox.from_dict(cfg["box"])
        return cls(cfg["centre"], cfg["radius"], box, int(cfg["resolution"]), int(cfg["features"]),
                   int(cfg["hidden"]), int(cfg["samples"]), float(cfg["far_factor"]), tuple(cfg.get("planes", ())),
                   int(cfg.get("plane_features", 8)), int(cfg.get("version", 1)),
                   int(cfg.get("support_samples", 0)))

    def tv_loss(self) -> torch.Tensor:
        """K-Planes' total variation of the feature planes: the mean squared difference of neighbouring
        texels along both axes, summed over the planes (0 for the dense grid).  Smooths what few
        photos see (the held-out views' walls), as ``TrainConfig.weight_background_tv`` weighs it."""
        if not self.planes:
            return self.mlp[0].weight.new_zeros(())
        total = 0.0
        for p in self.plane_params:
            total = total + ((p[..., 1:, :] - p[..., :-1, :]) ** 2).mean() + ((p[..., 1:] - p[..., :-1]) ** 2).mean()
        return total

    # -- sampling ------------------------------------------------------------------------------------
    def _frame(self, like: torch.Tensor):
        """(centre (3,), rotation (3,3)) of the model's space: the box's axes for version 2."""
        c = torch.as_tensor(self.centre_np, dtype=like.dtype, device=like.device)
        if self.version == 2 and self.box is not None:
            return c, torch.as_tensor(self.box.rotation, dtype=like.dtype, device=like.device)
        return c, None

    def ray_start(self, o: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Version 1: where each ray's background begins: the box exit, else its closest approach to
        the centre."""
        c = torch.as_tensor(self.centre_np, dtype=o.dtype, device=o.device)
        t_close = ((c - o) * d).sum(-1).clamp_min(0)
        if self.box is None:
            return torch.zeros_like(t_close)
        t_in, t_out = self._box_range(o, d)
        hit = (t_in <= t_out) & (t_out > 0)
        return torch.where(hit, t_out.clamp_min(0), t_close)

    def _box_range(self, o: torch.Tensor, d: torch.Tensor):
        bc = torch.as_tensor(self.box.centre, dtype=o.dtype, device=o.device)
        bh = torch.as_tensor(self.box.half_extents, dtype=o.dtype, device=o.device)
        br = torch.as_tensor(self.box.rotation, dtype=o.dtype, device=o.device)
        return ray_box_exit(o, d, bc, bh, br)

    def _edges_v1(self, origins, dirs, jitter):
        R, S = origins.shape[0], self.samples
        t0 = self.ray_start(origins, dirs).clamp_min(0.02 * self.radius)
        t_far = t0 + self.far_factor * self.radius
        u = torch.arange(S + 1, dtype=origins.dtype, device=origins.device) / S   # S intervals
        if jitter is not None:
            u = (u[None, :] + (jitter[:, None].to(origins.dtype) - 0.5) / S).clamp(0, 1)
        else:
            u = u[None, :].expand(R, -1)
        # evenly in disparity between 1/t0 and 1/t_far
        return 1.0 / (1.0 / t0[:, None] * (1 - u) + 1.0 / t_far[:, None] * u)

    def _edges_v2(self, origins, dirs, jitter, candidates: int = 128):
        """Interval edges (R, S+1) at even steps of each ray's length in the contracted space, from
        0.01 radius to ``far_factor`` radii (found on ``candidates`` points even in disparity)."""
        R, S = origins.shape[0], self.samples
        dt, dev = origins.dtype, origins.device
        near, far = 0.01 * self.radius, self.far_factor * self.radius
        u = torch.arange(candidates + 1, dtype=dt, device=dev) / candidates
        tc = 1.0 / (1.0 / near * (1 - u) + 1.0 / far * u)                          # (M+1,)
        c, rot = self._frame(origins)
        x = origins[:, None, :] + dirs[:, None, :] * tc[None, :, None] - c
        y = contract((x if rot is None else x @ rot) / self.radius)
        seg = (y[:, 1:] - y[:, :-1]).norm(dim=-1)                                   # (R, M)
        L = torch.cat([torch.zeros_like(seg[:, :1]), seg.cumsum(1)], 1)           # (R, M+1)
        v = torch.arange(S + 1, dtype=dt, device=dev) / S
        if jitter is not None:
            v = (v[None, :] + (jitter[:, None].to(dt) - 0.5) / S).clamp(0, 1)
        else:
            v = v[None, :].expand(R, -1)
        target = (v * L[:, -1:]).contiguous()
        k = torch.searchsorted(L.contiguous(), target).clamp(1, candidates)
        L0, L1 = L.gather(1, k - 1), L.gather(1, k)
        w = ((target - L0) / (L1 - L0).clamp_min(1e-12)).clamp(0, 1)
        return tc[k - 1] + w * (tc[k] - tc[k - 1])

    def _support_edges(self, origins, dirs, jitter):
        """(R, n) extra interval edges where each ray meets the support the box rests on (a wall, a
        table: just behind the box's face at -half_extents[2] on its third axis), ``support_samples``
        of them evenly over a slab from that face to a tenth of the box's third half-size behind it, so
        the room's nearest, most detailed surface is sampled where it is, not only at the even steps.
        Rays that meet the slab behind the camera or run along it get edges at the ray's start (empty
        intervals)."""
        n = self.support_samples
        dt = origins.dtype
        br = torch.as_tensor(self.box.rotation, dtype=dt, device=origins.device)
        bc = torch.as_tensor(self.box.centre, dtype=dt, device=origins.device)
        h = float(self.box.half_extents[2])
        oz = ((origins - bc) @ br)[:, 2]
        dz = (dirs @ br)[:, 2]
        u = (torch.arange(n, dtype=dt, device=origins.device) + 0.5) / n
        if jitter is not None:
            u = (u[None, :] + (jitter[:, None].to(dt) - 0.5) / n).clamp(0, 1)
        else:
            u = u[None, :].expand(origins.shape[0], -1)
        z = -h - 0.1 * h * u                                                      # face -> behind it
        ok = dz.abs() > 1e-6
        te = (z - oz[:, None]) / torch.where(ok, dz, torch.ones_like(dz))[:, None]
        near = 0.01 * self.radius
        return torch.where(ok[:, None] & (te > near), te, torch.full_like(te, near))

    def query(self, x: torch.Tensor, d: torch.Tensor):
        """Density per radius (S,) and colour (S,3) at world points ``x`` (S,3) seen along ``d``."""
        c, rot = self._frame(x)
        if rot is not None:
            x, d = (x - c) @ rot, d @ rot
            z = contract(x / self.radius) * 0.5          # in [-1, 1]^3 for grid_sample
        else:
            z = contract((x - c) / self.radius) * 0.5
        if not self.planes:
            g = F.grid_sample(self.grid, z.view(1, -1, 1, 1, 3), mode="bilinear", align_corners=True)
            g = g.view(1 + self.features, -1).t()
        else:
            g = self.density_mlp(plane_features(z, list(self.plane_params)))
        sigma = F.softplus(g[:, 0])
        rgb = torch.sigmoid(self.mlp(torch.cat([g[:, 1:], d], -1)))
        return sigma, rgb

    def forward(self, origins: torch.Tensor, dirs: torch.Tensor, jitter: Optional[torch.Tensor] = None,
                far: Optional[torch.Tensor] = None):
        """Render rays: premultiplied colour (R,3) and opacity (R,) of the background (1 where nothing
        cuts it: the last interval is opaque).  ``jitter`` (R,) in [0,1) shifts the samples (training);
        ``far`` (R,) cuts the background behind an occluder (nothing past it counts)."""
        R = origins.shape[0]
        if R == 0:
            return origins.new_zeros(0, 3), origins.new_zeros(0)
        t = self._edges_v2(origins, dirs, jitter) if self.version == 2 else self._edges_v1(origins, dirs, jitter)
        if self.support_samples and self.version == 2 and self.box is not None and self.box.on_support:
            t = torch.sort(torch.cat([t, self._support_edges(origins, dirs, jitter)], 1), 1).values
        S = t.shape[1] - 1
        mid = 0.5 * (t[:, 1:] + t[:, :-1])
        x = origins[:, None, :] + dirs[:, None, :] * mid[..., None]
        sigma, rgb = self.query(x.reshape(-1, 3), dirs[:, None, :].expand(-1, S, -1).reshape(-1, 3))
        sigma, rgb = sigma.view(R, S), rgb.view(R, S, 3)
        if self.version == 2 and self.box is not None:   # the object box holds nothing of the room
            t_in, t_out = self._box_range(origins, dirs)
            sigma = torch.where((mid > t_in[:, None]) & (mid < t_out[:, None]), torch.zeros_like(sigma), sigma)
        dt = (t[:, 1:] - t[:, :-1]) / self.radius
        alpha = 1 - torch.exp(-sigma * dt)
        alpha = torch.cat([alpha[:, :-1], torch.ones_like(alpha[:, -1:])], 1)   # opaque at infinity
        if far is not None:
            alpha = torch.where(mid < far.to(mid.dtype)[:, None], alpha, torch.zeros_like(alpha))
        trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), 1)
        w = trans * alpha
        return (w[..., None] * rgb).sum(1), w.sum(1)


def background_for(c2w: np.ndarray, box, points: Optional[np.ndarray] = None, radius: Optional[float] = None,
                   **kw) -> BackgroundModel:
    """A background model framed by the cameras (``data.frame.scene_frame``) around ``box``.  The
    contraction radius (the ball kept at full resolution) is the frame's radius, or ``radius`` (world
    units; e.g. twice the box's half-size, so the walls just behind the object get the fine texels)."""
    from ..data.frame import scene_frame

    fr = scene_frame(c2w, points)
    return BackgroundModel(fr.centre, fr.radius if radius is None else radius, box, **kw)


#: the background model of fitted real captures (neumesh fit): K-Planes at 128 and 512 texels in the
#: object box's axes, 32 samples a ray even in the contracted space and 8 more where it meets the
#: support the box rests on, the contraction ball centred on the box and twice its largest half-size
#: (docs/real_captures.md)
FIT_BACKGROUND = {"planes": (128, 512), "samples": 32, "version": 2, "support_samples": 8}


def fit_background_for(c2w: np.ndarray, box, points: Optional[np.ndarray] = None) -> BackgroundModel:
    """The background model ``neumesh fit`` trains for a real capture (:data:`FIT_BACKGROUND`): centred
    on ``box`` in its axes (without a box: the cameras' frame, world axes)."""
    if box is None:
        return background_for(c2w, None, points, **{**FIT_BACKGROUND, "version": 1})
    return BackgroundModel(box.centre, 2.0 * float(np.max(box.half_extents)), box, **FIT_BACKGROUND)


def attach_background(field, model: Optional[BackgroundModel]) -> None:
    """Give ``field`` its background model (None removes it); a submodule, so it moves with
    ``field.to`` and is saved by ``save_field``."""
    if model is None:
        if "background" in field._modules:
            del field._modules["background"]
        return
    field.background = model.to(field.rest_vertices.device)


def background_of(field) -> Optional[BackgroundModel]:
    return field._modules.get("background") if isinstance(field, nn.Module) else None
