"""Render rays and whole cameras from one or several fields."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Literal, Optional, Sequence

import numpy as np
import torch

from ..data.cameras import pixel_rays
from ..errors import Cancelled, NeuMeshError  # noqa: F401  (Cancelled: nm.Cancelled, lives in errors)
from ..kernels.path import BACKENDS, render_path
from ..sampling.marcher import march_rays
from .volume import composite, render_weights


@dataclass
class RenderSettings:
    """How rays are sampled.  step_scale: marching step = field radius x step_scale; None (default)
    uses the field's own ``FieldConfig.step_scale``, the step it was trained with."""

    step_scale: Optional[float] = None
    window: int = 32
    early_stop_eps: float = 1e-4
    weight_threshold: float = 1e-4
    near: float = 0.0
    chunk_rays: Optional[int] = None   # rays per batch; None: 32768 on the CPU, 2**20 on a GPU
    supersample: int = 1   # render_camera: S x S rays per pixel on a regular sub-pixel grid, averaged
    # render_camera: march each pixel only over the distances where its ray can meet an occupied cell,
    # and skip the pixels that meet none (OccupancyGrid.camera_ranges, ``empty_tile`` pixels square);
    # the same sample positions are evaluated, so the image is the same
    skip_empty: bool = True
    empty_tile: int = 8
    # which renderer marches and decodes: "auto" (the fused Triton kernel on CUDA when triton imports and
    # the field is covered; the torch path otherwise, the CPU included), "torch" (the reference) or
    # "triton" (the kernel, an error where it cannot run); kernels/path.render_path decides
    backend: Literal["auto", "torch", "triton"] = "auto"
    # render_camera: a field's background model (real captures, field/background.py) composited behind
    # the field by its transmittance: on, the photo-like frame; off, the object alone with a true alpha
    background_model: bool = True

    def __post_init__(self):
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be 'auto', 'torch' or 'triton', not {self.backend!r}")
        if int(self.supersample) != self.supersample or self.supersample < 1:
            raise ValueError(f"supersample must be a whole number >= 1, got {self.supersample}")


def chunk_size(settings: RenderSettings, device) -> int:
    """Rays per batch: ``settings.chunk_rays``, or by default 32768 on the CPU (large enough that the
    per-batch overheads of marching and the neighbour search stop mattering) and 2**20 on a GPU
    (a whole 800² frame in one batch: a GPU frame is bound by kernel launches, not memory)."""
    if settings.chunk_rays is not None:
        if int(settings.chunk_rays) < 1:
            raise ValueError(f"chunk_rays must be >= 1, got {settings.chunk_rays}")
        return int(settings.chunk_rays)
    return 1 << 20 if torch.device(device).type == "cuda" else 32768


def default_step(field, settings: RenderSettings) -> float:
    scale = settings.step_scale if settings.step_scale is not None else field.config.step_scale
    return float(field.config.radius) * float(scale)


def _as_list(fields):
    if isinstance(fields, (list, tuple)):
        return list(fields)
    return [fields]


def render_rays(fields, origins: torch.Tensor, dirs: torch.Tensor, background=None,
                settings: Optional[RenderSettings] = None, train: bool = False,
                jitter: Optional[torch.Tensor] = None, vertex_ids: bool = False,
                semantics: bool = False, far: Optional[torch.Tensor] = None,
                ranges: Optional[Sequence] = None, background_model=None) -> dict:
    """Render rays (R,3) through one field or a list of fields (composited jointly, sorted by depth).

    Returns tensors: rgb (R,3), opacity (R,), depth (R,) (expected distance, normalised by opacity;
    inf where empty), mod_colour (R,3), n_samples (int).  With ``train`` the decoders run with autograd;
    otherwise colours are decoded only for samples that survive marching.  With ``vertex_ids`` the
    output also lists, per field, the sorted unique scaffold vertices the samples looked up (for
    regularisers over the touched vertices; off by default, it costs a sort per call).  With
    ``semantics`` the output also holds ``sem`` (R,C): the fields' decoded semantic features composited
    with the colour's weights (every field must have a semantic branch of the same width); colour,
    opacity and depth are computed exactly as without it.
    ``background``: None (black / premultiplied), an (3,) colour, or (R,3) per-ray colours.
    ``far``: None, or (R,) distances along the rays past which nothing is sampled (an opaque surface
    in front of the field, e.g. a holdout object: the field behind it is cut).
    ``ranges``: None, or per field None or ((R,) near, (R,) far): the distances outside which that
    field's grid has nothing on each ray (:meth:`OccupancyGrid.camera_ranges`); marching skips them.
    ``background_model``: None, or a :class:`~neumesh_core.field.background.BackgroundModel` composited
    behind the fields by their transmittance (``rgb += (1 - opacity) * rgb_bg``; ``opacity`` stays the
    fields' own, the background's is ``bg_opacity``); ``background`` then fills what it leaves.
    """
    settings = settings or RenderSettings()
    fl = _as_list(fields)
    n = origins.shape[0]
    path = render_path(settings, fl, origins.device, train=train, jitter=jitter, vertex_ids=vertex_ids,
                       semantics=semantics)
    if path.fused:
        out = _render_fused(fl[0], origins, dirs, settings, far, None if ranges is None else ranges[0])
        return _over_and_behind(out, fl, origins, dirs, background, background_model, train, jitter, far)
    t_far = float("inf") if far is None else far.to(origins.device, torch.float32)
    sem_width = _semantic_width(fl) if semantics else 0
    parts = []
    touched = []
    for fi, f in enumerate(fl):
        near_f, far_f = settings.near, t_far
        if ranges is not None and ranges[fi] is not None:
            r_near, r_far = (x.to(origins.device) for x in ranges[fi])
            near_f = r_near.clamp_min(settings.near)
            far_f = torch.minimum(r_far, far_f) if torch.is_tensor(far_f) else r_far.clamp_max(far_f)
        s = _march(f, origins, dirs, settings, near_f, far_f, jitter, path.march[fi])
        if vertex_ids:
            touched.append(torch.unique(s.aux.idx[s.aux.valid]) if len(s) else
                           torch.zeros(0, dtype=torch.long, device=origins.device))
        if len(s) == 0:
            continue
        d = dirs.index_select(0, s.ray_indices)
        if train:
            sigma, rgb, mod = f.decode(s.aux, d, with_rgb=True)
        else:
            with torch.no_grad():
                _, rgb, mod = f.decode(s.aux, d, with_rgb=True, with_sigma=False)
            sigma = s.sigmas
        part = (s.ray_indices, s.t_starts, s.t_ends, sigma, rgb, mod)
        if semantics:
            with torch.set_grad_enabled(train and torch.is_grad_enabled()):
                part = part + (f.decode_semantics(s.aux),)
        parts.append(part)
    if not parts:
        z = torch.zeros(n, device=origins.device)
        rgb = torch.zeros(n, 3, device=origins.device)
        out = {"rgb": rgb, "opacity": z, "depth": torch.full_like(z, float("inf")),
               "mod_colour": rgb.clone(), "n_samples": 0}
        if semantics:
            out["sem"] = torch.zeros(n, sem_width, device=origins.device)
    else:
        if len(parts) == 1:
            cols = parts[0]
        else:
            cols = [torch.cat(x) for x in zip(*parts)]
            order = torch.sort(cols[1], stable=True).indices   # ties (equal t in two fields): field order
            order = order[torch.sort(cols[0][order], stable=True).indices]
            cols = [x[order] for x in cols]
        ri, ts, te, sig, rgb, mod = cols[:6]
        values = {"rgb": rgb, "mod_colour": mod}
        if semantics:
            values["sem"] = cols[6]
        c = composite(ri, ts, te, sig, values, n)
        depth = torch.where(c["opacity"] > 1e-6, c["depth"] / c["opacity"].clamp_min(1e-6),
                            torch.full_like(c["depth"], float("inf")))
        out = {"rgb": c["rgb"], "opacity": c["opacity"], "depth": depth, "mod_colour": c["mod_colour"],
               "n_samples": int(ri.shape[0])}
        if semantics:
            out["sem"] = c["sem"]
    if vertex_ids:
        out["vertex_ids"] = touched
    return _over_and_behind(out, fl, origins, dirs, background, background_model, train, jitter, far)


def _over_and_behind(out: dict, fl, origins, dirs, background, background_model, train, jitter, far) -> dict:
    """What goes over and behind the fields' own colour, for the torch and the fused path alike: texel
    paint (field.paint_atlas; not while training) at each ray's expected surface point, the background
    model by the fields' transmittance, then the plain ``background`` colour in what is left."""
    if not train:
        from ..field.paint_atlas import composite_paint

        out = composite_paint(fl, origins, dirs, out)
    rest = 1.0 - out["opacity"]
    if background_model is not None:
        t_far = None if far is None else far.to(origins.device, torch.float32)
        with torch.set_grad_enabled(train and torch.is_grad_enabled()):
            bg_rgb, bg_op = background_model(origins, dirs, jitter=jitter if train else None, far=t_far)
        out["rgb"] = out["rgb"] + rest[:, None] * bg_rgb
        out["bg_opacity"] = bg_op
        rest = rest * (1.0 - bg_op)
    if background is not None:
        bg = torch.as_tensor(background, dtype=out["rgb"].dtype, device=origins.device)
        out["rgb"] = out["rgb"] + rest[:, None] * bg
    return out


def _march(f, origins, dirs, settings, near, far, jitter, fused: bool):
    """A field's samples for the torch path (sorted by ray and t, ``aux`` their neighbourhoods): the fused
    kernel's march (kernels/fused.march_rays_fused: one launch, one synchronisation) when ``fused``
    (``render_path(...).march``), the torch marcher otherwise."""
    step = default_step(f, settings)
    kw = dict(near=near, far=far, window=settings.window, early_stop_eps=settings.early_stop_eps,
              weight_threshold=settings.weight_threshold, jitter=jitter)
    if fused:
        from ..kernels.fused import march_rays_fused

        return march_rays_fused(f, origins, dirs, step, **kw)
    return march_rays(origins, dirs, f.grid, f.sigma_fn, step, **kw)


def _render_fused(field, origins, dirs, settings, far, ranges) -> dict:
    """The fields' own part of :func:`render_rays` through the fused Triton kernel
    (kernels/fused.py): the same near/far limits as the torch path, the same outputs."""
    from ..kernels.fused import render_rays_fused

    near_f = settings.near
    far_f = float("inf") if far is None else far.to(origins.device, torch.float32)
    if ranges is not None:
        r_near, r_far = (x.to(origins.device) for x in ranges)
        near_f = r_near.clamp_min(settings.near)
        far_f = torch.minimum(r_far, far_f) if torch.is_tensor(far_f) else r_far.clamp_max(far_f)
    out = render_rays_fused(field, origins, dirs, settings, default_step(field, settings), near=near_f, far=far_f)
    out["n_samples"] = int(out["n_samples"].sum())
    return out


@torch.no_grad()
def mod_colour_weights(fields, origins: torch.Tensor, dirs: torch.Tensor,
                       settings: Optional[RenderSettings] = None) -> list:
    """How each ray's colour depends on the modification colours: for every field a scipy sparse
    (R, N_field) matrix W with ``rgb = rgb_without_mod + W @ field.mod_colours`` (each channel).

    The modification colour enters a sample linearly as sum_k w_k mod_k (post- and early
    interpolation alike), and samples composite with weights that do not depend on it, so once the
    geometry is fixed a ray's colour is affine in the modification colours: W[r, v] = sum over the
    ray's samples of (compositing weight x neighbour weight of v).  Rays are marched and composited
    exactly as :func:`render_rays` does (several fields jointly, sorted by depth).
    """
    import scipy.sparse as sp

    settings = settings or RenderSettings()
    fl = _as_list(fields)
    n = origins.shape[0]
    parts = []
    path = render_path(settings, fl, origins.device, march_only=True)
    for fi, f in enumerate(fl):
        s = _march(f, origins, dirs, settings, settings.near, float("inf"), None, path.march[fi])
        if len(s):
            parts.append((fi, s))
    out = [sp.csr_matrix((n, f.num_vertices), dtype=np.float64) for f in fl]
    if not parts:
        return out
    ri = torch.cat([s.ray_indices for _, s in parts])
    ts = torch.cat([s.t_starts for _, s in parts])
    te = torch.cat([s.t_ends for _, s in parts])
    sig = torch.cat([s.sigmas for _, s in parts])
    owner = torch.cat([torch.full((len(s),), fi, dtype=torch.long) for fi, s in parts])
    local = torch.cat([torch.arange(len(s)) for _, s in parts])
    if len(parts) > 1:   # the same order as render_rays
        order = torch.sort(ts, stable=True).indices
        order = order[torch.sort(ri[order], stable=True).indices]
        ri, ts, te, sig, owner, local = ri[order], ts[order], te[order], sig[order], owner[order], local[order]
    w = render_weights(ri, ts, te, sig, n)
    for fi, s in parts:
        m = owner == fi
        nb = s.aux.select(local[m])
        ww = (w[m][:, None] * nb.w) * nb.valid
        rows = ri[m][:, None].expand_as(nb.idx)
        keep = nb.valid & (ww > 0)
        out[fi] = sp.csr_matrix((ww[keep].double().cpu().numpy(),
                                 (rows[keep].cpu().numpy(), nb.idx[keep].cpu().numpy())),
                                shape=(n, fl[fi].num_vertices))
    return out


def _semantic_width(fields) -> int:
    for f in fields:
        if not getattr(f, "has_semantics", False):
            f._require_semantics()
    widths = {int(f.config.sem_features) for f in fields}
    if len(widths) != 1:
        from ..errors import NeuMeshError

        raise NeuMeshError(f"the fields' semantic features differ in width ({sorted(widths)}); render "
                           "their semantics one field at a time")
    return widths.pop()


@dataclass
class RenderOutput:
    """One rendered camera: numpy float32 arrays."""

    rgb: np.ndarray       # (H,W,3), composited on the background
    opacity: np.ndarray   # (H,W)
    depth: np.ndarray     # (H,W) distance along the ray (inf where empty)
    mod_colour: np.ndarray   # (H,W,3) rendered modification colour
    n_samples: int = 0
    seconds: float = 0.0
    sem: Optional[np.ndarray] = None   # (H,W,C) composited semantic features (render_camera(semantics=True))
    # (H,W) the background model's opacity behind the field (None: no background model rendered);
    # ``opacity`` stays the object's own (its true alpha), ``alpha`` is the frame's
    background_opacity: Optional[np.ndarray] = None

    @property
    def alpha(self) -> np.ndarray:
        """(H,W) coverage of the frame: the object's opacity, plus the background model's behind it."""
        if self.background_opacity is None:
            return self.opacity
        return self.opacity + (1.0 - self.opacity) * self.background_opacity

    def rgba(self, background=None) -> np.ndarray:
        """(H,W,4) straight-alpha RGBA. ``background``: the colour the rgb was composited on."""
        rgb = self.rgb
        alpha = self.alpha
        if background is not None:
            a = alpha[..., None]
            bg = np.asarray(background, np.float32)
            rgb = np.where(a > 1e-6, (rgb - (1 - a) * bg) / np.maximum(a, 1e-6), 0.0)
        return np.concatenate([np.clip(rgb, 0, 1), np.clip(alpha, 0, 1)[..., None]], -1)


def render_camera(fields, K, c2w, width: int, height: int, background=(1.0, 1.0, 1.0),
                  settings: Optional[RenderSettings] = None,
                  progress: Optional[Callable[[float], Optional[bool]]] = None,
                  semantics: bool = False, far=None) -> RenderOutput:
    """Render one pinhole camera (K (3,3) pixels, c2w (4,4) OpenCV) from a field or list of fields.

    ``settings.supersample`` S > 1 averages S x S rays per pixel (S^2 times the work): anti-aliasing
    that matches photographs' area-averaged pixels.
    ``background`` None leaves rgb premultiplied (black).  ``progress(fraction)`` returning False
    cancels with :class:`Cancelled`.  ``semantics``: also composite the fields' semantic features
    (``RenderOutput.sem``, premultiplied by opacity like ``mod_colour``).
    ``far``: None, or (H,W) distances along each pixel's centre ray (inf: no limit) past which nothing
    is sampled -- an opaque occluder in front of the field (supersampled rays use their pixel's value).
    """
    import time

    settings = settings or RenderSettings()
    fl = _as_list(fields)
    if not fl:
        raise ValueError("render_camera needs at least one field")
    device = fl[0].rest_vertices.device
    t0 = time.perf_counter()
    n = width * height
    # supersampling: a pixel is the box average of S x S rays (the area filter that downscaled photos
    # and a pixel sensor apply); S == 1 is the single ray through the centre
    ss = int(settings.supersample)
    offsets = [((i + 0.5) / ss, (j + 0.5) / ss) for j in range(ss) for i in range(ss)]
    # the image is assembled on the fields' device and copied to the host once (on a GPU: no copy and
    # no host-side scatter per batch)
    rgb = torch.zeros(n, 3, device=device)      # premultiplied; the background is added once at the end
    opac = torch.zeros(n, device=device)
    depth_w = torch.full((n,), float("inf"), device=device) if ss == 1 else torch.zeros(n, device=device)
    mod = torch.zeros(n, 3, device=device)
    sem = torch.zeros(n, _semantic_width(fl), device=device) if semantics else None
    n_samples = 0
    far_t = None if far is None else torch.as_tensor(np.asarray(far, np.float32).reshape(-1)).to(device)
    if far_t is not None and far_t.numel() != n:
        raise ValueError(f"far must be (height, width) = ({height}, {width}), got {np.shape(far)}")
    pixels, ranges = _live_pixels(fl, K, c2w, width, height, settings, far_t, device, semantics)
    m = n if pixels is None else len(pixels)
    chunk = chunk_size(settings, device)
    total = max(1, len(offsets) * m)
    far_m = far_t if pixels is None or far_t is None else far_t[pixels]
    pix_xy = None if pixels is None else torch.stack([pixels % width, pixels // width], -1)
    with torch.no_grad():
        for k, off in enumerate(offsets):
            origins, dirs = pixel_rays(K, c2w, width, height, device=device, pixels=pix_xy, offset=off)
            for s in range(0, m, chunk):
                e = min(m, s + chunk)
                out = render_rays(fl, origins[s:e], dirs[s:e], None, settings, train=False,
                                  semantics=semantics, far=None if far_m is None else far_m[s:e],
                                  ranges=None if ranges is None else
                                  [None if r is None else (r[0][s:e], r[1][s:e]) for r in ranges])
                rows = slice(s, e) if pixels is None else pixels[s:e]
                op = out["opacity"]
                rgb[rows] += out["rgb"]
                opac[rows] += op
                if ss == 1:
                    depth_w[rows] = out["depth"]
                else:
                    depth_w[rows] += torch.where(op > 1e-6, out["depth"] * op, torch.zeros_like(op))
                mod[rows] += out["mod_colour"]
                if sem is not None:
                    sem[rows] += out["sem"]
                n_samples += out["n_samples"]
                if progress is not None and progress((k * m + e) / total) is False:
                    raise Cancelled("rendering cancelled")
    if progress is not None and m == 0 and progress(1.0) is False:
        raise Cancelled("rendering cancelled")
    bg_model = _background_model(fl) if settings.background_model else None
    bg_op = None
    if bg_model is not None:   # behind the fields, every pixel (see _composite_background_model)
        rgb, bg_op = _composite_background_model(bg_model, K, c2w, width, height, device, rgb, opac,
                                                 len(offsets), far_t, chunk)
    if ss == 1:
        depth = depth_w
    else:   # the opacity-weighted mean depth of the sub-pixel rays
        depth = torch.where(opac > 1e-6, depth_w / opac.clamp_min(1e-12), torch.full_like(opac, float("inf")))
    inv = 1.0 / len(offsets)
    if background is not None:
        bg = torch.as_tensor(background, dtype=torch.float32, device=device)
        rgb = rgb + ((len(offsets) - opac) if bg_op is None else (len(offsets) - opac) * (1 - bg_op))[:, None] * bg
    planes = [rgb * inv, opac * inv, depth, mod * inv] + ([] if sem is None else [sem * inv]) + \
        ([] if bg_op is None else [bg_op])
    host = to_host(planes)
    rgb, opac, depth, mod = host[:4]
    return RenderOutput(rgb.reshape(height, width, 3), opac.reshape(height, width),
                        depth.reshape(height, width), mod.reshape(height, width, 3),
                        n_samples, time.perf_counter() - t0,
                        None if sem is None else host[4].reshape(height, width, -1),
                        None if bg_op is None else host[-1].reshape(height, width))


def _live_pixels(fl, K, c2w, width: int, height: int, settings: RenderSettings, far_t, device, semantics: bool):
    """The pixels whose rays can meet an occupied cell of some field (flat ids, in the order the
    renderer marches them) and per field the (near, far) distances along them.  Pixels None: every
    pixel (``settings.skip_empty`` off: no ranges either; or a camera inside some field's occupied
    cells: that field's ranges are None, it is unbounded)."""
    if not settings.skip_empty:
        return None, None
    ranges = [f.grid.camera_ranges(K, c2w, width, height, settings.empty_tile) for f in fl]
    if any(r is None for r in ranges):
        return None, ranges   # every pixel; the ranges of the bounded fields still apply
    live = torch.zeros(width * height, dtype=torch.bool, device=device)
    for r_near, r_far in ranges:
        live |= r_near <= r_far
    if far_t is not None:
        live &= far_t > 0
    pixels = live.nonzero().squeeze(1)
    if render_path(settings, fl, device, semantics=semantics).fused:
        from ..kernels.fused import KERNEL_OPTIONS

        if KERNEL_OPTIONS["ray_order"] == "tiles":   # a block of 32 rays: an 8 x 4 patch, not a line
            pixels = tile_order(pixels, width)
    return pixels, [(r_near[pixels], r_far[pixels]) for r_near, r_far in ranges]


def tile_order(pixels: torch.Tensor, width: int, tile=(8, 4)) -> torch.Tensor:
    """Flat pixel ids reordered tile by tile (``tile`` = (w, h) pixels; tiles row-major, pixels row-major
    inside each): consecutive rays are then neighbours on screen in both directions, so a GPU block of
    w*h consecutive rays meets a compact patch of surface (fewer distinct neighbour cells, rays of
    similar length) instead of a 32-pixel line."""
    tw, th = int(tile[0]), int(tile[1])
    x, y = pixels % width, pixels // width
    key = ((y // th) * -(-width // tw) + x // tw) * (tw * th) + (y % th) * tw + x % tw
    return pixels[torch.argsort(key)]


def to_host(tensors: Sequence[torch.Tensor]) -> list:
    """float32 device tensors as numpy arrays of the same shapes, each contiguous.  On a GPU in one
    copy: the tensors packed end to end, copied into page-locked host memory (torch's caching host
    allocator, so no allocation after the first frame of a size), the arrays views of it; one copy of
    ~20 MB instead of one pageable copy per output.  On the CPU: the tensors themselves."""
    if not tensors or tensors[0].device.type != "cuda":
        return [t.detach().cpu().float().numpy() for t in tensors]
    flat = torch.cat([t.detach().float().reshape(-1) for t in tensors])
    host = torch.empty(flat.shape, dtype=torch.float32, pin_memory=True)
    host.copy_(flat, non_blocking=True)
    torch.cuda.current_stream(flat.device).synchronize()
    out, s = [], 0
    arr = host.numpy()
    for t in tensors:
        n = t.numel()
        out.append(arr[s:s + n].reshape(t.shape))
        s += n
    return out


def _background_model(fields):
    """The first of ``fields`` that has a background model (field/background.py), or None."""
    for f in fields:
        m = f._modules.get("background") if isinstance(f, torch.nn.Module) else None
        if m is not None:
            return m
    return None


@torch.no_grad()
def _composite_background_model(model, K, c2w, width, height, device, rgb, opac, n_sub, far_t, chunk):
    """Add the background model behind the fields' summed sub-pixel colour ``rgb`` (n,3) and opacity
    ``opac`` (n,) (sums over ``n_sub`` sub-pixel rays): one ray per pixel centre, weighted by the
    pixel's mean transmittance (exact for one ray per pixel; with supersampling the background, which
    is smooth, is not supersampled).  Returns (rgb, background opacity (n,)), on ``device``."""
    n = width * height
    bg_rgb = torch.zeros(n, 3, device=device)
    bg_op = torch.zeros(n, device=device)
    origins, dirs = pixel_rays(K, c2w, width, height, device=device)
    for s in range(0, n, chunk):
        e = min(n, s + chunk)
        c, a = model(origins[s:e], dirs[s:e], far=None if far_t is None else far_t[s:e])
        bg_rgb[s:e], bg_op[s:e] = c, a
    return rgb + (n_sub - opac)[:, None] * bg_rgb, bg_op
