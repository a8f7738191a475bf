"""The preferences saved as soon as the add-on is enabled or *Existing environment* is set, so that a
`blender -b` started while this Blender is still open finds the NeuMesh engine and its dependencies.

Blender keeps changed preferences in memory and, with *Auto-Save Preferences* on (its default),
writes them only when it quits; until then any other Blender, a shell batch render included, reads
the old ones ("Engine 'NEUMESH' not available", torch not found).  With auto-save on, the add-on
writes them at once (what Blender would write on quit, written earlier).  With auto-save off the
artist keeps them by hand (*Save Preferences*), and the add-on's preferences say so while they are
unsaved.  Nothing is written in background runs (`blender -b`: scripts that enable add-ons there keep
them to that run) or under --factory-startup (not the artist's preferences).
"""
from __future__ import annotations

import bpy

LAST = {"result": ""}   # what the last check did: saved / clean / manual / skipped / failed: ... (tests)


def persist() -> str:
    """Save the preferences now when they are unsaved and Blender would save them on quit anyway.
    Returns "saved", "clean" (nothing unsaved), "manual" (Auto-Save Preferences off: the artist
    saves), "skipped" (background run or factory settings) or "failed: <why>"."""
    prefs = bpy.context.preferences
    if bpy.app.background or getattr(bpy.app, "factory_startup", False):
        result = "skipped"
    elif not prefs.is_dirty:
        result = "clean"
    elif not prefs.use_preferences_save:
        result = "manual"
    else:
        try:
            bpy.ops.wm.save_userpref()
            result = "saved"
        except RuntimeError as exc:
            result = f"failed: {exc}"
    LAST["result"] = result
    if result == "saved":
        print("NeuMesh: preferences saved (add-on enabled, Existing environment): `blender -b` finds them now")
    elif result.startswith("failed"):
        print(f"NeuMesh: cannot save the preferences ({result[8:]}); use Save Preferences before `blender -b`")
    return result


def _timer():
    try:
        persist()
    except Exception as exc:  # noqa: BLE001 - a timer must not raise into Blender
        print(f"NeuMesh: preferences not saved: {exc}")
    return None


def schedule(delay: float = 0.5) -> None:
    """:func:`persist` from a timer: Blender adds an add-on to the preferences only after its
    register() returned, and a property's update callback is no place for an operator."""
    try:
        if not bpy.app.timers.is_registered(_timer):
            bpy.app.timers.register(_timer, first_interval=delay)
    except Exception:  # noqa: BLE001 - no timers (some background runs): nothing to keep
        pass


def changed() -> None:
    """A preference that `blender -b` needs changed (*Existing environment*): marked unsaved (also
    when a script set it) and saved as :func:`persist` decides."""
    try:
        bpy.context.preferences.is_dirty = True
    except Exception:  # noqa: BLE001 - no preferences (some background runs)
        return
    schedule()


def unsaved_note() -> str:
    """What the add-on's preferences say while they are unsaved and only a manual save keeps them
    ('' otherwise)."""
    prefs = bpy.context.preferences
    if bpy.app.background or getattr(bpy.app, "factory_startup", False):
        return ""
    if prefs.is_dirty and not prefs.use_preferences_save:
        return ("Preferences not saved (Auto-Save Preferences is off): press Save Preferences (the menu at the "
                "bottom left of the Preferences), or a `blender -b` render started now will not find NeuMesh or "
                "Existing environment")
    return ""
