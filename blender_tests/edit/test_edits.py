"""The edit plumbing every edit operator shares: an edit is saved beside the field it came from and
shows at once in F12; Undo edit / Revert / Ctrl+Z bring the previous pixels back; the file training
produced is never overwritten.  (A core edit is simulated here by writing modification colours through
an EditRecord; the swap, fill and paint operators have their own tests.)

Tolerance: F12 EXR decoded to sRGB against ``nm.render_camera`` within 1e-4 (as in test_engine).
"""
from __future__ import annotations

import os
import shutil

import bpy
import numpy as np
import pytest

from helpers import add_camera, exact_colour_settings, f12_srgb, manual_K_c2w

W, H = 40, 32


def _scene(field_path):
    assert bpy.ops.neumesh.load_field(filepath=field_path, new_object=True) == {"FINISHED"}
    obj = bpy.context.active_object
    cam = add_camera((0.0, -4.6, 0.8), lens=35.0)
    scene = bpy.context.scene
    scene.render.engine = "NEUMESH"
    exact_colour_settings(scene, W, H)
    return obj, cam


def _core_render(path, cam):
    import neumesh_core as nm

    K, c2w = manual_K_c2w(cam, W, H)
    return np.clip(nm.render_camera(nm.load_field(path), K, c2w, W, H).rgb, 0, 1)  # F12 shows 0..1


def _paint_red(addon, obj):
    """A stand-in edit: vertices with x > 0 get a red modification colour."""
    import torch

    import neumesh_core as nm

    field, path = addon.edit.base.field_for_edit(obj)
    rows = np.nonzero(field.rest_vertices[:, 0].numpy() > 0)[0]
    rec = nm.edit.EditRecord.begin("test-paint", field, rows, ("mod_colours",))
    with torch.no_grad():
        field.mod_colours[torch.as_tensor(rows)] = torch.tensor([0.4, -0.4, -0.4])
    rec.finish(field)
    return addon.edit.base.commit_edit(obj, field, rec, path), path


def test_edit_is_saved_beside_shows_in_f12_and_undo_restores(addon, trained_field, tmp_path):
    src = str(tmp_path / "blob.neumesh")
    shutil.copy(trained_field, src)
    before_bytes = open(src, "rb").read()
    obj, cam = _scene(src)
    original = f12_srgb(tmp_path / "a.exr")
    assert np.abs(original - _core_render(src, cam)).max() <= 1e-4

    edited, parent = _paint_red(addon, obj)
    assert parent == src and edited == str(tmp_path / "blob.edit-001.neumesh")
    assert addon.scene.props.field_abspath(obj) == edited
    after = f12_srgb(tmp_path / "b.exr")
    assert np.abs(after - _core_render(edited, cam)).max() <= 1e-4
    assert (np.abs(after - original).max(-1) > 0.1).sum() > 20   # the edit is visible
    assert open(src, "rb").read() == before_bytes                 # the trained file is untouched

    assert bpy.ops.neumesh.undo_edit() == {"FINISHED"}
    assert addon.scene.props.field_abspath(obj) == src
    assert np.abs(f12_srgb(tmp_path / "c.exr") - original).max() <= 1e-4
    assert bpy.ops.neumesh.undo_edit() == {"CANCELLED"}           # nothing left to undo

    # two edits, then revert goes straight to the trained field
    props = addon.scene.props
    props.set_field_path(obj, edited)
    second, _ = _paint_red(addon, obj)
    assert second.endswith("blob.edit-002.neumesh") and os.path.isfile(edited)
    chain = addon.edit.base.edit_chain(obj)
    assert [op for op, _ in chain] == ["trained", "test-paint", "test-paint"]
    assert bpy.ops.neumesh.revert_field() == {"FINISHED"}
    assert addon.scene.props.field_abspath(obj) == src
    assert np.abs(f12_srgb(tmp_path / "d.exr") - original).max() <= 1e-4


def test_ctrl_z_steps_back_to_the_previous_field(addon, trained_field, tmp_path):
    src = str(tmp_path / "blob.neumesh")
    shutil.copy(trained_field, src)
    obj, cam = _scene(src)
    name = obj.name
    original = f12_srgb(tmp_path / "a.exr")
    bpy.ops.ed.undo_push(message="before edit")
    edited, _ = _paint_red(addon, obj)
    bpy.ops.ed.undo_push(message="NeuMesh edit")
    assert np.abs(f12_srgb(tmp_path / "b.exr") - original).max() > 0.1
    if bpy.ops.ed.undo.poll():
        bpy.ops.ed.undo()
    else:
        pytest.skip("this Blender has no undo stack in background mode")
    obj = bpy.data.objects[name]                # undo rebuilds the objects
    assert addon.scene.props.field_abspath(obj) == src
    assert np.abs(f12_srgb(tmp_path / "c.exr") - original).max() <= 1e-4


def test_edit_errors_change_nothing(addon, trained_field, tmp_path):
    bpy.ops.mesh.primitive_cube_add()
    cube = bpy.context.active_object
    with pytest.raises(addon.runtime.errors.UserError, match="has no NeuMesh field"):
        addon.edit.base.field_for_edit(cube)
    cube.neumesh.field_path = str(tmp_path / "gone.neumesh")
    with pytest.raises(addon.runtime.errors.UserError, match="field file not found"):
        addon.edit.base.field_for_edit(cube)
    bpy.context.view_layer.objects.active = cube
    assert bpy.ops.neumesh.undo_edit.poll()
    with pytest.raises(RuntimeError, match="field file not found"):
        bpy.ops.neumesh.undo_edit()
