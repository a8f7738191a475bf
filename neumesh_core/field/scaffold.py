"""The scaffold a field lives on: rest pose, current pose, normals, per-vertex rest frames, the
neighbour index and the occupancy grid.  Nothing here is learnable.

A sample x finds its K nearest scaffold vertices within ``radius`` (:meth:`Scaffold.neighbourhood`).
For each neighbour k the local indicator is h_k = (p_k, w_k): p_k the projection of v_k - x on the
vertex normal n_k, w_k the normalised inverse distance.  Vertex positions are inputs, not parameters:
:meth:`Scaffold.set_vertices` deforms the scaffold.  View directions reach the radiance decoder in
each vertex's *rest* frame (a per-vertex rotation from rest to current pose derived from a tangent
frame), so a rigid motion of scaffold and camera renders the same image and view-dependent effects
move with the surface.
"""
from __future__ import annotations

from dataclasses import dataclass
from concurrent.futures import ThreadPoolExecutor
from typing import Optional

import numpy as np
import torch
from torch import nn

from ..errors import VertexMismatchError
from ..mesh import Mesh, face_incidence, vertex_normals
from .knn import KDTreeIndex, make_index, vertex_neighbours

# builds neighbour indices beside the main thread (Scaffold.set_vertices)
_INDEX_BUILDER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="neumesh-index")

# persistent buffers of a Scaffold (saved in field files as ``buffer/scaffold.<name>``)
PERSISTENT = ("faces", "tangent_neighbour", "rest_vertices", "tv_neighbours")


def take_rows(table: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``table[idx]`` for an integer index of any shape, as one ``index_select`` over the flattened
    index: the same values (a copy of rows), two to three times faster than advanced indexing on the
    CPU for the narrow per-vertex tables gathered per sample; autograd flows as through indexing."""
    return table.index_select(0, idx.reshape(-1)).view(*idx.shape, *table.shape[1:])


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
        """The samples picked by ``m``: a boolean mask or an integer index."""
        if m.dtype == torch.bool:
            return Neighbourhood(self.idx[m], self.w[m], self.p[m], self.valid[m])
        return Neighbourhood(*(take_rows(getattr(self, f), m) for f in ("idx", "w", "p", "valid")))

    @staticmethod
    def cat(items) -> "Neighbourhood":
        return Neighbourhood(*(torch.cat([getattr(i, f) for i in items]) for f in ("idx", "w", "p", "valid")))


def tangent_frames(vertices: torch.Tensor, normals: torch.Tensor, towards: torch.Tensor) -> torch.Tensor:
    """(N,3,3) orthonormal frames with columns (t, b, n); t points towards vertex ``towards`` (each
    vertex's tangent neighbour, :func:`tangent_neighbours`).

    t is the edge to that vertex projected on the tangent plane; where that edge is missing or within 1e-4
    rad of the normal, a fixed axis projected instead.  Edges within 0.01 rad of the normal are
    projected twice, so float32 round-off cannot leave t off the plane.
    """
    e = vertices.index_select(0, towards) - vertices
    t = e - (e * normals).sum(-1, keepdim=True) * normals
    tl = torch.linalg.vector_norm(t, dim=-1, keepdim=True)
    el = torch.linalg.vector_norm(e, dim=-1, keepdim=True)
    t = t / tl.clamp_min(1e-30)
    steep = (tl[:, 0] < 1e-2 * el[:, 0]).nonzero().squeeze(1)
    if steep.numel():
        ns = normals.index_select(0, steep)
        ts = t.index_select(0, steep)
        ts = ts - (ts * ns).sum(-1, keepdim=True) * ns
        t = t.index_copy(0, steep, ts / torch.linalg.vector_norm(ts, dim=-1, keepdim=True).clamp_min(1e-30))
    bad = (tl[:, 0] <= 1e-4 * el[:, 0]).nonzero().squeeze(1)
    if bad.numel():
        nb = normals.index_select(0, bad)
        axis = torch.where(nb[:, :1].abs() < 0.9,
                           torch.tensor([1.0, 0.0, 0.0], device=normals.device).expand_as(nb),
                           torch.tensor([0.0, 1.0, 0.0], device=normals.device).expand_as(nb))
        t_fb = axis - (axis * nb).sum(-1, keepdim=True) * nb
        t = t.index_copy(0, bad, t_fb / t_fb.norm(dim=-1, keepdim=True))
    b = torch.linalg.cross(normals, t, dim=-1)
    return torch.stack([t, b, normals], -1)


def tangent_neighbours(n: int, edges: np.ndarray) -> torch.Tensor:
    """For every vertex a fixed edge neighbour, its tangent neighbour (its tangent points there);
    itself when isolated."""
    nb = np.arange(n, dtype=np.int64)
    if len(edges):
        # the smallest-index neighbour of each vertex: deterministic and topology-only
        a = np.concatenate([edges[:, 0], edges[:, 1]])
        b = np.concatenate([edges[:, 1], edges[:, 0]])
        order = np.lexsort((b, a))
        a, b = a[order], b[order]
        first = np.ones(len(a), bool)
        first[1:] = a[1:] != a[:-1]
        nb[a[first]] = b[first]
    return torch.from_numpy(nb)


class Scaffold(nn.Module):
    """Mesh geometry of a field: buffers move with ``.to()``; ``set_vertices`` deforms.

    ``radius``, ``k``, ``knn``, ``k_tv`` and ``grid_resolution`` come from the field's config.
    """

    def __init__(self, mesh: Mesh, edges: np.ndarray, radius: float, k: int, knn: str, k_tv: int,
                 grid_resolution: int):
        super().__init__()
        verts = torch.as_tensor(mesh.vertices, dtype=torch.float32)
        n = len(verts)
        self.radius = float(radius)
        self.k = int(k)
        self.knn = knn
        self.register_buffer("faces", torch.as_tensor(mesh.faces, dtype=torch.long))
        self.register_buffer("tangent_neighbour", tangent_neighbours(n, edges))
        self.register_buffer("rest_vertices", verts.clone())
        self.register_buffer("tv_neighbours", torch.from_numpy(vertex_neighbours(mesh.vertices, k_tv)))
        self.register_buffer("vertices_", verts.clone(), persistent=False)
        self.register_buffer("normals", torch.zeros_like(verts), persistent=False)
        self.register_buffer("rest_normals", torch.zeros_like(verts), persistent=False)
        self.register_buffer("rest_frames", torch.zeros(n, 3, 3), persistent=False)
        self.to_rest: Optional[torch.Tensor] = None  # (N,3,3) current->rest rotation; None at rest
        self.index = None  # KDTreeIndex, HashGridIndex or TritonKNNIndex (knn backend, make_index)
        self.update_rest_geometry()
        from ..sampling.occupancy import OccupancyGrid

        self.grid = OccupancyGrid.from_vertices(verts, self.radius, grid_resolution)
        self._rest_grid_state = None
        self._grid_anchors = None

    def update_rest_geometry(self) -> None:
        """Recompute rest normals/frames and the index from ``rest_vertices`` (after loading them)."""
        with torch.no_grad():
            self.rest_normals.copy_(vertex_normals(self.rest_vertices, self.faces))
            self.rest_frames.copy_(tangent_frames(self.rest_vertices, self.rest_normals, self.tangent_neighbour))
            self.vertices_.copy_(self.rest_vertices)
            self.normals.copy_(self.rest_normals)
        self.to_rest = None
        self.index = make_index(self.rest_vertices, self.k, self.radius, self.knn)

    @property
    def num_vertices(self) -> int:
        return self.rest_vertices.shape[0]

    @property
    def vertices(self) -> np.ndarray:
        """Current (possibly deformed) vertex positions, (N,3) numpy."""
        return self.vertices_.detach().cpu().numpy()

    def rest_grid_state(self) -> dict:
        """The occupancy grid of the rest pose (what a field file stores, also while deformed)."""
        return self._rest_grid_state or self.grid.state()

    def set_vertices(self, vertices) -> None:
        """Deform: new positions for the same vertices, in the same order.

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
        # the neighbour index is built on a worker thread (pykdtree's build releases the GIL) while the
        # normals and frames are computed here; nothing is changed before both are ready, so a failure
        # leaves the field as it was
        index = _INDEX_BUILDER.submit(make_index, v, self.k, self.radius, self.knn)
        with torch.no_grad():
            if torch.equal(v, self.rest_vertices):
                normals, to_rest = self.rest_normals, None
            else:
                normals = vertex_normals(v, self.faces, self._face_incidence())
                frames = tangent_frames(v, normals, self.tangent_neighbour)
                # rotation current -> rest: R = F_rest F_cur^T
                to_rest = self.rest_frames @ frames.transpose(1, 2)
            self.index = index.result()
            self.vertices_.copy_(v)
            self.normals.copy_(normals)
            self.to_rest = to_rest
        self._update_grid(v)

    def _derived(self, name: str, key: tuple, build):
        """``build()``, cached as ``name`` while ``key`` (tensor pointers and versions) stays the same."""
        cached = self.__dict__.get(name)
        if cached is None or cached[0] != key:
            cached = (key, build())
            self.__dict__[name] = cached
        return cached[1]

    def _face_incidence(self) -> torch.Tensor:
        """:func:`face_incidence` of the faces, rebuilt when the faces buffer is written or moved."""
        f = self.faces
        return self._derived("_incidence_cache", (f.data_ptr(), f._version, self.num_vertices),
                             lambda: face_incidence(f, self.num_vertices))

    def _update_grid(self, v: torch.Tensor) -> None:
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
                    centres = self.grid.occupied_centres()
                    nearest, _ = KDTreeIndex(self.rest_vertices, 1).query(centres)
                    nearest = nearest[:, 0]
                    self._grid_anchors = (nearest, centres - self.rest_vertices[nearest])
            carried = None
            if self._grid_anchors is not None:
                vid, offset = self._grid_anchors
                # rest -> current is to_rest transposed: offset_j R_ij summed over i, one bmm
                carried = v.index_select(0, vid) + torch.bmm(
                    offset[:, None, :], take_rows(self.to_rest, vid)).squeeze(1)
            self.grid.rebuild_from_vertices(v, self.radius, carried)

    def neighbourhood(self, x: torch.Tensor) -> Neighbourhood:
        """K nearest vertices within the radius and the local indicators h_k = (p_k, w_k)."""
        idx, dist = self.index.query(x)
        return self.neighbourhood_from(x, idx, dist)

    def neighbourhood_from(self, x: torch.Tensor, idx: torch.Tensor, dist: torch.Tensor) -> Neighbourhood:
        """The indicators of points x (M,3) whose K nearest vertices are already known: ``idx`` (M,K)
        (-1 where missing) and ``dist`` (M,K), as an index's ``query`` returns them (e.g. from the
        fused marcher, kernels/fused.march_rays_fused)."""
        valid = idx >= 0
        idx = idx.clamp_min(0)
        inv = torch.where(valid, 1.0 / dist.clamp_min(1e-8), torch.zeros_like(dist))
        w = inv / inv.sum(-1, keepdim=True).clamp_min(1e-12)
        vn = take_rows(self._vertex_table(), idx)    # one gather of (position, normal) rows
        p = ((vn[..., :3] - x[:, None, :]) * vn[..., 3:]).sum(-1)
        return Neighbourhood(idx, w, p, valid)

    def _vertex_table(self) -> torch.Tensor:
        """(N,6) current positions and normals side by side (one gather per neighbourhood instead of
        two); rebuilt whenever either buffer was written (their version counters) or moved."""
        v, n = self.vertices_, self.normals
        return self._derived("_vertex_table_cache", (v.data_ptr(), v._version, n.data_ptr(), n._version),
                             lambda: torch.cat([v, n], 1))

    def rest_dirs(self, idx: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """View directions d (...,3) in the rest frame of vertices idx (...,)."""
        if self.to_rest is None:
            return d
        return (take_rows(self.to_rest, idx) * d[..., None, :]).sum(-1)

    def __deepcopy__(self, memo):
        """A copy with its own tensors; the neighbour index (a C object) is rebuilt, not copied."""
        import copy

        new = type(self).__new__(type(self))
        memo[id(self)] = new
        for k, v in self.__dict__.items():
            if k.endswith("_cache"):   # derived data (vertex table, face incidence): rebuilt on use
                continue
            new.__dict__[k] = None if k == "index" else copy.deepcopy(v, memo)
        new.index = make_index(new.vertices_, new.k, new.radius, new.knn)
        return new

    def _apply(self, fn, *args, **kwargs):  # keep non-buffer tensors on the module's device
        before = self.vertices_.device if hasattr(self, "vertices_") else None
        super()._apply(fn, *args, **kwargs)
        if self.to_rest is not None:
            self.to_rest = fn(self.to_rest)
        if hasattr(self, "grid"):
            self.grid.to(self.rest_vertices.device)
        if getattr(self, "index", None) is not None and self.vertices_.device != before:
            # the index suits the vertices' device (a torch index lives with them; see make_index)
            self.index = make_index(self.vertices_, self.k, self.radius, self.knn)
        return self
