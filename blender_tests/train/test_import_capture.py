"""Real captures in Blender: Import Cameras of a COLMAP folder and of a transforms.json
folder written here (cameras, photos as backgrounds, sparse points, "NeuMesh Box"), and Poses from
Photos on a textured cube rendered here (the job's progress, cancel, the operator's import)."""
from __future__ import annotations

import os
import sys
import time

import numpy as np
import pytest

import bpy

pytest.importorskip("pycolmap")
pytest.importorskip("cv2")

from tests.data.test_capture import write_colmap, write_transforms  # noqa: E402
from tests.reconstruct.test_poses import write_cube_photos  # noqa: E402


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("NEUMESH_CACHE", str(tmp_path / "cache"))


def _cap(addon):
    return sys.modules[addon.__name__ + ".train.capture"]


def _cv_c2w(addon, obj):
    return sys.modules[addon.__name__ + ".scene.camera"].c2w_from_matrix_world([list(r) for r in obj.matrix_world])


def _cameras():
    coll = bpy.data.collections["NeuMesh Dataset"]
    return sorted((o for o in coll.objects if o.type == "CAMERA"), key=lambda o: o["neumesh_index"])


def test_import_cameras_of_a_colmap_folder(addon, tmp_path):
    root = str(tmp_path / "colmap cap")
    c2w, xyz = write_colmap(root, "PINHOLE", n=9, points=40)
    assert bpy.ops.neumesh.import_dataset(directory=root) == {"FINISHED"}
    cams = _cameras()
    assert len(cams) == 9
    got = np.stack([_cv_c2w(addon, o) for o in cams])
    np.testing.assert_allclose(got, c2w, atol=1e-4)
    cd = cams[0].data
    assert cd.show_background_images and len(cd.background_images) == 1
    assert os.path.samefile(bpy.path.abspath(cd.background_images[0].image.filepath),
                            os.path.join(root, "images", "IMG_000.png"))   # pinhole: the photo itself
    # fx = 50 px of a 64 px wide photo on a 36 mm sensor
    assert cd.lens == pytest.approx(50.0 * 36 / 64, rel=1e-4)
    assert (bpy.context.scene.render.resolution_x, bpy.context.scene.render.resolution_y) == (64, 48)
    pts = bpy.data.objects["NeuMesh Points"]
    V = np.zeros(len(pts.data.vertices) * 3, np.float32)
    pts.data.vertices.foreach_get("co", V)
    np.testing.assert_allclose(np.sort(V.reshape(-1, 3), 0), np.sort(xyz, 0), atol=1e-5)
    col = pts.data.color_attributes["Color"]
    assert col.domain == "POINT"
    rgba = np.zeros(len(col.data) * 4, np.float32)
    col.data.foreach_get("color", rgba)
    lin = addon.runtime.core.get().srgb_to_linear(np.array([10, 20, 30]) / 255.0)
    np.testing.assert_allclose(rgba.reshape(-1, 4)[:, :3], np.broadcast_to(lin, (40, 3)), atol=1e-5)
    assert any(m.type == "NODES" for m in pts.modifiers)   # drawn as points in Object Mode
    box = bpy.data.objects["NeuMesh Box"]
    assert box.type == "EMPTY" and box.empty_display_type == "CUBE"
    lo, hi = _cap(addon).box_bounds(box)
    inside = np.all((xyz >= lo) & (xyz <= hi), axis=1)
    assert inside.mean() >= 0.9 and np.all(hi - lo < 2.5)   # points uniform in [-1, 1]^3
    # the box `neumesh fit` finds for the scene loaded from this folder (one rule, the core's)
    import neumesh_core as nm

    found = nm.capture_box(nm.load_scene(root))
    np.testing.assert_allclose(box.location, found.centre, atol=1e-5)
    np.testing.assert_allclose(box.scale, found.half_extents, atol=1e-5)
    assert box["neumesh_box_source"] == found.source and "sparse points" in found.source
    assert bpy.context.scene.neumesh.dataset_path == root


def test_import_cameras_of_a_distorted_transforms_json(addon, tmp_path):
    root = str(tmp_path / "tj")
    c2w, lens = write_transforms(root, n=4, dist={"k1": 0.1, "k2": -0.02})
    assert bpy.ops.neumesh.import_dataset(directory=root) == {"FINISHED"}
    cams = _cameras()
    assert len(cams) == 4
    np.testing.assert_allclose(np.stack([_cv_c2w(addon, o) for o in cams]), c2w, atol=1e-4)
    img = bpy.path.abspath(cams[0].data.background_images[0].image.filepath)
    assert img.endswith(".png") and not img.startswith(root)   # the undistorted copy, not the photo
    assert "NeuMesh Points" not in bpy.data.objects   # transforms.json has no points
    box = bpy.data.objects["NeuMesh Box"]   # from the cameras, which all look at the origin
    assert np.linalg.norm(np.asarray(box.location)) < 0.5
    assert box["neumesh_box_source"] == "the cameras' common look-at point"


def test_import_cameras_of_a_folder_that_is_no_capture_says_so(addon, tmp_path):
    with pytest.raises(RuntimeError, match="cannot load dataset"):
        bpy.ops.neumesh.import_dataset(directory=str(tmp_path))


def _poll(job, timeout=600):
    seen = []
    t0 = time.time()
    while job.running and time.time() - t0 < timeout:
        seen.append((job.stage, job.fraction))
        time.sleep(0.02)
    job.join()
    return seen


def test_poses_job_progress_and_cancel(addon, tmp_path):
    cap = _cap(addon)
    photos = str(tmp_path / "photos")
    write_cube_photos(photos, n=12)
    nm = sys.modules["neumesh_core"]
    cfg = nm.PosesConfig(camera_model="PINHOLE", num_threads=1, max_num_features=1500)
    job = cap.CaptureJob("poses", str(tmp_path / "out"), source=photos, poses_config=cfg).start()
    seen = _poll(job)
    assert job.state == "DONE", job.message
    fr = [f for _, f in seen]
    assert fr == sorted(fr) and len(set(fr)) >= 5 and job.fraction == 1.0
    assert job.stages == ["extract", "match", "map"]
    assert {"extract", "match"} <= {s for s, _ in seen}   # the panel saw the long stages
    c, Ks, paths = job.result
    assert len(c) == 12 and c.points is not None and len(c.points) > 100
    # cancel during feature extraction: the job ends CANCELLED, nothing imported
    job = cap.CaptureJob("poses", str(tmp_path / "out2"), source=photos, poses_config=cfg).start()
    t0 = time.time()
    while job.running and job.fraction <= 0 and time.time() - t0 < 60:
        time.sleep(0.01)
    job.cancel()
    job.join()
    assert job.state == "CANCELLED" and job.result is None


def test_poses_from_photos_operator_imports_the_result(addon, tmp_path):
    photos = str(tmp_path / "shots")
    true_c2w, _ = write_cube_photos(photos, n=12)
    s = bpy.context.scene.neumesh
    s.capture_source = photos
    assert bpy.ops.neumesh.poses_from_photos(camera_model="PINHOLE", num_features=1500) == {"FINISHED"}
    out = str(tmp_path / "shots_poses")
    assert os.path.isfile(os.path.join(out, "poses_report.json"))
    assert len(_cameras()) == 12 and s.dataset_path == out
    pts = bpy.data.objects["NeuMesh Points"]
    assert len(pts.data.vertices) > 100
    lo, hi = _cap(addon).box_bounds(bpy.data.objects["NeuMesh Box"])
    V = np.zeros(len(pts.data.vertices) * 3, np.float64)
    pts.data.vertices.foreach_get("co", V)
    # in the photos' own frame (the recovered one is a similarity away): the box holds the cube
    # [-1, 1]^3 the cameras look at, not the room [-8, 8]^3 around it whose walls are points too
    from neumesh_core.edit.align import umeyama

    cams = _cameras()
    est = np.stack([_cv_c2w(addon, o)[:3, 3] for o in cams])
    ref = true_c2w[[int(o.name[-2:]) for o in cams], :3, 3]     # nm_<index>_shot_<nn>
    sim = umeyama(est, ref, with_scale=True)
    P = sim.apply(V.reshape(-1, 3))
    corners = sim.apply(np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]))
    blo, bhi = corners.min(0), corners.max(0)
    on_cube = np.abs(P).max(1) <= 1.05
    assert on_cube.sum() > 50 and (~on_cube).sum() > 0            # both the cube and the room have points
    assert np.mean(np.all((P[on_cube] >= blo) & (P[on_cube] <= bhi), axis=1)) >= 0.9
    assert np.all(bhi - blo < 4.0)                               # not the room


def test_poses_from_photos_names_missing_packages_and_bad_sources(addon, tmp_path, monkeypatch):
    deps = sys.modules[addon.__name__ + ".runtime.deps"]
    s = bpy.context.scene.neumesh
    s.capture_source = str(tmp_path / "nowhere")
    with pytest.raises(RuntimeError, match="no photos at"):
        bpy.ops.neumesh.poses_from_photos()
    txt = tmp_path / "notes.txt"
    txt.write_text("x")
    with pytest.raises(RuntimeError, match="not a video"):
        bpy.ops.neumesh.poses_from_photos(source=str(txt))
    monkeypatch.setattr(deps, "missing_for",
                        lambda feature, statuses=None: ["pycolmap"] if feature == "capture" else [])
    with pytest.raises(RuntimeError, match="pycolmap"):
        bpy.ops.neumesh.poses_from_photos(source=str(tmp_path))


def test_the_box_the_artist_left_drives_training(addon, tmp_path):
    """Import Cameras of a capture without masks, move, rotate and scale the NeuMesh Box, train: the
    field's object box is that box (oriented), and it trains a background model outside it."""
    import math

    import neumesh_core as nm

    root = str(tmp_path / "tj")
    write_transforms(root, n=5)
    assert bpy.ops.neumesh.import_dataset(directory=root) == {"FINISHED"}
    box = bpy.data.objects["NeuMesh Box"]
    box.location = (0.1, -0.05, 0.02)
    box.rotation_euler = (0.0, 0.0, math.radians(30))
    box.scale = (0.5, 0.4, 0.3)
    bpy.context.view_layer.update()
    centre, half, rot = _cap(addon).scene_box(bpy.context.scene)
    np.testing.assert_allclose(centre, [0.1, -0.05, 0.02], atol=1e-6)
    np.testing.assert_allclose(half, [0.5, 0.4, 0.3], atol=1e-6)
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    np.testing.assert_allclose(rot, [[c, -s, 0], [s, c, 0], [0, 0, 1]], atol=1e-6)
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=2, radius=0.3)
    obj = bpy.context.active_object
    bpy.context.scene.neumesh.train_object = obj
    assert bpy.ops.neumesh.train(steps=2, wait=True) == {"FINISHED"}
    field = nm.load_field(bpy.path.abspath(obj.neumesh.field_path))
    np.testing.assert_allclose(field.object_box.centre, centre, atol=1e-6)
    np.testing.assert_allclose(field.object_box.half_extents, half, atol=1e-6)
    np.testing.assert_allclose(field.object_box.rotation, rot, atol=1e-6)
    bg = nm.background_of(field)
    assert bg is not None and bg.box is not None and bg.planes   # the room outside the box
    # a sheared box (non-uniform scale under a rotated parent) falls back to its axis-aligned bounds
    parent = bpy.data.objects.new("tilt", None)
    bpy.context.scene.collection.objects.link(parent)
    parent.rotation_euler = (math.radians(40), 0, 0)
    parent.scale = (1.0, 2.0, 1.0)
    box.parent = parent
    bpy.context.view_layer.update()
    c2, h2, r2 = _cap(addon).scene_box(bpy.context.scene)
    lo, hi = _cap(addon).box_bounds(box)
    np.testing.assert_allclose(r2, np.eye(3))
    np.testing.assert_allclose(h2, (hi - lo) / 2, atol=1e-6)
    np.testing.assert_allclose(c2, (hi + lo) / 2, atol=1e-6)
