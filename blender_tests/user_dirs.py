"""Keep bpy's writes out of $HOME: call :func:`redirect` BEFORE ``import bpy``.

bpy writes user configuration, caches and temporary files under $HOME and the XDG folders; the
Blender tests (conftest.py), the Blender benchmarks and the picture scripts point them all into one
fresh temporary folder instead.  No bpy import here, so it can run first.
"""
from __future__ import annotations

import os
import tempfile

_DIRS = (("BLENDER_USER_RESOURCES", "blender_user"), ("XDG_CACHE_HOME", "cache"),
         ("XDG_CONFIG_HOME", "config"), ("TMPDIR", "tmp"), ("HOME", "home"))


def redirect(prefix: str) -> str:
    """Point bpy's user, cache, config, temp and home folders into a new temporary folder (made with
    ``prefix``); returns that folder."""
    base = tempfile.mkdtemp(prefix=prefix)
    for var, sub in _DIRS:
        os.makedirs(os.path.join(base, sub), exist_ok=True)
        os.environ[var] = os.path.join(base, sub)
    tempfile.tempdir = os.environ["TMPDIR"]
    return base
