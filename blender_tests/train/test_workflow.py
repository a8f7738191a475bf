"""Dataset import as cameras, mesh import, training from Blender (thread + cancel + resume)."""
from __future__ import annotations

import json
import os
import time

import bpy
import numpy as np
import pytest


def test_import_dataset_cameras_match_dataset(addon, tiny_dataset):
    import neumesh_core as nm

    assert bpy.ops.neumesh.import_dataset(directory=tiny_dataset, split="train") == {"FINISHED"}
    cams = addon.render.images.dataset_cameras()
    ds = nm.load_scene(tiny_dataset).splits["train"]
    assert len(cams) == len(ds.cameras) == 8
    scene = bpy.context.scene
    assert (scene.render.resolution_x, scene.render.resolution_y) == (ds.cameras.width, ds.cameras.height)
    dg = bpy.context.evaluated_depsgraph_get()
    for cam in cams:
        i = cam["neumesh_index"]
        K, c2w, w, h = addon.scene.camera.camera_K_c2w(cam, scene, dg)
        np.testing.assert_allclose(K, ds.cameras.K[i], atol=1e-3)
        np.testing.assert_allclose(c2w, ds.cameras.c2w[i], atol=1e-5)
        bg = cam.data.background_images
        assert cam.data.show_background_images and len(bg) == 1 and bg[0].image is not None
        assert tuple(bg[0].image.size) == (w, h)
    # the transforms file says the same (OpenGL matrix == Blender matrix_world)
    with open(os.path.join(tiny_dataset, "transforms_train.json")) as f:
        frames = json.load(f)["frames"]
    np.testing.assert_allclose(np.array(cams[0].matrix_world), np.array(frames[0]["transform_matrix"]),
                               atol=1e-5)


def test_import_dataset_error_is_reported(addon, tmp_path):
    with pytest.raises(RuntimeError, match="cannot load dataset"):
        bpy.ops.neumesh.import_dataset(directory=str(tmp_path))


def test_import_mesh_keeps_core_vertex_order(addon, tiny_dataset):
    import neumesh_core as nm

    assert bpy.ops.neumesh.import_mesh(filepath=os.path.join(tiny_dataset, "mesh.ply")) == {"FINISHED"}
    obj = bpy.context.active_object
    m = nm.load_mesh(os.path.join(tiny_dataset, "mesh.ply"))
    np.testing.assert_allclose(addon.scene.sync.mesh_vertices(obj.data), np.asarray(m.vertices), atol=1e-6)
    assert np.array_equal(addon.scene.sync.mesh_triangles(obj.data), np.asarray(m.faces))
    assert bpy.context.scene.neumesh.train_object == obj


def test_load_field_refuses_wrong_vertex_count(addon, trained_field):
    addon.scene.sync.new_mesh_object("tri", np.eye(3, dtype=np.float32), np.array([[0, 1, 2]]))
    bpy.context.view_layer.objects.active = bpy.data.objects["tri"]
    with pytest.raises(RuntimeError, match="vertices but the field has"):
        bpy.ops.neumesh.load_field(filepath=trained_field)


def test_load_field_reports_corrupt_file(addon, tmp_path):
    bad = tmp_path / "bad.neumesh"
    bad.write_bytes(b"not a field")
    with pytest.raises(RuntimeError, match="cannot load field"):
        bpy.ops.neumesh.load_field(filepath=str(bad), new_object=True)


def _setup_training(tiny_dataset, steps):
    bpy.ops.neumesh.import_dataset(directory=tiny_dataset, max_cameras=1)
    bpy.ops.neumesh.import_mesh(filepath=os.path.join(tiny_dataset, "mesh.ply"))
    s = bpy.context.scene.neumesh
    s.train_steps = steps
    return s.train_object


def test_train_from_blender_in_background_thread(addon, tiny_dataset, tmp_path):
    import neumesh_core as nm

    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "train.blend"))
    obj = _setup_training(tiny_dataset, steps=4)
    t0 = time.perf_counter()
    assert bpy.ops.neumesh.train() == {"FINISHED"}  # returns at once, training runs in a thread
    job = addon.train.worker.current()
    assert time.perf_counter() - t0 < 2.0 and job.running
    # the UI thread is free while training: progress is recorded
    assert job.join(timeout=180)
    assert job.state == "DONE", job.message
    assert job.step == 4 and np.isfinite(job.loss)
    addon.train.operators.finish_training()  # what bpy.app.timers runs on the main thread
    path = str(tmp_path / "mesh.neumesh")
    assert os.path.isfile(path)
    assert obj.neumesh.field_path == "//mesh.neumesh"
    assert nm.load_field(path).num_vertices == len(obj.data.vertices)


def test_cancel_saves_and_resume_continues(addon, tiny_dataset, tmp_path):
    import neumesh_core as nm

    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "c.blend"))
    obj = _setup_training(tiny_dataset, steps=400)
    bpy.ops.neumesh.train()
    job = addon.train.worker.current()
    t_end = time.time() + 120
    while job.step < 1 and job.running and time.time() < t_end:
        time.sleep(0.05)
    assert job.running, job.message
    assert bpy.ops.neumesh.train_cancel() == {"FINISHED"}
    assert job.join(timeout=120)
    assert job.state == "CANCELLED", job.message
    stopped_at = job.step
    assert 1 <= stopped_at < 400
    addon.train.operators.finish_training()
    path = addon.scene.props.field_abspath(obj)
    assert os.path.isfile(path)
    bpy.context.scene.neumesh.train_steps = stopped_at + 3
    assert bpy.ops.neumesh.train(resume=True, wait=True) == {"FINISHED"}
    job2 = addon.train.worker.current()
    assert job2.state == "DONE" and job2.step == stopped_at + 3, job2.message
    assert nm.load_field(path).num_vertices == len(obj.data.vertices)


def test_train_needs_dataset(addon):
    addon.scene.sync.new_mesh_object("m", np.eye(3, dtype=np.float32), np.array([[0, 1, 2]]))
    bpy.context.view_layer.objects.active = bpy.data.objects["m"]
    with pytest.raises(RuntimeError, match="dataset"):
        bpy.ops.neumesh.train()


def test_build_scaffold_operator(addon, tiny_dataset):
    with pytest.raises(RuntimeError, match="dataset folder"):
        bpy.ops.neumesh.build_scaffold()
    s = bpy.context.scene.neumesh
    s.dataset_path = tiny_dataset
    s.scaffold_method, s.scaffold_vertices = "hull", 2000
    res = bpy.ops.neumesh.build_scaffold(config_json='{"hull_resolution": 48}')
    assert res == {"FINISHED"}
    obj = bpy.context.active_object
    assert obj.name.startswith("NeuMesh Scaffold") and 1000 < len(obj.data.vertices) < 3000
    assert bpy.context.scene.neumesh.train_object == obj
