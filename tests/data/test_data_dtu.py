"""NeuS/IDR DTU reader (neumesh_core/data/dtu.py)."""
import os

import numpy as np
import pytest

from neumesh_core.data.cameras import pixel_rays
from neumesh_core.data.dtu import decompose_projection, load_dtu
from neumesh_core.data.loader import load_scene
from neumesh_core.errors import DataError
from neumesh_core.imageio import save_image

W, H = 24, 16
REAL_SCAN = os.path.join(os.path.dirname(__file__), "..", "..", "..", "shared", "data", "dtu", "scan24")


def _rot(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def make_dtu(root, n=5, masks=True, seed=0, drop_key=None):
    """Tiny NeuS dataset; returns the expected K (this project's pixel convention: the NeuS principal
    point + 0.5) and normalised OpenCV c2w per view."""
    rng = np.random.default_rng(seed)
    os.makedirs(os.path.join(root, "image"), exist_ok=True)
    s, trans = 2.5, np.array([0.3, -0.2, 1.1])
    scale_mat = np.eye(4)
    scale_mat[:3, :3] *= s
    scale_mat[:3, 3] = trans
    cams, Ks, c2ws = {}, [], []
    for i in range(n):
        K = np.array([[30.0 + i, 0.0, 11.5], [0.0, 31.0 + i, 8.25], [0.0, 0.0, 1.0]])
        R = _rot(rng)
        C_world = rng.normal(size=3) * 4 + trans
        t = -R @ C_world
        P = np.eye(4)
        P[:3, :4] = K @ np.hstack([R, t[:, None]])
        factor = -1.7 if i % 2 else 3.0  # projection matrices are defined up to (signed) scale
        cams[f"world_mat_{i}"] = P * factor
        cams[f"scale_mat_{i}"] = scale_mat
        Ks.append(K + np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]]))
        c2w = np.eye(4)
        c2w[:3, :3] = R.T
        c2w[:3, 3] = (C_world - trans) / s
        c2ws.append(c2w)
        img = np.zeros((H, W, 3), np.float32)
        img[..., 0] = i / n
        save_image(os.path.join(root, "image", f"{i:06d}.png"), img)
        if masks:
            m = np.zeros((H, W, 3), np.float32)
            m[4:12, 6:18] = 1.0
            m[0, 0] = 0.4  # below the threshold
            save_image(os.path.join(root, "mask", f"{i:03d}.png"), m)
    if drop_key is not None:
        cams[f"world_mat_{n + 3}"] = cams.pop(f"world_mat_{drop_key}")
    np.savez(os.path.join(root, "cameras_sphere.npz"), **cams)
    return np.stack(Ks), np.stack(c2ws)


def test_decompose_projection_recovers_k_and_pose():
    rng = np.random.default_rng(5)
    K = np.array([[800.0, 0.5, 320.0], [0.0, 820.0, 240.0], [0.0, 0.0, 1.0]])
    R = _rot(rng)
    C = rng.normal(size=3)
    P = K @ np.hstack([R, (-R @ C)[:, None]])
    for factor in (1.0, -0.01, 250.0):
        K2, c2w = decompose_projection(P * factor)
        np.testing.assert_allclose(K2, K, atol=1e-6)
        np.testing.assert_allclose(c2w[:3, :3], R.T, atol=1e-9)
        np.testing.assert_allclose(c2w[:3, 3], C, atol=1e-9)
    with pytest.raises(DataError, match="singular"):
        decompose_projection(np.zeros((3, 4)))


def test_load_dtu_recovers_cameras_splits_masks(tmp_path):
    root = str(tmp_path / "scan")
    Ks, c2ws = make_dtu(root, n=12)
    scene = load_dtu(root, holdout_every=5)
    assert scene.kind == "dtu" and scene.background is None
    np.testing.assert_allclose(scene.bbox, [[-1, -1, -1], [1, 1, 1]])
    tr, va = scene.split("train"), scene.split("val")
    val_idx, train_idx = [0, 5, 10], [i for i in range(12) if i % 5]
    assert len(va) == 3 and len(tr) == 9
    np.testing.assert_allclose(va.cameras.K, Ks[val_idx], atol=1e-4)
    np.testing.assert_allclose(tr.cameras.K, Ks[train_idx], atol=1e-4)
    np.testing.assert_allclose(tr.cameras.c2w, c2ws[train_idx], atol=1e-4)
    np.testing.assert_allclose(va.cameras.c2w, c2ws[val_idx], atol=1e-4)
    assert va.images.dtype == np.uint8 and tr.masks.dtype == np.bool_  # photos stay uint8
    np.testing.assert_allclose(va.float_view(1)[0, 0, 0], 5 / 12, atol=1 / 255)
    fm = tr.float_masks()
    assert fm.dtype == np.float32 and set(np.unique(fm)) == {0.0, 1.0}
    assert fm[0, 0, 0] == 0.0 and fm[0, 5, 7] == 1.0 and fm.sum() == 9 * 8 * 12
    assert scene.notes == []
    assert list(load_dtu(root, holdout_every=0).splits) == ["train"]
    assert load_scene(root).kind == "dtu"


def test_load_dtu_downscale(tmp_path):
    root = str(tmp_path / "scan")
    Ks, _ = make_dtu(root, n=2)
    tr = load_dtu(root, downscale=2, holdout_every=0).split("train")
    assert tr.images.shape == (2, H // 2, W // 2, 3) and tr.masks.shape == (2, H // 2, W // 2)
    np.testing.assert_allclose(tr.cameras.K[:, :2], Ks[:, :2] / 2, atol=1e-4)


def test_dtu_without_masks(tmp_path):
    root = str(tmp_path / "scan")
    make_dtu(root, n=3, masks=False)
    scene = load_dtu(root)
    assert scene.split("train").masks is None and "mask" in scene.notes[0]


def test_dtu_errors(tmp_path):
    with pytest.raises(DataError, match="cameras_sphere.npz"):
        os.makedirs(tmp_path / "empty")
        load_dtu(str(tmp_path / "empty"))
    root = str(tmp_path / "a")
    make_dtu(root, n=3, drop_key=1)
    with pytest.raises(DataError, match="world_mat_1.*000001.png"):
        load_dtu(root)
    root = str(tmp_path / "b")
    make_dtu(root, n=3)
    save_image(os.path.join(root, "image", "000003.png"), np.zeros((H, W, 3)))
    with pytest.raises(DataError, match="4 images .* 3 cameras"):
        load_dtu(root)
    root = str(tmp_path / "c")
    make_dtu(root, n=3)
    os.remove(os.path.join(root, "mask", "001.png"))
    with pytest.raises(DataError, match="2 masks"):
        load_dtu(root)
    root = str(tmp_path / "d")
    make_dtu(root, n=2)
    os.rename(os.path.join(root, "image"), os.path.join(root, "pictures"))
    with pytest.raises(DataError, match="image/ or images/"):
        load_dtu(root)


@pytest.mark.skipif(not os.path.isdir(REAL_SCAN), reason="real DTU scan24 not present in ../shared/data")
def test_real_scan24_geometry():
    scene = load_dtu(REAL_SCAN, downscale=8)
    assert sorted(scene.splits) == ["train", "val"] and len(scene.split("val")) == 5
    for name in ("train", "val"):
        s = scene.split(name)
        cams = s.cameras
        assert (cams.width, cams.height) == (200, 150) and s.masks is not None
        dist = np.linalg.norm(cams.centres, axis=1)
        assert (dist > 1.5).all()  # outside the unit sphere
        fwd = cams.c2w[:, :3, 2]
        assert ((fwd * -cams.centres).sum(1) / dist > 0.9).all()  # looking at the origin
        np.testing.assert_allclose(np.linalg.det(cams.c2w[:, :3, :3]), 1.0, atol=1e-4)
        for i in range(len(s)):
            w2c = np.linalg.inv(cams.c2w[i].astype(np.float64))
            p = cams.K[i] @ w2c[:3, 3]
            origin_px = p[:2] / p[2]
            m = s.masks[i] > 0.5
            ys, xs = np.nonzero(m)
            centroid = np.array([xs.mean() + 0.5, ys.mean() + 0.5])
            assert np.linalg.norm(origin_px - centroid) < 0.15 * np.hypot(200, 150)
            assert m[int(origin_px[1]), int(origin_px[0])]
            # every foreground pixel's ray passes through the unit sphere (object inside it)
            o, d = pixel_rays(cams.K[i], cams.c2w[i], 200, 150)
            b = (o * d).sum(-1)
            hit = (b * b - ((o * o).sum(-1) - 1.0) > 0).reshape(150, 200).numpy()
            assert (hit & m).sum() >= 0.99 * m.sum()
