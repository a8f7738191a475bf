"""Colour management for NeuMesh renders.

A field reproduces its training photos' pixel values (display-referred sRGB); the engine hands
Blender their scene-linear decoding. Blender's default view transform (Filmic in 3.x, AgX in 4.x/5.x)
tone-maps that again, so renders look flat and the white background turns grey. The first time a
scene's render engine is NeuMesh, its view transform is set to 'Standard' with no look; after that
the scene's settings are the user's. "The first time" is caught wherever it happens: in the
interface (a message-bus subscription on ``RenderSettings.engine``), when a file whose engine is
NeuMesh is opened (``load_post``), and before any render (``render_pre``: an engine given on the
command line, ``blender -b file.blend -E NEUMESH -a``, or set by a script), so F12, ``-a`` and the
viewport show the same pixels. A render with other settings says so in the log. The Render
properties panel says when the settings differ from the photographic ones, with a button
(:class:`NEUMESH_OT_photo_colour`) that sets them.
"""
from __future__ import annotations

import bpy
from bpy.app.handlers import persistent

PHOTO_VIEW = {"view_transform": "Standard", "look": "None", "exposure": 0.0, "gamma": 1.0}
_OWNER = object()


def photo_colour_issues(scene) -> list[str]:
    """What keeps a NeuMesh render from showing the field's (photo) colours; [] when nothing does."""
    vs = scene.view_settings
    out = []
    if vs.view_transform != "Standard":
        out.append(f"View Transform is '{vs.view_transform}'")
    if vs.look not in ("None", ""):
        out.append(f"Look is '{vs.look}'")
    if abs(vs.exposure) > 1e-6 or abs(vs.gamma - 1.0) > 1e-6:
        out.append("Exposure/Gamma are not 0/1")
    return out


def apply_photo_colour(scene, dither: bool = True):
    """View Transform 'Standard', Look None, Exposure 0, Gamma 1 (and Dither 0 when ``dither``)."""
    vs = scene.view_settings
    for k, v in PHOTO_VIEW.items():
        setattr(vs, k, v)
    if dither:
        scene.render.dither_intensity = 0.0


def engine_selected(scene) -> bool:
    """Called when a scene's render engine changed: the first time it is NeuMesh, use the photographic
    view transform (Standard, no look). Returns True when it changed the scene."""
    if scene is None or scene.render.engine != "NEUMESH" or scene.neumesh.photo_colour_set:
        return False
    scene.neumesh.photo_colour_set = True
    changed = bool(photo_colour_issues(scene))
    vs = scene.view_settings
    vs.view_transform, vs.look = "Standard", "None"
    if changed:
        print(f"NeuMesh: scene '{scene.name}': View Transform set to 'Standard' (photo colours; "
              "Render properties > Color Management to change it)")
    return changed


@persistent
def _render_pre(scene, *_args):
    """Before a render (F12, -a, -f, a script's render): the photographic view the first time."""
    try:
        engine_selected(scene if isinstance(scene, bpy.types.Scene) else bpy.context.scene)
    except Exception as exc:  # noqa: BLE001 - never stop a render over a convenience
        print(f"NeuMesh: colour management not set: {exc}")


def _on_engine_changed(*_args):
    try:
        engine_selected(bpy.context.scene)
    except Exception as exc:  # noqa: BLE001 - never break the interface over a convenience
        print(f"NeuMesh: colour management not set: {exc}")


def subscribe():
    bpy.msgbus.clear_by_owner(_OWNER)
    bpy.msgbus.subscribe_rna(key=(bpy.types.RenderSettings, "engine"), owner=_OWNER, args=(),
                             notify=_on_engine_changed, options={"PERSISTENT"})


@persistent
def _load_post(*_args):
    subscribe()  # a file load drops message-bus subscriptions
    for scene in bpy.data.scenes:   # a file saved with NeuMesh chosen by a script (no message then)
        try:
            engine_selected(scene)
        except Exception as exc:  # noqa: BLE001
            print(f"NeuMesh: colour management of scene '{scene.name}' not set: {exc}")


class NEUMESH_OT_photo_colour(bpy.types.Operator):
    """Colour management for photographs: View Transform 'Standard', no Look, Exposure 0, Gamma 1,
    Dither 0. NeuMesh fields hold the photos' colours; Filmic and AgX make them flat and grey"""

    bl_idname = "neumesh.photo_colour"
    bl_label = "Use Photo Colours"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        apply_photo_colour(context.scene)
        self.report({"INFO"}, "NeuMesh: View Transform 'Standard', Look None, Exposure 0, Gamma 1, Dither 0")
        return {"FINISHED"}


def _handlers():
    h = bpy.app.handlers
    return ((h.load_post, _load_post), (h.render_pre, _render_pre))


def register():
    bpy.utils.register_class(NEUMESH_OT_photo_colour)
    subscribe()
    for handlers, fn in _handlers():
        if fn not in handlers:
            handlers.append(fn)


def unregister():
    for handlers, fn in _handlers():
        if fn in handlers:
            handlers.remove(fn)
    bpy.msgbus.clear_by_owner(_OWNER)
    bpy.utils.unregister_class(NEUMESH_OT_photo_colour)
