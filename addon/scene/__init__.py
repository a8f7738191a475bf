"""scene: Blender data <-> numpy and what the .blend stores: object/scene properties and field paths
(props), evaluated vertices, triangles, groups, UVs (sync), vertex identity through topology edits
(identity), cameras (camera). Imports runtime only."""
from __future__ import annotations

from ..runtime import modules_factory
from . import identity, props

_modules = (props, identity)

register, unregister = modules_factory(_modules)
