"""The NeuMesh++ field: learnable codes on mesh vertices, decoded by small MLPs.

:class:`NeuMeshField` is one ``nn.Module`` (one state_dict, the same keys as ever) put together from
its parts: :mod:`.params` (FieldConfig, the per-vertex tables on the scaffold), :mod:`.decoders`
(geometry and radiance decoders, decoder binding, post/early decoding), :mod:`.heads` (semantic head)
and :mod:`.regularisers` (TV loss).

The mesh geometry (rest and current pose, normals, rest frames, neighbour index, occupancy grid) is a
:class:`~neumesh_core.field.scaffold.Scaffold` (``field.scaffold``); this module holds what is learned
on it.  A sample's K neighbours and local indicators h_k = (p_k, w_k) come from the scaffold.  The
geometry decoder maps (geo code, h_k) to sigma_k and a radiance decoder maps (tex code, h_k, view
direction, normal) to c_k, to which the vertex's view-independent modification colour is added.
Post-interpolation (the paper's default) takes the w-weighted mean of sigma_k and c_k; early
interpolation (config) interpolates codes and h first and decodes once.

**Decoder binding.** A field holds one geometry decoder and one or more radiance decoders
(``rad_decoders``) with a per-vertex ``decoder_id``: texture codes only mean something to the decoder
they were trained with, so a texture edit that brings codes from another field brings that field's
decoder too (:meth:`NeuMeshField.add_decoder`, added once per distinct decoder).  Post-interpolation
decodes each neighbour with its own vertex's decoder.  Early interpolation never mixes codes of
different decoders: for each decoder d among a sample's neighbours it interpolates the codes of the
neighbours bound to d (weights renormalised within the group), decodes once with d, and blends the
decoded colours with the group's total weight W_d = sum of w_k over those neighbours; the indicators
(p, w), normal and view direction are the sample's own, shared by all groups.  A sample whose
neighbours all share one decoder decodes exactly once, as before.  A field with a single decoder
takes the single-decoder code path (no per-sample grouping).

**Texture frames.** The radiance decoder sees the normal and the view direction in the rest pose's
world axes, so a texture code decodes to the colour it was trained for only in the orientation it was
trained in.  A texture edit that brings codes from a differently oriented surface (a swap from a
rotated region, a fill from a template) stores, for each vertex it writes, the rotation from the
vertex's rest frame into the frame of the code's origin (``tex_frame``, (N,3,3)); normals and view
directions are rotated by it before they reach the decoder (post: per neighbour; early: per neighbour,
then w-weighted means).  A field without texture frames (every trained field) skips this entirely.

**Semantics.** A field may carry a semantic code per vertex (``sem_codes``, ``FieldConfig.sem_dim``
wide) and a small semantic decoder (``sem_decoder``: sem_dim -> ``sem_features``), filled by
distillation from 2D image features (:mod:`neumesh_core.semantics`).  As in NeuMesh++ the codes are
interpolated first (the same normalised inverse-distance weights w_k as everything else) and decoded
once per sample (:meth:`NeuMeshField.decode_semantics`; an MLP with one hidden layer); the renderer
composites the decoded features with the colour's compositing weights.  ``sem_dim = 0`` (the default)
means no semantic branch: no decoder exists and nothing is decoded, so such a field renders and costs
exactly as before.
"""
from __future__ import annotations

import copy
from dataclasses import asdict
from typing import Optional

import numpy as np
import torch
from torch import nn

from ..mesh import Mesh, mean_edge_length, unique_edges
from .decoders import _INFERENCE_ROWS, RadianceDecoding, _mlp, decoder_key, run_decoder  # noqa: F401 (re-exported)
from .heads import SemanticsHead
from .knn import vertex_neighbours
from .params import FieldConfig, FieldParams
from .regularisers import tv_loss as _tv_loss
from .scaffold import Neighbourhood, Scaffold, tangent_neighbours, take_rows, tangent_frames  # noqa: F401 (re-exported)


class NeuMeshField(FieldParams, RadianceDecoding, SemanticsHead, nn.Module):
    """Per-vertex codes + decoders on a :class:`Scaffold` (``self.scaffold``).

    ``num_decoders``: radiance decoders to create (1 for a new field; more when a field file with bound
    decoders is loaded).
    """

    def __init__(self, mesh: Mesh, config: Optional[FieldConfig] = None, num_decoders: int = 1):
        super().__init__()
        cfg = config or FieldConfig()
        verts = torch.as_tensor(mesh.vertices, dtype=torch.float32)
        n = len(verts)
        if n < cfg.k:
            raise ValueError(f"the scaffold has {n} vertices; at least k={cfg.k} are needed")
        if not torch.isfinite(verts).all():
            raise ValueError("the scaffold mesh has NaN/inf vertex positions; repair the mesh first")
        if num_decoders < 1:
            raise ValueError("a field needs at least one radiance decoder")
        edges = unique_edges(mesh.faces) if len(mesh.faces) else np.zeros((0, 2), np.int64)
        if cfg.radius <= 0:
            if len(edges):
                mean_edge = mean_edge_length(mesh.vertices, edges)
            else:  # point cloud: use nearest-neighbour spacing
                nb = vertex_neighbours(mesh.vertices, 1)
                mean_edge = float(np.linalg.norm(mesh.vertices - mesh.vertices[nb[:, 0]], axis=1).mean())
            cfg = FieldConfig.from_dict({**asdict(cfg), "radius": cfg.radius_scale * max(mean_edge, 1e-6)})
        self.config = cfg

        # --- learnable per-vertex state
        g = torch.Generator().manual_seed(0)
        self.geo_codes = nn.Parameter(torch.randn(n, cfg.geo_dim, generator=g) * cfg.code_init_std)
        self.tex_codes = nn.Parameter(torch.randn(n, cfg.tex_dim, generator=g) * cfg.code_init_std)
        self.mod_colours = nn.Parameter(torch.zeros(n, 3))
        self.sem_codes = nn.Parameter(torch.randn(n, cfg.sem_dim, generator=g) * cfg.code_init_std,
                                      requires_grad=False)   # trained by semantics.distill only
        # what made the semantic codes (extractor, feature width, ...): saved in the field file's header
        self.semantics_info: dict = {}
        # True while training: code lookups give row-sparse gradients (see :meth:`rows`)
        self.sparse_grads = False
        # training-time coarse code levels added to geo/tex codes (field.pyramid.CodePyramid); not a
        # submodule, never saved: the trainer bakes it into the codes
        object.__setattr__(self, "_code_prior", None)

        # --- decoders
        pe = 1 + 2 * cfg.pos_freqs
        with torch.random.fork_rng(devices=[]):  # the same mesh and config give the same field
            torch.manual_seed(0)
            self.geo_decoder = _mlp(cfg.geo_dim + pe + 1, cfg.hidden, 1)
            rad = _mlp(cfg.tex_dim + pe + 1 + cfg.sh_degree ** 2 + 3, cfg.hidden, 3)
        self.rad_decoders = nn.ModuleList([rad] + [copy.deepcopy(rad) for _ in range(num_decoders - 1)])
        self.sem_decoder = self._new_sem_decoder(cfg)
        # which radiance decoder each vertex's texture code belongs to (all 0 in a trained field)
        self.register_buffer("decoder_id", torch.zeros(n, dtype=torch.int16))
        # per-vertex rotation from the vertex's rest frame into the frame its texture code was trained
        # in (normals and view directions reach the radiance decoder in that frame); None = identity for
        # every vertex (a trained field).  A texture edit that brings codes from a differently oriented
        # surface sets the rows it writes (see :meth:`ensure_tex_frame`).
        self.register_buffer("tex_frame", None)
        with torch.no_grad():
            # start with a moderate density in the shell so rays see the surface early in training
            self.geo_decoder[-1].bias.fill_(float(np.log(0.5 / cfg.radius)))
            self.geo_decoder[-1].weight.mul_(0.1)

        # --- scaffold geometry (buffers: saved, moved with .to(), never optimised)
        self.scaffold = Scaffold(mesh, edges, cfg.radius, cfg.k, cfg.knn, cfg.k_tv, cfg.grid_resolution)

    def tv_loss(self, n_samples: int = 16384, generator: Optional[torch.Generator] = None,
                vertices: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Total variation between each (sampled) vertex's codes and its k_tv nearest vertices
        (:func:`neumesh_core.field.regularisers.tv_loss`)."""
        return _tv_loss(self, n_samples, generator, vertices)


def create_field(mesh: Mesh, config: FieldConfig | None = None, device="cpu") -> NeuMeshField:
    """A new, untrained field on ``mesh`` (vertex order is the field's vertex order)."""
    return NeuMeshField(mesh, config or FieldConfig()).to(device)
