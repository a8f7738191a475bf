"""The add-on's preferences as the rest of the add-on reads them (no bpy classes here: the preferences
panel, :mod:`prefs`, imports this module, never the other way round)."""
from __future__ import annotations

import os

# "neumesh" (legacy add-on) or "bl_ext.<repo>.neumesh" (extension): the package above runtime/
ADDON_ID = __package__.rpartition(".")[0] if __package__ else "neumesh"


def get_prefs():
    """The add-on preferences, or None when the add-on is not enabled through the preferences."""
    try:
        import bpy

        addon = bpy.context.preferences.addons.get(ADDON_ID)
    except Exception:  # noqa: BLE001 - no Blender context
        return None
    return addon.preferences if addon is not None else None


def extra_paths() -> list[str]:
    """Dependency folders from the preferences: the existing environment first, then our own folder."""
    from . import deps

    out = []
    p = get_prefs()
    if p is not None and p.env_path.strip():
        import bpy

        out.append(bpy.path.abspath(p.env_path.strip()))
    try:
        own = deps.addon_deps_dir(ADDON_ID, create=False)
        if os.path.isdir(own):
            out.append(own)
    except Exception:  # noqa: BLE001 - no writable user folder
        pass
    return out


def torch_threads() -> int:
    """The preference *CPU threads* (0: all cores; also 0 without preferences)."""
    p = get_prefs()
    try:
        return int(p.torch_threads) if p is not None else 0
    except Exception:  # noqa: BLE001
        return 0


def device() -> str:
    """The preference *Device*: "auto" (a CUDA GPU when torch sees one, else the CPU), "cpu" or
    "cuda" ("auto" without preferences)."""
    p = get_prefs()
    try:
        return str(p.device).lower() if p is not None else "auto"
    except Exception:  # noqa: BLE001
        return "auto"


def preview_divisors() -> tuple:
    """The viewport preview's resolution divisors, coarsest first, from *Preview starts/ends at*."""
    p = get_prefs()
    start, final = (8, 2) if p is None else (int(p.preview_start), int(p.preview_final))
    divs = [d for d in (8, 4, 2, 1) if final <= d <= start]
    return tuple(divs or [final])
