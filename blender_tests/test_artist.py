"""What an artist meets (issue #35), in bpy 5.0.1: colour management when NeuMesh is chosen, the
training mesh after Load field, wrapped messages, the wording of errors, field paths across Save As
(the 3.4 binary has its own tests in test_real_blender.py / test_real_blender_ui.py)."""
from __future__ import annotations

import os
import shutil

import bpy
import numpy as np
import pytest

from helpers import add_camera, grid_mesh


# ------------------------------------------------------------------------------------ colour (4)
def test_choosing_neumesh_sets_photo_colours_once(addon):
    scene = bpy.context.scene
    default = scene.view_settings.view_transform
    assert default in ("AgX", "Filmic")  # Blender's default: what made renders flat and grey
    colour = addon.colour
    scene.render.engine = "CYCLES"
    assert colour.engine_selected(scene) is False and scene.view_settings.view_transform == default
    scene.render.engine = "NEUMESH"
    # what the message bus calls when the engine changes in the interface (bpy has no event loop:
    # the real window test checks the subscription itself)
    assert colour.engine_selected(scene) is True
    assert scene.view_settings.view_transform == "Standard" and scene.view_settings.look == "None"
    assert colour.photo_colour_issues(scene) == []
    # once per scene: a user who then picks another view transform keeps it
    scene.view_settings.view_transform = default
    scene.render.engine = "CYCLES"
    scene.render.engine = "NEUMESH"
    assert colour.engine_selected(scene) is False and scene.view_settings.view_transform == default
    assert colour.photo_colour_issues(scene) == [f"View Transform is '{default}'"]
    assert bpy.ops.neumesh.photo_colour() == {"FINISHED"}
    assert scene.view_settings.view_transform == "Standard" and scene.render.dither_intensity == 0.0
    # the subscription is in place after the add-on registered and after a file load
    assert colour._load_post in bpy.app.handlers.load_post


# ------------------------------------------------------------------------------------ wording (7)
def test_relative_field_path_in_unsaved_file_keeps_its_slashes(addon, trained_field):
    V, F = grid_mesh()
    obj = addon.sync.new_mesh_object("grid", V, F)
    obj.neumesh.field_path = "//field.neumesh"
    add_camera((0, -3, 0.5))
    bpy.context.scene.render.engine = "NEUMESH"
    bpy.context.scene.render.resolution_x = bpy.context.scene.render.resolution_y = 16
    with pytest.raises(FileNotFoundError) as exc:
        addon.render.collect(bpy.context.evaluated_depsgraph_get())
    msg = str(exc.value)
    assert "not found: //field.neumesh" in msg and "has not been saved" in msg
    try:
        bpy.ops.render.render()
    except RuntimeError:
        pass
    assert "//field.neumesh" in addon.engine.LAST_ERROR["message"]
    assert addon.engine.LAST_ERROR["message"].startswith("NeuMesh: object 'grid'")


# ------------------------------------------------------------------------------------ paths (3)
def _object_with_field(addon, field):
    V, F = grid_mesh()
    obj = addon.sync.new_mesh_object("grid", V, F)
    addon.props.set_field_path(obj, str(field))
    return obj


def _placeholder(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"placeholder")
    return path


def test_moving_the_folder_with_blend_and_field_keeps_working(addon, tmp_path):
    field = _placeholder(tmp_path / "project" / "fields" / "f.neumesh")
    _object_with_field(addon, field)
    blend = tmp_path / "project" / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    shutil.move(str(tmp_path / "project"), str(tmp_path / "moved"))
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "moved" / "scene.blend"))
    o = bpy.data.objects["grid"]
    assert o.neumesh.field_path == "//fields/f.neumesh"
    assert addon.props.field_abspath(o) == str(tmp_path / "moved" / "fields" / "f.neumesh")


def test_save_copy_leaves_the_open_file_pointing_at_its_field(addon, tmp_path):
    field = _placeholder(tmp_path / "fields" / "f.neumesh")
    obj = _object_with_field(addon, field)
    (tmp_path / "a").mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "a" / "scene.blend"))
    (tmp_path / "b" / "c").mkdir(parents=True)
    copy = tmp_path / "b" / "c" / "copy.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(copy), copy=True)
    assert obj.neumesh.field_path == "//../fields/f.neumesh"  # the open file is still in a/
    assert addon.props.field_abspath(obj) == str(field)
    bpy.ops.wm.open_mainfile(filepath=str(copy))
    o = bpy.data.objects["grid"]
    assert o.neumesh.field_path == "//../../fields/f.neumesh"
    assert addon.props.field_abspath(o) == str(field)


def test_save_as_when_blender_does_not_say_where(addon, tmp_path, monkeypatch):
    """Blender 3.x calls save_pre with (None, None): the add-on keeps the path relative to the old
    folder, records where the file is, and repairs the path after the save and on opening."""
    props = addon.props
    handlers = bpy.app.handlers.save_pre
    i = handlers.index(props._save_pre)

    def save_pre_like_blender_3(*_args):
        props._save_pre(None, None)

    field = _placeholder(tmp_path / "fields" / "f.neumesh")
    obj = _object_with_field(addon, field)
    handlers[i] = save_pre_like_blender_3
    (tmp_path / "a").mkdir()
    try:
        bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "a" / "scene.blend"))
        assert obj.neumesh.field_path == "//../fields/f.neumesh"
        (tmp_path / "b" / "deeper").mkdir(parents=True)
        second = tmp_path / "b" / "deeper" / "scene.blend"
        bpy.ops.wm.save_as_mainfile(filepath=str(second))
        # after the save: the path in memory is relative to the new folder
        assert obj.neumesh.field_path == "//../../fields/f.neumesh"
    finally:
        handlers[i] = props._save_pre
    # the file itself holds the path relative to a/ (save_pre could not know better) ...
    bpy.ops.wm.open_mainfile(filepath=str(second), load_ui=False)
    o = bpy.data.objects["grid"]
    # ... and opening it repairs the path from the recorded location
    assert o.neumesh.field_path == "//../../fields/f.neumesh"
    assert props.field_abspath(o) == str(field)
    # a path the user changes is theirs: no silent fallback to the recorded file
    o.neumesh.field_path = "//elsewhere.neumesh"
    assert props.field_abspath(o) == str(tmp_path / "b" / "deeper" / "elsewhere.neumesh")
