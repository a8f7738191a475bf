"""Where edits go: the scene's Edits folder, by default beside the .blend in a folder named after it
(``<blend name>_neumesh/``); an unsaved .blend without a chosen folder is refused with what to do; the
folder a field was read from is never written to unless the artist chose it.  The rule is one pure
function (``props.edits_folder``)."""
from __future__ import annotations

import os
import shutil
import stat

import bpy
import pytest

from helpers import field_in_camera, record_panel

W, H = 48, 40


def test_the_edits_folder_rule(addon, tmp_path):
    rule = addon.scene.props.edits_folder
    UserError = addon.runtime.errors.UserError
    blend = str(tmp_path / "shots" / "fox scene.blend")
    assert rule("", blend) == str(tmp_path / "shots" / "fox scene_neumesh")
    assert rule("  ", blend) == str(tmp_path / "shots" / "fox scene_neumesh")
    assert rule("//edits", blend) == str(tmp_path / "shots" / "edits")
    assert rule("//../elsewhere/", blend) == str(tmp_path / "elsewhere")
    assert rule(str(tmp_path / "chosen") + "/", blend) == str(tmp_path / "chosen")
    assert rule(str(tmp_path / "chosen"), "") == str(tmp_path / "chosen")   # chosen: no .blend needed
    with pytest.raises(UserError, match="save the .blend first, or choose an Edits folder"):
        rule("", "")
    with pytest.raises(UserError, match="relative to the .blend"):
        rule("//edits", "")
    assert not os.path.exists(tmp_path / "shots")   # the rule creates nothing


def _paint_scene(addon, field_path):
    obj = field_in_camera(field_path, W, H)
    assert bpy.ops.neumesh.paint_view() == {"FINISHED"}
    paint = addon.edit.paint
    img = bpy.data.images[paint.PAINT_IMAGE]
    px = paint._image_pixels(img)
    px[16:22, 18:30, :3] = (0.05, 0.1, 0.9)
    paint._set_pixels(img, px)
    return obj


def _listing(folder):
    return sorted((e.name, e.stat().st_size, e.stat().st_mtime_ns) for e in os.scandir(folder))


def test_an_edit_of_a_field_in_a_read_only_folder_goes_beside_the_blend(addon, trained_field, tmp_path, capfd):
    data = tmp_path / "capture"
    data.mkdir()
    src = data / "blob.neumesh"
    shutil.copy(trained_field, src)
    os.chmod(data, stat.S_IRUSR | stat.S_IXUSR | stat.S_IRGRP | stat.S_IXGRP)   # read-only, as a shared dataset
    try:
        before = _listing(data)
        project = tmp_path / "project"
        project.mkdir()
        bpy.context.scene.neumesh.edits_dir = ""   # the default
        assert bpy.ops.wm.save_as_mainfile(filepath=str(project / "shot.blend")) == {"FINISHED"}
        obj = _paint_scene(addon, str(src))
        capfd.readouterr()
        assert bpy.ops.neumesh.apply_paint() == {"FINISHED"}
        out = project / "shot_neumesh" / "blob.edit-001.neumesh"
        assert addon.scene.props.field_abspath(obj) == str(out) and out.is_file()
        assert _listing(data) == before                         # the field's folder is untouched
        assert addon.edit.base.edit_chain(obj)[0][1] == str(src)   # the edit knows where it came from
        report = capfd.readouterr().out
        size = addon.runtime.text.file_size(str(out))
        assert f"saved blob.edit-001.neumesh ({size}) in {project / 'shot_neumesh'}" in report, report
        # the next edit of the edited file numbers on in the same folder
        assert bpy.ops.neumesh.paint_view() == {"FINISHED"}
        img = bpy.data.images[addon.edit.paint.PAINT_IMAGE]
        px = addon.edit.paint._image_pixels(img)
        px[18:24, 20:28, :3] = (0.9, 0.8, 0.1)
        addon.edit.paint._set_pixels(img, px)
        assert bpy.ops.neumesh.apply_paint() == {"FINISHED"}
        assert addon.scene.props.field_abspath(obj) == str(project / "shot_neumesh" / "blob.edit-002.neumesh")
        assert _listing(data) == before
    finally:
        os.chmod(data, stat.S_IRWXU)


def test_an_unsaved_blend_without_an_edits_folder_refuses_and_says_what_to_do(addon, trained_field, tmp_path):
    src = tmp_path / "blob.neumesh"
    shutil.copy(trained_field, src)
    bpy.context.scene.neumesh.edits_dir = ""
    obj = _paint_scene(addon, str(src))
    before = sorted(os.listdir(tmp_path))
    with pytest.raises(RuntimeError, match="save the .blend first, or choose an Edits folder"):
        bpy.ops.neumesh.apply_paint()
    assert sorted(os.listdir(tmp_path)) == before and addon.scene.props.field_abspath(obj) == str(src)
    # the panel says it where the folder is chosen
    rec = record_panel(bpy.types.NEUMESH_PT_edit, bpy.context)
    assert "Save the .blend first (edits go beside it), or choose a folder" in " ".join(rec.labels)
    # a chosen folder works without a saved .blend
    bpy.context.scene.neumesh.edits_dir = str(tmp_path / "my edits")
    assert bpy.ops.neumesh.apply_paint() == {"FINISHED"}
    assert addon.scene.props.field_abspath(obj) == str(tmp_path / "my edits" / "blob.edit-001.neumesh")


def test_the_edit_panel_names_the_default_folder(addon, trained_field, tmp_path):
    bpy.context.scene.neumesh.edits_dir = ""
    assert bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "shot.blend")) == {"FINISHED"}
    assert bpy.ops.neumesh.load_field(filepath=trained_field, new_object=True) == {"FINISHED"}
    rec = record_panel(bpy.types.NEUMESH_PT_edit, bpy.context)
    assert "Edits folder" in rec.labels
    assert "Empty: the folder shot_neumesh beside the .blend" in " ".join(rec.labels)


def test_an_alignment_preview_needs_no_edits_folder_but_its_accept_does(addon, trained_field, tmp_path):
    from test_texture_edit import _setup

    for name in list(addon.edit.swap_preview._PREVIEWS):
        addon.edit.swap_preview.discard(name)
    target, _source, tgt_path, _src, _cam, _region = _setup(trained_field, tmp_path)
    bpy.context.scene.neumesh.edits_dir = ""
    assert bpy.ops.neumesh.swap_preview(target_group="region", source_object="Source",
                                        source_group="region") == {"FINISHED"}   # reads only
    with pytest.raises(RuntimeError, match="save the .blend first, or choose an Edits folder"):
        bpy.ops.neumesh.swap_accept()
    assert addon.scene.props.field_abspath(target) == tgt_path
    assert not any(".edit-" in n for n in os.listdir(tmp_path))
    addon.edit.swap_preview.discard(target.name_full)
