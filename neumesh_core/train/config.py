"""What a training run takes and gives: :class:`TrainConfig` (the hyper-parameters), the
:class:`TrainProgress` reports and the :class:`TrainResult`."""
from __future__ import annotations

from dataclasses import dataclass, field as dc_field
from typing import Literal, Optional

import numpy as np


@dataclass
class TrainConfig:
    """Training hyper-parameters.  Defaults suit 100-400 px scenes on a CPU."""

    steps: int = 3000
    rays_per_batch: int = 4096
    lr_codes: float = 1e-2
    lr_decoders: float = 2e-3
    lr_final_factor: float = 0.1      # exponential decay to lr * factor at the last step
    warmup_steps: int = 50
    weight_mod_colour: float = 0.01   # x mean squared rendered modification colour
    weight_mask: float = 0.05         # mask BCE (only when the scene has masks/alpha)
    weight_tv: float = 1e-3           # total variation between neighbouring vertex codes
    tv_samples: int = 8192            # vertices sampled per step for the TV loss ("random")
    tv_vertices: Literal["random", "batch"] = "random"   # TV over random vertices or the batch's
    # coarse-to-fine codes while training (field.pyramid.CodePyramid): this many coarse levels, each
    # code_level_factor times sparser than the last; baked into the per-vertex codes at the end.  0 = off
    code_levels: int = 0
    code_level_factor: float = 4.0
    code_level_kinds: tuple = ("geo", "tex")   # which codes get coarse levels
    # bake the coarse levels into the vertex codes once this fraction of the budget is used, and train
    # plain per-vertex codes from there (None: keep the levels to the end)
    code_levels_until: Optional[float] = None
    random_background: bool = True    # composite targets on random colours (needs masks)
    # without masks, a field's background model (field/background.py; real captures) trains with it on
    # full-frame colour; with masks it is left alone
    lr_background: float = 1e-2
    # K-Planes' plane total variation on that background model (its paper: 2e-4 for unbounded scenes;
    # off: no gain on fox, docs/real_captures.md)
    weight_background_tv: float = 0.0
    # per-image appearance (NeRF-W's remedy for exposure changes, here 6 numbers an image: colour x
    # exp(scale) + offset; their mean over the images is held at zero) applied to the rendered colour
    # while training; held-out renders use none
    appearance_codes: bool = False
    lr_appearance: float = 1e-3
    occ_refresh_every: int = 16
    occ_warmup_steps: int = 200
    step_scale: Optional[float] = None  # marching step = radius x step_scale (None: the field's own)
    split: str = "train"
    seed: int = 0
    log_every: int = 25
    checkpoint_path: Optional[str] = None
    checkpoint_every: int = 500
    max_seconds: Optional[float] = None  # stop after this wall time (the lr schedule then follows time)
    resume: bool = True               # continue from the step stored in a loaded field
    # parameter averaging (SWA / Polyak): from this fraction of the budget (steps or max_seconds)
    # on, every ``average_every`` steps, the trained parameters join a running mean that replaces
    # them at the end.  None = off.  The mean lives in memory only: a resumed run starts a new one.
    average_from: Optional[float] = None
    average_every: int = 10
    threads: Optional[int] = None     # torch CPU threads (default: all cores)

    def __post_init__(self) -> None:
        if self.average_from is not None and not 0.0 <= self.average_from < 1.0:
            raise ValueError(f"average_from must be a fraction of the budget in [0, 1) (e.g. 0.5), "
                             f"not {self.average_from}; None turns averaging off")
        if self.average_every < 1:
            raise ValueError(f"average_every must be at least 1 step, not {self.average_every}")
        if self.tv_vertices not in ("random", "batch"):
            raise ValueError(f"tv_vertices must be 'random' or 'batch', not {self.tv_vertices!r}")
        if self.code_levels < 0 or not self.code_level_factor > 1:
            raise ValueError(f"code_levels must be >= 0 and code_level_factor > 1, not "
                             f"{self.code_levels} / {self.code_level_factor}")
        if self.code_levels_until is not None and not 0.0 <= self.code_levels_until < 1.0:
            raise ValueError(f"code_levels_until must be a fraction of the budget in [0, 1) (e.g. 0.3), "
                             f"not {self.code_levels_until}; None keeps the levels to the end")
        if self.code_levels_until is not None and self.code_levels == 0:
            raise ValueError("code_levels_until folds the coarse code levels into the vertex codes, but "
                             "code_levels is 0 (no levels): set code_levels (e.g. 3) or leave "
                             "code_levels_until unset")
        if not self.lr_final_factor > 0:
            raise ValueError(f"lr_final_factor must be > 0 (e.g. 0.1), not {self.lr_final_factor}")


@dataclass
class TrainProgress:
    step: int
    total_steps: int
    loss: float
    psnr: float
    rays_per_sec: float
    elapsed_s: float
    eta_s: float
    samples_per_ray: float = 0.0
    occupied_fraction: float = 0.0
    # the budget, whichever part ends the run first: the steps, or the wall-clock budget
    # (TrainConfig.max_seconds, limit "time"; eta_s is then the time left of it)
    fraction: float = 0.0             # of the budget used, 0..1
    limit: Literal["steps", "time"] = "steps"   # what ends the run


@dataclass
class TrainResult:
    steps_done: int
    final_loss: float
    final_psnr: float
    seconds: float
    cancelled: bool = False
    interrupted: bool = False
    history: list = dc_field(default_factory=list)
    averaged: int = 0                 # parameter snapshots averaged into the result (0 = plain)
    appearance: Optional[np.ndarray] = None   # per-image codes (n, 6: log-scale rgb, offset rgb), centred
