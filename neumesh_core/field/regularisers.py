"""Regularisers of a field's per-vertex codes used while training: total variation over the
scaffold's k_tv nearest vertices (``NeuMeshField.tv_loss`` calls :func:`tv_loss`)."""
from __future__ import annotations

from typing import Optional

import torch

from ..device import draw_device


def tv_loss(field, n_samples: int = 16384, generator: Optional[torch.Generator] = None,
            vertices: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Total variation of ``field``'s geometry and texture codes: between each (sampled) vertex's codes
    and its k_tv nearest vertices.

    ``vertices`` (1-D indices) restricts the term to those vertices, e.g. the ones a training batch
    looked up, so that a vertex is smoothed on the steps its photometric gradient arrives.  Without
    it ``n_samples`` random vertices are drawn (all vertices when ``n_samples`` is 0 or >= N).
    """
    n = field.num_vertices
    if vertices is not None:
        i = vertices.to(device=field.geo_codes.device, dtype=torch.long).reshape(-1)
        if len(i) == 0:
            return field.geo_codes.sum() * 0.0
        if int(i.min()) < 0 or int(i.max()) >= n:
            raise IndexError(f"tv_loss: vertex indices must lie in [0, {n}), got "
                             f"[{int(i.min())}, {int(i.max())}]")
    elif n_samples and n_samples < n:
        # drawn on the generator's device (a CPU generator draws the same vertices on any device)
        i = torch.randint(0, n, (n_samples,), device=draw_device(generator, field.geo_codes),
                          generator=generator).to(field.geo_codes.device)
    else:
        i = torch.arange(n, device=field.geo_codes.device)
    j = field.scaffold.tv_neighbours[i]
    dg = (field.rows(field.geo_codes, i)[:, None] - field.rows(field.geo_codes, j)).pow(2).sum(-1).mean()
    dt = (field.rows(field.tex_codes, i)[:, None] - field.rows(field.tex_codes, j)).pow(2).sum(-1).mean()
    return dg + dt
