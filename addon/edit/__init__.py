"""edit: edits of a field's texture without retraining, each an operator with its panel under *Edit field*:
the shared plumbing, Undo edit and Revert (base; the parent panel of every room's edit panels), texture
swap and fill (swap_fill), the swap's alignment preview (swap_preview), paint (paint; Blender's Texture
Paint on the paint atlas: texture_paint, its image -> field sync: paint_sync).
Imports runtime, scene and render."""
from __future__ import annotations

from ..runtime import modules_factory
from . import base, paint, paint_sync, swap_fill, swap_preview, texture_paint

# base first: its panel is the others' parent
_modules = (base, swap_fill, swap_preview, paint, paint_sync, texture_paint)

register, unregister = modules_factory(_modules)
