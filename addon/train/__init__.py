"""train: dataset cameras, real captures (capture: Import Cameras of COLMAP / transforms.json, Poses
from Photos), scaffold building and training in the background (operators, worker), mesh import and loading a
field onto an object (imports: read in a background job). Imports runtime, scene and render."""
from __future__ import annotations

from ..runtime import modules_factory
from . import capture, imports, operators

_modules = (imports, operators, capture)

register, unregister = modules_factory(_modules)
