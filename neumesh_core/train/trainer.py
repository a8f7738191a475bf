"""Training: photometric + modification-colour + mask BCE + total-variation losses, Adam, schedule,
progress/cancel, periodic atomic checkpoints, resume, Ctrl-C safe."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Optional, Union

import numpy as np
import torch

from ..data.cameras import batch_pixel_rays
from ..data.scene import ImageSet, Scene, as_float
from ..render.renderer import RenderSettings, default_step, render_rays
from ..field.io import load_optimizer_state, save_field
from .config import TrainConfig, TrainProgress, TrainResult
from .optim import ParameterAverage, RowSparseAdam

_clock = time.perf_counter   # the wall clock of elapsed_s, eta_s and max_seconds (tests replace it)


class _Batcher:
    """Random pixels from all training images (held as one tensor in their stored dtype: uint8 photos
    stay uint8 on the device, each batch is converted to float32 by ``as_float``)."""

    def __init__(self, images: ImageSet, scene_bg, device, seed: int):
        self.images = torch.from_numpy(np.ascontiguousarray(images.images)).to(device)
        self.masks = None if images.masks is None else torch.from_numpy(
            np.ascontiguousarray(images.masks)).to(device)
        self.K = torch.from_numpy(images.cameras.K).to(device)
        self.c2w = torch.from_numpy(images.cameras.c2w).to(device)
        self.n, self.h, self.w = self.images.shape[:3]
        self.scene_bg = None if scene_bg is None else torch.tensor(scene_bg, dtype=torch.float32, device=device)
        self.gen = torch.Generator(device="cpu").manual_seed(seed)
        self.device = device

    def sample(self, b: int):
        g = self.gen
        i = torch.randint(0, self.n, (b,), generator=g).to(self.device)
        x = torch.randint(0, self.w, (b,), generator=g).to(self.device)
        y = torch.randint(0, self.h, (b,), generator=g).to(self.device)
        o, d = batch_pixel_rays(self.K[i], self.c2w[i], x, y)
        rgb = as_float(self.images[i, y, x])
        mask = None if self.masks is None else as_float(self.masks[i, y, x])
        self.last_index = i   # which image each ray came from (per-image appearance codes)
        return o, d, rgb, mask


def _make_optimizer(field, cfg: TrainConfig, extra_codes=(), background=None):
    groups = [
        {"params": [field.geo_codes, field.tex_codes, field.mod_colours, *extra_codes], "lr": cfg.lr_codes,
         "name": "codes"},
        {"params": list(field.geo_decoder.parameters()) + list(field.rad_decoder.parameters()),
         "lr": cfg.lr_decoders, "name": "decoders"},
    ]
    if background is not None:
        groups.append({"params": list(background.parameters()), "lr": cfg.lr_background, "name": "background"})
    for g in groups:
        g["base_lr"] = g["lr"]
    # codes get row-sparse gradients while training (field.sparse_grads); the update stays exactly Adam's
    kwargs = dict(betas=(0.9, 0.99), eps=1e-15)
    try:
        return RowSparseAdam(groups, fused=True, **kwargs)
    except (RuntimeError, TypeError, ValueError):
        return RowSparseAdam(groups, foreach=True, **kwargs)


def _progress(step: int, cfg: TrainConfig, elapsed_s: float = 0.0) -> float:
    """Fraction of the budget used: of the steps, or of max_seconds when that ends first."""
    progress = min(step, cfg.steps) / max(1, cfg.steps)
    if cfg.max_seconds:
        progress = max(progress, min(1.0, elapsed_s / cfg.max_seconds))
    return progress


def _eta(step: int, start: int, cfg: TrainConfig, elapsed_s: float) -> tuple:
    """(seconds left, "steps" | "time"): the steps left at this run's mean step time, or the time left
    of ``max_seconds`` when that ends the run first."""
    by_steps = elapsed_s / max(1, step - start) * max(0, cfg.steps - step)
    if cfg.max_seconds is not None:
        left = max(0.0, cfg.max_seconds - elapsed_s)
        if left < by_steps:
            return left, "time"
    return by_steps, "steps"


def _lr_factor(step: int, cfg: TrainConfig, elapsed_s: float = 0.0) -> float:
    """Warm-up then exponential decay over the budget: steps, or max_seconds when that ends first."""
    warm = min(1.0, (step + 1) / max(1, cfg.warmup_steps))
    return warm * cfg.lr_final_factor ** _progress(step, cfg, elapsed_s)


class _Meter:
    """Rays and samples done, and the rays per second since the last report."""

    def __init__(self):
        self.rays = self.samples = self.window_rays = 0
        self.window_t = _clock()

    def add(self, rays: int, samples: int) -> None:
        self.rays += rays
        self.samples += samples
        self.window_rays += rays

    def samples_per_ray(self) -> float:
        return self.samples / max(1, self.rays)

    def rays_per_second(self) -> float:
        """Since the last call (a new window starts)."""
        now = _clock()
        rps = self.window_rays / max(now - self.window_t, 1e-9)
        self.window_t, self.window_rays = now, 0
        return rps


@dataclass
class _TrainedParts:
    """What a training run optimises beside the field's own parameters, and where it starts."""

    optimizer: object
    start: int = 0                  # the step a resumed run goes on from
    pyramid: object = None          # coarse code levels (cfg.code_levels), baked into the codes at the end
    background: object = None       # the field's background model, fitted when the images have no masks
    appearance: object = None       # per-photo appearance codes (cfg.appearance_codes; not saved)
    averager: object = None         # the running parameter average (cfg.average_from)


def _trained_parts(field, cfg: TrainConfig, has_masks: bool, n_images: int, device) -> _TrainedParts:
    pyramid = None
    if cfg.code_levels > 0:
        from ..field.pyramid import CodePyramid

        pyramid = CodePyramid(field, cfg.code_levels, cfg.code_level_factor, kinds=cfg.code_level_kinds)
    # no masks: the background model (when the field has one) is fitted with the field, full frame
    bg_model = None if has_masks else field._modules.get("background")
    opt = _make_optimizer(field, cfg, () if pyramid is None else list(pyramid.parameters()), bg_model)
    start = 0
    meta = getattr(field, "_checkpoint_meta", None)
    if cfg.resume and meta:
        start = int(meta.get("train_state", {}).get("step", 0))
        load_optimizer_state(field, opt)
    appearance = None
    if cfg.appearance_codes:   # (not saved: they explain the training photos only)
        appearance = torch.zeros(n_images, 6, device=device, requires_grad=True)
        opt.add_param_group({"params": [appearance], "lr": cfg.lr_appearance, "base_lr": cfg.lr_appearance,
                             "name": "appearance"})
    averaged_params = list(field.parameters()) + ([] if pyramid is None else list(pyramid.parameters()))
    averager = ParameterAverage(averaged_params) if cfg.average_from is not None else None
    return _TrainedParts(opt, start, pyramid, bg_model, appearance, averager)


def _training_images(field, data: Union[Scene, ImageSet], cfg: TrainConfig):
    """The images ``train`` fits (a Scene's ``cfg.split``) and the scene's background colour, or a
    ValueError that says what is wrong with them or with the field."""
    if isinstance(data, Scene):
        images, scene_bg = data.split(cfg.split), data.background
    else:
        images, scene_bg = data, None
    if len(images) == 0:
        raise ValueError("no training images")
    if images.images.dtype.kind == "f" and not np.isfinite(images.images).all():
        raise ValueError("training images contain NaN/inf values; check the dataset")
    if field.to_rest is not None:
        raise ValueError("the field is deformed; call field.reset_vertices() before training")
    return images, scene_bg


def _targets(rgb_gt, mask, scene_bg, cfg: TrainConfig, gen, device):
    """The background a batch's rays composite over and the colours they must reach.  With masks and
    ``random_background`` the background is a random colour per ray, so only an opaque object matches."""
    if mask is not None and cfg.random_background:
        bg = torch.rand(len(rgb_gt), 3, generator=gen).to(device)
        if scene_bg is not None:
            return bg, rgb_gt + (1 - mask)[:, None] * (bg - scene_bg)
        return bg, rgb_gt * mask[:, None] + (1 - mask)[:, None] * bg
    return (scene_bg if scene_bg is not None else torch.zeros(3, device=device)), rgb_gt


def _loss(field, out: dict, target, mask, bg_model, cfg: TrainConfig, gen, step: int):
    """(loss, photometric MSE) of one batch: colour + modification colour + mask BCE + total variation
    (field and background model).  A NaN opacity or loss raises FloatingPointError (what to do)."""
    if not bool(torch.isfinite(out["opacity"]).all()):
        raise FloatingPointError(
            f"the rendered opacity became NaN/inf at step {step}; lower lr_codes/lr_decoders and "
            "resume from the last checkpoint")
    mse = torch.mean((out["rgb"] - target) ** 2)
    loss = mse + cfg.weight_mod_colour * torch.mean(out["mod_colour"] ** 2)
    if mask is not None and cfg.weight_mask > 0:
        op = out["opacity"].clamp(1e-4, 1 - 1e-4)
        loss = loss + cfg.weight_mask * torch.nn.functional.binary_cross_entropy(op, mask)
    if cfg.weight_tv > 0:
        touched = out["vertex_ids"][0] if cfg.tv_vertices == "batch" else None
        loss = loss + cfg.weight_tv * field.tv_loss(cfg.tv_samples, generator=gen, vertices=touched)
    if bg_model is not None and cfg.weight_background_tv > 0:
        loss = loss + cfg.weight_background_tv * bg_model.tv_loss()
    if not math.isfinite(float(loss.detach())):   # before the step: the field keeps its last finite state
        raise FloatingPointError(
            f"loss became {float(loss)} at step {step}; lower lr_codes/lr_decoders and resume from "
            "the last checkpoint")
    return loss, mse


def _schedule(field, opt, pyramid, step: int, cfg: TrainConfig, elapsed_s: float) -> None:
    """Before a step: the learning rates of the schedule, and the code levels baked into plain codes
    once ``cfg.code_levels_until`` of the run has passed."""
    if (pyramid is not None and field.code_prior is pyramid and cfg.code_levels_until is not None
            and _progress(step, cfg, elapsed_s) >= cfg.code_levels_until):
        pyramid.bake(field)   # plain per-vertex codes from here (a running average stays valid:
        #                       it is linear, and the baked levels are zero from now on)
    f = _lr_factor(step, cfg, elapsed_s)
    for g in opt.param_groups:
        g["lr"] = g["base_lr"] * f


def _finish(field, averager, pyramid, density, step_size: float, gen) -> int:
    """After the last step: the running parameter average applied, the code levels baked into plain
    codes, and the occupancy grid refreshed from the averaged density.  Returns the steps averaged."""
    averaged = 0
    if averager is not None and averager.count > 0:
        averager.apply()
        averaged = averager.count
    if pyramid is not None:
        pyramid.bake(field)
    if averaged:
        # the occupancy grid follows the averaged density (every cell, not a random subset)
        with torch.no_grad():
            field.grid.refresh(density, step_size, max_cells=None, generator=gen)
    return averaged


def train(field, data: Union[Scene, ImageSet], config: Optional[TrainConfig] = None,
          progress: Optional[Callable[[TrainProgress], Optional[bool]]] = None, *,
          callback: Optional[Callable[[TrainProgress], Optional[bool]]] = None) -> TrainResult:
    """Train ``field`` in place on ``data`` (a Scene: its ``config.split``; or an ImageSet).

    ``progress(p)`` (a :class:`TrainProgress`) is called every ``log_every`` steps and at the end;
    returning False cancels (the field keeps what it learned; a checkpoint is written when
    ``checkpoint_path`` is set).  ``callback``: the same, under the name older scripts pass.
    Ctrl-C (KeyboardInterrupt) stops cleanly the same way and is reported in ``TrainResult.interrupted``.
    """
    progress = progress if progress is not None else callback
    cfg = config or TrainConfig()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    images, scene_bg = _training_images(field, data, cfg)
    device = field.rest_vertices.device
    batcher = _Batcher(images, scene_bg, device, cfg.seed)
    parts = _trained_parts(field, cfg, images.masks is not None, batcher.n, device)
    pyramid, bg_model, opt, appearance = parts.pyramid, parts.background, parts.optimizer, parts.appearance
    start, averager = parts.start, parts.averager
    settings = RenderSettings(step_scale=cfg.step_scale)
    step_size = default_step(field, settings)
    gen = torch.Generator(device="cpu").manual_seed(cfg.seed + 1)

    def density(x):  # what the occupancy grid is refreshed from
        return field.query(x, with_rgb=False)[0]

    field.train()
    field.sparse_grads = True
    if pyramid is not None:
        field.set_code_prior(pyramid)
    t_begin = _clock()
    history = []
    loss_v = psnr_v = float("nan")
    cancelled = interrupted = False
    step = start
    meter = _Meter()

    def save(step_now):
        if cfg.checkpoint_path:
            # a checkpoint is a plain field: save_field folds the coarse code levels into the codes it stores
            save_field(field, cfg.checkpoint_path, optimizer=opt,
                       train_state={"step": step_now, "steps": cfg.steps, "loss": loss_v, "psnr": psnr_v})

    try:
        while step < cfg.steps:
            _schedule(field, opt, pyramid, step, cfg, _clock() - t_begin)
            o, d, rgb_gt, mask = batcher.sample(cfg.rays_per_batch)
            bg, target = _targets(rgb_gt, mask, batcher.scene_bg, cfg, gen, device)
            jitter = torch.rand(len(o), generator=gen).to(device)
            out = render_rays(field, o, d, background=bg, settings=settings, train=True, jitter=jitter,
                              vertex_ids=cfg.weight_tv > 0 and cfg.tv_vertices == "batch",
                              background_model=bg_model)
            if appearance is not None:   # centred: the field keeps the photos' mean appearance
                a = (appearance - appearance.mean(0))[batcher.last_index]
                out["rgb"] = out["rgb"] * torch.exp(a[:, :3]) + a[:, 3:]
            loss, mse = _loss(field, out, target, mask, bg_model, cfg, gen, step)
            opt.zero_grad(set_to_none=True)
            if loss.requires_grad:
                loss.backward()
                opt.step()
            step += 1
            meter.add(len(o), out["n_samples"])
            loss_v = float(loss.detach())
            psnr_v = float(-10.0 * torch.log10(mse.detach().clamp_min(1e-10)))
            if step > cfg.occ_warmup_steps and step % cfg.occ_refresh_every == 0:
                field.grid.refresh(density, step_size, generator=gen)
            last = step >= cfg.steps
            elapsed = _clock() - t_begin
            if (averager is not None and step % cfg.average_every == 0
                    and _progress(step, cfg, elapsed) >= cfg.average_from):
                averager.update()
            over_time = cfg.max_seconds is not None and elapsed >= cfg.max_seconds
            if step % cfg.log_every == 0 or last or step == start + 1 or over_time:
                eta, limit = _eta(step, start, cfg, elapsed)
                p = TrainProgress(step, cfg.steps, loss_v, psnr_v, meter.rays_per_second(), elapsed, eta,
                                  meter.samples_per_ray(), field.grid.occupied_fraction,
                                  _progress(step, cfg, elapsed), limit)
                history.append(p)
                if progress is not None and progress(p) is False:
                    cancelled = True
                    break
            if cfg.checkpoint_path and step % cfg.checkpoint_every == 0 and not last:
                save(step)
            if over_time:
                break
    except KeyboardInterrupt:
        interrupted = True
    except BaseException:
        if pyramid is not None:   # leave a plain field behind (it renders what was learned)
            pyramid.bake(field)
        raise
    finally:
        field.sparse_grads = False
    field.eval()
    averaged = _finish(field, averager, pyramid, density, step_size, gen)
    save(step)
    codes = None if appearance is None else (appearance - appearance.mean(0)).detach().cpu().numpy()
    return TrainResult(step, loss_v, psnr_v, _clock() - t_begin, cancelled, interrupted, history,
                       averaged, codes)
