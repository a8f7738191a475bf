"""Coarse-to-fine dense density + colour grid fitted by volume rendering random rays (pure torch).

Density is stored per node of a regular grid over the scaffold box and trilinearly interpolated;
sigma is expressed per voxel length (alpha of one voxel = 1 - exp(-sigma)).  Colour is a per-node
RGB (SH degree 0).  Density is confined to an ``allowed`` region (the dilated visual hull, or the
whole box without masks).  Losses: photometric MSE, mask BCE on opacity (when masks exist) and a
small total-variation term.  Behind the grid each ray sees: a known background colour, the ground
truth (masks), a background model (``field/background.py``: the room of a photo without masks,
trained with the grid, so the room is not painted onto the box), or a learnt colour per view.
:func:`grid_depths` renders the fitted grid's median depth and opacity per view (what
``fusion.py`` fuses into one surface).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from ..data.scene import ImageSet


@dataclass
class DensityResult:
    sigma: np.ndarray  # (nx,ny,nz) per-voxel-length density at nodes of the final grid
    lo: np.ndarray
    voxel: float
    iterations: int
    final_loss: float
    final_psnr: float
    rays_per_sec: float
    spacing: np.ndarray = None   # (3,) node spacing per axis of the final grid (voxel is their mean)


_CORNERS = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=torch.long)


def trilinear(table: torch.Tensor, dims, f: torch.Tensor) -> torch.Tensor:
    """Trilinear lookup in a node grid stored as a (nx*ny*nz, C) table (C order).

    f: (P,3) continuous node coordinates.  Uses F.embedding, whose backward is a fast dense
    scatter-add on CPU (much faster than grid_sample's 3-D backward).
    """
    hi = torch.tensor([d - 2 for d in dims], dtype=torch.float32)
    i0 = torch.minimum(f.floor().clamp_min(0.0), hi)
    w = (f - i0).clamp(0.0, 1.0)  # (P,3)
    i0 = i0.long()
    c = i0[:, None, :] + _CORNERS[None]  # (P,8,3)
    lin = (c[..., 0] * dims[1] + c[..., 1]) * dims[2] + c[..., 2]
    wc = torch.where(_CORNERS[None].bool(), w[:, None, :], 1.0 - w[:, None, :]).prod(-1)  # (P,8)
    vals = F.embedding(lin, table)  # (P,8,C)
    return (vals * wc[..., None]).sum(1)


def _ray_box(o, d, lo, hi):
    inv = 1.0 / torch.where(d.abs() < 1e-9, torch.full_like(d, 1e-9), d)
    t0 = (lo - o) * inv
    t1 = (hi - o) * inv
    tn = torch.minimum(t0, t1).max(-1).values.clamp_min(0.0)
    tf = torch.maximum(t0, t1).min(-1).values
    return tn, tf


def _pixel_rays(K: torch.Tensor, c2w: torch.Tensor, px: torch.Tensor):
    """Unit rays (origins, dirs) through pixel positions ``px`` (R,2) of cameras ``K`` (R,3,3),
    ``c2w`` (R,4,4) (OpenCV)."""
    yc = (px[:, 1] - K[:, 1, 2]) / K[:, 1, 1]
    xc = (px[:, 0] - K[:, 0, 2] - K[:, 0, 1] * yc) / K[:, 0, 0]
    dcam = torch.stack([xc, yc, torch.ones_like(xc)], -1)
    d = torch.einsum("rij,rj->ri", c2w[:, :3, :3], dcam)
    return c2w[:, :3, 3], d / d.norm(dim=-1, keepdim=True)


def _box_samples(o, d, lo_t, hi_t, n_samples: int, step_world: float, offset: torch.Tensor):
    """Samples along each ray from where it enters the box: t (R,S), points (R,S,3) and which lie in
    the box (R,S). ``offset`` (R,1): each ray's stratification offset in [0, 1)."""
    tn, tf = _ray_box(o, d, lo_t, hi_t)
    steps = torch.arange(n_samples, dtype=torch.float32)[None] + offset
    t = tn[:, None] + steps * step_world
    valid = (tf > tn)[:, None] & (t < tf[:, None])
    return t, o[:, None, :] + d[:, None, :] * t[..., None], valid


def _grid_index(pts, lo_t, vox_vec, dims):
    idx = ((pts - lo_t) / vox_vec).round().long()
    for a in range(3):
        idx[..., a] = idx[..., a].clamp(0, dims[a] - 1)
    return idx


@dataclass
class _Grid:
    """One stage's grid: ``table`` (M, 4) density parameter and colour logits per node, the allowed
    nodes (as floats for interpolation and as bools per cell), the node dims, the box and the voxel
    size (per axis and mean)."""

    table: torch.Tensor
    allow_flat: torch.Tensor
    allow_bool: torch.Tensor
    dims: tuple
    lo: torch.Tensor
    hi: torch.Tensor
    vox_vec: torch.Tensor
    vox: float

    @classmethod
    def of(cls, sig_param, col_param, allow, dims: tuple, lo, hi, vox_vec) -> "_Grid":
        """The stage's grid from its (1, 1, *dims) density and (1, 3, *dims) colour parameters (the
        table is a new leaf the optimiser trains) and its allowed nodes (1, 1, *dims floats)."""
        M = int(np.prod(dims))
        table = torch.cat([sig_param, col_param], 1)[0].reshape(4, M).T.contiguous().requires_grad_(True)
        return cls(table, allow[0, 0].reshape(M, 1).contiguous(), allow[0, 0] > 0.5, dims, lo, hi, vox_vec,
                   float(vox_vec.mean()))


def _composite(grid: _Grid, o, d, n_samples: int, step_world: float, u) -> tuple:
    """Colour (B, 3) and opacity (B,) of rays through the grid: stratified samples in the box (offset
    ``u``), only in allowed cells, alpha-composited."""
    B = len(o)
    _, pts, valid = _box_samples(o, d, grid.lo, grid.hi, n_samples, step_world, u)
    idx = _grid_index(pts, grid.lo, grid.vox_vec, grid.dims)
    valid &= grid.allow_bool[idx[..., 0], idx[..., 1], idx[..., 2]]
    sel = valid.nonzero(as_tuple=True)
    fc = (pts[sel] - grid.lo) / grid.vox_vec
    q = trilinear(grid.table, grid.dims, fc)
    with torch.no_grad():
        a_s = trilinear(grid.allow_flat, grid.dims, fc)[:, 0]
    sigma = F.softplus(q[:, 0]) * a_s
    dens = torch.zeros(B, n_samples).index_put(sel, sigma * (step_world / grid.vox))
    col = torch.zeros(B, n_samples, 3).index_put(sel, torch.sigmoid(q[:, 1:4]))
    w = _weights(dens)
    return (w[..., None] * col).sum(1), w.sum(1)


def _march(dims: tuple, ext) -> tuple:
    """(samples per ray, step in world units) through a grid of ``dims`` nodes spanning ``ext``: about
    1.6 samples per node along the longest axis (at most 512), over 1.8 times its length (a diagonal)."""
    n_samples = int(min(512, math.ceil(1.6 * max(dims))))
    return n_samples, float(ext.max() * 1.8 / n_samples)


def _weights(dens):
    """Compositing weights of samples with optical depths ``dens`` (rays x samples): alpha times the
    transmittance before each sample."""
    return (1.0 - torch.exp(-dens)) * torch.exp(-(torch.cumsum(dens, 1) - dens))


def _stage_start(sig_param, col_param, inside_t, dims: tuple, empty_init: float):
    """A stage's starting density and colour grids: the first from ``inside_t`` (dense inside, a fog
    of ``empty_init`` elsewhere), later ones the previous stage's resampled."""
    if sig_param is None:
        inside = F.interpolate(inside_t, size=dims, mode="trilinear", align_corners=True)
        sig0 = torch.where(inside > 0.5, torch.tensor(3.0), torch.tensor(float(empty_init)))
        return sig0.clone(), torch.zeros((1, 3) + dims)
    return (F.interpolate(sig_param.detach(), size=dims, mode="trilinear", align_corners=True),
            F.interpolate(col_param.detach(), size=dims, mode="trilinear", align_corners=True))


def _stage_optimizer(table, lr: float, bg_param, background_model, background_lr: float):
    """Adam over a stage's grid, the learnt background colours and the background model."""
    params = [{"params": [table], "lr": lr}]
    if bg_param is not None:
        params.append({"params": [bg_param], "lr": 0.01})
    if background_model is not None:
        params.append({"params": list(background_model.parameters()), "lr": background_lr})
    try:
        return torch.optim.Adam(params, betas=(0.9, 0.99), fused=True)
    except (RuntimeError, TypeError):  # fused kernels unavailable on this build
        return torch.optim.Adam(params, betas=(0.9, 0.99))


def _density_tv(table, dims: tuple):
    """Total variation of the density parameter over the grid's three axes."""
    s = table[:, 0].reshape(dims)
    return ((s[1:] - s[:-1]) ** 2).mean() + ((s[:, 1:] - s[:, :-1]) ** 2).mean() + \
        ((s[:, :, 1:] - s[:, :, :-1]) ** 2).mean()


def fit_density(images: ImageSet, allowed: np.ndarray, init_inside: np.ndarray, lo, voxel: float,
                resolutions=(64, 128), iters=(300, 400), batch_rays: int = 4096,
                background=None, use_masks: bool = True, lr: float = 0.1, mask_weight: float = 0.5,
                tv_weight: float = 1e-4, seed: int = 0, check=None, log=None, background_model=None,
                background_lr: float = 1e-2, empty_init: float = -2.0) -> DensityResult:
    """Fit the grid. ``allowed``/``init_inside``: bool node grids (any resolution) over the box
    starting at ``lo`` with spacing ``voxel``; they are resampled to each stage's grid.
    ``background_model``: a module ``(origins, dirs, jitter) -> (rgb, opacity)`` for what each ray
    sees behind the box (e.g. a BackgroundModel in the images' frame), trained with the grid at
    ``background_lr``; it takes the place of the learnt colour per view of photos without masks.
    ``empty_init``: the density parameter the nodes outside ``init_inside`` start from (softplus of it
    per voxel length: -2 is a light fog, -5 nearly clear air).
    ``check(fraction)`` is called every few iterations (it raises to cancel)."""
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    cams = images.cameras
    N, H, W = len(cams), cams.height, cams.width
    dims0 = np.asarray(allowed.shape)
    ext = (dims0 - 1) * voxel
    lo_t = torch.as_tensor(np.asarray(lo, np.float32))
    hi_t = lo_t + torch.as_tensor(ext, dtype=torch.float32)
    imgs = torch.from_numpy(np.ascontiguousarray(images.float_images().reshape(N, H * W, 3)))
    masks = None
    if use_masks and images.masks is not None:
        masks = torch.from_numpy(np.ascontiguousarray(images.float_masks().reshape(N, H * W)))
    bg = None if background is None else torch.tensor(background, dtype=torch.float32)
    learn_bg = masks is None and bg is None and background_model is None
    bg_param = torch.full((N, 3), 0.0, requires_grad=True) if learn_bg else None

    K = torch.as_tensor(cams.K)
    c2w = torch.as_tensor(cams.c2w)
    allowed_t = torch.from_numpy(allowed.astype(np.float32))[None, None]
    inside_t = torch.from_numpy(init_inside.astype(np.float32))[None, None]

    total_iters = int(sum(iters))
    done = 0
    sig_param = col_param = None
    t_start = time.perf_counter()
    rays_done = 0
    last_loss, last_psnr = float("nan"), float("nan")
    for stage, (res, n_it) in enumerate(zip(resolutions, iters)):
        vox0 = float(ext.max() / res)
        dims = tuple(int(max(2, math.ceil(e / vox0) + 1)) for e in ext)
        vox_vec = torch.as_tensor(ext / (np.asarray(dims) - 1), dtype=torch.float32)  # exact box
        allow = (F.interpolate(allowed_t, size=dims, mode="trilinear", align_corners=True) > 0.01).float()
        sig_param, col_param = _stage_start(sig_param, col_param, inside_t, dims, empty_init)
        grid = _Grid.of(sig_param, col_param, allow, dims, lo_t, hi_t, vox_vec)
        table, vox = grid.table, grid.vox
        opt = _stage_optimizer(table, lr, bg_param, background_model, background_lr)
        n_samples, step_world = _march(dims, ext)
        for it in range(n_it):
            # --- random rays over all views
            vi = torch.randint(0, N, (batch_rays,), generator=gen)
            pi = torch.randint(0, H * W, (batch_rays,), generator=gen)
            px = torch.stack([(pi % W).float() + torch.rand(batch_rays, generator=gen),
                              (pi // W).float() + torch.rand(batch_rays, generator=gen)], -1)
            o, d = _pixel_rays(K[vi], c2w[vi], px)
            gt = imgs[vi, pi]
            gm = masks[vi, pi] if masks is not None else None
            rgb, op = _composite(grid, o, d, n_samples, step_world, torch.rand(batch_rays, 1, generator=gen))
            if background_model is not None:
                bgc, _ = background_model(o, d, jitter=torch.rand(batch_rays, generator=gen))
            elif bg_param is not None:
                bgc = torch.sigmoid(bg_param[vi])
            elif bg is not None:
                bgc = bg.expand_as(rgb)
            else:  # masks but real background: composite on the ground truth (only foreground counts)
                bgc = gt
            pred = rgb + (1.0 - op[:, None]) * bgc
            mse = ((pred - gt) ** 2).mean()
            loss = mse
            if gm is not None:
                opc = op.clamp(1e-4, 1 - 1e-4)
                loss = loss + mask_weight * F.binary_cross_entropy(opc, gm)
            if tv_weight > 0:
                loss = loss + tv_weight * _density_tv(table, dims)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            rays_done += batch_rays
            done += 1
            last_loss = float(loss.detach())
            last_psnr = float(-10 * math.log10(max(float(mse.detach()), 1e-10)))
            if log is not None and (it % 100 == 0 or it == n_it - 1):
                log(f"density stage {stage} ({'x'.join(map(str, dims))}) it {it}/{n_it}: "
                    f"loss {last_loss:.4f} psnr {last_psnr:.2f}")
            if check is not None and (it % 10 == 0):
                check(done / max(total_iters, 1))
        with torch.no_grad():
            g = table.detach().T.reshape((1, 4) + dims)
            sig_param, col_param = g[:, :1].contiguous(), g[:, 1:].contiguous()
    with torch.no_grad():
        sig = (F.softplus(sig_param) * allow)[0, 0].numpy()  # last stage's grid
    el = time.perf_counter() - t_start
    return DensityResult(sig.astype(np.float32), np.asarray(lo, np.float32), vox, done, last_loss,
                         last_psnr, rays_done / max(el, 1e-9), vox_vec.numpy().astype(np.float64))


@torch.no_grad()
def grid_depths(res: DensityResult, cameras, chunk: int = 8192, check=None):
    """Median depth (the ray distance where the grid's opacity reaches half its total; inf where the
    total stays below 0.5) and opacity of every pixel of every camera: (depth (N,H,W), opacity
    (N,H,W)) float32, the grid composited as :func:`fit_density` trains it (no background)."""
    sig = torch.from_numpy(np.ascontiguousarray(res.sigma, np.float32))
    dims = tuple(sig.shape)
    table = sig.reshape(-1, 1).contiguous()
    vox_vec = torch.as_tensor(res.spacing, dtype=torch.float32)
    vox = float(vox_vec.mean())
    lo_t = torch.as_tensor(np.asarray(res.lo, np.float32))
    ext = vox_vec * (torch.tensor(dims, dtype=torch.float32) - 1)
    hi_t = lo_t + ext
    n_samples, step_world = _march(dims, ext)
    N, H, W = len(cameras), cameras.height, cameras.width
    K, c2w = torch.as_tensor(cameras.K, dtype=torch.float32), torch.as_tensor(cameras.c2w, dtype=torch.float32)
    depth = np.full((N, H * W), np.inf, np.float32)
    opac = np.zeros((N, H * W), np.float32)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float32) + 0.5, torch.arange(W, dtype=torch.float32) + 0.5,
                            indexing="ij")
    pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)
    for v in range(N):
        for s in range(0, H * W, chunk):
            px = pix[s:s + chunk]
            R = px.shape[0]
            o, d = _pixel_rays(K[v].expand(R, 3, 3), c2w[v].expand(R, 4, 4), px)
            t, pts, valid = _box_samples(o, d, lo_t, hi_t, n_samples, step_world, torch.full((R, 1), 0.5))
            sel = valid.nonzero(as_tuple=True)
            dens = torch.zeros(R, n_samples)
            dens[sel] = trilinear(table, dims, (pts[sel] - lo_t) / vox_vec)[:, 0] * (step_world / vox)
            w = _weights(dens)
            op = w.sum(1)
            cw = torch.cumsum(w, 1)
            k = torch.searchsorted(cw, (0.5 * op)[:, None].contiguous()).clamp_max(n_samples - 1)[:, 0]
            dep = t.gather(1, k[:, None])[:, 0]
            depth[v, s:s + R] = torch.where(op >= 0.5, dep, torch.full_like(dep, float("inf"))).numpy()
            opac[v, s:s + R] = op.numpy()
        if check is not None:
            check((v + 1) / N)
    return depth.reshape(N, H, W), opac.reshape(N, H, W)
