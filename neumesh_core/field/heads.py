"""The semantic head of a field: per-vertex semantic codes (``sem_codes``) decoded by a small MLP
(``sem_decoder``). :class:`SemanticsHead` is the part of
:class:`~neumesh_core.field.field.NeuMeshField` that creates and decodes them; distillation fills them
(:mod:`neumesh_core.semantics`).
"""
from __future__ import annotations

from dataclasses import asdict
from typing import Optional

import torch
from torch import nn

from .params import FieldConfig
from .scaffold import Neighbourhood


class SemanticsHead:
    """Mixin of :class:`NeuMeshField`: the semantic codes' decoder."""

    # ------------------------------------------------------------------ semantics
    @staticmethod
    def _new_sem_decoder(cfg: FieldConfig) -> Optional[nn.Module]:
        if not cfg.has_semantics:
            return None
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(1)
            # one hidden layer: the code is already a learned per-vertex embedding
            return nn.Sequential(nn.Linear(cfg.sem_dim, cfg.sem_hidden), nn.ReLU(inplace=True),
                                 nn.Linear(cfg.sem_hidden, cfg.sem_features))

    @property
    def has_semantics(self) -> bool:
        return self.sem_decoder is not None

    def enable_semantics(self, sem_dim: int, sem_features: int, hidden: int = 64, seed: int = 0) -> None:
        """(Re)create the semantic branch: fresh per-vertex codes (``sem_dim`` wide, small random values)
        and a fresh decoder to ``sem_features`` channels.  Nothing else in the field changes."""
        cfg = FieldConfig.from_dict({**asdict(self.config), "sem_dim": int(sem_dim),
                                     "sem_features": int(sem_features), "sem_hidden": int(hidden)})
        if not cfg.has_semantics:
            raise ValueError("enable_semantics needs sem_dim > 0 and sem_features > 0")
        dev = self.geo_codes.device
        g = torch.Generator().manual_seed(seed)
        codes = torch.randn(self.num_vertices, cfg.sem_dim, generator=g) * cfg.code_init_std
        self.config = cfg
        self.sem_codes = nn.Parameter(codes.to(dev), requires_grad=False)
        self.sem_decoder = self._new_sem_decoder(cfg).to(dev)
        self.semantics_info = {}

    def _require_semantics(self) -> None:
        if not self.has_semantics:
            from ..errors import NoSemanticsError

            raise NoSemanticsError(
                "this field has no semantic codes; distill them first: `neumesh semantics --field F "
                "--data DIR` (or 'Distill semantics' in Blender's NeuMesh > Edit panel)")

    def decode_semantics(self, nb: Neighbourhood) -> torch.Tensor:
        """Semantic features (M, sem_features) of samples: codes interpolated with the neighbours'
        weights w_k, then decoded once (NeuMesh++'s early interpolation for semantics)."""
        self._require_semantics()
        code = (self.rows(self.sem_codes, nb.idx) * nb.w[..., None]).sum(1)
        return self.sem_decoder(code)

    def vertex_semantics(self, vertices: Optional[torch.Tensor] = None, chunk: int = 65536) -> torch.Tensor:
        """Decoded semantic feature of each vertex's own code, (N or len(vertices), sem_features)."""
        self._require_semantics()
        codes = self.sem_codes if vertices is None else self.sem_codes[vertices]
        with torch.no_grad():
            return torch.cat([self.sem_decoder(codes[s:s + chunk]) for s in range(0, len(codes), chunk)]) \
                if len(codes) else codes.new_zeros(0, self.config.sem_features)
