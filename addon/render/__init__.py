"""render: the field cache (field_cache) and core renders (frame), the NEUMESH engine for F12 / -a / viewport
(engine, preview), colour management (colour), compositing with Cycles/EEVEE (composite), rendering
cameras to PNG files (images). Imports runtime and scene."""
from __future__ import annotations

from ..runtime import modules_factory
from . import colour, composite, engine, images

_modules = (images, composite, engine, colour)

register, unregister = modules_factory(_modules)
