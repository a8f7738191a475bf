"""The object box found from sparse points (neumesh_core/data/frame.py): the support plane an object
hangs from is left out, the whole object is inside (thin parts too, no percentile cut), the room's
clutter is outside, and a capture with too few points gets the cube around the cameras' focus."""
import numpy as np
import pytest

from neumesh_core.data.synthetic.scene import look_at_opencv
from neumesh_core.data.frame import find_object, object_box, support_plane


def _wall_scene(seed=0):
    """A head on a plaque on a wall (the plane y = 0, cameras at y > 0), like a trophy photographed
    from the front: wall points, a plaque (a slab just in front of the wall), a head (a ball) with two
    thin ears (sparse lines of points that the clustering splits off), clutter on the wall far away,
    and a picture frame beside the head (a separate cluster off the wall)."""
    rng = np.random.default_rng(seed)
    wall = np.c_[rng.uniform(-4, 4, 3000), rng.normal(0, 0.005, 3000), rng.uniform(-3, 3, 3000)]
    plaque = np.c_[rng.uniform(-0.5, 0.5, 400), rng.uniform(0.05, 0.12, 400), rng.uniform(-0.7, 0.7, 400)]
    d = rng.normal(size=(1500, 3))
    head = d / np.linalg.norm(d, axis=1, keepdims=True) * 0.4 + [0.0, 0.55, 0.0]
    t = rng.uniform(0, 1, (2, 14))
    ears = np.concatenate([np.c_[s * (0.25 + 0.35 * t[i]), 0.55 + 0 * t[i], 0.3 + 0.45 * t[i]]
                           for i, s in enumerate((-1, 1))])
    frame = np.c_[rng.uniform(2.2, 2.8, 300), rng.uniform(0.05, 0.1, 300), rng.uniform(-0.3, 0.3, 300)]
    eyes = np.array([[4 * np.sin(a), 4 * np.cos(a), 0.3 * np.cos(3 * a)] for a in np.linspace(-0.9, 0.9, 20)])
    c2w = np.stack([look_at_opencv(e, (0.0, 0.4, 0.0)) for e in eyes])
    points = np.concatenate([wall, plaque, head, ears, frame])
    parts = {"wall": slice(0, 3000), "plaque": slice(3000, 3400), "head": slice(3400, 4900),
             "ears": slice(4900, 4928), "frame": slice(4928, 5228)}
    return c2w, points, parts


def test_the_object_on_a_wall_is_found_whole_and_the_wall_is_left_out():
    c2w, P, parts = _wall_scene()
    found = find_object(c2w, P)
    assert found.support is not None
    np.testing.assert_allclose(np.abs(found.support.normal), [0, 1, 0], atol=0.02)
    assert found.support.normal[1] > 0   # towards the cameras
    box = found.box
    for part in ("plaque", "head", "ears"):   # the whole object, its thin ears too
        assert box.contains(P[parts[part]]).all(), part
    assert found.object_points[parts["ears"]].all()
    assert box.on_support
    assert box.contains(P[parts["wall"]]).mean() < 0.01   # the wall is the room's
    assert not box.contains(P[parts["frame"]]).any()       # so is the picture frame beside it
    assert not box.contains(c2w[:, :3, 3]).any()
    assert any("support plane" in n for n in found.notes) and any("object:" in n for n in found.notes)
    assert object_box(c2w, P).half_extents == pytest.approx(box.half_extents)


def test_an_object_standing_free_is_boxed_from_its_own_points():
    c2w, P, parts = _wall_scene()
    free = np.concatenate([P[parts["head"]], P[parts["ears"]]])
    found = find_object(c2w, free)
    assert found.support is None
    assert found.box.contains(free).all()
    assert np.all(found.box.half_extents < 1.0)   # tight: the ball and ears span about 1.5 x 0.8 x 1.2


def test_a_face_of_the_object_is_not_its_support():
    rng = np.random.default_rng(2)
    u = rng.uniform(-1, 1, (6, 300, 2))   # a box's visible faces, its top the largest plane in the points
    top = np.c_[u[0] * [1, 1], np.ones(300)]
    sides = [np.c_[np.ones(300), u[i, :, 0], u[i, :, 1] * 0.5 + 0.5] for i in (1, 2)]
    P = np.concatenate([top, top + [0, 0, 1e-3], *sides])
    eyes = np.array([[4 * np.cos(a), 4 * np.sin(a), 3.0] for a in np.linspace(-0.6, 0.6, 12)])
    c2w = np.stack([look_at_opencv(e) for e in eyes])
    found = find_object(c2w, P)
    assert found.support is None and found.box.source.startswith("the sparse points of the object")
    assert found.box.contains(P).all() and np.all(found.box.half_extents < 1.5)


def test_support_plane_needs_the_cameras_on_one_side():
    rng = np.random.default_rng(1)
    plane = np.c_[rng.uniform(-1, 1, 500), rng.uniform(-1, 1, 500), rng.normal(0, 0.002, 500)]
    above = np.array([[0, 0, 3.0], [1, 0, 2.0], [0, 1, 2.5]])
    found = support_plane(plane, above, threshold=0.01)
    assert found is not None and found.inliers > 450
    np.testing.assert_allclose(found.normal, [0, 0, 1], atol=0.01)
    assert found.sigma == pytest.approx(0.002, rel=0.3)
    both = np.concatenate([above, -above])
    assert support_plane(plane, both, threshold=0.01) is None   # a plane between the cameras holds nothing up
    assert support_plane(rng.uniform(-1, 1, (500, 3)), above, threshold=0.01) is None   # no dominant plane


@pytest.mark.parametrize("points", [None, np.zeros((5, 3))])
def test_too_few_points_give_the_cube_around_the_focus_and_say_so(points):
    c2w, _, _ = _wall_scene()
    found = find_object(c2w, points)
    assert found.box.source == "the cameras' common look-at point"
    assert found.support is None and "needed" in found.notes[0]
    np.testing.assert_allclose(found.box.half_extents, found.box.half_extents[0])   # a cube
