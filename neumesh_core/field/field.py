"""The NeuMesh++ field: learnable codes on mesh vertices, decoded by small MLPs.

A sample x finds its K nearest scaffold vertices within ``radius``.  For each neighbour k the local
indicator is h_k = (p_k, w_k): p_k the projection of v_k - x on the vertex normal n_k, w_k the
normalised inverse distance.  The geometry decoder maps (geo code, h_k) to sigma_k and the radiance
decoder maps (tex code, h_k, view direction, normal) to c_k, to which the vertex's view-independent
modification colour is added.  Post-interpolation (the paper's default) takes the w-weighted mean of
sigma_k and c_k; early interpolation (config) interpolates codes and h first and decodes once.

Vertex positions are inputs, not parameters: :meth:`NeuMeshField.set_vertices` deforms the field.
View directions and normals reach the radiance decoder in each vertex's *rest* frame (a per-vertex
rotation from rest to current pose is derived from a tangent frame), so a rigid motion of scaffold
and camera renders the same image and view-dependent effects move with the surface.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Optional

import numpy as np
import torch
from torch import nn

from ..device import draw_device
from ..errors import VertexMismatchError
from ..mesh import Mesh, mean_edge_length, unique_edges, vertex_normals
from .encoding import frequency_encoding, sh_encoding, trunc_exp
from .knn import KNN_BACKENDS, HashGridIndex, VertexIndex, make_index, vertex_neighbours


@dataclass
class FieldConfig:
    """Field hyper-parameters (saved in every checkpoint)."""

    geo_dim: int = 6            # geometry code per vertex
    tex_dim: int = 15           # texture code per vertex
    sem_dim: int = 0            # semantic code slot (filled by semantic distillation; 0 = unused)
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

    @classmethod
    def from_dict(cls, d: dict) -> "FieldConfig":
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})


@dataclass
class Neighbourhood:
    """Geometry of samples w.r.t. their neighbours; independent of learnable parameters.

    idx (M,K) vertex indices (0 where invalid), w (M,K) normalised inverse-distance weights (0 where
    invalid), p (M,K) signed projections on the vertex normals, valid (M,K) bool.
    """

    idx: torch.Tensor
    w: torch.Tensor
    p: torch.Tensor
    valid: torch.Tensor

    def __len__(self) -> int:
        return self.idx.shape[0]

    def select(self, m: torch.Tensor) -> "Neighbourhood":
        return Neighbourhood(self.idx[m], self.w[m], self.p[m], self.valid[m])

    @staticmethod
    def cat(items) -> "Neighbourhood":
        return Neighbourhood(*(torch.cat([getattr(i, f) for i in items]) for f in ("idx", "w", "p", "valid")))


def _mlp(d_in: int, hidden: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(d_in, hidden), nn.ReLU(inplace=True),
        nn.Linear(hidden, hidden), nn.ReLU(inplace=True),
        nn.Linear(hidden, d_out),
    )


def _tangent_frames(vertices: torch.Tensor, normals: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """(N,3,3) orthonormal frames with columns (t, b, n); t points towards vertex ``ref``."""
    e = vertices[ref] - vertices
    t = e - (e * normals).sum(-1, keepdim=True) * normals
    # fall back to a fixed axis where the edge is (nearly) parallel to the normal or missing
    axis = torch.where(normals[:, :1].abs() < 0.9,
                       torch.tensor([1.0, 0.0, 0.0], device=normals.device).expand_as(normals),
                       torch.tensor([0.0, 1.0, 0.0], device=normals.device).expand_as(normals))
    t_fb = axis - (axis * normals).sum(-1, keepdim=True) * normals
    tl = t.norm(dim=-1, keepdim=True)
    t = torch.where(tl > 1e-8, t / tl.clamp_min(1e-12), t_fb / t_fb.norm(dim=-1, keepdim=True))
    b = torch.cross(normals, t, dim=-1)
    return torch.stack([t, b, normals], -1)


class NeuMeshField(nn.Module):
    """Per-vertex codes + decoders + the scaffold geometry they live on."""

    def __init__(self, mesh: Mesh, config: Optional[FieldConfig] = None):
        super().__init__()
        cfg = config or FieldConfig()
        verts = torch.as_tensor(mesh.vertices, dtype=torch.float32)
        faces = torch.as_tensor(mesh.faces, dtype=torch.long)
        n = len(verts)
        if n < cfg.k:
            raise ValueError(f"the scaffold has {n} vertices; at least k={cfg.k} are needed")
        if not torch.isfinite(verts).all():
            raise ValueError("the scaffold mesh has NaN/inf vertex positions; repair the mesh first")
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
        self.sem_codes = nn.Parameter(torch.zeros(n, cfg.sem_dim), requires_grad=False)
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
            self.rad_decoder = _mlp(cfg.tex_dim + pe + 1 + cfg.sh_degree ** 2 + 3, cfg.hidden, 3)
        with torch.no_grad():
            # start with a moderate density in the shell so rays see the surface early in training
            self.geo_decoder[-1].bias.fill_(float(np.log(0.5 / cfg.radius)))
            self.geo_decoder[-1].weight.mul_(0.1)

        # --- scaffold geometry (buffers: saved, moved with .to(), never optimised)
        ref = self._reference_neighbours(n, edges)
        self.register_buffer("faces", faces)
        self.register_buffer("tangent_ref", ref)
        self.register_buffer("rest_vertices", verts.clone())
        self.register_buffer("tv_neighbours", torch.from_numpy(vertex_neighbours(mesh.vertices, cfg.k_tv)))
        self.register_buffer("vertices_", verts.clone(), persistent=False)
        self.register_buffer("normals", torch.zeros_like(verts), persistent=False)
        self.register_buffer("rest_normals", torch.zeros_like(verts), persistent=False)
        self.register_buffer("rest_frames", torch.zeros(n, 3, 3), persistent=False)
        self.to_rest: Optional[torch.Tensor] = None  # (N,3,3) current->rest rotation; None at rest
        self.index = None  # VertexIndex or HashGridIndex (config.knn)
        self._update_rest_geometry()
        from ..sampling.occupancy import OccupancyGrid

        self.grid = OccupancyGrid.from_vertices(verts, cfg.radius, cfg.grid_resolution)
        self._rest_grid_state = None
        self._grid_anchors = None

    # ------------------------------------------------------------------ geometry
    @staticmethod
    def _reference_neighbours(n: int, edges: np.ndarray) -> torch.Tensor:
        """For every vertex a fixed edge neighbour (defines its tangent); itself when isolated."""
        ref = np.arange(n, dtype=np.int64)
        if len(edges):
            # the smallest-index neighbour of each vertex: deterministic and topology-only
            a = np.concatenate([edges[:, 0], edges[:, 1]])
            b = np.concatenate([edges[:, 1], edges[:, 0]])
            order = np.lexsort((b, a))
            a, b = a[order], b[order]
            first = np.ones(len(a), bool)
            first[1:] = a[1:] != a[:-1]
            ref[a[first]] = b[first]
        return torch.from_numpy(ref)

    def _update_rest_geometry(self) -> None:
        with torch.no_grad():
            self.rest_normals.copy_(vertex_normals(self.rest_vertices, self.faces))
            self.rest_frames.copy_(_tangent_frames(self.rest_vertices, self.rest_normals, self.tangent_ref))
            self.vertices_.copy_(self.rest_vertices)
            self.normals.copy_(self.rest_normals)
        self.to_rest = None
        self.index = make_index(self.rest_vertices, self.config.k, self.config.radius, self.config.knn)

    @property
    def num_vertices(self) -> int:
        return self.rest_vertices.shape[0]

    @property
    def radius(self) -> float:
        return float(self.config.radius)

    @property
    def vertices(self) -> np.ndarray:
        """Current (possibly deformed) vertex positions, (N,3) numpy."""
        return self.vertices_.detach().cpu().numpy()

    @property
    def mesh(self) -> Mesh:
        return Mesh(self.vertices, self.faces.cpu().numpy())

    @property
    def rest_mesh(self) -> Mesh:
        return Mesh(self.rest_vertices.cpu().numpy(), self.faces.cpu().numpy())

    def set_vertices(self, vertices) -> None:
        """Deform the field: new positions for the same vertices, in the same order.

        Normals, per-vertex rotations, the neighbour index and the occupancy grid are refreshed.
        """
        v = torch.as_tensor(np.asarray(vertices) if not torch.is_tensor(vertices) else vertices,
                            dtype=torch.float32).to(self.rest_vertices.device)
        if v.ndim != 2 or v.shape[1] != 3:
            raise VertexMismatchError(f"expected vertex positions of shape (N,3), got {tuple(v.shape)}")
        if v.shape[0] != self.num_vertices:
            raise VertexMismatchError(
                f"the field has {self.num_vertices} vertices but {v.shape[0]} positions were given; "
                "the mesh topology changed (e.g. a subdivision/remesh/decimate modifier). Apply the "
                "deformation only with modifiers that keep vertex count and order, or retrain the field "
                "on the new mesh.")
        if not torch.isfinite(v).all():
            raise VertexMismatchError("new vertex positions contain NaN/inf; check the deformer")
        with torch.no_grad():
            self.vertices_.copy_(v)
            if torch.equal(v, self.rest_vertices):
                self.normals.copy_(self.rest_normals)
                self.to_rest = None
            else:
                self.normals.copy_(vertex_normals(v, self.faces))
                frames = _tangent_frames(v, self.normals, self.tangent_ref)
                # rotation current -> rest: R = F_rest F_cur^T
                self.to_rest = self.rest_frames @ frames.transpose(1, 2)
        self.index = make_index(v, self.config.k, self.config.radius, self.config.knn)
        # the grid refined from densities is valid in the rest pose only: keep it aside while deformed,
        # and carry its occupied cells along with the surface (each moves rigidly with its nearest vertex)
        if self.to_rest is None:
            if self._rest_grid_state is not None:
                self.grid.load_state(self._rest_grid_state)
                self._rest_grid_state = None
                self._grid_anchors = None
        else:
            if self._rest_grid_state is None:
                self._rest_grid_state = self.grid.state()
                self._grid_anchors = None
                if self.grid.refined:
                    centers = self.grid.occupied_centers()
                    nearest, _ = VertexIndex(self.rest_vertices, 1).query(centers)
                    nearest = nearest[:, 0]
                    self._grid_anchors = (nearest, centers - self.rest_vertices[nearest])
            carried = None
            if self._grid_anchors is not None:
                vid, offset = self._grid_anchors
                rest_to_cur = self.to_rest[vid].transpose(1, 2)
                carried = v[vid] + (rest_to_cur * offset[:, None, :]).sum(-1)
            self.grid.rebuild_from_vertices(v, self.config.radius, carried)

    def reset_vertices(self) -> None:
        """Back to the rest (training) pose."""
        self.set_vertices(self.rest_vertices)

    # ------------------------------------------------------------------ queries
    def rows(self, table: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """``table[idx]`` for a per-vertex table.  With :attr:`sparse_grads` the backward pass gives a
        sparse gradient holding only the rows looked up: a dense one costs a fill and an add of the
        whole table per lookup, which made a training step at 1.8M vertices twice as slow."""
        if self.sparse_grads and table.requires_grad and torch.is_grad_enabled():
            return torch.nn.functional.embedding(idx, table, sparse=True)
        return table[idx]

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

    def neighbourhood(self, x: torch.Tensor) -> Neighbourhood:
        """K nearest vertices within the radius and the local indicators h_k = (p_k, w_k)."""
        idx, dist = self.index.query(x)
        valid = idx >= 0
        idx = idx.clamp_min(0)
        inv = torch.where(valid, 1.0 / dist.clamp_min(1e-8), torch.zeros_like(dist))
        w = inv / inv.sum(-1, keepdim=True).clamp_min(1e-12)
        vk = self.vertices_[idx]
        nk = self.normals[idx]
        p = ((vk - x[:, None, :]) * nk).sum(-1)
        return Neighbourhood(idx, w, p, valid)

    def _p_encoding(self, p: torch.Tensor) -> torch.Tensor:
        return frequency_encoding(p / self.config.radius, self.config.pos_freqs)

    def _rest_dirs(self, idx: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """View directions d (P,3) in the rest frame of vertices idx (P,)."""
        if self.to_rest is None:
            return d
        r = self.to_rest[idx]
        return (r * d[:, None, :]).sum(-1)

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
            geo_in = torch.cat([self.codes(("geo",), vid)[0], pe, wk[:, None]], -1)
            sigma = reduce(trunc_exp(self.geo_decoder(geo_in))).squeeze(-1)
        if not with_rgb:
            return sigma, None, None
        d = dirs[:, None, :].expand(m, k, 3).reshape(-1, 3) if sample is None else dirs[sample]
        d = self._rest_dirs(vid, d)
        rad_in = torch.cat([self.codes(("tex",), vid)[0], pe, wk[:, None], sh_encoding(d, self.config.sh_degree),
                            self.rest_normals[vid]], -1)
        mod_k = self.rows(self.mod_colors, vid)
        c_k = torch.sigmoid(self.rad_decoder(rad_in)) + mod_k
        out = reduce(torch.cat([c_k, mod_k], -1))
        return sigma, out[:, :3], out[:, 3:]

    def _decode_early(self, nb: Neighbourhood, dirs, with_rgb: bool, with_sigma: bool):
        w = nb.w[..., None]
        p = (nb.p * nb.w).sum(1)
        wi = (nb.w * nb.w).sum(1)
        pe = self._p_encoding(p)
        names = (("geo",) if with_sigma else ()) + (("tex",) if with_rgb else ())
        codes = dict(zip(names, self.codes(names, nb.idx)))
        sigma = None
        if with_sigma:
            geo = (codes["geo"] * w).sum(1)
            sigma = trunc_exp(self.geo_decoder(torch.cat([geo, pe, wi[:, None]], -1)).squeeze(-1))
            sigma = torch.where(nb.valid.any(1), sigma, torch.zeros_like(sigma))
        if not with_rgb:
            return sigma, None, None
        tex = (codes["tex"] * w).sum(1)
        n = (self.rest_normals[nb.idx] * w).sum(1)
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        if self.to_rest is None:
            d = dirs
        else:
            d = (self.to_rest[nb.idx] * dirs[:, None, None, :]).sum(-1)
            d = (d * w).sum(1)
            d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        mod = (self.rows(self.mod_colors, nb.idx) * w).sum(1)
        rad_in = torch.cat([tex, pe, wi[:, None], sh_encoding(d, self.config.sh_degree), n], -1)
        rgb = torch.sigmoid(self.rad_decoder(rad_in)) + mod
        return sigma, rgb, mod

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
        j = self.tv_neighbours[i]
        dg = (self.rows(self.geo_codes, i)[:, None] - self.rows(self.geo_codes, j)).pow(2).sum(-1).mean()
        dt = (self.rows(self.tex_codes, i)[:, None] - self.rows(self.tex_codes, j)).pow(2).sum(-1).mean()
        return dg + dt

    # ------------------------------------------------------------------ misc
    def persistent_buffer_names(self) -> set:
        return {n for n, _ in self.named_buffers() if n not in self._non_persistent_buffers_set}

    def _apply(self, fn, *args, **kwargs):  # keep non-buffer tensors on the module's device
        super()._apply(fn, *args, **kwargs)
        if self.to_rest is not None:
            self.to_rest = fn(self.to_rest)
        if hasattr(self, "grid"):
            self.grid.to(self.rest_vertices.device)
        if isinstance(getattr(self, "index", None), HashGridIndex) and self.index.v.device != self.vertices_.device:
            # the torch index lives with the vertices
            self.index = make_index(self.vertices_, self.config.k, self.config.radius, self.config.knn)
        return self
