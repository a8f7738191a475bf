"""Topology edits keep the field: delete, separate, duplicate, join, subdivide, save and reload.

Vertex ids and rest positions travel as point attributes (addon/identity.py); the renderer maps mesh
vertices to field vertices through them.  Each test compares F12 with the field's image before the
edit (or, for the moved duplicate, the core's render from a moved camera).  F12 images are read
back as display values (EXR decoded to sRGB, clipped to [0, 1]).
"""
from __future__ import annotations

import os
import shutil

import bmesh
import bpy
import numpy as np
import pytest

from helpers import add_camera, exact_colour_settings, f12_srgb, manual_K_c2w

W, H = 48, 40


@pytest.fixture(scope="module")
def second_field(tiny_dataset, tmp_path_factory):
    """Another field trained on the same scene (other ray batches, more steps): other codes and
    another decoder."""
    import neumesh_core as nm

    field = nm.create_field(nm.load_mesh(os.path.join(tiny_dataset, "mesh.ply")), nm.FieldConfig())
    nm.train(field, nm.load_scene(tiny_dataset), nm.TrainConfig(steps=60, rays_per_batch=512, seed=7))
    path = str(tmp_path_factory.mktemp("second") / "second.neumesh")
    nm.save_field(field, path)
    return path


def _load(src, tmp_path, name):
    path = str(tmp_path / f"{name}.neumesh")
    shutil.copy(src, path)
    assert bpy.ops.neumesh.load_field(filepath=path, new_object=True) == {"FINISHED"}
    obj = bpy.context.active_object
    obj.name = name
    return obj, path


def _scene(cam_x=0.0, distance=4.6):
    cam = add_camera((cam_x, -distance, 0.8), look_at=(cam_x, 0, 0), lens=35.0)
    exact_colour_settings(bpy.context.scene, W, H)
    bpy.context.scene.render.engine = "NEUMESH"
    return cam


def _f12(path):
    return np.clip(f12_srgb(path), 0, 1)


def _psnr(a, b):
    return float(-10 * np.log10(max(np.mean((a - b) ** 2), 1e-12)))


def _select_only(obj):
    for o in bpy.context.view_layer.objects:
        o.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj


def _delete_vertices(obj, indices):
    bm = bmesh.new()
    bm.from_mesh(obj.data)
    bm.verts.ensure_lookup_table()
    bmesh.ops.delete(bm, geom=[bm.verts[int(i)] for i in indices], context="VERTS")
    bm.to_mesh(obj.data)
    bm.free()
    obj.data.update()


def test_attach_writes_vertex_ids_and_the_scene_knows_the_field(addon, trained_field, tmp_path):
    obj, path = _load(trained_field, tmp_path, "A")
    vid, rest, key = addon.scene.identity.read(obj.data)
    assert np.array_equal(vid, np.arange(len(obj.data.vertices)))
    field = addon.render.field_cache.get_field(obj.name_full, path)
    assert np.allclose(rest, field.rest_vertices.numpy(), atol=1e-6)
    assert (key == addon.scene.identity.key_of(field)).all()
    assert addon.scene.identity.lookup(bpy.context.scene, int(key[0])) == path


def test_delete_half_renders_the_kept_half_as_before(addon, trained_field, tmp_path):
    obj, path = _load(trained_field, tmp_path, "A")
    cam = _scene()
    before = _f12(tmp_path / "a.exr")
    xs = np.array([v.co.x for v in obj.data.vertices])
    _delete_vertices(obj, np.nonzero(xs > 0.05)[0])          # the camera's right half
    after = _f12(tmp_path / "b.exr")
    K, c2w = manual_K_c2w(cam, W, H)
    cols = np.arange(W)
    left, right = cols < W // 2 - 4, cols > W // 2 + 6
    assert np.abs(after[:, left] - before[:, left]).max() < 0.02            # the kept half as before
    assert np.abs(after[:, right] - 1.0).max() < 0.02                       # the deleted half is gone
    assert (np.abs(before[:, right] - 1.0).max(-1) > 0.2).sum() > 50        # (it was there before)


def test_separate_into_two_objects_renders_the_original_image(addon, trained_field, tmp_path):
    obj, path = _load(trained_field, tmp_path, "A")
    _scene()
    before = _f12(tmp_path / "a.exr")
    _select_only(obj)
    bpy.ops.object.mode_set(mode="EDIT")
    bm = bmesh.from_edit_mesh(obj.data)
    for v in bm.verts:
        v.select = v.co.z > 0.1
    bm.select_flush(True)
    bmesh.update_edit_mesh(obj.data)
    bpy.ops.mesh.separate(type="SELECTED")
    bpy.ops.object.mode_set(mode="OBJECT")
    parts = [o for o in bpy.context.scene.objects if o.type == "MESH"]
    assert len(parts) == 2 and all(addon.scene.props.field_abspath(o) == path for o in parts)
    after = _f12(tmp_path / "b.exr")
    p = _psnr(after, before)
    print(f"separate: {p:.1f} dB against the unseparated render")
    assert p > 50.0   # identical up to float rounding


def test_a_moved_duplicate_renders_like_the_original_seen_from_a_moved_camera(addon, trained_field, tmp_path):
    import neumesh_core as nm

    obj, path = _load(trained_field, tmp_path, "A")
    cam = _scene()
    _select_only(obj)
    bpy.ops.object.duplicate()
    copy = bpy.context.active_object
    assert copy != obj and addon.scene.props.field_abspath(copy) == path
    copy.location.z += 0.3
    obj.neumesh.enabled = False                # only the copy renders
    bpy.context.view_layer.update()
    after = _f12(tmp_path / "b.exr")
    K, c2w = manual_K_c2w(cam, W, H)
    moved = c2w.copy()
    moved[2, 3] -= 0.3
    want = np.clip(nm.render_camera(nm.load_field(path), K, moved, W, H).rgb, 0, 1)
    assert np.abs(after - want).max() < 2e-3


def test_joined_fields_render_as_they_did_apart(addon, trained_field, second_field, tmp_path):
    a, _ = _load(trained_field, tmp_path, "A")
    b, _ = _load(second_field, tmp_path, "B")
    b.location.x = 2.4
    _scene(cam_x=1.2, distance=6.0)
    bpy.context.view_layer.update()
    apart = _f12(tmp_path / "a.exr")
    for o in bpy.context.view_layer.objects:
        o.select_set(o in (a, b))
    bpy.context.view_layer.objects.active = a
    bpy.ops.object.join()
    joined = [o for o in bpy.context.scene.objects if o.type == "MESH"]
    assert len(joined) == 1
    keys = np.unique(addon.scene.identity.read(joined[0].data)[2])
    assert len(keys) == 2                       # one mesh, two fields
    together = _f12(tmp_path / "b.exr")
    assert np.abs(together - apart).max() < 2e-3


def test_subdivision_surface_renders_close_to_the_original(addon, trained_field, tmp_path):
    obj, _ = _load(trained_field, tmp_path, "A")
    _scene()
    before = _f12(tmp_path / "a.exr")
    obj.modifiers.new("Subdivision", "SUBSURF").levels = 1
    bpy.context.view_layer.update()
    after = _f12(tmp_path / "b.exr")
    p = _psnr(after, before)
    print(f"subdivision surface level 1: {p:.1f} dB against the original render")
    assert p > 35.0   # the new vertices' codes are interpolated (see identity.py)
    assert addon.render.field_cache.STATS.get("remaps", 0) > 0


def test_save_and_reload_render_the_same_pixels(addon, trained_field, second_field, tmp_path):
    a, _ = _load(trained_field, tmp_path, "A")
    b, _ = _load(second_field, tmp_path, "B")
    b.location.x = 2.4
    _scene(cam_x=1.2, distance=6.0)
    for o in bpy.context.view_layer.objects:
        o.select_set(o in (a, b))
    bpy.context.view_layer.objects.active = a
    bpy.ops.object.join()
    _delete_vertices(bpy.context.active_object, [0, 1, 2, 3])
    before = _f12(tmp_path / "a.exr")
    blend = str(tmp_path / "scene.blend")
    bpy.ops.wm.save_as_mainfile(filepath=blend)
    addon.render.field_cache.clear_cache()
    bpy.ops.wm.open_mainfile(filepath=blend)
    after = _f12(tmp_path / "b.exr")
    assert np.abs(after - before).max() < 1e-5
