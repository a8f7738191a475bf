"""EditRecord: what an edit changed, so that it can be undone (and redone) exactly.

Edits change rows of per-vertex tables (texture codes, modification colours, decoder ids, ...) and may
append radiance decoders.  A record keeps the old and new values of exactly the rows it changed, so
undo and redo are row writes, never re-training.  Records undo in the reverse order they were made.
"""
from __future__ import annotations

from dataclasses import dataclass, field as dc_field
from typing import Dict, Iterable, Optional

import numpy as np
import torch

from ..errors import EditError

# per-vertex tables an edit may change (attribute names on NeuMeshField)
TABLES = ("tex_codes", "mod_colours", "decoder_id", "tex_frame", "geo_codes", "sem_codes")


def _table(field, name: str) -> torch.Tensor:
    """The per-vertex table ``name`` of ``field`` (texture frames are materialised as identities when
    the field has none, so that their rows can be read and written like any other table)."""
    if name not in TABLES:
        raise EditError(f"unknown per-vertex table {name!r}; known: {', '.join(TABLES)}")
    if name == "tex_frame":
        return field.ensure_tex_frame()
    return getattr(field, name)


def as_vertex_ids(vertices, num_vertices: int, what: str = "vertex indices") -> np.ndarray:
    """``vertices`` as sorted unique int64 indices; clear errors for bad input.

    Accepts an index array/list, or a boolean mask of length ``num_vertices``.
    """
    v = np.asarray(vertices)
    if v.dtype == bool:
        if v.shape != (num_vertices,):
            raise EditError(f"{what}: a boolean mask must have one entry per vertex ({num_vertices}), "
                             f"got shape {v.shape}")
        v = np.nonzero(v)[0]
    if v.size == 0:
        raise EditError(f"{what}: the region is empty; select at least one vertex")
    if not np.issubdtype(v.dtype, np.integer):
        if np.issubdtype(v.dtype, np.floating) and np.all(np.isfinite(v)) and np.all(v == np.round(v)):
            v = v.astype(np.int64)
        else:
            raise EditError(f"{what}: expected whole vertex indices, got {v.dtype} values")
    v = np.unique(v.reshape(-1).astype(np.int64))
    if v[0] < 0 or v[-1] >= num_vertices:
        raise EditError(f"{what}: indices must lie in [0, {num_vertices}) for this field, got "
                         f"[{int(v[0])}, {int(v[-1])}]; is the region from another mesh?")
    return v


def _rows_differ(old: Dict[str, torch.Tensor], new: Dict[str, torch.Tensor], n: int) -> np.ndarray:
    """(n,) bool: rows where any table's new value differs from its old one (exact comparison: any
    change, even a rounding one, is a change)."""
    out = torch.zeros(n, dtype=torch.bool)
    for t, a in old.items():
        b = new[t]
        if a.numel():
            out |= (a != b).reshape(n, -1).any(1)
    return out.numpy()


@dataclass
class EditRecord:
    """The rows one edit changed.

    ``vertices`` (int64, sorted) are the rows the edit wrote; ``old``/``new`` map a table name to the
    rows' values before/after (CPU tensors); ``changed`` (int64, sorted, set by :meth:`finish`) are the
    rows among them whose values differ afterwards (a region swapped onto itself writes every row and
    changes none; :attr:`num_changed` counts these); ``decoders_before`` is how many radiance decoders
    the field had before the edit (undo drops the ones it added); ``info`` holds what the edit reports (alignment
    transform, residual, timings...), JSON-friendly.
    """

    op: str
    vertices: np.ndarray
    old: Dict[str, torch.Tensor]
    new: Dict[str, torch.Tensor] = dc_field(default_factory=dict)
    decoders_before: int = 1
    decoders_after: int = 1
    added_decoders: list = dc_field(default_factory=list)   # the decoder modules the edit appended
    info: dict = dc_field(default_factory=dict)
    changed: Optional[np.ndarray] = None   # rows whose values the edit changed (None before finish)

    @classmethod
    def begin(cls, op: str, field, vertices, tables: Iterable[str]) -> "EditRecord":
        """Snapshot the rows ``vertices`` of ``tables`` before an edit writes them."""
        v = as_vertex_ids(vertices, field.num_vertices)
        idx = torch.as_tensor(v, device=field.geo_codes.device)
        old = {t: _table(field, t).detach()[idx].cpu().clone() for t in tables}
        n = field.num_decoders
        return cls(op=op, vertices=v, old=old, decoders_before=n, decoders_after=n)

    def finish(self, field, **info) -> "EditRecord":
        """Snapshot the new values of the same rows after the edit; ``info`` is merged into
        :attr:`info`."""
        idx = torch.as_tensor(self.vertices, device=field.geo_codes.device)
        self.new = {t: _table(field, t).detach()[idx].cpu().clone() for t in self.old}
        self.changed = self.vertices[_rows_differ(self.old, self.new, len(self.vertices))]
        self.decoders_after = field.num_decoders
        self.added_decoders = list(field.rad_decoders)[self.decoders_before:]
        self.info.update(info)
        field.compact_tex_frame()   # all identities (e.g. a region swapped onto itself): none needed
        return self

    @property
    def num_changed(self) -> int:
        """How many rows the edit changed (rows written with the values they held do not count)."""
        return int(len(self.vertices if self.changed is None else self.changed))

    def count_changed(self, rtol: float = 1e-5, atol: float = 1e-6) -> int:
        """How many of the rows the edit wrote hold other values than before, floats compared with a
        tolerance (never bit for bit: a row written back with a rounding difference is unchanged).
        :attr:`num_changed` when there are no new values to compare (before :meth:`finish`, or a record
        of something other than per-vertex rows)."""
        if not self.new:
            return self.num_changed
        changed = torch.zeros(len(self.vertices), dtype=torch.bool)
        for t, old in self.old.items():
            new = self.new[t]
            if old.dtype.is_floating_point:
                diff = ~torch.isclose(new, old, rtol=rtol, atol=atol)
            else:
                diff = new != old
            changed |= diff.reshape(len(changed), -1).any(1)
        return int(changed.sum())

    def _write(self, field, values: Dict[str, torch.Tensor]) -> None:
        idx = torch.as_tensor(self.vertices, device=field.geo_codes.device)
        with torch.no_grad():
            for t, v in values.items():
                tab = _table(field, t)
                tab[idx] = v.to(device=tab.device, dtype=tab.dtype)

    def undo(self, field) -> None:
        """Restore the rows as they were before the edit and drop the decoders it added."""
        if field.num_decoders != self.decoders_after:
            raise RuntimeError(f"cannot undo '{self.op}': the field has {field.num_decoders} radiance "
                               f"decoders, the edit left {self.decoders_after}; undo later edits first")
        self._write(field, self.old)
        field.drop_unused_decoders(keep=self.decoders_before)
        field.compact_tex_frame()

    def redo(self, field) -> None:
        """Write the edit's new rows (and decoders) again after :meth:`undo`."""
        if field.num_decoders != self.decoders_before:
            raise RuntimeError(f"cannot redo '{self.op}': the field has {field.num_decoders} radiance "
                               f"decoders, the edit started from {self.decoders_before}")
        for d in self.added_decoders:
            field.rad_decoders.append(d)
        self._write(field, self.new)
        field.compact_tex_frame()
