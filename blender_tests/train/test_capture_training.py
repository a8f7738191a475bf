"""A capture without masks in Blender: the NeuMesh Box that Import Cameras makes is
what Build scaffold and Train take as the object (moved, rotated and scaled by the artist), the field
keeps it and learns a background model, and the render setting *Background* shows the room or the
object alone (with Film > Transparent: alpha = the object's own opacity)."""
from __future__ import annotations

import math
import sys

import numpy as np
import pytest

import bpy

from helpers import exact_colour_settings, f12_srgb, read_exr

pytest.importorskip("cv2")

from tests.test_fit_real import _write_room_capture  # noqa: E402


def _mod(addon, name):
    return sys.modules[addon.__name__ + "." + name]


def test_box_drives_scaffold_and_training_and_background_toggle(addon, tmp_path):
    import neumesh_core as nm

    root = str(tmp_path / "room")
    _write_room_capture(root, n=16, res=32)
    assert bpy.ops.neumesh.import_dataset(directory=root) == {"FINISHED"}
    scene = bpy.context.scene
    box = bpy.data.objects["NeuMesh Box"]
    box.location = (0.05, -0.02, 0.0)               # the artist moves, turns and sizes the box
    box.rotation_euler = (0.0, 0.0, math.radians(30))
    box.scale = (1.3, 1.2, 1.25)
    bpy.context.view_layer.update()
    centre, half, R = _mod(addon, "train.capture").scene_box(scene)
    np.testing.assert_allclose(centre, [0.05, -0.02, 0.0], atol=1e-6)
    np.testing.assert_allclose(half, [1.3, 1.2, 1.25], atol=1e-6)
    np.testing.assert_allclose(R[:, 0], [math.cos(math.radians(30)), math.sin(math.radians(30)), 0], atol=1e-6)

    s = scene.neumesh
    s.scaffold_method, s.scaffold_vertices = "density", 3000
    assert bpy.ops.neumesh.build_scaffold(
        config_json='{"density_iters": [20, 20], "density_resolutions": [16, 24]}') == {"FINISHED"}
    scaffold = bpy.context.active_object
    V = np.array([tuple(v.co) for v in scaffold.data.vertices])
    aabb = nm.ObjectBox(centre, half, R).aabb()
    margin = 0.2 * (aabb[1] - aabb[0])              # the density grid's cells reach a little past
    assert (V >= aabb[0] - margin).all() and (V <= aabb[1] + margin).all()

    s.train_object, s.train_steps = scaffold, 4
    assert bpy.ops.neumesh.train(wait=True) == {"FINISHED"}
    path = bpy.path.abspath(scaffold.neumesh.field_path)
    field = nm.load_field(path)
    np.testing.assert_allclose(field.object_box.centre, centre, atol=1e-6)
    np.testing.assert_allclose(field.object_box.half_extents, half, atol=1e-6)
    np.testing.assert_allclose(field.object_box.rotation, R, atol=1e-6)
    assert nm.background_of(field) is not None

    # F12 with the background on (the room) and off (the object alone)
    cam = next(o for o in bpy.data.collections["NeuMesh Dataset"].objects if o.type == "CAMERA")
    scene.camera = cam
    scene.render.engine = "NEUMESH"
    exact_colour_settings(scene, 32, 32)
    s.render_background = True
    on = f12_srgb(tmp_path / "on.exr")
    s.render_background = False
    off = f12_srgb(tmp_path / "off.exr")
    K, c2w, W, H = _mod(addon, "scene.camera").camera_K_c2w(cam, scene, bpy.context.evaluated_depsgraph_get())
    field.set_vertices(field.rest_vertices.numpy())
    ref = {b: nm.render_camera(field, np.asarray(K, np.float32), np.asarray(c2w, np.float32), W, H,
                               background=(1.0, 1.0, 1.0), settings=nm.RenderSettings(background_model=b))
           for b in (True, False)}
    assert np.abs(on - ref[True].rgb).max() <= 2e-3
    assert np.abs(off - ref[False].rgb).max() <= 2e-3
    assert np.abs(on - off).mean() > 0.02            # the room is there, or not
    scene.render.film_transparent = True
    f12_srgb(tmp_path / "alpha.exr")
    alpha = read_exr(str(tmp_path / "alpha.exr"))[..., 3]
    assert np.abs(alpha - ref[False].opacity).max() <= 2e-3
    s.render_background = True
