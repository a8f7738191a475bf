"""Reading edit inputs from files: vertex regions, UV maps and correspondence pairs.

- Regions: ``.npy`` (integer vertex indices, or a boolean mask with one entry per vertex) or text
  (whole numbers separated by spaces, commas or new lines; ``#`` starts a comment).
- UVs: ``.obj`` with ``vt`` coordinates and ``f v/vt`` faces (its vertices must be the field's, in the
  field's order: export the scaffold with "keep vertex order"), giving one UV per face corner; or
  ``.npy`` of shape (num_vertices, 2), one UV per field vertex.
- Pairs: ``.npy`` or text with rows of two vertex indices (source, target) or six numbers (a source
  point and a target point, rest pose).
"""
from __future__ import annotations

import os

import numpy as np

from ..errors import EditError
from .fill import CornerUVs
from .record import as_vertex_ids


def _exists(path: str, what: str) -> None:
    if not os.path.isfile(path):
        raise EditError(f"{what} file not found: {path}")


def _load_array(path: str, what: str) -> np.ndarray:
    _exists(path, what)
    if path.lower().endswith(".npy"):
        try:
            return np.load(path, allow_pickle=False)
        except Exception as exc:  # noqa: BLE001 - numpy raises several types for bad files
            raise EditError(f"{what} file {path} is not a readable .npy array ({exc})") from exc
    rows = []
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            line = line.split("#", 1)[0].replace(",", " ").split()
            if line:
                rows.append(line)
    try:
        return np.array(rows, dtype=np.float64) if rows and len({len(r) for r in rows}) == 1 \
            else np.array([float(x) for r in rows for x in r], dtype=np.float64)
    except ValueError as exc:
        raise EditError(f"{what} file {path} holds something other than numbers ({exc})") from exc


def read_region(path: str, num_vertices: int) -> np.ndarray:
    """Sorted unique vertex ids from a region file (see the module docstring)."""
    a = _load_array(path, "region")
    if a.dtype != bool:
        a = a.reshape(-1)
    return as_vertex_ids(a, num_vertices, f"region {os.path.basename(path)}")


def read_uvs(path: str, num_vertices: int) -> CornerUVs:
    """UVs of a field's vertices from an ``.obj`` (per face corner) or an ``.npy`` (per vertex)."""
    _exists(path, "UV")
    if path.lower().endswith(".npy"):
        uv = _load_array(path, "UV")
        if uv.ndim != 2 or uv.shape != (num_vertices, 2):
            raise EditError(f"UV file {path}: expected shape ({num_vertices}, 2), one UV per field vertex, "
                            f"got {uv.shape}")
        return CornerUVs(np.arange(num_vertices), uv)
    if not path.lower().endswith(".obj"):
        raise EditError(f"UV file {path}: give an .obj with vt coordinates or an .npy of per-vertex UVs")
    n_v, vts, corners_v, corners_t = 0, [], [], []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if line.startswith("v "):
                n_v += 1
            elif line.startswith("vt "):
                parts = line.split()
                vts.append((float(parts[1]), float(parts[2]) if len(parts) > 2 else 0.0))
            elif line.startswith("f "):
                refs = line.split()[1:]
                vv, tt = [], []
                for r in refs:
                    p = r.split("/")
                    if len(p) < 2 or not p[1]:
                        raise EditError(f"UV file {path}: face corner '{r}' has no UV index; export the mesh "
                                        "with UV coordinates")
                    vv.append(int(p[0]))
                    tt.append(int(p[1]))
                vv = [v - 1 if v > 0 else n_v + v for v in vv]
                tt = [t - 1 if t > 0 else len(vts) + t for t in tt]
                corners_v.extend(vv)
                corners_t.extend(tt)
    if n_v != num_vertices:
        raise EditError(f"UV file {path} has {n_v} vertices but the field has {num_vertices}; export the "
                        "field's own mesh (same vertices, same order) with its UV map")
    if not corners_v:
        raise EditError(f"UV file {path} has no faces with UVs")
    vts = np.asarray(vts, np.float64)
    t = np.asarray(corners_t)
    if t.min() < 0 or t.max() >= len(vts):
        raise EditError(f"UV file {path}: a face refers to a UV index that does not exist")
    return CornerUVs(np.asarray(corners_v, np.int64), vts[t])


def read_pairs(path: str) -> np.ndarray:
    """(P,2) vertex index pairs or (P,6) point pairs from a pairs file."""
    a = _load_array(path, "pairs")
    if a.ndim != 2 or a.shape[1] not in (2, 6):
        raise EditError(f"pairs file {path}: expected rows of 2 vertex indices (source, target) or 6 "
                        f"numbers (source point, target point), got shape {a.shape}")
    return a
