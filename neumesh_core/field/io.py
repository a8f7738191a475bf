"""Field files: safetensors tensors + a JSON header.  Atomic writes; no pickle on load.

Layout: tensors ``param/<name>``, ``buffer/<name>``, ``grid/<name>``, optional ``optim/<name>/<key>``;
metadata ``neumesh`` = JSON {format, version, field_config, train_state, num_vertices, num_decoders,
edit}.  ``edit`` (absent in trained fields) describes the edit that made the file: its operation, the
parent file it was made from, the training file at the root of the chain and the history of edits.

Versions: 1 (one radiance decoder ``rad_decoder``; scaffold buffers at the top level) and 2 (radiance
decoders ``rad_decoders.<i>`` with a per-vertex ``decoder_id``, and ``tex_frame`` (N,3,3) when a
texture edit rotated the frames of the codes it brought; scaffold buffers under ``scaffold.``).
Version-1 files load as single-decoder fields with every vertex bound to decoder 0.  Tensors a file
holds under an earlier name (``param/mod_colors``, ``buffer/scaffold.tangent_ref``) load under the
field's name for them.

Semantics (optional in both versions): ``field_config.sem_dim``/``sem_features`` > 0 means the file
holds ``param/sem_codes`` (N, sem_dim) and ``param/sem_decoder.*``; the header's ``semantics`` entry
says how they were distilled.  A file without them loads as a field without semantics.

Real captures (optional in version 2): the header's ``object_box`` (centre, half_extents,
rotation) and ``background`` (the background model's configuration; its tensors are
``param/background.*``).  Files without them load as fields without a box or background.
"""
from __future__ import annotations

import json
import os
import tempfile
from typing import Optional

import torch

from ..errors import CheckpointError
from ..mesh import Mesh

FORMAT = "neumesh-field"
VERSION = 2
# version-1 names -> version-2 names (prefix renames)
_V1_RENAMES = (("rad_decoder.", "rad_decoders.0."), ("faces", "scaffold.faces"),
               ("tangent_ref", "scaffold.tangent_ref"), ("rest_vertices", "scaffold.rest_vertices"),
               ("tv_neighbours", "scaffold.tv_neighbours"))


# tensors saved under an earlier name (any version) -> the name the field has now
_RENAMED = {"mod_colors": "mod_colours", "scaffold.tangent_ref": "scaffold.tangent_neighbour"}


def _v1_to_v2_name(name: str) -> str:
    for old, new in _V1_RENAMES:
        if name == old or (old.endswith(".") and name.startswith(old)):
            return new + name[len(old):]
    return name


def _rename_tensors(tensors: dict, rename) -> dict:
    """``tensors`` with each parameter's and buffer's name, and the parameter name of each optimiser
    entry, passed through ``rename``."""
    out = {}
    for k, v in tensors.items():
        kind, _, rest = k.partition("/")
        if kind in ("param", "buffer"):
            k = f"{kind}/{rename(rest)}"
        elif kind == "optim":
            pname, _, skey = rest.rpartition("/")
            k = f"optim/{rename(pname)}/{skey}"
        out[k] = v
    return out


def _current_names(tensors: dict) -> dict:
    """``tensors`` with every parameter, buffer and optimiser entry saved under an earlier name
    (:data:`_RENAMED`) under the field's name for it."""
    return _rename_tensors(tensors, lambda name: _RENAMED.get(name, name))


def _upgrade_v1(tensors: dict) -> dict:
    return _rename_tensors(tensors, _v1_to_v2_name)


def _atomic_write(path: str, write) -> None:
    d = os.path.dirname(os.path.abspath(path)) or "."
    os.makedirs(d, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".neumesh", dir=d)
    os.close(fd)
    try:
        write(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600 files; a field file is an ordinary file
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def save_field(field, path: str, optimizer: Optional[torch.optim.Optimizer] = None,
               train_state: Optional[dict] = None, edit: Optional[dict] = None) -> None:
    """Write ``field`` (mesh, codes, decoders, occupancy grid, config) to ``path`` atomically.

    With ``optimizer`` its moments are stored too, so training can resume exactly.  A field that trains
    with coarse code levels (``field.code_prior``) is written as a plain field: the levels are folded
    into the per-vertex codes it stores, and the field in memory is left as it was.  ``edit``: the
    JSON-serialisable edit description stored in the header (see :mod:`neumesh_core.edit.edited_files`);
    by default a field loaded from an edited file keeps its description.
    """
    prior = getattr(field, "code_prior", None)
    if prior is not None:
        with prior.baked_into(field):
            return save_field(field, path, optimizer=optimizer, train_state=train_state, edit=edit)
    from dataclasses import asdict

    from safetensors.torch import save_file

    tensors = {}
    for name, p in field.named_parameters():   # (a background model's: param/background.*)
        tensors[f"param/{name}"] = p.detach().cpu().contiguous()
    for name, b in field.named_buffers():
        if name in field.persistent_buffer_names():
            tensors[f"buffer/{name}"] = b.detach().cpu().contiguous()
    grid_state = field.scaffold.rest_grid_state()
    for k, v in grid_state.items():
        t = v.detach().cpu()
        tensors[f"grid/{k}"] = (t.to(torch.uint8) if t.dtype == torch.bool else t).contiguous()
    if optimizer is not None:
        names = {id(p): n for n, p in field.named_parameters()}
        for group in optimizer.param_groups:
            for p in group["params"]:
                if id(p) not in names:   # training-only parameters (e.g. a CodePyramid's) are not kept
                    continue
                st = optimizer.state.get(p, {})
                for k, v in st.items():
                    if torch.is_tensor(v):
                        tensors[f"optim/{names[id(p)]}/{k}"] = v.detach().cpu().reshape(v.shape).contiguous()
    atlas = getattr(field, "paint_atlas", None)   # texel paint (paint_atlas.py), saved when present
    atlas_meta = None
    if atlas is not None:
        atlas_tensors, atlas_meta = atlas.to_tensors()
        tensors.update(atlas_tensors)
    for k, v in tensors.items():
        if v.dtype.is_floating_point and not torch.isfinite(v).all():
            raise CheckpointError(f"refusing to save: tensor {k} holds NaN/inf (training diverged); "
                                  "lower the learning rate and resume from the last good checkpoint")
    if train_state is None:
        train_state = (getattr(field, "_checkpoint_meta", None) or {}).get("train_state", {})
    if edit is None:
        edit = (getattr(field, "_checkpoint_meta", None) or {}).get("edit")
    meta = {"format": FORMAT, "version": VERSION, "field_config": asdict(field.config),
            "train_state": train_state or {}, "num_vertices": field.num_vertices,
            "num_decoders": field.num_decoders}
    if edit:
        meta["edit"] = edit
    if atlas_meta is not None:
        meta["paint_atlas"] = atlas_meta
    if getattr(field, "has_semantics", False) and getattr(field, "semantics_info", None):
        meta["semantics"] = field.semantics_info
    _save_real_capture_meta(field, meta)
    _atomic_write(path, lambda tmp: save_file(tensors, tmp, metadata={"neumesh": json.dumps(meta)}))


def read_header(path: str) -> dict:
    """The JSON header of a field file, without reading its tensors."""
    from safetensors import safe_open

    if not os.path.isfile(path):
        raise CheckpointError(f"field file not found: {path}")
    try:
        with safe_open(path, framework="pt") as fh:
            meta_raw = (fh.metadata() or {}).get("neumesh")
        meta = json.loads(meta_raw) if meta_raw is not None else None
    except Exception as exc:
        raise CheckpointError(f"{path} is not a readable NeuMesh field ({exc})") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a NeuMesh field (no 'neumesh' header)")
    return meta


def read_checkpoint(path: str):
    """Return (meta dict, tensors dict). Raises CheckpointError with a clear message."""
    from safetensors import safe_open

    if not os.path.isfile(path):
        raise CheckpointError(f"field file not found: {path}")
    try:
        with safe_open(path, framework="pt") as fh:
            meta_raw = (fh.metadata() or {}).get("neumesh")
            tensors = {k: fh.get_tensor(k) for k in fh.keys()}
    except CheckpointError:
        raise
    except Exception as exc:
        raise CheckpointError(
            f"{path} is not a readable NeuMesh field (truncated or corrupt: {exc}). Use a backup or "
            "re-export the field; files are written atomically, so a crash never leaves a half file "
            "under the final name.") from exc
    if meta_raw is None:
        raise CheckpointError(f"{path} is a safetensors file but not a NeuMesh field (no 'neumesh' header)")
    try:
        meta = json.loads(meta_raw)
    except json.JSONDecodeError as exc:
        raise CheckpointError(f"{path}: the field header is not valid JSON ({exc})") from exc
    if meta.get("format") != FORMAT:
        raise CheckpointError(f"{path}: unknown format {meta.get('format')!r}")
    if int(meta.get("version", -1)) > VERSION:
        raise CheckpointError(f"{path}: format version {meta.get('version')} is newer than this "
                              f"neumesh ({VERSION}); update neumesh")
    if int(meta.get("version", 1)) < 2:
        tensors = _upgrade_v1(tensors)
    return meta, _current_names(tensors)


def _num_decoders(tensors: dict) -> int:
    ids = {int(k.split(".")[1]) for k in tensors if k.startswith("param/rad_decoders.")}
    if not ids or ids != set(range(len(ids))):
        raise KeyError("param/rad_decoders.<i>")
    return len(ids)


def load_field(path: str, device="cpu"):
    """Load a field saved by :func:`save_field` (no code is unpickled)."""
    from .field import FieldConfig, NeuMeshField

    meta, t = read_checkpoint(path)
    try:
        cfg = FieldConfig.from_dict({"step_scale": 0.25,  # fields saved before it was stored used 0.25
                                     **meta["field_config"]})
        mesh = Mesh(t["buffer/scaffold.rest_vertices"].numpy(), t["buffer/scaffold.faces"].numpy())
        field = NeuMeshField(mesh, cfg, num_decoders=_num_decoders(t))
        with torch.no_grad():
            for name, p in field.named_parameters():
                if name == "sem_codes" and p.shape[1] == 0 and "param/sem_codes" not in t:
                    continue   # no semantic slot stored: nothing to load
                src = t[f"param/{name}"]
                if p.shape != src.shape:
                    raise CheckpointError(f"{path}: parameter {name} has shape {tuple(src.shape)}, "
                                          f"expected {tuple(p.shape)}")
                p.copy_(src)
            for name, b in field.named_buffers():
                key = f"buffer/{name}"
                if key in t:
                    if b.shape != t[key].shape:
                        raise CheckpointError(f"{path}: buffer {name} has shape {tuple(t[key].shape)}, "
                                              f"expected {tuple(b.shape)}")
                    b.copy_(t[key])
            if "buffer/tex_frame" in t:   # per-vertex texture frames (absent: identity everywhere)
                tf = t["buffer/tex_frame"].float()
                if tuple(tf.shape) != (field.num_vertices, 3, 3) or not torch.isfinite(tf).all():
                    raise CheckpointError(f"{path}: buffer tex_frame has shape {tuple(tf.shape)} or non-finite "
                                          f"values, expected ({field.num_vertices}, 3, 3); the file is corrupt")
                field.tex_frame = tf.clone()
            ids = field.decoder_id
            if int(ids.min()) < 0 or int(ids.max()) >= field.num_decoders:
                raise CheckpointError(f"{path}: decoder ids outside [0, {field.num_decoders}); the file "
                                      "is corrupt")
            for dec in list(field.rad_decoders)[1:]:   # bound decoders come from other fields: frozen
                for prm in dec.parameters():
                    prm.requires_grad_(False)
            field.grid.load_state({k[5:]: t[k] for k in t if k.startswith("grid/")})
        if "paint_atlas" in meta:   # texel paint; files without it (all older ones) have none
            from .paint_atlas import PaintAtlas

            field.paint_atlas = PaintAtlas.from_tensors(meta["paint_atlas"], t, len(mesh.faces), path)
    except KeyError as exc:
        raise CheckpointError(f"{path}: missing entry {exc}; the file is incomplete") from exc
    _load_real_capture_meta(path, field, meta, t)
    field._checkpoint_meta = meta
    if field.has_semantics:
        field.semantics_info = dict(meta.get("semantics") or {})
    field._checkpoint_optim = {k[6:]: v for k, v in t.items() if k.startswith("optim/")}
    return field.to(device)


def _save_real_capture_meta(field, meta: dict) -> None:
    from .background import background_of

    box = getattr(field, "object_box", None)
    if box is not None:
        meta["object_box"] = box.to_dict()
    bg = background_of(field)
    if bg is not None:
        meta["background"] = bg.config()


def _load_real_capture_meta(path: str, field, meta: dict, t: dict) -> None:
    """The object box and background model of a real-capture field (absent in older files)."""
    if meta.get("object_box") is not None:
        from ..data.frame import ObjectBox

        try:
            field.object_box = ObjectBox.from_dict(meta["object_box"])
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{path}: the object box in the header is invalid ({exc}); the file is corrupt")
    if meta.get("background") is not None:
        from .background import BackgroundModel, attach_background

        try:
            bg = BackgroundModel.from_config(meta["background"])
            state = {k[len("param/background."):]: v for k, v in t.items() if k.startswith("param/background.")}
            bg.load_state_dict(state, strict=True)
        except (KeyError, TypeError, ValueError, RuntimeError) as exc:
            raise CheckpointError(f"{path}: the background model is incomplete or invalid ({exc}); the file "
                                  "is corrupt (load it without the background by re-saving from a backup)") from exc
        attach_background(field, bg)


def load_optimizer_state(field, optimizer: torch.optim.Optimizer) -> bool:
    """Restore Adam moments stored by save_field(optimizer=...). Returns True if anything was loaded."""
    stored = getattr(field, "_checkpoint_optim", None) or {}
    if not stored:
        return False
    params = dict(field.named_parameters())
    for key, v in stored.items():
        pname, _, skey = key.rpartition("/")
        p = params.get(pname)
        if p is None:
            continue
        optimizer.state.setdefault(p, {})[skey] = v.to(p.device)
    return True

