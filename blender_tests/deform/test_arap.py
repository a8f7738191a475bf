"""ARAP deform in Blender (addon/deform/arap.py): Anchor/Handle vertex groups, one Empty per handle group,
the solve written into the live shape key on depsgraph updates and frame changes, Apply as shape key."""
from __future__ import annotations

import math

import bpy
import numpy as np
import pytest

from helpers import add_camera, exact_colour_settings, grid_mesh, manual_K_c2w


def _evaluated(obj):
    dg = bpy.context.evaluated_depsgraph_get()
    me = obj.evaluated_get(dg).data
    v = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", v)
    return v.reshape(-1, 3)


def _group(obj, name, idx):
    vg = obj.vertex_groups.new(name=name)
    vg.add([int(i) for i in idx], 1.0, "REPLACE")
    return vg


def _bar(addon, nx=16, ny=4):
    V, F = grid_mesh(nx, ny, size=(1.6, 0.4))
    obj = addon.scene.sync.new_mesh_object("bar", V, F)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    anchors = np.nonzero(V[:, 0] < -0.6)[0]
    handles = np.nonzero(V[:, 0] > 0.6)[0]
    _group(obj, "Anchor", anchors)
    _group(obj, "Handle", handles)
    return obj, V, anchors, handles


def _empty(obj):
    names = [n for n in obj.neumesh_arap.handle_empties.split("\n") if n]
    assert len(names) == 1
    return bpy.data.objects[names[0]]


def test_moving_the_empty_moves_handles_and_keeps_anchors(addon):
    obj, V, anchors, handles = _bar(addon)
    assert bpy.ops.neumesh.arap_add() == {"FINISHED"}
    e = _empty(obj)
    np.testing.assert_allclose(np.array(e.matrix_world.translation), V[handles].mean(0), atol=1e-5)
    np.testing.assert_allclose(_evaluated(obj), V, atol=1e-4)   # at rest: the rest shape
    assert addon.deform.arap.TIMINGS[obj.name_full]["mode"] == "rest"   # written without a solve
    e.location.z += 0.3
    bpy.context.view_layer.update()   # depsgraph_update_post -> solve
    W = _evaluated(obj)
    np.testing.assert_allclose(W[anchors], V[anchors], atol=1e-5)
    np.testing.assert_allclose(W[handles], V[handles] + [0, 0, 0.3], atol=1e-4)
    middle = np.nonzero(np.abs(V[:, 0]) < 0.2)[0]
    dz = W[middle, 2] - V[middle, 2]
    assert 0.02 < dz.mean() < 0.28   # bends in between
    # rotation of the Empty rotates the handle group about its centroid
    e.rotation_euler.y = math.radians(30)
    bpy.context.view_layer.update()
    W2 = _evaluated(obj)
    c = V[handles].mean(0)
    R = np.array(e.matrix_world.to_3x3())
    np.testing.assert_allclose(W2[handles], (V[handles] - c) @ R.T + c + [0, 0, 0.3], atol=1e-4)
    # the mesh itself is untouched (non-destructive): the Basis key holds the rest shape
    basis = obj.data.shape_keys.reference_key
    b = np.empty(len(V) * 3, np.float32)
    basis.data.foreach_get("co", b)
    np.testing.assert_allclose(b.reshape(-1, 3), V, atol=1e-6)


def test_keyframed_empty_gives_different_frames_and_same_frame_same_shape(addon):
    obj, V, anchors, handles = _bar(addon)
    bpy.ops.neumesh.arap_add()
    e = _empty(obj)
    e.keyframe_insert("location", frame=1)
    e.location.z += 0.4
    e.keyframe_insert("location", frame=10)
    scene = bpy.context.scene
    scene.frame_set(10)
    W10 = _evaluated(obj)
    np.testing.assert_allclose(W10[handles], V[handles] + [0, 0, 0.4], atol=1e-4)
    np.testing.assert_allclose(W10[anchors], V[anchors], atol=1e-5)
    scene.frame_set(1)
    np.testing.assert_allclose(_evaluated(obj), V, atol=1e-4)
    scene.frame_set(10)   # solved from rest: the same frame gives the same shape
    np.testing.assert_allclose(_evaluated(obj), W10, atol=1e-5)


def test_apply_as_shape_key_bakes_the_pose_and_removes_the_setup(addon):
    obj, V, anchors, handles = _bar(addon)
    bpy.ops.neumesh.arap_add()
    e = _empty(obj)
    ename = e.name
    e.location.z += 0.25
    bpy.context.view_layer.update()
    posed = _evaluated(obj)
    assert bpy.ops.neumesh.arap_apply() == {"FINISHED"}
    keys = obj.data.shape_keys.key_blocks
    assert "ARAP pose" in keys and "NeuMesh ARAP" not in keys
    assert bpy.data.objects.get(ename) is None and not obj.neumesh_arap.enabled
    np.testing.assert_allclose(_evaluated(obj), posed, atol=1e-5)
    with pytest.raises(RuntimeError, match="no ARAP deform to apply"):   # nothing left to apply
        bpy.ops.neumesh.arap_apply()


def test_missing_and_overlapping_groups_are_clear_errors(addon):
    V, F = grid_mesh(8, 3)
    obj = addon.scene.sync.new_mesh_object("g", V, F)
    bpy.context.view_layer.objects.active = obj
    err = addon.deform.arap.read_groups
    UserError = addon.runtime.errors.UserError
    s = obj.neumesh_arap
    try:
        err(obj, s)
        raise AssertionError("no error without groups")
    except UserError as exc:
        assert "'Anchor'" in str(exc) and "Assign" in str(exc)
    _group(obj, "Anchor", [0, 1, 2])
    try:
        err(obj, s)
        raise AssertionError("no error without handles")
    except UserError as exc:
        assert "handle group" in str(exc)
    _group(obj, "Handle", [2, 3])
    try:
        err(obj, s)
        raise AssertionError("no error on overlap")
    except UserError as exc:
        assert "both 'Anchor' and 'Handle'" in str(exc)
    with pytest.raises(RuntimeError, match="both"):
        bpy.ops.neumesh.arap_add()
    assert obj.data.shape_keys is None and not s.enabled   # nothing changed


def test_animation_render_follows_keyed_handle(addon, trained_field, tmp_path):
    """`-a` through the operator: frames 1 and 2 differ, and frame 2 is the core's render of the
    ARAP-deformed vertices."""
    import neumesh_core as nm

    assert bpy.ops.neumesh.load_field(filepath=trained_field, new_object=True) == {"FINISHED"}
    obj = bpy.context.active_object
    V = np.array([tuple(v.co) for v in obj.data.vertices], np.float32)
    z = V[:, 2]
    _group(obj, "Anchor", np.nonzero(z < np.quantile(z, 0.3))[0])
    _group(obj, "Handle", np.nonzero(z > np.quantile(z, 0.8))[0])
    assert bpy.ops.neumesh.arap_add() == {"FINISHED"}
    e = _empty(obj)
    e.keyframe_insert("location", frame=1)
    e.location.x += 0.5
    e.rotation_euler.y = math.radians(35)
    e.keyframe_insert("location", frame=2)
    e.keyframe_insert("rotation_euler", frame=2)
    e.rotation_euler.y = 0.0
    e.keyframe_insert("rotation_euler", frame=1)
    cam = add_camera((0.0, -4.6, 0.8))
    scene = bpy.context.scene
    scene.render.engine = "NEUMESH"
    W, H = 48, 36
    exact_colour_settings(scene, W, H, filepath=str(tmp_path / "arap_####"), depth="8")
    scene.frame_start, scene.frame_end = 1, 2
    bpy.ops.render.render(animation=True)
    from PIL import Image

    a, b = (np.asarray(Image.open(str(tmp_path / f"arap_000{i}.png")).convert("RGBA"), np.float32) / 255
            for i in (1, 2))
    assert np.abs(a - b).max() > 0.2
    scene.frame_set(2)
    field = nm.load_field(trained_field)
    M = np.array(obj.matrix_world)
    field.set_vertices((_evaluated(obj) @ M[:3, :3].T + M[:3, 3]).astype(np.float32))
    K, c2w = manual_K_c2w(cam, W, H)
    ref = nm.render_camera(field, K, c2w, W, H, background=(1.0, 1.0, 1.0))
    assert np.abs(b[..., :3] - ref.rgb).max() <= 1.5 / 255


def test_drag_solves_in_a_thread_on_the_preview_cage(addon):
    """The viewport path: a moved Empty queues a solve in the object's drag thread (here on a cage of
    40 of the bar's vertices); the timer writes it into the live key."""
    import mathutils

    obj, V, anchors, handles = _bar(addon)
    obj.neumesh_arap.preview_vertices = 40
    bpy.ops.neumesh.arap_add()
    e = _empty(obj)
    arap = addon.deform.arap
    e.matrix_world = mathutils.Matrix.Translation((0, 0, 0.2)) @ e.matrix_world
    assert arap.drag(obj) is True
    arap.wait_for_drags()
    assert arap.drag(obj) is False   # nothing moved since
    W = _evaluated(obj)
    np.testing.assert_allclose(W[handles], V[handles] + [0, 0, 0.2], atol=1e-4)
    np.testing.assert_allclose(W[anchors], V[anchors], atol=1e-5)
    middle = np.nonzero(np.abs(V[:, 0]) < 0.2)[0]
    assert 0.02 < (W[middle, 2] - V[middle, 2]).mean() < 0.18
    t = arap.TIMINGS[obj.name_full]
    assert t["mode"] == "drag" and t["cage"] and t["move_to_preview_s"] >= t["solve_s"] > 0


def _live(obj):
    kb = obj.data.shape_keys.key_blocks["NeuMesh ARAP"]
    arr = np.empty(len(kb.data) * 3, np.float32)
    kb.data.foreach_get("co", arr)
    return arr.reshape(-1, 3)


def test_undo_drops_a_late_drag_solve_and_gives_back_the_shape_from_before_the_drag_exactly(addon):
    """What Ctrl+Z does to a drag (test_real_blender_ui.py presses the keys): a drag solve that ends
    after the undo began writes nothing; after the undo the key, which still holds the dragged shape
    (Blender's undo step was pushed before the drag's solve arrived, and keeps the key as it is),
    gets the shape shown before the drag back exactly, and a redo the dragged one."""
    import mathutils

    obj, V, anchors, handles = _bar(addon)
    bpy.ops.neumesh.arap_add()
    e = _empty(obj)
    arap, undo = addon.deform.arap, addon.deform.arap_undo
    before = _live(obj)
    rest = e.matrix_world.copy()
    e.matrix_world = mathutils.Matrix.Translation((0, 0, 0.3)) @ rest
    assert arap.drag(obj) is True
    arap.wait_for_drags()
    dragged = _live(obj)
    assert np.abs(dragged - before).max() > 0.25
    e.matrix_world = mathutils.Matrix.Translation((0, 0, 0.5)) @ rest   # a move still solving ...
    assert arap.drag(obj) is True
    undo.on_undo_pre()                                                   # ... when Ctrl+Z begins
    e.matrix_world = rest                  # the undo puts the Empty back; the key stays as in memory
    arap.wait_for_drags()
    np.testing.assert_array_equal(_live(obj), dragged)                   # the late solve wrote nothing
    undo.on_undo_post()
    np.testing.assert_array_equal(_live(obj), before)
    assert arap.drag(obj) is False                                       # counted as solved
    undo.on_undo_pre()                                                   # Ctrl+Shift+Z
    e.matrix_world = mathutils.Matrix.Translation((0, 0, 0.3)) @ rest
    undo.on_undo_post()
    np.testing.assert_array_equal(_live(obj), dragged)
    # Empties at transforms never shown (no shape kept for them): solved again from rest
    e.matrix_world = mathutils.Matrix.Translation((0, 0, 0.2)) @ rest
    undo.on_undo_pre()
    undo.on_undo_post()
    W = _live(obj)
    np.testing.assert_allclose(W[handles], V[handles] + [0, 0, 0.2], atol=1e-4)
    np.testing.assert_allclose(W[anchors], V[anchors], atol=1e-5)


def test_the_edit_field_panels_follow_the_handle_empty_to_the_object_it_deforms(addon, trained_field, tmp_path):
    """Selecting the handle Empty (to move it with G, as the docs say) keeps the Edit field panels on
    the field object the Empty deforms: the ARAP panel with its buttons, which act on that object;
    an Empty that is no handle shows 'Select an object with a field' as before."""
    import shutil

    from helpers import Recorder, draw_panel

    path = str(tmp_path / "blob.neumesh")
    shutil.copy(trained_field, path)
    assert bpy.ops.neumesh.load_field(filepath=path, new_object=True) == {"FINISHED"}
    obj = bpy.context.active_object
    V = np.array([tuple(v.co) for v in obj.data.vertices])
    _group(obj, "Anchor", np.nonzero(V[:, 2] < -0.4)[0])
    _group(obj, "Handle", np.nonzero(V[:, 2] > 0.4)[0])
    assert bpy.ops.neumesh.arap_add() == {"FINISHED"}
    e = _empty(obj)
    obj.select_set(False)
    e.select_set(True)
    bpy.context.view_layer.objects.active = e
    assert addon.edit.base.shown_object(e) == obj
    labels, ops = draw_panel(bpy.types.NEUMESH_PT_edit, bpy.context)
    assert not any("Select an object" in t for t in labels)
    assert any(f"'{obj.name}'" in t and "handle" in t for t in labels), labels
    rec = Recorder()
    labels, ops = draw_panel(bpy.types.NEUMESH_PT_arap, bpy.context, rec)
    assert {"neumesh.arap_refresh", "neumesh.arap_remove", "neumesh.arap_apply"} <= set(ops)
    assert not any("Select an object" in t for t in labels)
    assert rec.pointers == {"active_object": obj}              # the buttons act on the field object
    assert bpy.ops.neumesh.arap_refresh() == {"FINISHED"}     # with the Empty active
    assert obj.neumesh_arap.enabled and _empty(obj).name == e.name
    other = bpy.data.objects.new("plain empty", None)
    bpy.context.scene.collection.objects.link(other)
    bpy.context.view_layer.objects.active = other
    labels, _ops = draw_panel(bpy.types.NEUMESH_PT_arap, bpy.context)
    assert any("Select an object with a field" in t for t in labels)


def test_a_frame_change_during_a_texture_paint_stroke_writes_the_key_once_the_stroke_has_ended(addon):
    """Blender's projection paint reads the painted object's evaluated mesh through pointers it took
    when the stroke began; a live key written meanwhile (a frame change: a render or frame_set from a
    script or timer) makes the mesh evaluate anew under the stroke, and Blender 3.4 segfaults at its
    next dab (test_real_blender_redo.py runs that in a real window).  While a stroke runs on the
    object, the frame change's solve and a finished drag solve wait; once it has ended they are
    written."""
    import mathutils

    obj, V, anchors, handles = _bar(addon)
    bpy.ops.neumesh.arap_add()
    e = _empty(obj)
    arap, ps = addon.deform.arap, addon.edit.paint_sync
    rest = e.matrix_world.copy()
    e.matrix_world = mathutils.Matrix.Translation((0, 0, 0.3)) @ rest
    assert arap.drag(obj) is True
    arap.wait_for_drags()
    dragged = _live(obj)      # a drag's solve: the next frame change solves again from rest
    bpy.ops.object.mode_set(mode="TEXTURE_PAINT")
    saved = dict(ps.WATCH)
    ps.WATCH.update(running=True, stroke=True)    # the watcher saw the press and no event since
    try:
        assert ps.stroke_running(obj) and ps.stroke_running()
        bpy.context.scene.frame_set(bpy.context.scene.frame_current)
        np.testing.assert_array_equal(_live(obj), dragged)       # nothing written under the stroke
        assert arap.TIMINGS[obj.name_full]["mode"] == "drag"
        assert bpy.app.timers.is_registered(arap._after_stroke)
        assert arap._after_stroke() == 0.25                      # still running: it waits
        np.testing.assert_array_equal(_live(obj), dragged)
        # a drag solve that finishes during the stroke waits too
        e.matrix_world = mathutils.Matrix.Translation((0, 0, 0.2)) @ rest
        assert arap.drag(obj) is True
        arap._DRAGS[obj.name_full]["thread"].join(60)
        assert arap._apply_drags() == 0.02 and arap._DRAGS[obj.name_full]["done"] is not None
        np.testing.assert_array_equal(_live(obj), dragged)
        ps.WATCH["stroke"] = False                               # the stroke has ended
        assert not ps.stroke_running(obj)
        assert arap._apply_drags() is None
        W = _live(obj)
        np.testing.assert_allclose(W[handles], V[handles] + [0, 0, 0.2], atol=1e-4)
        e.matrix_world = mathutils.Matrix.Translation((0, 0, 0.3)) @ rest
        ps.WATCH["stroke"] = True
        bpy.context.scene.frame_set(bpy.context.scene.frame_current)
        np.testing.assert_array_equal(_live(obj), W)
        ps.WATCH["stroke"] = False
        assert arap._after_stroke() is None                      # solved from rest for the Empty now
        assert arap.TIMINGS[obj.name_full]["mode"] == "frame" and not arap._HELD
        W = _live(obj)
        np.testing.assert_allclose(W[handles], V[handles] + [0, 0, 0.3], atol=1e-4)
        np.testing.assert_allclose(W[anchors], V[anchors], atol=1e-5)
    finally:
        ps.WATCH.clear()
        ps.WATCH.update(saved)
        if bpy.app.timers.is_registered(arap._after_stroke):
            bpy.app.timers.unregister(arap._after_stroke)
        bpy.ops.object.mode_set(mode="OBJECT")
