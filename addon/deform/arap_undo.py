"""ARAP deform across Ctrl+Z / Ctrl+Shift+Z (:mod:`.arap` solves and writes the live shape key).

The key is written from Python (a timer, a handler) outside Blender's undo steps: the step a drag
pushes when it ends may hold the key from before the drag's last solve arrived, and Blender's undo
then keeps the key as it is in memory; a solve for the restored Empties, warm-started from the undone
pose, would not give the old shape back either.  So every write records (on the key) the Empties'
transforms it was solved for, :mod:`.arap` keeps the last few shapes it showed per object (the one
before each drag, the one an undo replaced), and after an undo or redo a key solved for other
transforms than the restored Empties' gets the shape shown for them back, else a solve from rest.
Between undo_pre and undo_post no solve runs and a drag solve still running is dropped; the next drag
starts from rest, not from the undone pose.
"""
from __future__ import annotations

import bpy
from bpy.app.handlers import persistent

from ..runtime.errors import UserError
from .arap import (LIVE_KEY, SOLVED_FOR, TIMINGS, _DRAGS, _SHAPES, _SOLVERS, _UNDO, _arap_objects, _digest,
                   _remember, _write_live, handle_transforms, start)


@persistent
def on_undo_pre(*_args):
    """Ctrl+Z / Ctrl+Shift+Z is about to put the Empties and the live shape key back as they were
    together: no solve may write over that (a drag solve running now was asked for the Empties as
    they are before the undo)."""
    _UNDO["busy"] = True
    for d in _DRAGS.values():
        d["epoch"] = d.get("epoch", 0) + 1
        d.pop("want", None)
        d["done"] = None


@persistent
def on_undo_post(*_args):
    """A restored shape key solved for the restored Empties is kept exactly (counted as solved, so the
    depsgraph update after the undo solves nothing); one solved for other transforms (the undo step
    was pushed before a drag's last solve arrived) is replaced by the shape shown for the restored
    Empties before, or else solved again from rest.  Either way the next drag starts from rest, not
    from the undone pose."""
    again = []
    try:
        for obj in _arap_objects(bpy.context.scene):
            ent = _SOLVERS.get(obj.name_full)
            try:
                moved = handle_transforms(obj, obj.neumesh_arap).round(7).tobytes()
            except UserError:      # an Empty is gone (undone past Add ARAP deform): built again later
                _SOLVERS.pop(obj.name_full, None)
                continue
            if ent is not None:
                ent["stale"] = {"preview", "full"}
            keys = obj.data.shape_keys
            if keys is not None and keys.key_blocks.get(LIVE_KEY) is not None and \
                    keys.get(SOLVED_FOR) == _digest(moved):
                if ent is not None:
                    ent["last"] = (moved, False)
            else:
                again.append((obj, moved))
    finally:
        _UNDO["busy"] = False
    for obj, moved in again:
        try:
            _remember(obj)                      # what the undo left in place (a redo may want it back)
            shape = _SHAPES.get(obj.name_full, {}).get(_digest(moved))
            if shape is None:
                start(obj)
                continue
            _write_live(obj, shape, moved)
            TIMINGS.setdefault(obj.name_full, {})["mode"] = "restored"
            if obj.name_full in _SOLVERS:
                _SOLVERS[obj.name_full]["last"] = (moved, False)
        except Exception as exc:  # noqa: BLE001 - a handler must not raise
            print(f"NeuMesh ARAP '{obj.name}': {exc}")
