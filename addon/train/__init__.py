"""train: dataset cameras, scaffold and mesh import, training in the background (worker), loading a
field onto an object (operators). Imports runtime, scene and render."""
from __future__ import annotations

from ..runtime import modules_factory
from . import operators

_modules = (operators,)

register, unregister = modules_factory(_modules)
