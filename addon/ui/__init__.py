"""ui: the sidebar and properties panels of the dataset, scaffold, training and field/render steps
(panels). Imports every room below it; nothing imports ui."""
from __future__ import annotations

from ..runtime import modules_factory
from . import panels

_modules = (panels,)

register, unregister = modules_factory(_modules)
