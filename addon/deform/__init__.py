"""deform: ARAP deform with handle Empties (arap: solves, drag thread, handlers; arap_undo: undo and redo;
arap_ops: settings, operators and the panel under *Edit field*).
Imports runtime, scene, render and edit."""
from __future__ import annotations

from ..runtime import modules_factory
from . import arap_ops

_modules = (arap_ops,)

register, unregister = modules_factory(_modules)
