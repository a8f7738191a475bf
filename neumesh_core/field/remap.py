"""A field carried onto another mesh through a vertex identity map (topology edits in a modeller).

Modelling tools delete, separate, duplicate, join and subdivide meshes.  A mesh that carries, per
vertex, the id of the field vertex it came from and that vertex's rest position (Blender keeps such
point attributes through all of those operations, and interpolates them for new vertices) can be
rendered by a field *remapped* onto it: vertex i of the mesh is field vertex ``ids[i]``, with all its
per-vertex rows (codes, modification colour, decoder binding, texture frame) and its rest position.

A vertex whose id is missing, out of range, or whose stored rest position is not the rest position of
that field vertex (a vertex that a subdivision or an extrusion made: its attributes were interpolated
or copied) is a *new* vertex.  It sits at its own stored rest position, and its rows are the
inverse-distance-weighted mean of the rows of its k=4 nearest field vertices in the rest pose (codes
of different decoders are not mixed: see :func:`~neumesh_core.edit.transfer.blend_rows`).

The remapped field shares its decoders with the source field (no copies), keeps the source's radius,
and starts from the source's occupancy grid, restricted to where its own vertices are.
"""
from __future__ import annotations

import hashlib
from dataclasses import asdict

import numpy as np
import torch
from torch import nn

from ..errors import VertexMismatchError
from ..mesh import Mesh
from .neighbours import blend_rows, idw_neighbours, snap_identity

REST_TOLERANCE = 1e-5   # a stored rest position matches a field vertex within this x the field's extent


def field_key(field) -> int:
    """A 31-bit key of a field's lineage: a hash of its rest vertices, faces and geometry codes.

    Texture edits keep it (they never change those), two separately trained fields have different
    keys (their geometry codes differ) even on the same scaffold.  Cached on the field."""
    cached = getattr(field, "_lineage_key", None)
    if cached is not None:
        return cached
    h = hashlib.sha1()
    for t in (field.rest_vertices, field.faces, field.geo_codes):
        h.update(np.ascontiguousarray(t.detach().cpu().numpy()).tobytes())
    key = int(h.hexdigest()[:8], 16) & 0x7FFFFFFF
    object.__setattr__(field, "_lineage_key", key)
    return key


def resolve_ids(field, ids, rest) -> np.ndarray:
    """``ids`` (M,) with -1 where a vertex is not that field vertex: id out of range, or its stored rest
    position ``rest`` (M,3) differs from the field vertex's rest position (more than
    :data:`REST_TOLERANCE` of the field's extent)."""
    ids = np.asarray(ids).astype(np.int64).reshape(-1)
    rest = np.asarray(rest, np.float64).reshape(-1, 3)
    if len(ids) != len(rest):
        raise VertexMismatchError(f"{len(ids)} vertex ids but {len(rest)} rest positions")
    fr = field.rest_vertices.detach().cpu().numpy().astype(np.float64)
    ok = (ids >= 0) & (ids < len(fr))
    tol = REST_TOLERANCE * max(float(np.ptp(fr, axis=0).max()), 1e-12)
    out = np.full(len(ids), -1, np.int64)
    cand = np.nonzero(ok)[0]
    match = np.abs(fr[ids[cand]] - rest[cand]).max(1) <= tol
    out[cand[match]] = ids[cand[match]]
    return out


def is_identity(field, ids) -> bool:
    """True when vertex i of the mesh is field vertex i for every i (the field itself renders it)."""
    ids = np.asarray(ids)
    return len(ids) == field.num_vertices and bool(np.array_equal(ids, np.arange(len(ids))))


def remap_field(source, ids, rest, faces, k: int = 4):
    """The field of ``source`` on a mesh whose vertex i is ``source`` vertex ``ids[i]`` (>= 0), or a new
    vertex at rest position ``rest[i]`` (``ids[i] < 0``; see :func:`resolve_ids`).

    ``faces`` (F,3) index the mesh's vertices.  Returns a new :class:`NeuMeshField` (rest pose: mapped
    vertices at the source's rest positions, new ones at theirs) whose rows are copied (mapped) or
    interpolated (new), sharing the source's decoders.
    """
    from .field import FieldConfig, NeuMeshField

    ids = np.asarray(ids).astype(np.int64).reshape(-1)
    rest = np.asarray(rest, np.float64).reshape(-1, 3)
    m = len(ids)
    if m == 0:
        raise VertexMismatchError("the mesh has no vertices to carry the field")
    if len(rest) != m:
        raise VertexMismatchError(f"{m} vertex ids but {len(rest)} rest positions")
    src_rest = source.rest_vertices.detach().cpu().numpy().astype(np.float64)
    valid = ids >= 0
    if (ids >= len(src_rest)).any():
        raise VertexMismatchError(f"vertex ids must lie below the field's {len(src_rest)} vertices")
    new = ~valid
    if new.any() and not np.isfinite(rest[new]).all():
        raise VertexMismatchError("new vertices have no valid rest position to interpolate the field at")
    kk = min(int(k), len(src_rest))
    src = np.zeros((m, kk), np.int64)
    w = np.zeros((m, kk))
    src[valid, 0] = ids[valid]
    w[valid, 0] = 1.0
    if new.any():
        idx, ww = idw_neighbours(rest[new], src_rest, kk)
        src[new], w[new] = idx, ww
    pos = np.where(valid[:, None], src_rest[np.maximum(ids, 0)], rest).astype(np.float32)
    tables = ("geo_codes", "tex_codes", "mod_colours", "sem_codes")
    rows = blend_rows(source, src, w, tables)
    cfg = FieldConfig.from_dict(asdict(source.config))
    field = NeuMeshField(Mesh(pos, np.asarray(faces, np.int64).reshape(-1, 3)), cfg,
                         num_decoders=source.num_decoders)
    field.geo_decoder = source.geo_decoder
    field.rad_decoders = nn.ModuleList(list(source.rad_decoders))
    for name, mod in source.named_children():   # any further decoder (e.g. semantic) is shared too
        if name not in ("geo_decoder", "rad_decoders", "scaffold") and isinstance(mod, nn.Module):
            setattr(field, name, mod)
    with torch.no_grad():
        for name in tables:
            getattr(field, name).copy_(rows.tables[name].to(getattr(field, name).dtype))
        field.decoder_id.copy_(torch.as_tensor(rows.decoder, dtype=field.decoder_id.dtype))
        if rows.frames is not None:
            field.tex_frame = torch.as_tensor(snap_identity(rows.frames), dtype=torch.float32)
            field.compact_tex_frame()
    _restrict_grid(field, source)
    field.eval()
    return field.to(source.geo_codes.device)


def _restrict_grid(field, source) -> None:
    """Start from the source's rest-pose occupancy (pruned by training), limited to the cells near the
    remapped field's own vertices."""
    from ..sampling.occupancy import OccupancyGrid

    state = source.scaffold.rest_grid_state()
    g = field.grid
    aabb, res = state["aabb"], state["resolution"]
    v = field.rest_vertices.to(aabb.device)
    inside = ((v >= aabb[0]) & (v <= aabb[1])).all()
    if not bool(inside):
        return   # vertices outside the source's box: keep the grid made from the vertices
    g.load_state({k: t.clone() for k, t in state.items()})
    near = OccupancyGrid.mask_from_vertices(v, aabb, res.to(aabb.device), float(field.radius))
    g.mesh_mask = g.mesh_mask & near
    g.occ = g.occ & near


def split_by_key(keys, known, own: int) -> list:
    """The vertices of a joined mesh grouped by the field they came from: ``[(key, vertex indices)]``
    sorted by key.  ``keys`` (V,) is each vertex's field key (:func:`field_key`); a key not in
    ``known`` (interpolated between vertices by a modifier, lost, or the key of the field before it was
    trained further) counts as ``own``, the key of the mesh's own field."""
    keys = np.asarray(keys, np.int64).reshape(-1)
    keys = np.where(np.isin(keys, np.asarray(list(known), np.int64)), keys, np.int64(own))
    return [(int(k), np.nonzero(keys == k)[0]) for k in np.unique(keys)]


def sub_triangles(triangles, selection, num_vertices: int) -> np.ndarray:
    """The triangles (F,3) of a mesh with ``num_vertices`` vertices whose three corners all lie in
    ``selection`` (vertex indices), with their corners renumbered to positions in ``selection``."""
    pos = np.full(int(num_vertices), -1, np.int64)
    pos[np.asarray(selection, np.int64)] = np.arange(len(selection))
    f = pos[np.asarray(triangles, np.int64).reshape(-1, 3)]
    return f[(f >= 0).all(1)]
