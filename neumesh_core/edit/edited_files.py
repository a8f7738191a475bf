"""Edited field files: an edit never overwrites the file it started from.

An edit of ``lego.neumesh`` is saved beside it as ``lego.edit-001.neumesh``, the next one as
``lego.edit-002.neumesh`` and so on (the number is one more than the highest in the folder).  Each
edited file's header says which edit made it (``edit.op``), the file it was made from
(``edit.parent``) and the trained file at the root of the chain (``edit.root``), both relative to the
file's own folder, and the history of edits from the root.  Undo in the add-on steps to the parent;
"revert" goes to the root.
"""
from __future__ import annotations

import os
import re
import time
from typing import Optional

from ..errors import NeuMeshError
from ..field.io import read_header, save_field

SUFFIX = ".neumesh"
_EDIT_RE = re.compile(r"\.edit-(\d{3,})$")


def _stem(path: str) -> str:
    base = os.path.basename(path)
    if base.endswith(SUFFIX):
        base = base[: -len(SUFFIX)]
    return _EDIT_RE.sub("", base)


def next_edit_path(path: str) -> str:
    """The next free ``<stem>.edit-NNN.neumesh`` beside ``path`` (``path`` itself is never returned)."""
    d = os.path.dirname(os.path.abspath(path))
    stem = _stem(path)
    pat = re.compile(re.escape(stem) + r"\.edit-(\d{3,})" + re.escape(SUFFIX) + "$")
    highest = 0
    if os.path.isdir(d):
        for name in os.listdir(d):
            m = pat.match(name)
            if m:
                highest = max(highest, int(m.group(1)))
    return os.path.join(d, f"{stem}.edit-{highest + 1:03d}{SUFFIX}")


def edit_info(path: str) -> Optional[dict]:
    """The ``edit`` header of a field file (None for a trained, unedited file)."""
    return read_header(path).get("edit")


def _resolve(rel: str, base_file: str) -> str:
    return os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(base_file)), rel))


def parent_of(path: str) -> Optional[str]:
    """Absolute path of the file that ``path`` was edited from (None when it is not an edit)."""
    e = edit_info(path)
    return _resolve(e["parent"], path) if e and e.get("parent") else None


def root_of(path: str) -> str:
    """Absolute path of the trained file at the root of ``path``'s edit chain (``path`` if unedited)."""
    e = edit_info(path)
    return _resolve(e["root"], path) if e and e.get("root") else os.path.abspath(path)


def check_out_path(parent_path: str, out_path: Optional[str] = None) -> str:
    """The absolute file an edit of ``parent_path`` will be written to (``out_path`` or the next
    ``<name>.edit-NNN.neumesh``); :class:`NeuMeshError` when that would overwrite the parent or the
    trained file at the root of its chain.  Callers check before a long edit, not only when saving."""
    parent = os.path.abspath(parent_path)
    out = os.path.abspath(out_path) if out_path else next_edit_path(parent)
    root = root_of(parent) if os.path.isfile(parent) else parent
    for keep, what in ((parent, "the field it was edited from"), (root, "the trained field")):
        if _same_file(out, keep):
            raise NeuMeshError(f"refusing to overwrite {what} ({keep}) with an edit; choose another "
                               "output file (the default is the next <name>.edit-NNN.neumesh beside it)")
    return out


def save_edited(field, parent_path: str, record, out_path: Optional[str] = None) -> str:
    """Save ``field`` after the edit ``record`` (an :class:`~neumesh_core.edit.record.EditRecord`) was
    applied to the field loaded from ``parent_path``.  Writes ``out_path`` (default
    :func:`next_edit_path`) atomically and returns it.  Refuses to overwrite the parent or the root
    file of the chain."""
    parent = os.path.abspath(parent_path)
    out = check_out_path(parent, out_path)
    root = root_of(parent) if os.path.isfile(parent) else parent
    parent_edit = edit_info(parent) if os.path.isfile(parent) else None
    history = list((parent_edit or {}).get("history", []))
    history.append({"op": record.op, "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
                    "vertices": record.num_changed, "info": _jsonable(record.info)})
    out_dir = os.path.dirname(out)
    edit = {"op": record.op, "parent": os.path.relpath(parent, out_dir),
            "root": os.path.relpath(root, out_dir), "history": history}
    save_field(field, out, edit=edit)
    return out


def _same_file(a: str, b: str) -> bool:
    if os.path.exists(a) and os.path.exists(b):
        return os.path.samefile(a, b)
    return os.path.normcase(os.path.abspath(a)) == os.path.normcase(os.path.abspath(b))


def _jsonable(x):
    """``x`` with numpy/torch values turned into plain lists and numbers (for the JSON header)."""
    import numpy as np
    import torch

    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if torch.is_tensor(x):
        x = x.detach().cpu().numpy()
    if isinstance(x, np.ndarray):
        return x.tolist() if x.size <= 64 else f"<array {x.shape}>"
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, (str, int, float, bool)) or x is None:
        return x
    return str(x)
