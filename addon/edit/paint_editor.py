"""Paint on view's Image Editor: the paint image shown in an Image Editor of the main window in Paint
mode (an Image Editor already on screen, else half of the largest 3D View, a new window only when
neither can be done)."""
from __future__ import annotations

import bpy

from ..runtime import quiet

OPENED_KEY = "neumesh_opened_area"   # on the paint image: the add-on split a 3D View for it


def _split_view(context):
    """Split the largest 3D View of the window in two (side by side); the new right half, or None."""
    window, screen = context.window, context.screen
    views = [a for a in screen.areas if a.type == "VIEW_3D"]
    if window is None or not views:
        return None
    area = max(views, key=lambda a: a.width * a.height)
    before = set(screen.areas[:])
    region = next((r for r in area.regions if r.type == "WINDOW"), None)
    with quiet.override(context, window=window, screen=screen, area=area, region=region):
        bpy.ops.screen.area_split(direction="VERTICAL", factor=0.5)
    new = [a for a in screen.areas if a not in before]
    return new[0] if new else None


def open_in_image_editor(context, img) -> None:
    """Show ``img`` in an Image Editor of the main window in Paint mode, its sidebar open on the NeuMesh
    tab (Apply / Cancel): an existing Image Editor, else half of the largest 3D View; a new window only
    when the screen has neither."""
    screen = getattr(context, "screen", None)
    if screen is None or bpy.app.background:
        return
    area = next((a for a in screen.areas if a.type == "IMAGE_EDITOR"), None)
    if area is None:
        try:
            area = _split_view(context)
        except Exception:  # noqa: BLE001 - a new window below
            area = None
        if area is not None:
            area.type = "IMAGE_EDITOR"
            img[OPENED_KEY] = True
    if area is None:
        try:
            bpy.ops.wm.window_new()
            area = bpy.context.window_manager.windows[-1].screen.areas[0]
            area.type = "IMAGE_EDITOR"
        except Exception:  # noqa: BLE001 - painting still works from any Image Editor the user opens
            return
    space = area.spaces.active
    space.image = img
    try:
        space.show_region_ui = True
    except Exception:  # noqa: BLE001
        pass
    try:
        space.ui_mode = "PAINT"
    except Exception:  # noqa: BLE001 - older Blender: mode on the space
        try:
            space.mode = "PAINT"
        except Exception:  # noqa: BLE001
            pass
