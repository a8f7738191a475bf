"""semantics: the Semantics panel under *Edit field* (panel) and its tools: Distill semantics in a
background job (distill), Select by click (select), Show semantic colours (semantic_colours).
Imports runtime, scene, render and edit."""
from __future__ import annotations

from ..runtime import modules_factory
from . import distill, panel, select, semantic_colours

_modules = (distill, select, semantic_colours, panel)

register, unregister = modules_factory(_modules)
