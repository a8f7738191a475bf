"""Readers of real captures: transforms.json, COLMAP (via pycolmap), lens undistortion.

Every capture is made here: analytic photos (a smooth pattern of the normalised image coordinates, so
a pinhole render of any K can be computed exactly), cameras on a ring, written in each format.
"""
import json
import os
import shutil
import warnings

import numpy as np
import pytest

from neumesh_core.data.capture import auto_downscale, scene_from_capture
from neumesh_core.data.colmap import read_colmap
from neumesh_core.data.loader import detect_kind, load_scene, read_capture
from neumesh_core.data.transforms import read_transforms
from neumesh_core.data.undistort import Lens, pinhole_for, undistort_image
from neumesh_core.errors import DataError

cv2 = pytest.importorskip("cv2")
pycolmap = pytest.importorskip("pycolmap")

W, H = 64, 48
GL = np.diag([1.0, -1.0, -1.0, 1.0])


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("NEUMESH_CACHE", str(tmp_path / "cache"))


def pattern(xn, yn):
    """RGB in [0.1, 0.9] of normalised image coordinates (smooth: a period of ~1 normalised unit)."""
    return np.stack([0.5 + 0.4 * np.sin(6 * xn + 0.3) * np.cos(5 * yn),
                     0.5 + 0.4 * np.cos(4 * xn - 7 * yn),
                     0.5 + 0.4 * np.sin(3 * xn + 5 * yn + 1.0)], -1).astype(np.float32)


def pinhole_render(K, w=W, h=H):
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    return pattern((xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1])


def distorted_render(lens: Lens):
    """The photo a distorted lens takes of the pattern: each pixel centre undistorted to normalised coords."""
    ys, xs = np.mgrid[0:lens.height, 0:lens.width] + 0.5
    pts = np.stack([xs, ys], -1).reshape(-1, 1, 2) - 0.5  # OpenCV pixel centres at integers
    K = lens.K.copy()
    K[:2, 2] -= 0.5
    D = lens.opencv_coeffs()
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    if lens.is_fisheye:
        und = cv2.fisheye.undistortPoints(pts.astype(np.float64), K, D.reshape(4, 1), criteria=crit)
    else:
        und = cv2.undistortPointsIter(pts.astype(np.float64), K, D, None, None, crit)
    und = und.reshape(lens.height, lens.width, 2)
    return pattern(und[..., 0], und[..., 1])


def to_u8(img):
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def save_png(path, img):
    from PIL import Image

    os.makedirs(os.path.dirname(path), exist_ok=True)
    Image.fromarray(to_u8(img) if img.dtype != np.uint8 else img).save(path)


def ring_c2w(n, radius=4.0, seed=0):
    """OpenCV camera-to-world matrices on a ring around the origin, looking at it."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n
        eye = np.array([radius * np.cos(a), radius * np.sin(a), 1.0 + 0.3 * rng.normal()])
        z = -eye / np.linalg.norm(eye)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        m = np.eye(4)
        m[:3, :3] = np.stack([x, y, z], 1)
        m[:3, 3] = eye
        out.append(m)
    return np.stack(out)


FX, FY, CX, CY = 50.0, 52.0, 31.5, 24.5


def write_transforms(root, n=10, missing=(), dist=None, model=None, per_frame=False, backslash=False,
                     extra=None, masks=False):
    c2w = ring_c2w(n)
    lens = Lens(model or ("OPENCV" if dist else "PINHOLE"), W, H, FX, FY, CX, CY, dist or {})
    img = distorted_render(lens) if dist else pinhole_render(lens.K)
    frames = []
    for i in range(n):
        name = f"images/{i:04d}.png"
        if i not in missing:
            save_png(os.path.join(root, name), img)
        fr = {"file_path": name.replace("/", "\\") if backslash else name, "transform_matrix": (c2w[i] @ GL).tolist()}
        if per_frame:
            fr.update(fl_x=FX + i, fl_y=FY + i, cx=CX, cy=CY, w=W, h=H)
        if masks:
            mname = f"masks/{i:04d}.png"
            m = np.zeros((H, W), np.uint8)
            m[10:30, 20:40] = 255
            from PIL import Image

            os.makedirs(os.path.join(root, "masks"), exist_ok=True)
            Image.fromarray(m).save(os.path.join(root, mname))
            fr["mask_path"] = mname
        frames.append(fr)
    meta = {"w": W, "h": H, "aabb_scale": 4, "frames": frames}
    if not per_frame:
        meta.update(fl_x=FX, fl_y=FY, cx=CX, cy=CY)
    if model:
        meta["camera_model"] = model
    meta.update(dist or {})
    meta.update(extra or {})
    os.makedirs(root, exist_ok=True)
    with open(os.path.join(root, "transforms.json"), "w") as fh:
        json.dump(meta, fh)
    return c2w, lens


# --------------------------------------------------------------------------------------------- transforms


def test_transforms_reads_cameras_and_holds_out_every_8th(tmp_path):
    root = str(tmp_path / "cap")
    c2w, lens = write_transforms(root, n=10)
    assert detect_kind(root) == "transforms"
    scene = load_scene(root, log=lambda m: None)
    assert scene.kind == "transforms" and not scene.has_masks and scene.background is None
    assert {k: len(v) for k, v in scene.splits.items()} == {"train": 8, "val": 2}
    assert scene.split("val").names == ["images/0000.png", "images/0008.png"]
    tr = scene.split("train")
    np.testing.assert_allclose(tr.cameras.c2w, c2w[[1, 2, 3, 4, 5, 6, 7, 9]], atol=1e-5)
    np.testing.assert_allclose(tr.cameras.K[0], lens.K, atol=1e-4)
    assert tr.images.dtype == np.uint8 and tr.images.shape == (8, H, W, 3)  # photos stay uint8
    np.testing.assert_array_equal(tr.images[0], to_u8(pinhole_render(lens.K)))
    f = tr.float_view(0)
    assert f.dtype == np.float32 and f.shape == (H, W, 3)
    np.testing.assert_allclose(f, to_u8(pinhole_render(lens.K)) / 255.0, atol=1e-6)
    assert scene.capture.aabb_scale == 4 and any("no masks" in n for n in scene.notes)


def test_transforms_missing_frames_one_warning_that_counts(tmp_path):
    root = str(tmp_path / "cap")
    write_transforms(root, n=12, missing=(3, 7))
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        cap = read_transforms(root)
    msgs = [str(x.message) for x in w]
    assert len(msgs) == 1 and "2 of 12 frames" in msgs[0]
    assert len(cap) == 10 and "images/0003.png" in cap.skipped
    msgs = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # through the loader the count goes to the progress output instead
        scene = load_scene(root, log=msgs.append)
    assert sum("2 of 12 frames" in m for m in msgs) == 1 and len(scene.split("train")) + len(scene.split("val")) == 10


def test_transforms_windows_paths_and_per_frame_intrinsics(tmp_path):
    root = str(tmp_path / "cap")
    write_transforms(root, n=4, backslash=True, per_frame=True)
    cap = read_transforms(root)
    assert len(cap) == 4
    assert [lens.fx for lens in cap.lenses] == [FX, FX + 1, FX + 2, FX + 3]
    # no w/h and only a field of view (as NeRF-synthetic-style exports write): size from the photos
    meta = json.load(open(os.path.join(root, "transforms.json")))
    meta["camera_angle_x"] = 2 * np.arctan(0.5 * W / FX)
    del meta["w"], meta["h"]
    for fr in meta["frames"]:
        for k in ("w", "h", "fl_x", "fl_y", "cx", "cy"):
            fr.pop(k)
    json.dump(meta, open(os.path.join(root, "transforms.json"), "w"))
    lens = read_transforms(root).lenses[0]
    assert (lens.width, lens.height, lens.cx, lens.cy) == (W, H, W / 2, H / 2) and abs(lens.fx - FX) < 1e-9


def test_transforms_named_splits_and_masks(tmp_path):
    root = str(tmp_path / "cap")
    write_transforms(root, n=6, masks=True,
                     extra={"train_filenames": [f"images/{i:04d}.png" for i in (0, 1, 2, 3)],
                            "test_filenames": ["images\\0004.png", "images/0005.png"]})
    scene = load_scene(root, log=lambda m: None)
    assert sorted(scene.splits) == ["test", "train"] and len(scene.split("test")) == 2
    assert scene.has_masks
    assert scene.split("train").masks.dtype == np.uint8
    m = scene.split("train").float_mask(0)
    assert m[20, 30] == 1.0 and m[0, 0] == 0.0


def test_transforms_without_intrinsics_or_images_is_a_clear_error(tmp_path):
    root = str(tmp_path / "cap")
    write_transforms(root, n=3)
    meta = json.load(open(os.path.join(root, "transforms.json")))
    for k in ("fl_x", "fl_y"):
        del meta[k]
    json.dump(meta, open(os.path.join(root, "transforms.json"), "w"))
    with pytest.raises(DataError, match="fl_x"):
        read_transforms(root)
    shutil.rmtree(os.path.join(root, "images"))
    meta["fl_x"] = FX
    json.dump(meta, open(os.path.join(root, "transforms.json"), "w"))
    with pytest.raises(DataError, match="none of their images exists"):
        read_transforms(root)
    open(os.path.join(root, "transforms.json"), "w").write("{not json")
    with pytest.raises(DataError, match="valid JSON"):
        read_transforms(root)


# --------------------------------------------------------------------------------------------- distortion


@pytest.mark.parametrize("model,dist", [
    ("OPENCV", {"k1": 0.12, "k2": -0.05, "p1": 0.004, "p2": -0.003}),
    ("OPENCV_FISHEYE", {"k1": 0.05, "k2": 0.01, "k3": -0.004, "k4": 0.001}),
])
def test_distortion_round_trip_matches_the_pinhole_render(tmp_path, model, dist):
    """Distort an analytic image with known coefficients, load it: the result equals the pinhole
    render of the loader's K (up to bilinear interpolation and 8-bit storage)."""
    root = str(tmp_path / "cap")
    write_transforms(root, n=3, dist=dist, model=model)
    scene = load_scene(root, holdout_every=0, log=lambda m: None)
    tr = scene.split("train")
    K = tr.cameras.K[0].astype(np.float64)
    ref = pinhole_render(K)
    err = np.abs(tr.float_view(0) - ref)[3:-3, 3:-3]
    plain = np.abs(to_u8(distorted_render(Lens(model, W, H, FX, FY, CX, CY, dist))) / 255.0 - ref)[3:-3, 3:-3]
    assert err.mean() < 0.01 and np.percentile(err, 99) < 0.05
    assert plain.mean() > 3 * err.mean()  # the distortion was real and was removed
    # the second load reuses the cache and gives the same pixels
    again = load_scene(root, holdout_every=0, log=lambda m: None)
    assert any("3 of 3 photos from the cache" in n for n in again.notes)
    np.testing.assert_array_equal(again.split("train").images, tr.images)


def test_undistort_keeps_only_valid_pixels_and_pinhole_is_identity():
    lens = Lens("OPENCV", W, H, FX, FY, CX, CY, {"k1": -0.2})
    img = np.full((H, W, 3), 200, np.uint8)
    out, K = undistort_image(img, lens)
    assert out.shape == img.shape and (out == 200).all() and K[0, 0] > 0
    pin = Lens("PINHOLE", W, H, FX, FY, CX, CY)
    same, K2 = undistort_image(img, pin)
    assert same is img
    np.testing.assert_allclose(K2, pin.K)
    np.testing.assert_allclose(pinhole_for(pin), pin.K)


# --------------------------------------------------------------------------------------------- COLMAP

COLMAP_CASES = {
    "SIMPLE_PINHOLE": [FX, CX, CY],
    "PINHOLE": [FX, FY, CX, CY],
    "SIMPLE_RADIAL": [FX, CX, CY, 0.05],
    "RADIAL": [FX, CX, CY, 0.05, -0.01],
    "OPENCV": [FX, FY, CX, CY, 0.05, -0.01, 0.002, -0.001],
    "FULL_OPENCV": [FX, FY, CX, CY, 0.05, -0.01, 0.002, -0.001, 0.001, 0.0, 0.0, 0.0],
    "OPENCV_FISHEYE": [FX, FY, CX, CY, 0.05, 0.01, 0.0, 0.0],
}


def write_colmap(root, model="PINHOLE", params=None, n=9, text=False, legacy=False, points=40):
    """A COLMAP capture written by pycolmap: sparse/0 + images/ (images named as in images.bin)."""
    params = COLMAP_CASES[model] if params is None else params
    c2w = ring_c2w(n, seed=1)
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, model, FX, W, H)
    cam.params = np.asarray(params, np.float64)
    rec.add_camera_with_trivial_rig(cam)
    lens = Lens.from_colmap(model, W, H, params)
    img = distorted_render(lens) if not lens.is_pinhole else pinhole_render(lens.K)
    for i in range(n):
        im = pycolmap.Image(name=f"IMG_{i:03d}.png", camera_id=1, image_id=i + 1)
        w2c = np.linalg.inv(c2w[i])
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(w2c[:3, :4]))
        save_png(os.path.join(root, "images", im.name), img)
    rng = np.random.default_rng(2)
    xyz = rng.uniform(-1, 1, size=(points, 3))
    for p in xyz:
        rec.add_point3D(p, pycolmap.Track(), np.array([10, 20, 30], np.uint8))
    d = os.path.join(root, "sparse", "0")
    os.makedirs(d, exist_ok=True)
    (rec.write_text if text else rec.write_binary)(d)
    if legacy:  # COLMAP < 3.12 and gaussian-splatting's convert.py write no rigs/frames files
        for f in os.listdir(d):
            if f.startswith(("rigs", "frames")):
                os.remove(os.path.join(d, f))
    return c2w, xyz


@pytest.mark.parametrize("model", sorted(COLMAP_CASES))
def test_colmap_camera_models_load(tmp_path, model):
    root = str(tmp_path / model)
    c2w, xyz = write_colmap(root, model)
    assert detect_kind(root) == "colmap"
    scene = load_scene(root, log=lambda m: None)
    assert scene.kind == "colmap" and len(scene.split("train")) == 7 and len(scene.split("val")) == 2
    np.testing.assert_allclose(scene.split("val").cameras.c2w, c2w[[0, 8]], atol=1e-5)
    lens = scene.capture.lenses[0]
    assert lens.model == model and lens.fx == FX
    if lens.is_pinhole:
        np.testing.assert_allclose(scene.split("train").cameras.K[0], lens.K, atol=1e-4)
    else:  # distortion removed: the photo now matches the pinhole render of the new K
        tr = scene.split("train")
        err = np.abs(tr.float_view(0) - pinhole_render(tr.cameras.K[0].astype(np.float64)))[3:-3, 3:-3]
        assert err.mean() < 0.01
    np.testing.assert_allclose(np.sort(scene.capture.points, 0), np.sort(xyz, 0).astype(np.float32), atol=1e-6)
    assert (scene.capture.point_colours == [10, 20, 30]).all()


@pytest.mark.parametrize("text,legacy", [(True, False), (False, True), (True, True)])
def test_colmap_text_and_legacy_models(tmp_path, text, legacy):
    root = str(tmp_path / "cap")
    c2w, _ = write_colmap(root, "SIMPLE_RADIAL", text=text, legacy=legacy, n=5)
    cap = read_colmap(root)
    assert cap.names == [f"IMG_{i:03d}.png" for i in range(5)]
    np.testing.assert_allclose(cap.c2w, c2w, atol=1e-9)


def test_colmap_truncated_images_bin_is_a_clear_error(tmp_path):
    root = str(tmp_path / "cap")
    write_colmap(root, n=4)
    p = os.path.join(root, "sparse", "0", "images.bin")
    data = open(p, "rb").read()
    open(p, "wb").write(data[: len(data) // 2])
    with pytest.raises(DataError, match="truncated or corrupt"):
        load_scene(root)


def test_colmap_photos_elsewhere_and_named_splits(tmp_path):
    root = str(tmp_path / "cap")
    write_colmap(root, n=6)
    photos = str(tmp_path / "photos")
    shutil.move(os.path.join(root, "images"), photos)
    with pytest.raises(DataError, match="put the photos in"):
        read_colmap(root)
    json.dump({"images": photos}, open(os.path.join(root, "poses_report.json"), "w"))
    open(os.path.join(root, "test_list.txt"), "w").write("IMG_001.png\nIMG_004.png\n")
    cap = read_capture(root)
    assert os.path.dirname(cap.image_paths[0]) == photos
    scene = scene_from_capture(cap, log=lambda m: None)
    assert scene.split("test").names == ["IMG_001.png", "IMG_004.png"] and len(scene.split("train")) == 4


def test_unsupported_model_and_unknown_folder_say_what_to_do(tmp_path):
    with pytest.raises(DataError, match="image_undistorter"):
        Lens.from_colmap("FOV", W, H, [FX, CX, CY, 0.1])
    os.makedirs(tmp_path / "x" / "images")
    with pytest.raises(DataError, match="neumesh poses"):
        detect_kind(str(tmp_path / "x"))


def test_large_photos_get_a_default_downscale(tmp_path):
    assert auto_downscale(4000, 3000) == 3 and auto_downscale(1600, 900) == 1 and auto_downscale(1080, 1920) == 2
    root = str(tmp_path / "cap")
    write_colmap(root, n=3)
    cap = read_colmap(root)
    # pretend the photos are big: the loader must pick a factor and say so
    cap.lenses = [Lens("PINHOLE", W * 40, H * 40, FX * 40, FX * 40, CX * 40, CY * 40) for _ in cap.lenses]
    msgs = []
    with pytest.raises(DataError):  # the files are 64x48, the cameras say 2560x1920: a clear mismatch error
        scene_from_capture(cap, log=msgs.append)
    assert msgs and "downscale 2" in msgs[0]


def test_too_many_pixels_for_the_memory_is_a_clear_error(tmp_path, monkeypatch):
    import neumesh_core.data.capture as capture_mod

    root = str(tmp_path / "cap")
    write_colmap(root, n=3)
    monkeypatch.setattr(capture_mod, "_physical_memory", lambda: 20_000)  # 3 x 64x48 x 3 uint8 = 27.6 KB
    with pytest.raises(DataError, match="--downscale 2"):
        load_scene(root, downscale=1, log=lambda m: None)


def test_a_capture_without_masks_trains(tmp_path, blob_mesh):
    """masks None and background None (a real background): training runs and its loss is finite."""
    import neumesh_core as nm

    root = str(tmp_path / "cap")
    write_transforms(root, n=9, dist={"k1": 0.05})
    scene = load_scene(root, log=lambda m: None)
    assert scene.split("train").masks is None and not scene.has_masks
    field = nm.create_field(blob_mesh, nm.FieldConfig())
    res = nm.train(field, scene, nm.TrainConfig(steps=3, rays_per_batch=128, log_every=1))
    assert res.steps_done == 3 and np.isfinite(res.final_loss)


def test_undistorted_images_for_blender_backgrounds(tmp_path):
    """read_capture + undistorted_images: what Import Cameras needs (no pixels until asked; PNG files)."""
    from neumesh_core.data import read_capture as rc, undistorted_images
    from neumesh_core.errors import Cancelled

    root = str(tmp_path / "cap")
    write_transforms(root, n=3, dist={"k1": 0.1, "k2": -0.02})
    cap = rc(root)
    assert cap.is_distorted and cap.points is None and cap.aabb_scale == 4
    Ks, paths = undistorted_images(cap)
    assert all(p.endswith(".png") and os.path.isfile(p) and not p.startswith(root) for p in paths)
    from PIL import Image

    img = np.asarray(Image.open(paths[0]), np.float32) / 255
    err = np.abs(img - pinhole_render(Ks[0]))[3:-3, 3:-3]
    assert err.mean() < 0.01
    with pytest.raises(Cancelled):
        undistorted_images(cap, progress=lambda f: False)
    pin = str(tmp_path / "pin")
    write_transforms(pin, n=2)
    Ks, paths = undistorted_images(rc(pin))
    assert paths == rc(pin).image_paths


def test_capture_object_box_is_the_box_fit_finds(tmp_path):
    """One rule for the object box: the capture's (read without its photos; the add-on's Import Cameras)
    and the loaded scene's (neumesh fit) are the same box, from the training photos' cameras."""
    import neumesh_core as nm

    root = str(tmp_path / "c")
    write_colmap(root, "PINHOLE", n=9, points=40)
    cap = nm.read_capture(root)
    box = nm.capture_object_box(cap)
    found = nm.capture_box(nm.load_scene(root))
    np.testing.assert_allclose(box.centre, found.centre, atol=1e-9)
    np.testing.assert_allclose(box.half_extents, found.half_extents, atol=1e-9)
    assert box.source == found.source and "sparse points" in box.source
    cap.points = None   # without points: around the cameras' common look-at point
    assert nm.capture_object_box(cap).source == "the cameras' common look-at point"
