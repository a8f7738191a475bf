"""Blender state -> numpy (no torch needed): evaluated vertices, topology errors, groups, UVs,
cameras, field paths stored relative to the .blend."""
from __future__ import annotations


import bpy
import numpy as np
import pytest

from helpers import add_armature_bend, add_camera, grid_mesh, manual_K_c2w


def _grid_object(addon, nx=12, ny=4):
    V, F = grid_mesh(nx, ny)
    return addon.scene.sync.new_mesh_object("grid", V, F), V, F


def test_new_mesh_object_keeps_vertex_order_and_triangles(addon):
    obj, V, F = _grid_object(addon)
    assert np.array_equal(addon.scene.sync.mesh_vertices(obj.data), V)
    assert np.array_equal(addon.scene.sync.mesh_triangles(obj.data), F)


def test_evaluated_world_vertices_follow_armature_and_matrix_world(addon):
    obj, V, _ = _grid_object(addon)
    obj.location = (0.5, -1.0, 2.0)
    obj.rotation_euler = (0, 0, np.pi / 2)
    bpy.context.view_layer.update()
    _arm, idx_root, idx_tip = add_armature_bend(obj, split_x=0.0, angle_deg=60.0)
    dg = bpy.context.evaluated_depsgraph_get()
    W = addon.scene.sync.evaluated_world_vertices(obj, dg, expected_count=len(V))
    M = np.array(obj.matrix_world)
    rest_world = V @ M[:3, :3].T + M[:3, 3]
    # the root half only gets matrix_world, the tip half is bent by the bone
    np.testing.assert_allclose(W[idx_root], rest_world[idx_root], atol=1e-5)
    moved = np.linalg.norm(W[idx_tip] - rest_world[idx_tip], axis=1)
    assert moved.max() > 0.2
    # a bend about the bone's local Y keeps distances to the joint (rigid), so lengths are preserved
    joint = M[:3, :3] @ np.zeros(3) + M[:3, 3]
    np.testing.assert_allclose(np.linalg.norm(W[idx_tip] - joint, axis=1),
                               np.linalg.norm(rest_world[idx_tip] - joint, axis=1), atol=1e-4)


def test_shape_keys_move_vertices(addon):
    obj, V, _ = _grid_object(addon)
    obj.shape_key_add(name="Basis")
    sk = obj.shape_key_add(name="lift")
    co = V.copy()
    co[:, 2] += 0.3
    sk.data.foreach_set("co", co.ravel())
    sk.value = 0.5
    dg = bpy.context.evaluated_depsgraph_get()
    W = addon.scene.sync.evaluated_world_vertices(obj, dg, expected_count=len(V))
    np.testing.assert_allclose(W[:, 2], V[:, 2] + 0.15, atol=1e-6)


def test_topology_change_names_the_modifier(addon):
    obj, V, _ = _grid_object(addon)
    mod = obj.modifiers.new("MySubdiv", "SUBSURF")
    mod.levels = mod.render_levels = 1
    dg = bpy.context.evaluated_depsgraph_get()
    with pytest.raises(addon.scene.sync.TopologyError, match=r"'MySubdiv' \(Subsurf\)") as ei:
        addon.scene.sync.evaluated_world_vertices(obj, dg, expected_count=len(V))
    assert f"field has {len(V)}" in str(ei.value)
    # disabled for render -> fine for F12, still an error for the viewport
    mod.show_render = False
    dg = bpy.context.evaluated_depsgraph_get()
    with pytest.raises(addon.scene.sync.TopologyError):
        addon.scene.sync.evaluated_world_vertices(obj, dg, expected_count=len(V), for_render=False)


def test_same_count_but_reordering_modifier_is_refused(addon):
    obj, V, _ = _grid_object(addon)
    obj.modifiers.new("Dec", "DECIMATE").ratio = 1.0  # keeps the count, may still reorder
    dg = bpy.context.evaluated_depsgraph_get()
    with pytest.raises(addon.scene.sync.TopologyError, match="'Dec'"):
        addon.scene.sync.evaluated_world_vertices(obj, dg, expected_count=len(V))


def test_vertex_count_mismatch_without_modifier(addon):
    obj, V, _ = _grid_object(addon)
    dg = bpy.context.evaluated_depsgraph_get()
    with pytest.raises(addon.scene.sync.TopologyError, match="edited"):
        addon.scene.sync.evaluated_world_vertices(obj, dg, expected_count=len(V) + 1)


def test_vertex_groups_and_uvs_to_numpy(addon):
    obj, V, F = _grid_object(addon)
    g = obj.vertex_groups.new(name="sel")
    want = [1, 5, 7, 20]
    g.add(want, 0.7, "REPLACE")
    g.add([3], 0.0, "REPLACE")
    assert addon.scene.sync.vertex_group_indices(obj, "sel").tolist() == want
    w = addon.scene.sync.vertex_group_weights(obj, "sel")
    assert w.shape == (len(V),) and np.isclose(w[5], 0.7) and w[0] == 0
    with pytest.raises(KeyError, match="nope"):
        addon.scene.sync.vertex_group_indices(obj, "nope")
    uvl = obj.data.uv_layers.new(name="UVMap")
    n = len(obj.data.loops)
    vi = np.empty(n, np.int32)
    obj.data.loops.foreach_get("vertex_index", vi)
    uv_set = V[vi][:, :2] * 0.5 + 0.5
    uvl.data.foreach_set("uv", uv_set.astype(np.float32).ravel())
    np.testing.assert_allclose(addon.scene.sync.uv_loops(obj.data, "UVMap"), uv_set, atol=1e-6)
    np.testing.assert_allclose(addon.scene.sync.uv_vertices(obj.data), V[:, :2] * 0.5 + 0.5, atol=1e-6)


def test_camera_K_matches_lens_and_roundtrips(addon):
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 80, 60, 100
    cam = add_camera((2.0, -3.0, 1.5), lens=40.0)
    dg = bpy.context.evaluated_depsgraph_get()
    K, c2w, W, H = addon.scene.camera.camera_K_c2w(cam, scene, dg)
    K_ref, c2w_ref = manual_K_c2w(cam, 80, 60)
    assert (W, H) == (80, 60)
    np.testing.assert_allclose(K, K_ref, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(c2w, c2w_ref, atol=1e-5)
    # OpenCV camera looks down +z: the target (origin) is in front, near the optical axis
    p_cam = np.linalg.inv(c2w) @ np.array([0, 0, 0, 1.0])
    assert p_cam[2] > 0 and abs(p_cam[0]) < 1e-4 and abs(p_cam[1]) < 1e-4
    # K with an off-centre principal point and a non-square image survives Blender's camera model
    K2 = np.array([[70.0, 0, 37.0], [0, 70.0, 33.5], [0, 0, 1]], np.float32)
    c2w2 = c2w_ref.copy()
    c2w2[:3, 3] += (0.1, 0.2, 0.3)
    cam2 = add_camera((0, 0, 1), name="cam2")
    addon.scene.camera.set_camera_from_K(cam2, K2, c2w2, 80, 60)
    dg = bpy.context.evaluated_depsgraph_get()
    K3, c2w3, _, _ = addon.scene.camera.camera_K_c2w(cam2, scene, dg)
    np.testing.assert_allclose(K3, K2, atol=1e-3)
    np.testing.assert_allclose(c2w3, c2w2, atol=1e-5)


def test_field_path_is_stored_relative_and_survives_save_reload(addon, tmp_path):
    field = tmp_path / "fields" / "thing.neumesh"
    field.parent.mkdir()
    field.write_bytes(b"placeholder")
    obj, _, _ = _grid_object(addon)
    addon.scene.props.set_field_path(obj, str(field))
    assert obj.neumesh.field_path == str(field)  # unsaved .blend: absolute
    blend = tmp_path / "scenes" / "a.blend"
    blend.parent.mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    assert bpy.data.objects["grid"].neumesh.field_path == "//../fields/thing.neumesh"
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    o = bpy.data.objects["grid"]
    assert o.neumesh.field_path.startswith("//")
    assert addon.scene.props.field_abspath(o) == str(field)
    # saving somewhere else rewrites the relative path so it still points at the same file
    blend2 = tmp_path / "elsewhere" / "deeper" / "b.blend"
    blend2.parent.mkdir(parents=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(blend2))
    bpy.ops.wm.open_mainfile(filepath=str(blend2))
    o = bpy.data.objects["grid"]
    assert o.neumesh.field_path == "//../../fields/thing.neumesh"
    assert addon.scene.props.field_abspath(o) == str(field)
