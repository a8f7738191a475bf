"""What an artist meets, in bpy 5.0.1: colour management when NeuMesh is chosen, the
training mesh after Load field, wrapped messages, the wording of errors, field paths across Save As
(the 3.4 binary has its own tests in test_real_blender.py / test_real_blender_ui.py)."""
from __future__ import annotations

import shutil

import bpy
import pytest

from helpers import add_camera, grid_mesh


# ------------------------------------------------------------------------------------ colour (4)
def test_choosing_neumesh_sets_photo_colours_once(addon):
    scene = bpy.context.scene
    default = scene.view_settings.view_transform
    assert default in ("AgX", "Filmic")  # Blender's default: what made renders flat and grey
    colour = addon.render.colour
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


def test_a_render_chosen_by_script_or_command_line_uses_photo_colours(addon, tmp_path):
    """`-E NEUMESH` (or a script setting the engine) does not reach the message bus, so a file saved
    with Filmic would render flat and grey: the render_pre handler sets the photographic view before
    the first NeuMesh render, once per scene, as the interface does."""
    scene = bpy.context.scene
    default = scene.view_settings.view_transform
    assert default != "Standard" and not scene.neumesh.photo_colour_set
    colour = addon.render.colour
    assert colour._render_pre in bpy.app.handlers.render_pre
    scene.render.engine = "NEUMESH"          # no message-bus event in background mode
    add_camera((0.0, -4.0, 0.0), lens=35.0)
    scene.render.resolution_x, scene.render.resolution_y = 16, 12
    scene.render.filepath = str(tmp_path / "r.png")
    bpy.ops.render.render(write_still=True)   # Blender calls render_pre: the view switches first
    assert scene.view_settings.view_transform == "Standard" and scene.neumesh.photo_colour_set
    scene.view_settings.view_transform = default   # the user's later choice is kept
    bpy.ops.render.render(write_still=True)
    assert scene.view_settings.view_transform == default


def test_render_panel_note_is_wrapped_to_the_panel(addon):
    """The Render properties note is wrapped to the panel: every line fits, none is cut off mid-word."""
    ui = addon.runtime.text
    measure = ui.text_measure()
    text = ("Colours look flat: View Transform is 'AgX', Look is 'AgX - Punchy'. NeuMesh fields hold the "
            "photos' colours; show them with 'Standard'.")
    for width in (150.0, 220.0, 400.0):
        lines = ui.wrap_text(text, width, measure)
        assert len(lines) >= 2 and " ".join(lines) == text
        assert all(measure(l) <= width for l in lines)


def test_wrap_text_splits_long_paths():
    import importlib

    import conftest

    ui = importlib.import_module(conftest.ADDON_MODULE + ".runtime.text")
    measure = len  # one pixel per character
    path = "/very/long/folder/name/that/does/not/fit/field.neumesh"
    lines = ui.wrap_text("not found: " + path, 20, measure)
    assert all(len(l) <= 20 for l in lines) and "".join(lines).replace("not found:", "") == path
    assert lines[1].endswith("/")  # cut after a slash where there is one
    assert ui.wrap_text("a b", 10, measure) == ["a b"] and ui.wrap_text("", 10, measure) == [""]


# ------------------------------------------------------------------------------------ panels (6)
def test_load_field_fills_the_training_mesh(addon, trained_field):
    assert bpy.context.scene.neumesh.train_object is None
    assert bpy.ops.neumesh.load_field(filepath=trained_field, new_object=True) == {"FINISHED"}
    obj = bpy.context.active_object
    assert bpy.context.scene.neumesh.train_object == obj
    # loading onto an existing mesh with the right vertex count does the same
    other = addon.scene.sync.new_mesh_object("copy", addon.scene.sync.mesh_vertices(obj.data),
                                       addon.scene.sync.mesh_triangles(obj.data))
    bpy.context.view_layer.objects.active = other
    assert bpy.ops.neumesh.load_field(filepath=trained_field) == {"FINISHED"}
    assert bpy.context.scene.neumesh.train_object == other


def test_scaffold_is_explained_where_it_is_seen(addon):
    help_words = ("mesh the field is stored on", "mesh whose field is trained")
    texts = [
        bpy.types.NEUMESH_PT_scaffold.bl_description,
        bpy.ops.neumesh.build_scaffold.get_rna_type().description,
        bpy.ops.neumesh.import_mesh.get_rna_type().description,
        bpy.types.Scene.bl_rna.properties["neumesh"].fixed_type.properties["scaffold_method"].description,
        bpy.types.Scene.bl_rna.properties["neumesh"].fixed_type.properties["train_object"].description,
    ]
    for t in texts:
        assert any(w in t for w in help_words), t


def test_training_status_lines_are_short(addon):
    job = addon.train.worker.TrainJob(dataset_path="", field_path="/tmp/x.neumesh", steps=2000)
    job.state, job.step, job.loss, job.psnr, job.rays_per_sec, job.eta_s = "TRAINING", 120, 0.0123, 23.4, 40100, 4000
    assert job.status_lines() == ["Step 120/2000 (6%)", "Loss 0.0123, PSNR 23.40 dB", "40.1k rays/s, ETA 1 h 06 min"]
    assert max(len(l) for l in job.status_lines()) <= 30


# ------------------------------------------------------------------------------------ wording (7)
def test_missing_dependency_message_has_one_neumesh(addon, monkeypatch):
    monkeypatch.setattr(addon.runtime.deps, "missing_required", lambda statuses=None: ["torch"])
    monkeypatch.setattr(addon.runtime.core, "_nm", None)
    with pytest.raises(RuntimeError) as exc:
        bpy.ops.neumesh.import_mesh(filepath="/nonexistent.ply")
    msg = str(exc.value)
    assert "NeuMesh: missing Python package(s) torch" in msg and msg.count("NeuMesh") == 2  # + "> NeuMesh"
    assert "NeuMesh: NeuMesh" not in msg and "Install dependencies" in msg
    prefixed = addon.render.engine.prefixed
    assert prefixed("NeuMesh: x") == "NeuMesh: x" and prefixed("x") == "NeuMesh: x"


def test_relative_field_path_in_unsaved_file_keeps_its_slashes(addon, trained_field):
    V, F = grid_mesh()
    obj = addon.scene.sync.new_mesh_object("grid", V, F)
    obj.neumesh.field_path = "//field.neumesh"
    add_camera((0, -3, 0.5))
    bpy.context.scene.render.engine = "NEUMESH"
    bpy.context.scene.render.resolution_x = bpy.context.scene.render.resolution_y = 16
    with pytest.raises(FileNotFoundError) as exc:
        addon.render.field_cache.collect(bpy.context.evaluated_depsgraph_get())
    msg = str(exc.value)
    assert "not found: //field.neumesh" in msg and "has not been saved" in msg
    try:
        bpy.ops.render.render()
    except RuntimeError:
        pass
    assert "//field.neumesh" in addon.render.engine.LAST_ERROR["message"]
    assert addon.render.engine.LAST_ERROR["message"].startswith("NeuMesh: object 'grid'")


# ------------------------------------------------------------------------------------ paths (3)
def _object_with_field(addon, field):
    V, F = grid_mesh()
    obj = addon.scene.sync.new_mesh_object("grid", V, F)
    addon.scene.props.set_field_path(obj, str(field))
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
    assert addon.scene.props.field_abspath(o) == str(tmp_path / "moved" / "fields" / "f.neumesh")


def test_save_copy_leaves_the_open_file_pointing_at_its_field(addon, tmp_path):
    field = _placeholder(tmp_path / "fields" / "f.neumesh")
    obj = _object_with_field(addon, field)
    (tmp_path / "a").mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "a" / "scene.blend"))
    (tmp_path / "b" / "c").mkdir(parents=True)
    copy = tmp_path / "b" / "c" / "copy.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(copy), copy=True)
    assert obj.neumesh.field_path == "//../fields/f.neumesh"  # the open file is still in a/
    assert addon.scene.props.field_abspath(obj) == str(field)
    bpy.ops.wm.open_mainfile(filepath=str(copy))
    o = bpy.data.objects["grid"]
    assert o.neumesh.field_path == "//../../fields/f.neumesh"
    assert addon.scene.props.field_abspath(o) == str(field)


def test_save_as_when_blender_does_not_say_where(addon, tmp_path, monkeypatch):
    """Blender 3.x calls save_pre with (None, None): the add-on keeps the path relative to the old
    folder, records where the file is, and repairs the path after the save and on opening."""
    props = addon.scene.props
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
