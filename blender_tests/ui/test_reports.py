"""What the add-on says: Import Mesh and Load Field report what they loaded (and check the field
against the mesh); their file browsers start where the artist works and list only their files;
Cancel painting after Apply says what it does and the buttons are enabled only when they do
something; a field without semantics names the panel button that makes them; Import Cameras of a
capture names the photos training holds out, and the core's "frames have no image" warning arrives
as a Blender report, not a Python warning; the sidebar says which pass the Rendered viewport shows."""
from __future__ import annotations

import os
import shutil
import types

import bpy
import numpy as np
import pytest

from helpers import add_camera, field_in_camera, manual_K_c2w, record_panel

W, H = 48, 40


def _infos(out: str) -> list[str]:
    return [line for line in out.splitlines() if line.startswith(("Info: NeuMesh", "Warning: NeuMesh"))]


# ------------------------------------------------------------------------------ Import Mesh, Load Field
def test_import_mesh_reports_what_it_read(addon, tiny_dataset, capfd):
    path = os.path.join(tiny_dataset, "mesh.ply")
    capfd.readouterr()
    assert bpy.ops.neumesh.import_mesh(filepath=path) == {"FINISHED"}
    obj = bpy.context.active_object
    nv, nf = len(obj.data.vertices), len(obj.data.polygons)
    size = addon.runtime.text.file_size(path)
    assert _infos(capfd.readouterr().out) == [
        f"Info: NeuMesh: imported mesh.ply ({size}): {nv:,} vertices, {nf:,} faces as '{obj.name}', the Training mesh"]
    with pytest.raises(RuntimeError, match="cannot load mesh .*not found"):
        bpy.ops.neumesh.import_mesh(filepath=os.path.join(tiny_dataset, "none.ply"))


def test_import_mesh_builds_big_meshes_with_foreach_set(addon, tmp_path):
    """The object is made with vertices.add + foreach_set (sync.new_mesh_object), not vertex by vertex:
    a 90,000-vertex grid comes in whole, in the file's order."""
    import neumesh_core as nm

    n = 300
    xs, ys = np.meshgrid(np.arange(n, dtype=np.float32), np.arange(n, dtype=np.float32))
    V = np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n, np.float32)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    path = str(tmp_path / "grid.ply")
    nm.save_mesh(nm.Mesh(V, F), path)
    calls = []
    real = addon.scene.sync.new_mesh_object
    addon.scene.sync.new_mesh_object = lambda *a, **k: calls.append(len(a[1])) or real(*a, **k)
    try:
        assert bpy.ops.neumesh.import_mesh(filepath=path) == {"FINISHED"}
    finally:
        addon.scene.sync.new_mesh_object = real
    assert calls == [n * n]
    obj = bpy.context.active_object
    np.testing.assert_array_equal(addon.scene.sync.mesh_vertices(obj.data), V)
    assert np.array_equal(addon.scene.sync.mesh_triangles(obj.data), F)


def test_load_field_reports_the_field_and_its_check_against_the_mesh(addon, trained_field, tmp_path, capfd):
    import neumesh_core as nm

    field = nm.load_field(trained_field)
    nv, nf = field.num_vertices, len(field.faces)
    head = f"loaded blob.neumesh ({addon.runtime.text.file_size(trained_field)}): {nv:,} vertices, {nf:,} faces"
    capfd.readouterr()
    assert bpy.ops.neumesh.load_field(filepath=trained_field, new_object=True) == {"FINISHED"}
    obj = bpy.context.active_object
    assert _infos(capfd.readouterr().out) == [
        f"Info: NeuMesh: {head}, as the new object '{obj.name}' (the field's own scaffold)"]
    # the render uses the field read here: no second read of the file
    loads = addon.render.field_cache.STATS["loads"]
    assert addon.render.field_cache.get_field(obj.name_full, trained_field) is not None
    assert addon.render.field_cache.STATS["loads"] == loads
    # onto a copy of its mesh: the vertices match
    sync = addon.scene.sync
    copy = sync.new_mesh_object("copy", sync.mesh_vertices(obj.data), sync.mesh_triangles(obj.data))
    bpy.context.view_layer.objects.active = copy
    capfd.readouterr()
    assert bpy.ops.neumesh.load_field(filepath=trained_field) == {"FINISHED"}
    assert _infos(capfd.readouterr().out) == [
        f"Info: NeuMesh: {head}, on 'copy': its {nv:,} vertices match the field's scaffold"]
    # onto a mesh with the same count whose vertices lie elsewhere: a warning that says so
    moved = sync.new_mesh_object("moved", sync.mesh_vertices(obj.data) * 1.5, sync.mesh_triangles(obj.data))
    bpy.context.view_layer.objects.active = moved
    capfd.readouterr()
    assert bpy.ops.neumesh.load_field(filepath=trained_field) == {"FINISHED"}
    (line,) = _infos(capfd.readouterr().out)
    assert line.startswith(f"Warning: NeuMesh: {head}, on 'moved': its vertices lie up to ") and "New object" in line


def test_file_browsers_start_where_the_artist_works_and_list_their_files(addon, trained_field, tiny_dataset,
                                                                        tmp_path):
    imports = addon.train.imports
    ops = bpy.ops.neumesh
    assert ops.import_mesh.get_rna_type().properties["filter_glob"].default == "*.ply;*.obj"
    assert ops.load_field.get_rna_type().properties["filter_glob"].default == "*.neumesh"
    me = types.SimpleNamespace()
    ctx = bpy.context
    # nothing known: Blender's own default
    assert imports.NEUMESH_OT_import_mesh.start_in(me, ctx) == ""
    # the .blend's folder, then the dataset's
    (tmp_path / "project").mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "project" / "a.blend"))
    assert imports.NEUMESH_OT_import_mesh.start_in(me, ctx) == str(tmp_path / "project") + os.sep
    ctx.scene.neumesh.dataset_path = tiny_dataset
    assert imports.NEUMESH_OT_import_mesh.start_in(me, ctx) == os.path.join(tiny_dataset, "")
    assert imports.NEUMESH_OT_load_field.start_in(me, ctx) == os.path.join(tiny_dataset, "")
    # Load Field: the active object's field folder first
    assert ops.load_field(filepath=trained_field, new_object=True) == {"FINISHED"}
    assert imports.NEUMESH_OT_load_field.start_in(me, ctx) == os.path.join(os.path.dirname(trained_field), "")
    assert imports.start_folder("", str(tmp_path / "gone"), trained_field) == \
        os.path.join(os.path.dirname(trained_field), "")


# ------------------------------------------------------------------------------ painting: Apply, Cancel
def _paint_scene(addon, tmp_path, trained_field):
    src = str(tmp_path / "A.neumesh")
    shutil.copy(trained_field, src)
    return field_in_camera(src, W, H)


def _stroke(addon, rows, cols, colour):
    paint = addon.edit.paint
    img = bpy.data.images[paint.PAINT_IMAGE]
    px = paint._image_pixels(img)
    px[rows[0]:rows[1], cols[0]:cols[1], :3] = colour
    paint._set_pixels(img, px)


def _buttons(addon):
    rec = record_panel(bpy.types.NEUMESH_PT_paint, bpy.context)
    return rec.button("neumesh.apply_paint"), rec.button("neumesh.cancel_paint"), " ".join(rec.labels)


def test_cancel_after_apply_says_the_paint_stays_and_buttons_do_something(addon, trained_field, tmp_path, capfd):
    obj = _paint_scene(addon, tmp_path, trained_field)
    (_, apply_on), (cancel_text, cancel_on), _ = _buttons(addon)
    assert not apply_on and not cancel_on                      # no paint image: nothing to apply or cancel
    assert bpy.ops.neumesh.paint_view() == {"FINISHED"}
    (_, apply_on), (cancel_text, cancel_on), _ = _buttons(addon)
    assert not apply_on and cancel_on and cancel_text == "Cancel painting"   # nothing painted yet
    _stroke(addon, (16, 22), (18, 30), (0.05, 0.1, 0.9))
    assert _buttons(addon)[0] == ("", True)                    # a stroke to apply
    assert bpy.ops.neumesh.apply_paint() == {"FINISHED"}
    edited = addon.scene.props.field_abspath(obj)
    assert edited.endswith("A.edit-001.neumesh")
    (_, apply_on), (cancel_text, cancel_on), labels = _buttons(addon)
    assert not apply_on and cancel_on and cancel_text == "Close painting"
    assert "Applied; paint more to apply again" in labels
    # the Image Editor's header says the same
    rec = addon.edit.paint
    header = __import__("helpers").Recorder()
    rec.draw_image_header(types.SimpleNamespace(layout=header),
                          types.SimpleNamespace(space_data=types.SimpleNamespace(
                              type="IMAGE_EDITOR", image=bpy.data.images[rec.PAINT_IMAGE])))
    assert header.button("neumesh.apply_paint") == ("Apply", False)
    assert header.button("neumesh.cancel_paint") == ("Close", True)
    # painting again makes Apply do something again
    _stroke(addon, (18, 24), (20, 28), (0.9, 0.8, 0.1))
    assert _buttons(addon)[0] == ("", True)
    capfd.readouterr()
    assert bpy.ops.neumesh.cancel_paint() == {"FINISHED"}
    out = capfd.readouterr().out
    assert ("Info: NeuMesh: painting closed; the strokes not applied were discarded, the paint applied before "
            "stays in the fields (Undo edit takes it out)") in out, out
    assert "nothing was applied" not in out
    assert addon.scene.props.field_abspath(obj) == edited       # the applied paint stays


def test_cancel_without_apply_says_nothing_was_applied(addon, trained_field, tmp_path, capfd):
    obj = _paint_scene(addon, tmp_path, trained_field)
    assert bpy.ops.neumesh.paint_view() == {"FINISHED"}
    _stroke(addon, (16, 22), (18, 30), (1.0, 0.0, 0.0))
    capfd.readouterr()
    assert bpy.ops.neumesh.cancel_paint() == {"FINISHED"}
    assert "Info: NeuMesh: painting cancelled; nothing was applied" in capfd.readouterr().out
    assert addon.scene.props.field_abspath(obj) == str(tmp_path / "A.neumesh")
    assert bpy.ops.neumesh.paint_view() == {"FINISHED"}
    capfd.readouterr()
    assert bpy.ops.neumesh.cancel_paint() == {"FINISHED"}
    assert "Info: NeuMesh: painting closed; nothing was painted, nothing was applied" in capfd.readouterr().out


# ------------------------------------------------------------------------------ semantics
def test_a_field_without_semantics_names_the_panel_button(addon, trained_field):
    assert bpy.ops.neumesh.load_field(filepath=trained_field, new_object=True) == {"FINISHED"}
    obj = bpy.context.active_object
    with pytest.raises(RuntimeError) as exc:
        bpy.ops.neumesh.semantic_colours()
    msg = str(exc.value)
    assert f"'{obj.name}' has no semantic codes yet: press Distill semantics (Edit field > Semantics)" in msg
    assert "neumesh semantics" not in msg and "--field" not in msg


# ------------------------------------------------------------------------------ Import Cameras of a capture
def test_import_cameras_of_a_capture_names_the_held_out_photos_and_reports_missing_frames(addon, tmp_path, capfd,
                                                                                        monkeypatch):
    from tests.data.test_capture import write_transforms

    import neumesh_core as nm

    monkeypatch.setenv("NEUMESH_CACHE", str(tmp_path / "cache"))
    root = str(tmp_path / "cap")
    write_transforms(root, n=18, missing=(3, 5))
    capfd.readouterr()
    assert bpy.ops.neumesh.import_dataset(directory=root) == {"FINISHED"}
    out, err = capfd.readouterr()
    coll = bpy.data.collections["NeuMesh Dataset"]
    cams = sorted((o for o in coll.objects if o.type == "CAMERA"), key=lambda o: o["neumesh_index"])
    assert len(cams) == 16                                              # every photo that exists
    with pytest.warns(UserWarning, match="have no image"):   # the core called directly warns
        cap = nm.read_capture(root)
    train = set(nm.training_photos(cap).names)
    held = [o for o in cams if o["neumesh_held_out"]]
    assert [o["neumesh_photo"] for o in held] == [n for n in cap.names if n not in train] and len(held) == 2
    names = ", ".join(os.path.basename(o["neumesh_photo"]) for o in held)
    assert f"training holds out 2 of the 16 photos for evaluation (their cameras have 'neumesh_held_out'): {names}" \
        in out, out
    # the core's warning is a Blender report, once, and no Python warning with a source line
    assert out.count("2 of 18 frames have no image and were skipped") == 1, out
    assert "Warning: NeuMesh: " + os.path.join(root, "transforms.json") + ": 2 of 18 frames" in out, out
    assert "UserWarning" not in err and "warnings.warn" not in err, err


def test_the_import_cameras_browser_offers_no_split_for_a_capture(addon, tiny_dataset, tmp_path):
    from tests.data.test_capture import write_transforms

    ops = addon.train.operators
    root = str(tmp_path / "cap")
    write_transforms(root, n=3)
    assert ops.looks_like_capture(root) and not ops.looks_like_capture(tiny_dataset)
    assert not ops.looks_like_capture(str(tmp_path / "nothing here"))
    assert bpy.ops.neumesh.import_dataset.get_rna_type().name == "Import Cameras"   # the browser's button

    def drawn(folder):
        from helpers import Recorder

        rec = Recorder()
        me = types.SimpleNamespace(layout=rec, directory=folder)
        ctx = types.SimpleNamespace(space_data=types.SimpleNamespace(params=types.SimpleNamespace(
            directory=folder.encode())), region=None, preferences=bpy.context.preferences)
        ops.NEUMESH_OT_import_dataset.draw(me, ctx)
        return rec.props, " ".join(rec.labels)

    shown, labels = drawn(root)
    assert "split" not in shown and "downscale" not in shown and "every photo becomes a camera" in labels
    shown, labels = drawn(tiny_dataset)
    assert "split" in shown and "downscale" in shown and labels == ""


# ------------------------------------------------------------------------------ the viewport's passes
def test_the_sidebar_says_which_pass_the_rendered_viewport_shows(addon, trained_field):
    text = addon.ui.panels.viewport_level_text
    assert text(None) == "" and text((None, 2, False, None)) == ""
    assert text((None, 2, True, None)) == "Viewport preview: rendering its first pass"
    assert text((4, 2, True, 1.25)) == "Viewport preview: 1/4 resolution (1.2 s), finest 1/2 to come"
    assert text((2, 2, True, 3.0)) == "Viewport preview: 1/2 resolution (3.0 s), rendering the changed view"
    assert text((2, 2, False, 19.0)) == ("Viewport preview: 1/2 resolution (19.0 s), the finest "
                                         "(Preferences > Preview ends at)")
    assert text((1, 1, False, None)) == "Viewport preview: full resolution, the finest (Preferences > Preview ends at)"
    # what a real preview reports, level by level
    assert bpy.ops.neumesh.load_field(filepath=trained_field, new_object=True) == {"FINISHED"}
    cam = add_camera((0.0, -4.6, 0.8), lens=35.0)
    items = addon.render.field_cache.collect(bpy.context.evaluated_depsgraph_get(), for_render=False)
    K, c2w = manual_K_c2w(cam, 64, 48)
    pv = addon.render.preview.PreviewRenderer(divisors=(4, 2))
    try:
        assert pv.progress() == (None, 2, False, None)
        serial = pv.request(items, K, c2w, 64, 48)
        assert pv.wait(serial, divisor=2, timeout=60), pv.error
        shown, finest, busy, seconds = pv.progress()
        assert (shown, finest, busy) == (2, 2, False) and seconds == pv.timings[-1][1] > 0
        assert text(pv.progress()).startswith("Viewport preview: 1/2 resolution (")
    finally:
        pv.stop()
