"""Sparse points of a capture with known poses (neumesh_core/reconstruct/points.py): triangulated from
photos the test renders itself (a textured cube in a textured room) with the true poses held fixed,
cached, with progress, cancel and pycolmap's log hidden; the object box found from them holds the cube."""
import json
import os

import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")
cv2 = pytest.importorskip("cv2")

from neumesh_core.data.capture import capture_object_box  # noqa: E402
from neumesh_core.data.loader import read_capture  # noqa: E402
from neumesh_core.errors import Cancelled  # noqa: E402
from neumesh_core.reconstruct.points import PointsConfig, capture_points, triangulate_capture, view_pairs  # noqa: E402

from .test_poses import GLOG_LINE, write_cube_photos  # noqa: E402


@pytest.fixture(autouse=True)
def _cache(tmp_path, monkeypatch):
    monkeypatch.setenv("NEUMESH_CACHE", str(tmp_path / "cache"))


def _write_transforms(root, n=16):
    """The cube photos with their true poses as an instant-ngp transforms.json (no points in it)."""
    c2w, K = write_cube_photos(os.path.join(root, "images"), n=n)
    frames = [{"file_path": f"images/shot_{i:02d}.png",
               "transform_matrix": (c2w[i] @ np.diag([1.0, -1.0, -1.0, 1.0])).tolist()} for i in range(n)]
    meta = {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": 240, "h": 180, "frames": frames}
    with open(os.path.join(root, "transforms.json"), "w") as fh:
        json.dump(meta, fh)
    return c2w


def _cube_distance(p):
    """Distance of points to the surface of the cube [-1, 1]^3."""
    q = np.abs(p) - 1.0
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.maximum(-q.max(1), 0.0)


def test_view_pairs_match_each_photo_with_its_nearest_views():
    eyes = [np.array([4 * np.cos(a), 4 * np.sin(a), 0.0]) for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)]
    from .test_poses import _look_at

    c2w = np.stack([_look_at(e) for e in eyes])
    pairs = view_pairs(c2w, neighbours=2)
    assert all(i < j for i, j in pairs) and len(set(pairs)) == len(pairs)
    neighbours = {i: set() for i in range(12)}
    for i, j in pairs:
        neighbours[i].add(j)
        neighbours[j].add(i)
    for i in range(12):   # on a ring the two nearest views are the two beside it
        assert {(i - 1) % 12, (i + 1) % 12} <= neighbours[i]


def test_points_triangulated_with_fixed_poses_lie_on_the_surfaces_and_are_cached(tmp_path, capfd):
    root = str(tmp_path / "capture")
    c2w = _write_transforms(root)
    capture = read_capture(root)
    assert capture.points is None
    cfg = PointsConfig(max_num_features=2000, num_threads=1)
    seen, said = [], []
    capfd.readouterr()
    pts = triangulate_capture(capture, cfg, progress=seen.append, log=said.append)
    assert not GLOG_LINE.search(capfd.readouterr().err)   # pycolmap's own log stays hidden
    assert len(pts) > 200 and not pts.cached
    assert seen == sorted(seen) and seen[-1] == 1.0 and len(set(seen)) >= 3
    assert "triangulated from 16 photos" in said[-1]
    # the poses were held fixed: the points land on the true cube (or the room's walls at 8)
    on_cube = _cube_distance(pts.points.astype(np.float64)) < 0.05
    on_room = np.abs(np.abs(pts.points).max(1) - 8.0) < 0.4
    assert (on_cube | on_room).mean() > 0.9 and on_cube.sum() > 100
    assert np.median(pts.errors) < 1.0 and pts.track_lengths.min() >= cfg.min_track_length

    again = triangulate_capture(capture, cfg, log=said.append)
    assert again.cached and "read back from the cache" in said[-1]
    np.testing.assert_array_equal(again.points, pts.points)
    assert not any(os.path.basename(f).endswith(".npz") for f in os.listdir(root))   # the dataset is not written

    # the object box found from them holds every point on the cube (its top face, seen from above,
    # is not taken for a table it stands on) and leaves the room and the cameras out
    box = capture_object_box(capture, capture_points(capture))
    assert box.source.startswith("the sparse points of the object")
    assert box.contains(pts.points[on_cube]).all()
    assert not box.contains(pts.points[on_room]).any()
    assert np.all(box.half_extents < 2.0)
    assert not box.contains(c2w[:, :3, 3]).any()


def test_triangulation_can_be_cancelled(tmp_path):
    root = str(tmp_path / "capture")
    _write_transforms(root, n=8)
    capture = read_capture(root)
    with pytest.raises(Cancelled):
        triangulate_capture(capture, PointsConfig(num_threads=1), progress=lambda f: False)
    assert not list((tmp_path / "cache").rglob("*.npz"))   # nothing half-made is kept


def test_capture_points_prefers_the_captures_own_points(tmp_path):
    root = str(tmp_path / "capture")
    _write_transforms(root, n=4)
    capture = read_capture(root)
    assert capture_points(capture, cached_only=True) is None   # nothing triangulated yet: no work done
    own = np.random.default_rng(0).uniform(-1, 1, (50, 3)).astype(np.float32)
    capture.points = own
    np.testing.assert_array_equal(capture_points(capture), own)


def test_the_scaffold_command_finds_the_box_of_photos_without_masks(tmp_path, capsys, monkeypatch):
    """`neumesh scaffold` on photos without masks builds inside the box `neumesh fit` finds (the
    fused scaffold itself: test_fusion.py)."""
    import neumesh_core.reconstruct.build as build
    from neumesh_core.cli import main

    class Built(Exception):
        pass

    def build_scaffold(scene, config, progress=None, log=None, box=None):
        raise Built(scene, config, box)

    monkeypatch.setattr(build, "build_scaffold", build_scaffold)
    root = str(tmp_path / "capture")
    _write_transforms(root)
    with pytest.raises(Built) as built:
        main(["scaffold", "--data", root, "--out", str(tmp_path / "scaffold.ply"), "--downscale", "2"])
    scene, config, box = built.value.args
    assert config.method == "auto" and box is not None
    assert box.source.startswith("the sparse points of the object")
    np.testing.assert_allclose(scene.bbox, box.aabb())   # the scaffold is bounded by the box
    assert np.all(box.half_extents < 2.0) and np.linalg.norm(box.centre) < 1.0   # the cube, not the room
    assert "object box (automatic, from the sparse points of the object" in capsys.readouterr().err
