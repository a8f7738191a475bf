"""bake: Bake to material (material): the field as it renders now turned into a plain Blender object with
a UV map, an image texture and a material; its panel sits under *Edit field*.
Imports runtime, scene, render and edit."""
from __future__ import annotations

from ..runtime import modules_factory
from . import material

_modules = (material,)

register, unregister = modules_factory(_modules)
