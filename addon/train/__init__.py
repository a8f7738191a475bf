"""train: dataset cameras, real captures (capture: Import Cameras of COLMAP / transforms.json, Poses
from Photos), scaffold and mesh import, training in the background (worker), loading a
field onto an object (operators). Imports runtime, scene and render."""
from __future__ import annotations

from ..runtime import modules_factory
from . import capture, operators

_modules = (operators, capture)

register, unregister = modules_factory(_modules)
