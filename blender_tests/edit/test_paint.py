"""Paint on view / Apply painting: the paint image carries its view; painted pixels become surface
paint in the fields they cover; F12 matches the core's render of the edited file; bad input changes
nothing.  Tolerance for F12 against the core: 1e-4 (as in test_engine)."""
from __future__ import annotations

import shutil

import bpy
import numpy as np
import pytest

from helpers import add_camera, exact_colour_settings, f12_srgb, manual_K_c2w

W, H = 48, 40


def _scene(trained_field, tmp_path, names=("A",)):
    objs = []
    for i, name in enumerate(names):
        path = str(tmp_path / f"{name}.neumesh")
        shutil.copy(trained_field, path)
        assert bpy.ops.neumesh.load_field(filepath=path, new_object=True) == {"FINISHED"}
        obj = bpy.context.active_object
        obj.name = name
        obj.location.x = 2.6 * i
        objs.append(obj)
    cam = add_camera((1.3 * (len(names) - 1), -4.8 - 2.5 * (len(names) - 1), 0.6),
                     look_at=(1.3 * (len(names) - 1), 0, 0), lens=35.0)
    scene = bpy.context.scene
    scene.render.engine = "NEUMESH"
    exact_colour_settings(scene, W, H)
    bpy.context.view_layer.update()
    return objs, cam


def _paint(addon, rows, cols, colour):
    img = bpy.data.images[addon.edit.paint.PAINT_IMAGE]
    px = addon.edit.paint._image_pixels(img)
    px[rows[0]:rows[1], cols[0]:cols[1], :3] = colour
    addon.edit.paint._set_pixels(img, px)
    return img


def _core(path, cam):
    import neumesh_core as nm

    K, c2w = manual_K_c2w(cam, W, H)
    return np.clip(nm.render_camera(nm.load_field(path), K, c2w, W, H).rgb, 0, 1)


def test_paint_on_view_then_apply_shows_the_paint_in_f12(addon, trained_field, tmp_path):
    (obj,), cam = _scene(trained_field, tmp_path)
    assert bpy.ops.neumesh.paint_view() == {"FINISHED"}
    img = bpy.data.images[addon.edit.paint.PAINT_IMAGE]
    assert tuple(img.size) == (W, H) and img["neumesh_camera"] == cam.name
    # the image holds the render (8-bit), the unpainted copy beside it
    shown = addon.edit.paint._image_pixels(img)[..., :3]
    assert np.abs(shown - _core(str(tmp_path / "A.neumesh"), cam)).max() < 1 / 255 + 1e-6
    before = addon.edit.paint._image_pixels(img)[16:22, 18:30, :3]
    _paint(addon, (16, 22), (18, 30), (0.05, 0.1, 0.9))
    assert bpy.ops.neumesh.apply_paint() == {"FINISHED"}
    edited = addon.scene.props.field_abspath(obj)
    assert edited.endswith("A.edit-001.neumesh")
    after = np.clip(f12_srgb(tmp_path / "b.exr"), 0, 1)
    assert np.abs(after - _core(edited, cam)).max() <= 1e-4
    # the paint is there (this 642-vertex test scaffold holds only a blurred 6x12 px stroke)
    stroke = after[16:22, 18:30]
    assert np.abs(stroke - [0.05, 0.1, 0.9]).mean() < 0.3 * np.abs(before - [0.05, 0.1, 0.9]).mean()
    assert bpy.ops.neumesh.undo_edit() == {"FINISHED"}
    assert addon.scene.props.field_abspath(obj) == str(tmp_path / "A.neumesh")


def test_paint_on_a_subdivided_mesh_lands_in_the_objects_own_field(addon, trained_field, tmp_path):
    """A mesh with a Subdivision Surface shows its field remapped onto the subdivided mesh; paint applied
    there changes the modification colours (only) of the object's own field, towards the paint."""
    import torch

    import neumesh_core as nm

    (obj,), cam = _scene(trained_field, tmp_path)
    obj.modifiers.new("Subdivision", "SUBSURF").levels = 1
    bpy.context.view_layer.update()
    assert bpy.ops.neumesh.paint_view() == {"FINISHED"}
    assert addon.render.field_cache.STATS.get("remaps", 0) > 0
    _paint(addon, (16, 22), (18, 30), (0.05, 0.1, 0.9))
    assert bpy.ops.neumesh.apply_paint() == {"FINISHED"}
    edited = addon.scene.props.field_abspath(obj)
    assert edited.endswith("A.edit-001.neumesh")
    before, after = nm.load_field(str(tmp_path / "A.neumesh")), nm.load_field(edited)
    assert after.num_vertices == before.num_vertices
    delta = (after.mod_colours - before.mod_colours).detach()
    moved = delta.abs().amax(1) > 1e-4
    assert 0 < int(moved.sum()) < before.num_vertices
    assert torch.equal(after.tex_codes, before.tex_codes) and torch.equal(after.decoder_id, before.decoder_id)
    assert float(delta[moved, 2].mean()) > float(delta[moved, 0].mean())   # towards blue
    assert bpy.ops.neumesh.undo_edit() == {"FINISHED"}
    assert addon.scene.props.field_abspath(obj) == str(tmp_path / "A.neumesh")


def test_only_the_fields_under_the_paint_change(addon, trained_field, tmp_path):
    (a, b), cam = _scene(trained_field, tmp_path, names=("A", "B"))
    assert bpy.ops.neumesh.paint_view() == {"FINISHED"}
    # paint on the left object only
    K, c2w = manual_K_c2w(cam, W, H)
    x_a = int(round((K @ (np.linalg.inv(c2w) @ np.array([0, 0, 0, 1.0]))[:3])[0] /
                    (K @ (np.linalg.inv(c2w) @ np.array([0, 0, 0, 1.0]))[:3])[2]))
    _paint(addon, (17, 22), (x_a - 3, x_a + 3), (1.0, 1.0, 0.0))
    assert bpy.ops.neumesh.apply_paint() == {"FINISHED"}
    assert addon.scene.props.field_abspath(a).endswith("A.edit-001.neumesh")
    assert addon.scene.props.field_abspath(b) == str(tmp_path / "B.neumesh")


def test_bad_paint_input_changes_nothing(addon, trained_field, tmp_path):
    (obj,), cam = _scene(trained_field, tmp_path)
    with pytest.raises(RuntimeError, match="press Paint on view first"):
        bpy.ops.neumesh.apply_paint()
    assert bpy.ops.neumesh.paint_view() == {"FINISHED"}
    with pytest.raises(RuntimeError, match="nothing is painted"):
        bpy.ops.neumesh.apply_paint()
    _paint(addon, (0, 3), (0, 4), (1.0, 0.0, 0.0))        # a corner: background only
    with pytest.raises(RuntimeError, match="only background"):
        bpy.ops.neumesh.apply_paint()
    _paint(addon, (16, 22), (18, 30), (1.0, 0.0, 0.0))
    cam.location.x += 0.3
    bpy.context.view_layer.update()
    with pytest.raises(RuntimeError, match="camera or the render size changed"):
        bpy.ops.neumesh.apply_paint()
    cam.location.x -= 0.3
    bpy.context.scene.render.resolution_x = W + 8
    with pytest.raises(RuntimeError, match="camera or the render size changed"):
        bpy.ops.neumesh.apply_paint()
    assert addon.scene.props.field_abspath(obj) == str(tmp_path / "A.neumesh")


def test_apply_and_cancel_sit_in_the_image_editor_showing_the_paint(addon, trained_field, tmp_path):
    """The Image Editor that shows the paint image has a NeuMesh sidebar panel and header
    buttons with Apply / Cancel (for that image); Cancel discards both images and applies nothing.
    (Opening an Image Editor inside the main window is checked in the real window: test_real_blender_ui.)"""
    import types

    from helpers import Recorder, draw_panel

    paint = addon.edit.paint
    (obj,), cam = _scene(trained_field, tmp_path)
    panel = bpy.types.NEUMESH_PT_paint_image
    space = types.SimpleNamespace(type="IMAGE_EDITOR", image=None)
    ctx = types.SimpleNamespace(space_data=space)
    assert not panel.poll(ctx)                                   # no paint image yet
    labels, ops = draw_panel(bpy.types.NEUMESH_PT_paint, bpy.context)
    assert "neumesh.paint_view" in ops and "neumesh.cancel_paint" in ops
    assert bpy.ops.neumesh.paint_view() == {"FINISHED"}
    img = bpy.data.images[paint.PAINT_IMAGE]
    space.image = bpy.data.images[paint.ORIGINAL_IMAGE]
    assert not panel.poll(ctx)                                   # another image: no panel
    space.image = img
    assert panel.poll(ctx)
    rec = Recorder()
    paint.draw_image_header(types.SimpleNamespace(layout=rec), ctx)
    assert rec.operators == ["neumesh.apply_paint", "neumesh.cancel_paint"]
    # cancel: both images go, the field is untouched
    _paint(addon, (16, 22), (18, 30), (1.0, 0.0, 0.0))
    assert bpy.ops.neumesh.cancel_paint() == {"FINISHED"}
    assert paint.PAINT_IMAGE not in bpy.data.images and paint.ORIGINAL_IMAGE not in bpy.data.images
    assert addon.scene.props.field_abspath(obj) == str(tmp_path / "A.neumesh")
    with pytest.raises(RuntimeError, match="no paint image"):
        bpy.ops.neumesh.cancel_paint()
    # and the whole round from the image editor's buttons: paint again, apply
    assert bpy.ops.neumesh.paint_view() == {"FINISHED"}
    _paint(addon, (16, 22), (18, 30), (1.0, 0.0, 0.0))
    assert bpy.ops.neumesh.apply_paint(image=paint.PAINT_IMAGE) == {"FINISHED"}
    assert addon.scene.props.field_abspath(obj).endswith("A.edit-001.neumesh")
