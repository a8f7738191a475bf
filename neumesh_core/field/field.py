"""The NeuMesh++ field: learnable codes on mesh vertices, decoded by small MLPs.

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
once per sample (:meth:`NeuMeshField.decode_semantics`; an MLP with one hidden layer); the renderer composites the decoded features
with the colour's compositing weights.  ``sem_dim = 0`` (the default) means no semantic branch: no
decoder exists and nothing is decoded, so such a field renders and costs exactly as before.
"""
from __future__ import annotations

import copy
import hashlib
from dataclasses import asdict, dataclass, fields
from typing import Optional

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from ..device import draw_device
from ..mesh import Mesh, mean_edge_length, unique_edges
from .encoding import frequency_encoding, sh_encoding, trunc_exp
from .knn import KNN_BACKENDS, vertex_neighbours
from .scaffold import Neighbourhood, Scaffold, reference_neighbours, take_rows, tangent_frames  # noqa: F401 (re-exported)

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
    interpolation: str = "post"  # "post" (paper default) or "early" (~3x cheaper, ~0.15 dB worse)
    pos_freqs: int = 4          # frequencies of the encoding of p / radius
    sh_degree: int = 4          # spherical-harmonics degree of the view-direction encoding
    k_tv: int = 8               # neighbours per vertex in the total-variation loss
    grid_resolution: int = 128  # occupancy grid cells along the longest axis
    step_scale: float = 0.5     # marching step = radius x step_scale (training and rendering)
    code_init_std: float = 1e-2
    knn: str = "kdtree"         # neighbour search: "kdtree" (pykdtree, CPU) or "hashgrid" (torch, any device)

    def __post_init__(self) -> None:
        if self.knn not in KNN_BACKENDS:
            raise ValueError(f"knn must be one of {', '.join(KNN_BACKENDS)}, not {self.knn!r}")
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


def _mlp(d_in: int, hidden: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(d_in, hidden), nn.ReLU(inplace=True),
        nn.Linear(hidden, hidden), nn.ReLU(inplace=True),
        nn.Linear(hidden, d_out),
    )


# rows per decoder call when no gradient is needed: the hidden activations of ~16k rows stay in the
# CPU's cache, where one call on 600k rows streams them through memory (2-3x slower on this machine;
# benchmarks/bench_render.py)
_INFERENCE_ROWS = 16384


def run_decoder(module: nn.Module, x) -> torch.Tensor:
    """``module(x)``, in row blocks of ``_INFERENCE_ROWS`` when autograd is off (rows are independent,
    so the result is the same up to the float rounding of the matrix products).

    ``x``: the input, or a list of column blocks (tensors with the same rows) that make the input side
    by side.  On the CPU without autograd the blocks are copied into one small reused buffer per row
    block, so the whole concatenated input never exists (``torch.cat`` along columns is ~3x slower than
    slice copies on the CPU, and the decoder then reads its input from the cache, not from memory).
    With autograd or on a GPU the blocks are concatenated (the reference)."""
    parts = list(x) if isinstance(x, (list, tuple)) else None
    first = parts[0] if parts is not None else x
    n = first.shape[0]
    if torch.is_grad_enabled() or first.device.type != "cpu":
        return module(torch.cat(parts, -1) if parts is not None else x)
    if parts is None:
        if n <= _INFERENCE_ROWS:
            return module(x)
        return torch.cat([module(x[s:s + _INFERENCE_ROWS]) for s in range(0, n, _INFERENCE_ROWS)])
    widths = [p.shape[1] for p in parts]
    if n == 0:
        return module(first.new_empty(0, sum(widths)))
    rows = min(n, _INFERENCE_ROWS)
    buf = first.new_empty(rows, sum(widths))
    outs = []
    for s in range(0, n, rows):
        e = min(n, s + rows)
        o = 0
        for p, w in zip(parts, widths):
            buf[:e - s, o:o + w].copy_(p[s:e])
            o += w
        outs.append(module(buf[:e - s]))
    return outs[0] if len(outs) == 1 else torch.cat(outs)


def decoder_key(module: nn.Module) -> str:
    """Content hash of a decoder's weights: equal keys mean bit-identical decoders (copies of one)."""
    h = hashlib.sha1()
    for name, t in module.state_dict().items():
        t = t.detach().cpu().contiguous()
        h.update(name.encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(t.numpy().tobytes())
    return h.hexdigest()


class NeuMeshField(nn.Module):
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
        self.mod_colors = nn.Parameter(torch.zeros(n, 3))
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

    # ------------------------------------------------------------------ decoder binding
    @property
    def rad_decoder(self) -> nn.Module:
        """The field's own (first) radiance decoder."""
        return self.rad_decoders[0]

    @property
    def num_decoders(self) -> int:
        return len(self.rad_decoders)

    def decoder_keys(self) -> list:
        """Content hash of each radiance decoder (see :func:`decoder_key`)."""
        return [decoder_key(d) for d in self.rad_decoders]

    def add_decoder(self, decoder: nn.Module) -> int:
        """Index of ``decoder`` in this field, appending a frozen copy of it when no bit-identical
        decoder is here yet (so binding codes from one source several times adds its decoder once)."""
        key = decoder_key(decoder)
        for i, d in enumerate(self.rad_decoders):
            if decoder_key(d) == key:
                return i
        if len(self.rad_decoders) >= torch.iinfo(self.decoder_id.dtype).max:
            raise ValueError("too many radiance decoders in one field")
        dec = copy.deepcopy(decoder).to(self.geo_codes.device)
        for prm in dec.parameters():
            prm.requires_grad_(False)
        self.rad_decoders.append(dec)
        return len(self.rad_decoders) - 1

    def drop_unused_decoders(self, keep: int = 1) -> int:
        """Remove trailing radiance decoders (index >= ``keep``) that no vertex is bound to; returns how
        many were removed.  Used to undo an edit that added decoders."""
        removed = 0
        used = int(self.decoder_id.max()) if self.num_vertices else 0
        while len(self.rad_decoders) > max(1, keep) and len(self.rad_decoders) - 1 > used:
            del self.rad_decoders[len(self.rad_decoders) - 1]
            removed += 1
        return removed

    def ensure_tex_frame(self) -> torch.Tensor:
        """The (N,3,3) texture frames, created as identities when the field has none yet."""
        if self.tex_frame is None:
            eye = torch.eye(3, device=self.geo_codes.device)
            self.tex_frame = eye.expand(self.num_vertices, 3, 3).clone()
        return self.tex_frame

    def compact_tex_frame(self) -> bool:
        """Drop the texture frames when every one is exactly the identity (the field then decodes as a
        trained field does, at no extra cost).  Returns True when the field has none afterwards."""
        if self.tex_frame is not None:
            eye = torch.eye(3, device=self.tex_frame.device)
            if bool((self.tex_frame == eye).all()):
                self.tex_frame = None
        return self.tex_frame is None

    def _code_frame(self, vid: torch.Tensor, d: torch.Tensor):
        """View directions ``d`` (...,3) (world, current pose) and rest normals of vertices ``vid`` (...,),
        both in the frame of each vertex's texture code (rest frame, then :attr:`tex_frame`)."""
        d = self.scaffold.rest_dirs(vid, d)
        n = take_rows(self.rest_normals, vid)
        if self.tex_frame is not None:
            Q = take_rows(self.tex_frame, vid)
            d = (Q * d[..., None, :]).sum(-1)
            n = (Q * n[..., None, :]).sum(-1)
        return d, n

    def _decode_rgb_rows(self, rad_in: list, vid: torch.Tensor) -> torch.Tensor:
        """Radiance decoder output (pre-sigmoid) for rows whose texture codes belong to vertices ``vid``
        (post-interpolation: each row with its own vertex's decoder).  ``rad_in``: the input's column
        blocks (:func:`run_decoder`)."""
        if len(self.rad_decoders) == 1:
            return run_decoder(self.rad_decoders[0], rad_in)
        dec = take_rows(self.decoder_id, vid).long()
        if len(dec) == 0:
            return rad_in[0].new_zeros(0, 3)
        lo, hi = int(dec.min()), int(dec.max())
        if lo == hi:   # every row on one decoder (most chunks of an edited field): no grouping
            return run_decoder(self.rad_decoders[lo], rad_in)
        out = None
        for d in torch.unique(dec).tolist():
            rows = (dec == d).nonzero().squeeze(1)
            y = run_decoder(self.rad_decoders[d], [p.index_select(0, rows) for p in rad_in])
            if out is None:
                out = y.new_zeros(len(dec), y.shape[1])
            out = out.index_copy(0, rows, y)
        return out if out is not None else rad_in[0].new_zeros(0, 3)

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
                "this field has no semantic codes; distil them first: `neumesh semantics --field F "
                "--data DIR` (or 'Distil semantics' in Blender's NeuMesh > Edit panel)")

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

    def _p_encoding(self, p: torch.Tensor) -> torch.Tensor:
        return frequency_encoding(p / self.config.radius, self.config.pos_freqs)

    def decode(self, nb: Neighbourhood, dirs: Optional[torch.Tensor] = None, with_rgb: bool = True,
               with_sigma: bool = True):
        """Decode samples: returns (sigma (M,) or None, rgb (M,3) or None, mod (M,3) or None).

        ``dirs`` (M,3) are unit ray directions (towards the scene), needed for rgb.
        """
        if self.config.interpolation == "early":
            return self._decode_early(nb, dirs, with_rgb, with_sigma)
        m, k = nb.idx.shape
        n_valid = int(nb.valid.sum())
        if n_valid >= 0.85 * m * k:
            # dense: decode every slot (invalid ones carry w=0), reduce with a reshape-sum
            vid, wk, pk = nb.idx.reshape(-1), nb.w.reshape(-1), nb.p.reshape(-1)
            sample = None
        else:
            flat = nb.valid.reshape(-1).nonzero().squeeze(1)
            vid, wk, pk = nb.idx.reshape(-1)[flat], nb.w.reshape(-1)[flat], nb.p.reshape(-1)[flat]
            sample = torch.div(flat, k, rounding_mode="floor")

        def reduce(values):  # sum_k w_k * values_k per sample
            wv = wk[:, None] * values
            if sample is None:
                return wv.view(m, k, -1).sum(1)
            return torch.zeros(m, wv.shape[1], device=wv.device, dtype=wv.dtype).index_add(0, sample, wv)

        pe = self._p_encoding(pk)
        sigma = None
        if with_sigma:
            geo_in = [self.codes(("geo",), vid)[0], pe, wk[:, None]]
            sigma = reduce(trunc_exp(run_decoder(self.geo_decoder, geo_in))).squeeze(-1)
        if not with_rgb:
            return sigma, None, None
        if self.to_rest is None and self.tex_frame is None and not torch.is_grad_enabled():
            # every neighbour of a sample sees the same direction: encode it once per sample (the SH
            # of each row, below, is the reference; the same values)
            sh_s = sh_encoding(dirs, self.config.sh_degree)
            sh = sh_s[:, None, :].expand(m, k, -1).reshape(m * k, -1) if sample is None else take_rows(sh_s, sample)
            n = take_rows(self.rest_normals, vid)
        else:
            d = dirs[:, None, :].expand(m, k, 3).reshape(-1, 3) if sample is None else dirs[sample]
            d, n = self._code_frame(vid, d)
            sh = sh_encoding(d, self.config.sh_degree)
        rad_in = [self.codes(("tex",), vid)[0], pe, wk[:, None], sh, n]
        mod_k = self.rows(self.mod_colors, vid)
        c_k = torch.sigmoid(self._decode_rgb_rows(rad_in, vid)) + mod_k
        return sigma, reduce(c_k), reduce(mod_k)

    def _decode_early(self, nb: Neighbourhood, dirs, with_rgb: bool, with_sigma: bool):
        w = nb.w[..., None]
        wb = nb.w[:, None, :]     # (M,1,K): w-weighted sums over the neighbours as batched products

        def wsum(rows):           # (M,K,C) -> (M,C)
            return torch.bmm(wb, rows).squeeze(1)

        # without autograd and coarse code levels, sum_k w_k table[idx_k] is one embedding bag: no (M,K,C)
        # gather (several times faster on the CPU; the reference is the gather-and-sum)
        bag = not torch.is_grad_enabled() and self._code_prior is None

        def wsum_rows(table):     # sum_k w_k table[idx_k] -> (M,C)
            if bag:
                return F.embedding_bag(nb.idx, table, per_sample_weights=nb.w, mode="sum")
            return wsum(self.rows(table, nb.idx))

        def code_sum(name):       # sum_k w_k codes_k (with the coarse levels, when attached)
            return wsum_rows(self.code_table(name)) if bag else wsum(codes[name])

        p = (nb.p * nb.w).sum(1)
        wi = (nb.w * nb.w).sum(1)
        pe = self._p_encoding(p)
        names = (("geo",) if with_sigma else ()) + (("tex",) if with_rgb else ())
        codes = {} if bag else dict(zip(names, self.codes(names, nb.idx)))
        sigma = None
        if with_sigma:
            geo = code_sum("geo")
            sigma = trunc_exp(run_decoder(self.geo_decoder, [geo, pe, wi[:, None]]).squeeze(-1))
            sigma = torch.where(nb.valid.any(1), sigma, torch.zeros_like(sigma))
        if not with_rgb:
            return sigma, None, None
        if self.tex_frame is None:
            n = wsum_rows(self.rest_normals)
            if self.to_rest is None:
                d = dirs
            else:   # sum_k w_k R_k d = (sum_k w_k R_k) d: one weighted sum of the (N,9) rotations
                r = wsum_rows(self.to_rest.reshape(-1, 9)).view(-1, 3, 3)
                d = torch.bmm(r, dirs[:, :, None]).squeeze(-1)
                d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        else:   # each neighbour's normal and view direction in its code frame, then w-weighted means
            dk, nk = self._code_frame(nb.idx, dirs[:, None, :].expand(-1, nb.idx.shape[1], 3))
            n = (nk * w).sum(1)
            d = (dk * w).sum(1)
            d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        mod = wsum_rows(self.mod_colors)
        shared = [pe, wi[:, None], sh_encoding(d, self.config.sh_degree), n]   # column blocks
        single = 0 if len(self.rad_decoders) == 1 else self._single_decoder(nb)
        if single is not None:   # one decoder for every neighbour: decode the interpolated code once
            tex = code_sum("tex")
            rgb = torch.sigmoid(run_decoder(self.rad_decoders[single], [tex] + shared)) + mod
        else:
            tex_k = take_rows(self.tex_codes, nb.idx) if bag else codes["tex"]
            rgb = self._early_rgb_by_decoder(nb, tex_k, shared) + mod
        return sigma, rgb, mod

    def _single_decoder(self, nb: Neighbourhood) -> Optional[int]:
        """The decoder every valid neighbour of every sample is bound to, or None when they differ."""
        dec = take_rows(self.decoder_id, nb.idx)
        if not bool(nb.valid.any()):
            return 0
        lo = int(torch.where(nb.valid, dec, dec.new_full((), torch.iinfo(dec.dtype).max)).min())
        hi = int(torch.where(nb.valid, dec, dec.new_full((), -1)).max())
        return lo if lo == hi else None

    def _early_rgb_by_decoder(self, nb: Neighbourhood, tex_k: torch.Tensor, shared: list):
        """Early interpolation over several decoders: sum_d W_d sigmoid(dec_d(codes of group d, h))."""
        dec = take_rows(self.decoder_id, nb.idx).long()
        rgb = shared[0].new_zeros(shared[0].shape[0], 3)
        for d in torch.unique(dec[nb.valid]).tolist():
            wd = torch.where((dec == d) & nb.valid, nb.w, torch.zeros_like(nb.w))   # (M,K)
            W = wd.sum(1)
            rows = (W > 0).nonzero().squeeze(1)
            wn = wd[rows] / W[rows, None]
            tex = (tex_k[rows] * wn[..., None]).sum(1)
            c = torch.sigmoid(run_decoder(self.rad_decoders[d], [tex] + [p.index_select(0, rows) for p in shared]))
            rgb = rgb.index_add(0, rows, W[rows, None] * c)
        return rgb

    def query(self, x: torch.Tensor, dirs: Optional[torch.Tensor] = None, with_rgb: bool = True):
        """Convenience: neighbourhood + decode for world points x (M,3)."""
        return self.decode(self.neighbourhood(x), dirs, with_rgb)

    def sigma_fn(self, x: torch.Tensor):
        """Density callback for the marcher: returns (sigma, neighbourhood)."""
        nb = self.neighbourhood(x)
        sigma, _, _ = self.decode(nb, None, with_rgb=False)
        return sigma, nb

    # ------------------------------------------------------------------ regularisers
    def tv_loss(self, n_samples: int = 16384, generator: Optional[torch.Generator] = None,
                vertices: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Total variation between each (sampled) vertex's codes and its k_tv nearest vertices.

        ``vertices`` (1-D indices) restricts the term to those vertices, e.g. the ones a training batch
        looked up, so that a vertex is smoothed on the steps its photometric gradient arrives.  Without
        it ``n_samples`` random vertices are drawn (all vertices when ``n_samples`` is 0 or >= N).
        """
        n = self.num_vertices
        if vertices is not None:
            i = vertices.to(device=self.geo_codes.device, dtype=torch.long).reshape(-1)
            if len(i) == 0:
                return self.geo_codes.sum() * 0.0
            if int(i.min()) < 0 or int(i.max()) >= n:
                raise IndexError(f"tv_loss: vertex indices must lie in [0, {n}), got "
                                 f"[{int(i.min())}, {int(i.max())}]")
        elif n_samples and n_samples < n:
            # drawn on the generator's device (a CPU generator draws the same vertices on any device)
            i = torch.randint(0, n, (n_samples,), device=draw_device(generator, self.geo_codes),
                              generator=generator).to(self.geo_codes.device)
        else:
            i = torch.arange(n, device=self.geo_codes.device)
        j = self.scaffold.tv_neighbours[i]
        dg = (self.rows(self.geo_codes, i)[:, None] - self.rows(self.geo_codes, j)).pow(2).sum(-1).mean()
        dt = (self.rows(self.tex_codes, i)[:, None] - self.rows(self.tex_codes, j)).pow(2).sum(-1).mean()
        return dg + dt

    # ------------------------------------------------------------------ misc
    def persistent_buffer_names(self) -> set:
        out = set()
        for mod_name, mod in self.named_modules():
            for name, _ in mod.named_buffers(recurse=False):
                if name not in mod._non_persistent_buffers_set:
                    out.add(f"{mod_name}.{name}" if mod_name else name)
        return out


def create_field(mesh: Mesh, config: FieldConfig | None = None, device="cpu") -> NeuMeshField:
    """A new, untrained field on ``mesh`` (vertex order is the field's vertex order)."""
    return NeuMeshField(mesh, config or FieldConfig()).to(device)
