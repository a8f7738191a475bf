"""edit: edits of a field without retraining, each an operator with its panel under *Edit field*:
the shared plumbing, Undo edit and Revert (base), texture swap and fill (swap_fill), the swap's
alignment preview (swap_preview), paint (paint; Blender's Texture Paint on the paint atlas: texture_paint, its image -> field sync: paint_sync), semantics (distil, select, semantic_colours; the
panel: semantics), bake to material (bake), ARAP deform with handle Empties (arap: solves, drag
thread, handlers; arap_undo: undo and redo; arap_ops: operators and panel).
Imports runtime, scene and render."""
from __future__ import annotations

from ..runtime import modules_factory
from . import arap_ops, bake, base, distil, paint, select, semantic_colours, semantics, swap_fill, swap_preview, paint_sync, texture_paint

_modules = (base, swap_fill, swap_preview, paint, paint_sync, texture_paint, distil, select, semantic_colours, semantics, bake,
            arap_ops)   # base first: its panel is the others' parent

register, unregister = modules_factory(_modules)
