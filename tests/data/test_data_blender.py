"""NeRF-synthetic reader (neumesh_core/data/blender.py) and load_scene auto-detection."""
import json
import math
import os

import numpy as np
import pytest

from neumesh_core.data.blender import load_blender
from neumesh_core.data.cameras import opengl_to_opencv
from neumesh_core.data.loader import detect_kind, load_scene
from neumesh_core.errors import DataError
from neumesh_core.imageio import save_image

W, H = 16, 12
ANGLE = 0.7


def _pose(i):
    a = 0.4 * i
    c2w = np.eye(4)
    c2w[:3, 3] = [3 * math.cos(a), 3 * math.sin(a), 0.5]
    # OpenGL: -z towards the origin
    back = c2w[:3, 3] / np.linalg.norm(c2w[:3, 3])
    right = np.cross([0, 0, 1], back)
    right /= np.linalg.norm(right)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2] = right, np.cross(back, right), back
    return c2w


def _rgba(i):
    img = np.zeros((H, W, 4), np.float32)
    img[..., 0] = 0.8
    img[..., 1] = (i + 1) / 10
    img[..., 2] = 0.2
    img[..., 3] = 0.0
    img[3:9, 4:12, 3] = 1.0
    img[3:9, 12, 3] = 0.4  # a partially transparent column
    return img


def make_dataset(root, counts=None, extra=None, ext_in_json=False):
    counts = counts or {"train": 3, "val": 2, "test": 1}
    os.makedirs(root, exist_ok=True)
    k = 0
    for split, n in counts.items():
        frames = []
        for i in range(n):
            save_image(os.path.join(root, split, f"r_{i}.png"), _rgba(k))
            fp = f"./{split}/r_{i}" + (".png" if ext_in_json else "")
            frames.append({"file_path": fp, "transform_matrix": _pose(k).tolist()})
            k += 1
        meta = {"camera_angle_x": ANGLE, "frames": frames}
        meta.update(extra or {})
        with open(os.path.join(root, f"transforms_{split}.json"), "w") as fh:
            json.dump(meta, fh)
    return str(root)


def test_reads_splits_cameras_and_masks(tmp_path):
    root = make_dataset(tmp_path / "ds")
    scene = load_blender(root)
    assert scene.kind == "blender" and sorted(scene.splits) == ["test", "train", "val"]
    tr = scene.split("train")
    assert tr.images.shape == (3, H, W, 3) and tr.masks.shape == (3, H, W)
    f = 0.5 * W / math.tan(0.5 * ANGLE)
    np.testing.assert_allclose(tr.cameras.K[0], [[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]], rtol=1e-6)
    np.testing.assert_allclose(tr.cameras.c2w[1], opengl_to_opencv(_pose(1)), atol=1e-6)
    # OpenCV +z looks at the origin
    c = tr.cameras.c2w[0]
    assert np.dot(c[:3, 2], -c[:3, 3]) / np.linalg.norm(c[:3, 3]) > 0.999
    np.testing.assert_allclose(scene.bbox, [[-1.5] * 3, [1.5] * 3])
    assert scene.mesh_path is None and scene.background == (1.0, 1.0, 1.0)
    assert tr.names[0].replace("\\", "/") == "train/r_0.png"
    np.testing.assert_allclose(tr.masks[0, 5, 5], 1.0)
    np.testing.assert_allclose(tr.masks[0, 5, 12], 0.4, atol=1 / 255)


def test_background_compositing(tmp_path):
    root = make_dataset(tmp_path / "ds", ext_in_json=True)
    white = load_blender(root, splits=("train",), background="white").split("train").images
    black = load_blender(root, splits=("train",), background="black").split("train").images
    raw = load_blender(root, splits=("train",), background=None).split("train").images
    np.testing.assert_allclose(white[0, 0, 0], [1, 1, 1], atol=1e-6)  # alpha 0 -> background
    np.testing.assert_allclose(black[0, 0, 0], [0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(raw[0, 0, 0], [0.8, 0.1, 0.2], atol=1 / 255)
    np.testing.assert_allclose(white[0, 5, 5], raw[0, 5, 5], atol=1e-6)  # opaque -> unchanged
    a = 0.4
    np.testing.assert_allclose(white[0, 5, 12], raw[0, 5, 12] * a + (1 - a), atol=2 / 255)
    np.testing.assert_allclose(black[0, 5, 12], raw[0, 5, 12] * a, atol=2 / 255)
    grey = load_blender(root, splits=("train",), background=(0.5, 0.5, 0.5))
    assert grey.background == (0.5, 0.5, 0.5)
    np.testing.assert_allclose(grey.split("train").images[0, 0, 0], 0.5, atol=1e-6)


def test_downscale_intrinsics_and_optional_keys(tmp_path):
    root = make_dataset(tmp_path / "ds", counts={"train": 2}, extra={"fl_x": 20.0, "fl_y": 22.0, "cx": 7.0,
                                                                      "cy": 5.0, "aabb": [[-1, -2, -3], [1, 2, 3]]})
    scene = load_blender(root, downscale=2)
    tr = scene.split("train")
    assert tr.images.shape == (2, H // 2, W // 2, 3)
    np.testing.assert_allclose(tr.cameras.K[0], [[10, 0, 3.5], [0, 11, 2.5], [0, 0, 1]], rtol=1e-6)
    np.testing.assert_allclose(scene.bbox, [[-1, -2, -3], [1, 2, 3]])
    assert list(scene.splits) == ["train"]  # missing val/test files are skipped


def test_mesh_path_detected(tmp_path):
    root = make_dataset(tmp_path / "ds", counts={"train": 1})
    open(os.path.join(root, "mesh.ply"), "w").close()
    assert load_blender(root).mesh_path == os.path.join(root, "mesh.ply")


def test_errors(tmp_path):
    with pytest.raises(DataError, match="not found"):
        load_blender(str(tmp_path / "nope"))
    root = make_dataset(tmp_path / "ds", counts={"val": 1})
    with pytest.raises(DataError, match="transforms_train.json.*transforms_val.json"):
        load_blender(root)
    root = make_dataset(tmp_path / "ds2", counts={"train": 2})
    os.remove(os.path.join(root, "train", "r_1.png"))
    with pytest.raises(DataError, match="r_1"):
        load_blender(root)
    root = make_dataset(tmp_path / "ds3", counts={"train": 2})
    save_image(os.path.join(root, "train", "r_1.png"), np.zeros((5, 5, 4), np.float32))
    with pytest.raises(DataError, match="different sizes"):
        load_blender(root)
    with open(os.path.join(root, "transforms_train.json"), "w") as fh:
        fh.write("{not json")
    with pytest.raises(DataError, match="valid JSON"):
        load_blender(root)
    with open(os.path.join(root, "transforms_train.json"), "w") as fh:
        json.dump({"frames": [{"file_path": "./train/r_0", "transform_matrix": np.eye(4).tolist()}]}, fh)
    with pytest.raises(DataError, match="camera_angle_x"):
        load_blender(root)


def test_load_scene_autodetect(tmp_path):
    root = make_dataset(tmp_path / "ds", counts={"train": 1})
    assert detect_kind(root) == "blender"
    scene = load_scene(root, background="black")
    assert scene.kind == "blender" and scene.background == (0.0, 0.0, 0.0)
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "readme.txt").write_text("x")
    with pytest.raises(DataError, match="transforms_train.json.*cameras_sphere.npz") as ei:
        load_scene(str(empty))
    assert "readme.txt" in str(ei.value)
    with pytest.raises(ValueError, match="kind"):
        load_scene(root, kind="meshroom")
