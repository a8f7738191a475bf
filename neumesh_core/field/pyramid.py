"""Coarse-to-fine parameterisation of the per-vertex codes, for training only.

While training, a vertex's geometry/texture code is its own code plus smooth interpolations of codes
stored on coarser subsets of the scaffold (every ``factor``-th spacing, then ``factor``^2, ...):

    code(v) = own(v) + sum_l sum_j a_lj(v) coarse_l[parent_lj(v)]

Every ray that touches a region updates the coarse codes it shares with its neighbours, so appearance
that many views agree on is learned at a coarse scale first and a vertex seen by few rays inherits it
from its surroundings instead of staying near its random start; the total-variation loss then acts on
the fine residuals only.  The function space is unchanged (the sum is linear in the parameters), and
:meth:`CodePyramid.bake` folds the coarse levels into the per-vertex codes at the end, so a trained
field is a plain NeuMesh field: per-vertex codes, nothing else (editing and checkpoints are unaffected).
"""
from __future__ import annotations

import contextlib
from typing import List

import numpy as np
import torch
from torch import nn


def subsample_vertices(vertices: np.ndarray, spacing: float) -> np.ndarray:
    """Indices of one vertex per cell of a grid with cells ``spacing`` wide (the one nearest the cell's
    mean), sorted.  Deterministic."""
    v = np.asarray(vertices, dtype=np.float64)
    if spacing <= 0:
        raise ValueError(f"spacing must be > 0, got {spacing}")
    cell = np.floor((v - v.min(0)) / spacing).astype(np.int64)
    _, inv, counts = np.unique(cell, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inv, v)
    centre = sums / counts[:, None]
    d = np.linalg.norm(v - centre[inv], axis=1)
    order = np.lexsort((np.arange(len(v)), d, inv))   # by cell, then distance, then index
    first = np.ones(len(order), bool)
    first[1:] = inv[order][1:] != inv[order][:-1]
    return np.sort(order[first])


def parent_weights(vertices: np.ndarray, normals: np.ndarray, coarse: np.ndarray, spacing: float,
                   j: int = 4):
    """For every vertex its ``j`` nearest coarse vertices (indices into ``coarse``) and normalised weights
    ``exp(-(d/spacing)^2) * max(n_v . n_c, 0)``: smooth over the surface, and zero across a thin wall
    whose two sides face away from each other.  A vertex whose parents all face away gets no coarse
    contribution (all weights 0)."""
    from .knn import kd_tree

    v = np.ascontiguousarray(vertices, dtype=np.float32)
    c = np.ascontiguousarray(v[coarse])
    jj = min(j, len(coarse))
    dist, idx = kd_tree(c).query(v, k=jj)
    dist = np.asarray(dist, np.float64).reshape(len(v), jj)
    idx = np.asarray(idx, np.int64).reshape(len(v), jj)
    facing = np.clip((normals[:, None, :] * normals[coarse][idx]).sum(-1), 0.0, 1.0)
    w = np.exp(-(dist / spacing) ** 2) * facing
    total = w.sum(1, keepdims=True)
    w = np.where(total > 1e-12, w / np.maximum(total, 1e-12), 0.0)
    return idx, w.astype(np.float32)


class CodePyramid(nn.Module):
    """Coarse code levels over a field's scaffold (see the module docstring).

    ``levels``: how many coarse levels; level l keeps one vertex per cell of ``factor``^l mean edge
    lengths.  The levels' codes are stacked in one table per code kind ("geo", "tex"), and every vertex
    lists its ``parents`` per level (indices into the stacked table) with their weights.  Coarse codes
    start at zero, so attaching a pyramid does not change what the field renders.
    """

    def __init__(self, field, levels: int = 2, factor: float = 4.0, parents: int = 4,
                 kinds=("geo", "tex")):
        super().__init__()
        if levels < 1 or factor <= 1 or parents < 1:
            raise ValueError("CodePyramid needs levels >= 1, factor > 1 and parents >= 1")
        kinds = tuple(kinds)
        if not kinds or any(k not in ("geo", "tex") for k in kinds):
            raise ValueError(f"CodePyramid kinds must be a non-empty subset of ('geo', 'tex'), not {kinds}")
        self.kinds = kinds
        verts = field.rest_vertices.detach().cpu().numpy()
        normals = field.rest_normals.detach().cpu().numpy()
        edge = float(field.config.radius) / float(field.config.radius_scale)
        dev = field.rest_vertices.device
        self.sizes: List[int] = []
        par, wts = [], []
        offset = 0
        for lv in range(levels):
            spacing = edge * factor ** (lv + 1)
            coarse = subsample_vertices(verts, spacing)
            if len(coarse) < 2:
                break
            idx, w = parent_weights(verts, normals, coarse, spacing, parents)
            par.append(idx + offset)
            wts.append(w)
            offset += len(coarse)
            self.sizes.append(len(coarse))
        if not self.sizes:
            raise ValueError("the scaffold is too small for a coarse code level; use code_levels=0")
        self.levels = len(self.sizes)
        self.register_buffer("parents", torch.from_numpy(np.concatenate(par, 1)).to(dev))
        self.register_buffer("weights", torch.from_numpy(np.concatenate(wts, 1)).to(dev))
        for k in kinds:
            setattr(self, k, nn.Parameter(torch.zeros(offset, field.code_table(k).shape[1], device=dev)))

    def lookup(self, names, idx: torch.Tensor):
        """Coarse contributions to the codes named in ``names`` (a tuple of "geo"/"tex") of vertices
        ``idx`` (any shape): a list of tensors shaped ``idx.shape + (dim,)``, None for a kind this
        pyramid does not hold.  Each distinct vertex is computed once; the coarse tables are small, so
        their gradients stay dense."""
        if not any(n in self.kinds for n in names):
            return [None] * len(names)
        flat = idx.reshape(-1)
        uniq, inv = torch.unique(flat, return_inverse=True)
        par = self.parents[uniq].reshape(-1)
        w = self.weights[uniq][:, None, :]
        out = []
        for n in names:
            if n not in self.kinds:
                out.append(None)
                continue
            table = getattr(self, n)
            # index_select: its backward (an index_add into the small table) is the cheapest on CPU
            rows = table.index_select(0, par).view(len(uniq), self.parents.shape[1], table.shape[1])
            out.append(torch.bmm(w, rows).squeeze(1)[inv].reshape(*idx.shape, table.shape[1]))
        return out

    @torch.no_grad()
    def dense(self, name: str, chunk: int = 1 << 18) -> torch.Tensor:
        """The coarse contribution for every vertex, (N, dim)."""
        n = self.parents.shape[0]
        table = getattr(self, name)
        parts = []
        for s in range(0, n, chunk):
            e = min(n, s + chunk)
            parts.append(torch.bmm(self.weights[s:e, None, :], table[self.parents[s:e]]).squeeze(1))
        return torch.cat(parts)

    @torch.no_grad()
    def _fold_into(self, field) -> None:
        for k in self.kinds:
            field.code_table(k).add_(self.dense(k))

    @torch.no_grad()
    def bake(self, field) -> None:
        """Fold the coarse levels into the field's per-vertex codes, zero them and detach them from the
        field: what is left is a plain field that renders the same as before."""
        self._fold_into(field)
        for k in self.kinds:
            getattr(self, k).zero_()
        if field.code_prior is self:
            field.set_code_prior(None)

    @contextlib.contextmanager
    def baked_into(self, field):
        """Inside the block the field's codes include the coarse levels (to save a checkpoint that is a
        plain field); afterwards the split is restored exactly as it was."""
        with torch.no_grad():
            kept = {k: field.code_table(k).detach().clone() for k in self.kinds}
        self._fold_into(field)
        prior = field.code_prior
        field.set_code_prior(None)
        try:
            yield
        finally:
            field.set_code_prior(prior)
            with torch.no_grad():
                for k, v in kept.items():
                    field.code_table(k).copy_(v)
