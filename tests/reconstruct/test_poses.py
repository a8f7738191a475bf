"""Poses from photos (neumesh_core/reconstruct/poses.py, video.py, cli/poses.py): pycolmap on photos the
test renders itself (a textured cube), mapping of a pycolmap synthetic database, cancel, clear errors, video frames."""
import json
import os
import re

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")
cv2 = pytest.importorskip("cv2")

from neumesh_core.data.loader import load_scene  # noqa: E402
from neumesh_core.errors import Cancelled  # noqa: E402
from neumesh_core.reconstruct.poses import PosesConfig, PosesError, estimate_poses, map_database  # noqa: E402
from neumesh_core.reconstruct.video import frames_from_video  # noqa: E402


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("NEUMESH_CACHE", str(tmp_path / "cache"))


# a line of COLMAP's own log (glog): "I20261206 06:20:52.601087 140327946024640 feature_extraction.cc:498] ..."
GLOG_LINE = re.compile(r"^[IWEF]\d{8} \d\d:\d\d:\d\d\.\d+ +\d+ \S+:\d+\]", re.M)


def _look_at(eye):
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    m[:3, 3] = eye
    return m


def _textures(seed=0, n=6, res=256, blobs=16):
    """Grey blob noise in one colour per face (SIFT sees grey: contrast matters more than hue)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        small = rng.uniform(0, 1, size=(blobs, blobs)).astype(np.float32)
        grey = cv2.resize(small, (res, res), interpolation=cv2.INTER_CUBIC).clip(0, 1)
        out.append(grey[..., None] * rng.uniform(0.3, 1, size=3).astype(np.float32))
    return out


def _box_hits(o, d, half):
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - o) / d, (half - o) / d
    return np.nanmax(np.minimum(t1, t2), -1), np.nanmin(np.maximum(t1, t2), -1)


def _paint(img, m, p, half, tex):
    axis = np.argmax(np.abs(p) / half, -1)
    for a in range(3):
        for s, sign in enumerate((-1, 1)):
            f = m & (axis == a) & (np.sign(p[..., a]) == sign)
            uv = np.delete(p[f], a, axis=1) / half
            ij = np.clip(((uv + 1) / 2 * 255).astype(int), 0, 255)
            img[f] = tex[2 * a + s][ij[:, 1], ij[:, 0]]


def render_cube(c2w, K, w, h, tex, room_tex):
    """Photo of the cube [-1,1]^3 (a blob texture per face) inside a textured room [-8,8]^3."""
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    d = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1) @ c2w[:3, :3].T
    o = c2w[:3, 3]
    tn, tf = _box_hits(o, d, 1.0)
    hit = (tn < tf) & (tf > 0)
    img = np.zeros((h, w, 3), np.float32)
    _, room_far = _box_hits(o, d, 8.0)
    _paint(img, ~hit, o + room_far[..., None] * d, 8.0, room_tex)
    _paint(img, hit, o + tn[..., None] * d, 1.0, tex)
    return img


def write_cube_photos(folder, n=16, w=240, h=180):
    """n photos on 40 % of a circle around a textured cube in a textured room (all register)."""
    tex, room = _textures(0), _textures(1, blobs=48)
    K = np.array([[200.0, 0, w / 2], [0, 200.0, h / 2], [0, 0, 1]])
    os.makedirs(folder, exist_ok=True)
    c2ws = []
    for i in range(n):
        a = 2 * np.pi * i / n * 0.4
        eye = np.array([3.5 * np.cos(a), 3.5 * np.sin(a), 1.5 + 0.5 * np.sin(3 * a)])
        c2w = _look_at(eye)
        c2ws.append(c2w)
        img = render_cube(c2w, K, w, h, tex, room)
        cv2.imwrite(os.path.join(folder, f"shot_{i:02d}.png"), (img[..., ::-1] * 255 + 0.5).astype(np.uint8))
    return np.stack(c2ws), K


def _relative_rotation_errors(est, ref):
    """Degrees between R_i^T R_j of two camera sets (invariant to the similarity between their frames)."""
    errs = []
    for i in range(len(est)):
        for j in range(i + 1, len(est)):
            a = est[i, :3, :3].T @ est[j, :3, :3]
            b = ref[i, :3, :3].T @ ref[j, :3, :3]
            c = np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1)
            errs.append(np.degrees(np.arccos(c)))
    return np.array(errs)


def test_estimate_poses_on_rendered_photos_and_load_the_result(tmp_path, capfd):
    photos = str(tmp_path / "my photos")
    c2w, K = write_cube_photos(photos)
    out = str(tmp_path / "out")
    seen = []
    cfg = PosesConfig(camera_model="PINHOLE", num_threads=1, max_num_features=2000)
    capfd.readouterr()
    rep = estimate_poses(photos, out, cfg, progress=lambda p: seen.append((p.stage, p.fraction)))
    err = capfd.readouterr().err   # what pycolmap's C++ wrote to fd 2 as well
    assert not GLOG_LINE.search(err), err[:500]
    assert rep.registered == rep.num_images == 16 and rep.mean_reprojection_error < 1.0
    assert {s for s, _ in seen} >= {"extract", "match", "map"} and seen[-1][1] == 1.0
    fractions = [f for _, f in seen]
    assert fractions == sorted(fractions)  # progress never goes back
    for stage in ("extract", "match"):  # and moves within the long stages
        assert len({f for s, f in seen if s == stage}) >= 3
    report = json.load(open(os.path.join(out, "poses_report.json")))
    assert report["registered"] == 16 and report["images"] == photos
    scene = load_scene(out, holdout_every=0, log=lambda m: None)  # photos read where they are
    assert scene.kind == "colmap" and len(scene.split("train")) == 16
    assert scene.capture.points is not None and len(scene.capture.points) > 100
    est = scene.split("train").cameras.c2w.astype(np.float64)
    order = [int(n[5:7]) for n in scene.split("train").names]
    assert np.median(_relative_rotation_errors(est, c2w[order])) < 1.0


def test_map_database_from_a_synthetic_database_and_cancel(tmp_path, capfd):
    db_path = str(tmp_path / "database.db")
    opt = pycolmap.SyntheticDatasetOptions()
    opt.num_rigs, opt.num_frames_per_rig, opt.num_points3D = 1, 12, 300
    opt.camera_width, opt.camera_height = 128, 96
    opt.camera_model_id = pycolmap.CameraModelId.SIMPLE_RADIAL
    opt.camera_params = [150.0, 64.0, 48.0, 0.0]
    db = pycolmap.Database.open(db_path)
    truth = pycolmap.synthesize_dataset(opt, db)
    db.close()
    images = tmp_path / "images"
    images.mkdir()
    for im in truth.images.values():
        cv2.imwrite(str(images / im.name), np.full((96, 128, 3), 128, np.uint8))
    with pytest.raises(Cancelled):
        map_database(db_path, str(images), str(tmp_path / "cancelled"), progress=lambda p: False)
    level = pycolmap.logging.minloglevel
    capfd.readouterr()
    rep = map_database(db_path, str(images), str(tmp_path / "out"), PosesConfig(num_threads=1))
    assert not GLOG_LINE.search(capfd.readouterr().err)   # COLMAP's own log hidden by default ...
    assert rep.registered == 12 and rep.unregistered == []
    map_database(db_path, str(images), str(tmp_path / "shown"), PosesConfig(num_threads=1, colmap_log=True))
    assert len(GLOG_LINE.findall(capfd.readouterr().err)) > 10   # ... shown when asked for
    assert pycolmap.logging.minloglevel == level   # and the process's level is left as it was
    scene = load_scene(str(tmp_path / "out"), holdout_every=0, log=lambda m: None)
    by_name = {im.name: im for im in truth.images.values()}
    ref = []
    for name in scene.split("train").names:
        cfw = by_name[name].cam_from_world
        cfw = cfw() if callable(cfw) else cfw
        m = np.eye(4)
        m[:3, :4] = cfw.inverse().matrix()
        ref.append(m)
    est = scene.split("train").cameras.c2w.astype(np.float64)
    assert np.median(_relative_rotation_errors(est, np.stack(ref))) < 0.1


def test_pair_lists():
    from neumesh_core.reconstruct.poses import _exhaustive_pairs, _sequential_pairs

    assert _exhaustive_pairs(4) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    seq = _sequential_pairs(20, 3)
    assert (0, 1) in seq and (0, 3) in seq and (0, 4) in seq and (0, 8) in seq and (0, 5) not in seq
    assert all(i < j < 20 for i, j in seq) and len(set(seq)) == len(seq)


def test_clear_errors_for_missing_or_too_few_photos(tmp_path):
    with pytest.raises(PosesError, match="not found"):
        estimate_poses(str(tmp_path / "nope"), str(tmp_path / "out"))
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("x")
    with pytest.raises(PosesError, match="holds no photos"):
        estimate_poses(str(empty), str(tmp_path / "out"))
    for i in range(2):
        cv2.imwrite(str(empty / f"{i}.jpg"), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(PosesError, match="at least 3"):
        estimate_poses(str(empty), str(tmp_path / "out"))


def test_featureless_photos_say_what_to_do(tmp_path):
    photos = tmp_path / "flat"
    photos.mkdir()
    for i in range(4):
        cv2.imwrite(str(photos / f"{i}.png"), np.full((60, 80, 3), 100 + i, np.uint8))
    with pytest.raises(PosesError, match="overlap"):
        estimate_poses(str(photos), str(tmp_path / "out"), PosesConfig(num_threads=1))


def _write_video(path, frames, fps=10):
    h, w = frames[0].shape[:2]
    vw = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert vw.isOpened()
    for f in frames:
        vw.write(f)
    vw.release()


def test_frames_from_video_keeps_sharp_frames_and_refuses_blur(tmp_path):
    rng = np.random.default_rng(0)
    big = (rng.uniform(0, 255, size=(120, 400, 3))).astype(np.uint8)
    sharp = [np.ascontiguousarray(big[:, 4 * i:4 * i + 160]) for i in range(40)]
    clip = str(tmp_path / "clip.avi")
    _write_video(clip, sharp, fps=10)
    paths = frames_from_video(clip, str(tmp_path / "frames"), fps=2)
    assert 7 <= len(paths) <= 9 and all(os.path.isfile(p) for p in paths)
    blurry = [cv2.GaussianBlur(f, (0, 0), 8) for f in sharp]
    clip2 = str(tmp_path / "blurry.avi")
    _write_video(clip2, blurry, fps=10)
    with pytest.raises(PosesError, match="too blurry"):
        frames_from_video(clip2, str(tmp_path / "frames2"), fps=2)
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"not a video")
    with pytest.raises(PosesError):
        frames_from_video(str(bad), str(tmp_path / "frames3"))


def test_cli_poses_errors_are_clear(tmp_path, capsys):
    from neumesh_core.cli import main

    assert main(["poses", "--images", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "holds no photos" in capsys.readouterr().err
    assert main(["poses", "--out", str(tmp_path / "o")]) == 2


def test_cli_poses_from_a_video(tmp_path, capsys):
    """`neumesh poses --video`: frames extracted, matched sequentially, every frame placed, loadable."""
    from neumesh_core.cli import main

    photos = tmp_path / "frames_src"
    write_cube_photos(str(photos), n=20)
    clip = str(tmp_path / "clip.avi")
    _write_video(clip, [cv2.imread(str(photos / n)) for n in sorted(os.listdir(photos))], fps=8)
    out = tmp_path / "out"
    assert main(["poses", "--video", clip, "--fps", "8", "--out", str(out), "--threads", "1",
                 "--camera-model", "PINHOLE"]) == 0
    text = capsys.readouterr().out
    assert "registered 20 of 20 photos" in text
    report = json.load(open(out / "poses_report.json"))
    assert report["matcher"] == "sequential" and report["images"] == str(out / "images")
    assert len(load_scene(str(out), log=lambda m: None).split("train")) == 17


def test_cli_fit_from_plain_photos_recovers_poses_first_and_reuses_them(tmp_path, capfd):
    """`neumesh fit --images DIR`: poses into OUT/poses (photos read in place), then scaffold, training and
    evaluation on them; a second run reuses the poses. Neither --data nor --images: a clear error.
    Its stderr, a file here (capfd), reads clean: NeuMesh's lines for each stage, none of COLMAP's."""
    from neumesh_core.cli import main

    photos = str(tmp_path / "photos")
    write_cube_photos(photos, n=16)
    out = tmp_path / "out"
    args = ["fit", "--images", photos, "--out", str(out), "--steps", "4", "--method", "density",
            "--iters", "10,10", "--density-resolutions", "16,24", "--threads", "1", "--vertices", "2000",
            "--downscale", "2"]
    assert main(args) == 0
    err = capfd.readouterr().err
    assert "stage 0/3: poses from the photos" in err and "stage 1/3: scaffold" in err
    assert not GLOG_LINE.search(err) and "\r" not in err
    for stage in ("poses: features", "poses: matching", "poses: cameras", "scaffold: density", "training",
                  "evaluation"):
        lines = [ln for ln in err.splitlines() if ln.startswith(f"[{stage}] ")]
        assert len(lines) >= 2 and re.fullmatch(rf"\[{stage}\] done in \d:\d\d:\d\d.*", lines[-1]), (stage, err)
    assert "registered 16 of 16 photos" in err   # the poses' summary is in the log too
    report = json.load(open(out / "poses" / "poses_report.json"))
    assert report["registered"] == 16 and report["images"] == photos
    summary = json.load(open(out / "fit.json"))
    assert np.isfinite(summary["eval"]["psnr"]) and (out / "field.neumesh").is_file()
    assert main(args + ["--steps", "5"]) == 0
    assert "stage 0/3: poses (reusing" in capfd.readouterr().err
    assert main(["fit", "--out", str(out)]) == 2
    assert "give one of --data DIR" in capfd.readouterr().err
