"""What a field learns per vertex, and where: :class:`FieldConfig` (saved in every field file) and
:class:`FieldParams`, the part of :class:`~neumesh_core.field.field.NeuMeshField` that holds the
per-vertex tables (``geo_codes``, ``tex_codes``, ``mod_colours``, ``sem_codes``, ``decoder_id``,
``tex_frame``) on the scaffold (``field.scaffold``): the scaffold's geometry, row lookups (sparse
gradients while training), the code tables with the training-time coarse levels.

The decoders that read these tables are :mod:`.decoders` (radiance and geometry) and :mod:`.heads`
(semantics); :mod:`.field` puts them together.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Literal, Optional

import numpy as np
import torch

from ..mesh import Mesh
from .knn import KNN_BACKENDS, knn_backend
from .scaffold import Neighbourhood, take_rows


@dataclass
class FieldConfig:
    """Field hyper-parameters (saved in every checkpoint)."""

    geo_dim: int = 6            # geometry code per vertex
    tex_dim: int = 15           # texture code per vertex
    sem_dim: int = 0            # semantic code per vertex (filled by semantic distillation; 0 = none)
    sem_features: int = 0       # width of the decoded semantic feature (0 = no semantic decoder)
    sem_hidden: int = 64        # semantic decoder width
    k: int = 4                  # neighbours per sample
    radius: float = 0.0         # neighbour search radius; 0 = auto (radius_scale x mean edge length)
    radius_scale: float = 2.5
    hidden: int = 64            # decoder width
    interpolation: Literal["post", "early"] = "post"   # post: the paper's default; early: cheaper, a little worse
    pos_freqs: int = 4          # frequencies of the encoding of p / radius
    sh_degree: int = 4          # spherical-harmonics degree of the view-direction encoding
    k_tv: int = 8               # neighbours per vertex in the total-variation loss
    grid_resolution: int = 128  # occupancy grid cells along the longest axis
    step_scale: float = 0.5     # marching step = radius x step_scale (training and rendering)
    code_init_std: float = 1e-2
    knn: Literal["auto", "hashgrid", "triton"] = "auto"   # neighbour search: "auto" (pykdtree on the CPU; on
    #                             a GPU the Triton kernel, or the hash grid without triton), "hashgrid" (torch,
    #                             any device) or "triton" (GPU); "kdtree", the name older files saved, is "auto"

    def __post_init__(self) -> None:
        try:
            self.knn = knn_backend(self.knn)
        except ValueError:
            raise ValueError(f"knn must be one of {', '.join(KNN_BACKENDS)}, not {self.knn!r}") from None
        if self.interpolation not in ("post", "early"):
            raise ValueError(f"interpolation must be 'post' or 'early', not {self.interpolation!r}")
        if self.k < 1 or self.hidden < 1:
            raise ValueError("k and hidden must be positive")
        if self.sem_dim < 0 or self.sem_features < 0 or self.sem_hidden < 1:
            raise ValueError("sem_dim and sem_features must be >= 0 and sem_hidden positive")
        if (self.sem_dim > 0) != (self.sem_features > 0):
            raise ValueError(f"a semantic branch needs both sem_dim and sem_features (got {self.sem_dim} "
                             f"and {self.sem_features}); set both to 0 for a field without semantics")

    @property
    def has_semantics(self) -> bool:
        return self.sem_dim > 0

    @classmethod
    def from_dict(cls, d: dict) -> "FieldConfig":
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})


class FieldParams:
    """Mixin of :class:`NeuMeshField` (an ``nn.Module``): the per-vertex tables and the scaffold they
    live on. The attributes are created by ``NeuMeshField.__init__``."""

    # ------------------------------------------------------------------ geometry (the scaffold's)
    @property
    def num_vertices(self) -> int:
        return self.scaffold.num_vertices

    @property
    def radius(self) -> float:
        return float(self.config.radius)

    @property
    def vertices(self) -> np.ndarray:
        """Current (possibly deformed) vertex positions, (N,3) numpy."""
        return self.scaffold.vertices

    @property
    def rest_vertices(self) -> torch.Tensor:
        return self.scaffold.rest_vertices

    @property
    def rest_normals(self) -> torch.Tensor:
        return self.scaffold.rest_normals

    @property
    def faces(self) -> torch.Tensor:
        return self.scaffold.faces

    @property
    def grid(self):
        return self.scaffold.grid

    @property
    def to_rest(self) -> Optional[torch.Tensor]:
        return self.scaffold.to_rest

    @property
    def mesh(self) -> Mesh:
        return Mesh(self.vertices, self.faces.cpu().numpy())

    @property
    def rest_mesh(self) -> Mesh:
        return Mesh(self.rest_vertices.cpu().numpy(), self.faces.cpu().numpy())

    def set_vertices(self, vertices) -> None:
        """Deform the field: new positions for the same vertices, in the same order (see
        :meth:`Scaffold.set_vertices`)."""
        self.scaffold.set_vertices(vertices)

    def reset_vertices(self) -> None:
        """Back to the rest (training) pose."""
        self.scaffold.set_vertices(self.rest_vertices)

    def neighbourhood(self, x: torch.Tensor) -> Neighbourhood:
        """K nearest vertices within the radius and the local indicators h_k = (p_k, w_k)."""
        return self.scaffold.neighbourhood(x)

    # ------------------------------------------------------------------ queries
    def rows(self, table: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """``table[idx]`` for a per-vertex table.  With :attr:`sparse_grads` the backward pass gives a
        sparse gradient holding only the rows looked up: a dense one costs a fill and an add of the
        whole table per lookup, which made a training step at 1.8M vertices twice as slow."""
        if self.sparse_grads and table.requires_grad and torch.is_grad_enabled():
            return torch.nn.functional.embedding(idx, table, sparse=True)
        return take_rows(table, idx)

    @property
    def code_prior(self):
        """The attached training-time coarse code levels (a CodePyramid) or None."""
        return self._code_prior

    def set_code_prior(self, prior) -> None:
        """Attach (or with None detach) coarse code levels.  Kept outside the module tree on purpose
        (``nn.Module`` would register a module attribute as a submodule and save it)."""
        object.__setattr__(self, "_code_prior", prior)

    def code_table(self, name: str) -> torch.Tensor:
        """The per-vertex code table called ``name`` ("geo" or "tex")."""
        return self.geo_codes if name == "geo" else self.tex_codes

    def codes(self, names, idx: torch.Tensor):
        """Per-vertex codes of vertices ``idx`` for each of ``names`` ("geo" and/or "tex"), as a list,
        including the training-time coarse levels when a :attr:`code_prior` is attached."""
        out = [self.rows(self.code_table(n), idx) for n in names]
        if self._code_prior is not None:
            out = [a if b is None else a + b for a, b in zip(out, self._code_prior.lookup(names, idx))]
        return out

    # ------------------------------------------------------------------ misc
    def persistent_buffer_names(self) -> set:
        out = set()
        for mod_name, mod in self.named_modules():
            for name, _ in mod.named_buffers(recurse=False):
                if name not in mod._non_persistent_buffers_set:
                    out.add(f"{mod_name}.{name}" if mod_name else name)
        return out
