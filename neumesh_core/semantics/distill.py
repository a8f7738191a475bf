"""Semantic distillation: fit the field's semantic codes and decoder to 2D image features.

1. Every training view goes through a 2D feature extractor (:mod:`.extractors`).
2. A bank of rays is drawn per view (foreground pixels where the data has masks) and each ray's target
   is the feature map sampled bilinearly at its pixel centre ("features resized to the rendered rays").
   Optionally the targets are reduced by PCA (scikit-learn) to ``pca_dim`` channels; they are centred
   and scaled to a mean squared norm of 1, so the loss reads as the fraction of feature energy missed.
3. Geometry is frozen, so every bank ray is marched once: its samples' neighbours, interpolation
   weights w_k and compositing weights (the colour's) are kept.  Rays whose opacity is below
   ``min_opacity`` (background, thin edges) are dropped, and so are samples whose weight is below
   ``min_sample_weight`` (half of them carry ~1% of a ray's weight; each costs a decoder pass).
4. Only the per-vertex semantic codes and the semantic decoder train: the rendered feature of a ray is
   sum_i weight_i * decoder(sum_k w_ik code_k) (codes interpolated first, decoded once), and the loss is
   the squared error against opacity x target, plus a small total variation between neighbouring
   vertices' codes.  Geometry, texture, decoders and modification colours are never in the graph.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field as dc_field
from typing import Callable, Literal, Optional, Union

import numpy as np
import torch

from ..data.cameras import batch_pixel_rays
from ..data.scene import ImageSet, Scene
from ..render.renderer import Cancelled, RenderSettings, default_step
from ..render.volume import render_weights
from ..sampling.marcher import march_rays
from .extractors import FeatureExtractor, make_extractor


@dataclass
class DistillConfig:
    """Semantic distillation settings (sizes in the spirit of NeuMesh++: an 8-wide code per vertex)."""

    sem_dim: int = 8                  # semantic code per vertex
    hidden: int = 64                  # semantic decoder width
    pca_dim: Optional[int] = 16       # reduce the 2D features to this many channels (None: keep all)
    steps: int = 1500
    rays_per_batch: int = 8192
    rays_per_view: int = 4096         # bank rays drawn per training view
    lr_codes: float = 3e-2
    lr_decoder: float = 3e-3
    lr_final_factor: float = 0.1
    weight_tv: float = 1e-2           # total variation between neighbouring vertices' semantic codes
    tv_samples: int = 8192
    min_opacity: float = 0.5          # bank rays below this opacity are dropped
    min_sample_weight: float = 0.01   # bank samples with a smaller compositing weight are dropped (on the
    #                                   built-in scene: half the samples, 1.3% of the rays' weight)
    split: str = "train"
    max_views: Optional[int] = None   # use at most this many views (evenly spaced); None = all
    seed: int = 0
    log_every: int = 25
    threads: Optional[int] = None

    def __post_init__(self) -> None:
        if self.sem_dim < 1 or self.hidden < 1:
            raise ValueError(f"sem_dim and hidden must be positive, not {self.sem_dim} / {self.hidden}")
        if self.pca_dim is not None and self.pca_dim < 1:
            raise ValueError(f"pca_dim must be positive or None (keep every channel), not {self.pca_dim}")
        if self.steps < 0 or self.rays_per_batch < 1 or self.rays_per_view < 1:
            raise ValueError("steps must be >= 0 and rays_per_batch, rays_per_view positive")
        if not 0.0 <= self.min_sample_weight < 1.0:
            raise ValueError(f"min_sample_weight must lie in [0, 1), not {self.min_sample_weight}")
        if not 0.0 <= self.min_opacity < 1.0:
            raise ValueError(f"min_opacity must lie in [0, 1), not {self.min_opacity}")


@dataclass
class DistillProgress:
    stage: Literal["features", "rays", "train"]
    step: int           # views done (features, rays) or optimisation steps done (train)
    total: int
    loss: float = float("nan")
    elapsed_s: float = 0.0
    eta_s: float = float("nan")


@dataclass
class DistillResult:
    steps_done: int
    final_loss: float
    seconds: float
    cancelled: bool = False
    bank_rays: int = 0
    bank_samples: int = 0
    feature_channels: int = 0
    timings: dict = dc_field(default_factory=dict)
    history: list = dc_field(default_factory=list)


@dataclass
class RayBank:
    """Marched rays with their targets: samples in CSR order (``offsets`` (R+1,)); per sample the K
    neighbours ``idx`` (S,K), their weights ``w`` (S,K) and its compositing weight ``weight`` (S,);
    per ray ``opacity`` (R,) and ``target`` (R,C)."""

    offsets: torch.Tensor
    idx: torch.Tensor
    w: torch.Tensor
    weight: torch.Tensor
    opacity: torch.Tensor
    target: torch.Tensor

    @property
    def num_rays(self) -> int:
        return int(self.opacity.shape[0])

    def gather(self, rays: torch.Tensor):
        """(sample ids, the batch row of each sample) for a batch of ray ids."""
        start = self.offsets[rays]
        count = self.offsets[rays + 1] - start
        row = torch.repeat_interleave(torch.arange(len(rays), device=rays.device), count)
        first = torch.cumsum(count, 0) - count
        sid = start[row] + torch.arange(int(count.sum()), device=rays.device) - first[row]
        return sid, row


def _images(data: Union[Scene, ImageSet], cfg: DistillConfig) -> ImageSet:
    images = data.split(cfg.split) if isinstance(data, Scene) else data
    if len(images) == 0:
        raise ValueError(f"no images in split '{cfg.split}' to distill semantics from")
    if cfg.max_views is not None and len(images) > cfg.max_views:
        keep = np.unique(np.linspace(0, len(images) - 1, cfg.max_views).round().astype(int))
        images = images.subset(keep)
    return images


def sample_features(fmap: np.ndarray, x: np.ndarray, y: np.ndarray, width: int, height: int) -> torch.Tensor:
    """Bilinear samples (P,C) of a feature map (h,w,C) covering a (height,width) image at the pixel
    centres (x, y)."""
    import torch.nn.functional as F

    f = torch.from_numpy(np.ascontiguousarray(fmap, np.float32)).permute(2, 0, 1)[None]
    gx = (torch.as_tensor(x, dtype=torch.float32) + 0.5) / width * 2 - 1
    gy = (torch.as_tensor(y, dtype=torch.float32) + 0.5) / height * 2 - 1
    grid = torch.stack([gx, gy], -1)[None, None]
    return F.grid_sample(f, grid, mode="bilinear", padding_mode="border", align_corners=False)[0, :, 0].T


def _fit_targets(raw: torch.Tensor, cfg: DistillConfig, gen: torch.Generator):
    """Centre, optionally PCA-reduce and scale the targets; returns (targets, info)."""
    c = raw.shape[1]
    sub = raw if len(raw) <= 50_000 else raw[torch.randperm(len(raw), generator=gen)[:50_000]]
    info = {"input_channels": int(c)}
    if cfg.pca_dim is not None and cfg.pca_dim < c:
        from sklearn.decomposition import PCA

        pca = PCA(n_components=cfg.pca_dim, random_state=cfg.seed).fit(sub.numpy().astype(np.float64))
        mean = torch.as_tensor(pca.mean_, dtype=torch.float32)
        comps = torch.as_tensor(pca.components_, dtype=torch.float32)
        out = (raw - mean) @ comps.T
        info["pca_explained_variance"] = float(pca.explained_variance_ratio_.sum())
    else:
        out = raw - sub.mean(0)
    scale = float(out.pow(2).sum(1).mean().sqrt().clamp_min(1e-12))
    info["target_scale"] = scale
    return out / scale, info


@torch.no_grad()
def build_bank(field, images: ImageSet, fmaps: list, cfg: DistillConfig, gen: torch.Generator,
               progress: Optional[Callable] = None) -> tuple:
    """March ``cfg.rays_per_view`` rays per view through the frozen field; returns (RayBank, info)."""
    device = field.rest_vertices.device
    cams = images.cameras
    step = default_step(field, RenderSettings())
    pix, raw = [], []
    for i in range(len(images)):
        if images.masks is not None:
            ys, xs = np.nonzero(images.float_mask(i) > 0.5)
        else:
            ys, xs = np.divmod(np.arange(cams.width * cams.height), cams.width)
        if len(xs) == 0:
            continue
        pick = torch.randperm(len(xs), generator=gen)[:cfg.rays_per_view].numpy()
        x, y = xs[pick], ys[pick]
        pix.append((i, x, y))
        raw.append(sample_features(fmaps[i], x, y, cams.width, cams.height))
    if not pix:
        raise ValueError("every view's mask is empty: there is no object to distill semantics from")
    target, info = _fit_targets(torch.cat(raw), cfg, gen)
    K_all = torch.from_numpy(cams.K).to(device)
    c2w_all = torch.from_numpy(cams.c2w).to(device)
    offs, idx, w, wt, op, tg = [0], [], [], [], [], []
    total = 0
    row0 = 0
    for v, (i, x, y) in enumerate(pix):
        n = len(x)
        xt = torch.as_tensor(x, device=device)
        yt = torch.as_tensor(y, device=device)
        o, d = batch_pixel_rays(K_all[i].expand(n, 3, 3), c2w_all[i].expand(n, 4, 4), xt, yt)
        s = march_rays(o, d, field.grid, field.sigma_fn, step)
        if len(s):
            wgt = render_weights(s.ray_indices, s.t_starts, s.t_ends, s.sigmas, n)
            opacity = torch.zeros(n, device=device).index_add(0, s.ray_indices, wgt)
            keep_ray = opacity >= cfg.min_opacity
            keep_s = keep_ray[s.ray_indices] & (wgt >= cfg.min_sample_weight)
            # the opacity of what is kept (rendered features and targets stay consistent)
            opacity = torch.zeros(n, device=device).index_add(0, s.ray_indices, torch.where(keep_s, wgt, 0 * wgt))
            counts = torch.bincount(s.ray_indices[keep_s], minlength=n)[keep_ray]
            nb = s.aux.select(keep_s.nonzero().squeeze(1))
            idx.append(nb.idx.to(torch.int32))
            w.append(nb.w)
            wt.append(wgt[keep_s])
            op.append(opacity[keep_ray])
            tg.append(target[row0:row0 + n][keep_ray.cpu()].to(device))
            c = torch.cumsum(counts, 0) + total
            offs.extend(c.tolist())
            total = int(c[-1]) if len(c) else total
        row0 += n
        if progress is not None and progress(v + 1, len(pix)) is False:
            raise Cancelled("semantic distillation cancelled")
    if not op or sum(len(t) for t in op) == 0:
        raise ValueError(f"no training ray reaches opacity {cfg.min_opacity}: is the field trained, and "
                         "does it match these images?")
    bank = RayBank(torch.as_tensor(offs, dtype=torch.long, device=device), torch.cat(idx), torch.cat(w),
                   torch.cat(wt), torch.cat(op), torch.cat(tg))
    return bank, info


DistillProgressFn = Callable[[DistillProgress], Optional[bool]]   # returns False to cancel


def distill_semantics(field, data: Union[Scene, ImageSet], extractor: Optional[FeatureExtractor] = None,
                      config: Optional[DistillConfig] = None, progress: Optional[DistillProgressFn] = None, *,
                      callback: Optional[DistillProgressFn] = None) -> DistillResult:
    """Give ``field`` a semantic branch distilled from 2D features of ``data``'s training images.

    ``extractor``: any :class:`FeatureExtractor` (default: the weight-free "colour-texture").
    ``progress(p)`` (a :class:`DistillProgress`) is called per view while extracting and marching, and
    every ``log_every`` steps while training; returning False cancels (``callback``: its older name).  A
    cancel before training leaves the field as it was; a cancel while training keeps what was learned
    (``DistillResult.cancelled``).  Only ``sem_codes`` and ``sem_decoder`` change.
    """
    progress = progress if progress is not None else callback
    cfg = config or DistillConfig()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    if field.to_rest is not None:
        raise ValueError("the field is deformed; call field.reset_vertices() before distilling semantics")
    extractor = extractor or make_extractor()
    images = _images(data, cfg)
    gen = torch.Generator().manual_seed(cfg.seed)
    t0 = time.perf_counter()
    timings = {}
    history = []

    def report(stage, step, total, loss=float("nan")):
        el = time.perf_counter() - t0
        p = DistillProgress(stage, step, total, loss, el)
        if stage == "train" and step > 0:
            p.eta_s = (time.perf_counter() - t_train) / step * (total - step)
        if stage == "train":
            history.append(p)
        return progress(p) if progress is not None else None

    # 1. 2D features
    fmaps = []
    try:
        for i in range(len(images)):
            fmaps.append(extractor(images.float_view(i), images.float_mask(i)))
            if report("features", i + 1, len(images)) is False:
                raise Cancelled("semantic distillation cancelled")
        timings["features_s"] = time.perf_counter() - t0
        # 2.-3. the ray bank
        t1 = time.perf_counter()
        bank, tinfo = build_bank(field, images, fmaps, cfg, gen, lambda v, n: report("rays", v, n))
        timings["rays_s"] = time.perf_counter() - t1
    except Cancelled:
        return DistillResult(0, float("nan"), time.perf_counter() - t0, cancelled=True, timings=timings)
    del fmaps

    # 4. train codes + decoder
    n_feat = int(bank.target.shape[1])
    field.enable_semantics(cfg.sem_dim, n_feat, cfg.hidden, seed=cfg.seed)
    codes = field.sem_codes
    codes.requires_grad_(True)
    dec_params = list(field.sem_decoder.parameters())
    opt = torch.optim.Adam([{"params": [codes], "lr": cfg.lr_codes, "base": cfg.lr_codes},
                            {"params": dec_params, "lr": cfg.lr_decoder, "base": cfg.lr_decoder}],
                           betas=(0.9, 0.99))
    t_train = time.perf_counter()
    loss_v = float("nan")
    cancelled = False
    step = 0
    tv_nb = field.scaffold.tv_neighbours
    n_vert = field.num_vertices
    device = codes.device
    try:
        for step in range(1, cfg.steps + 1):
            f = cfg.lr_final_factor ** ((step - 1) / max(1, cfg.steps))
            for g in opt.param_groups:
                g["lr"] = g["base"] * f
            rays = torch.randint(0, bank.num_rays, (min(cfg.rays_per_batch, bank.num_rays),),
                                 generator=gen).to(device)
            sid, row = bank.gather(rays)
            code = (codes[bank.idx[sid].long()] * bank.w[sid, :, None]).sum(1)
            feat = field.sem_decoder(code)
            rendered = torch.zeros(len(rays), n_feat, device=device).index_add(0, row, bank.weight[sid, None] * feat)
            target = bank.opacity[rays, None] * bank.target[rays]
            loss = (rendered - target).pow(2).sum(1).mean()
            if cfg.weight_tv > 0:
                vi = torch.randint(0, n_vert, (min(cfg.tv_samples, n_vert),), generator=gen).to(device)
                loss = loss + cfg.weight_tv * (codes[vi, None] - codes[tv_nb[vi]]).pow(2).sum(-1).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            loss_v = float(loss.detach())
            if not math.isfinite(loss_v):
                raise FloatingPointError(f"semantic distillation diverged at step {step}; lower lr_codes")
            if (step % cfg.log_every == 0 or step == cfg.steps) and report("train", step, cfg.steps, loss_v) is False:
                cancelled = True
                break
    finally:
        codes.requires_grad_(False)
    timings["train_s"] = time.perf_counter() - t_train
    seconds = time.perf_counter() - t0
    field.semantics_info = {
        "extractor": extractor.info(), "config": {k: v for k, v in asdict(cfg).items() if k != "threads"},
        "targets": tinfo, "steps": step, "loss": loss_v, "bank_rays": bank.num_rays,
        "seconds": round(seconds, 2), "cancelled": cancelled}
    return DistillResult(step, loss_v, seconds, cancelled, bank.num_rays, int(bank.weight.shape[0]), n_feat,
                         timings, history)


def semantics_record(field, result: DistillResult):
    """The edit record of a distillation, for :func:`neumesh_core.edit.save_edited`: every vertex's
    semantic code changed, and the record's info (the file header's history) says how.  The semantic
    branch is new structure, not rows, so it is undone by going back to the parent file (the add-on's
    "Undo edit"), not by :meth:`EditRecord.undo`, which leaves it in place."""
    from ..edit import EditRecord

    n = field.num_decoders
    info = {"extractor": field.semantics_info.get("extractor", {}).get("name"), "steps": result.steps_done,
            "loss": result.final_loss, "seconds": round(result.seconds, 1)}
    return EditRecord(op="semantics", vertices=np.arange(field.num_vertices), old={}, new={},
                      decoders_before=n, decoders_after=n, info=info)
