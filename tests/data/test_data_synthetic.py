"""Built-in default scene (neumesh_core/data/synthetic.py)."""
import json
import os

import numpy as np
import pytest
import torch
from scipy.spatial import ConvexHull

from neumesh_core.data import synthetic as S
from neumesh_core.data.blender import load_blender
from neumesh_core.imageio import read_image
from neumesh_core.mesh import load_mesh


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("cache")
    return S.default_scene_dir(cache_root=str(root), small=True), str(root)


def _K(res, angle=S.CAMERA_ANGLE_X):
    f = 0.5 * res / np.tan(0.5 * angle)
    return np.array([[f, 0, res / 2], [0, f, res / 2], [0, 0, 1]])


def test_mesh_on_analytic_surface_and_non_convex():
    m = S.default_mesh(5)
    assert m.vertices.shape == (10242, 3) and m.faces.shape == (20480, 3)
    v = m.vertices.astype(np.float64)
    err = np.abs(np.linalg.norm(v, axis=1) - S.surface_radius(v))
    assert err.max() < 1e-5
    tri = v[m.faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert ((fn * tri.mean(1)).sum(1) > 0).all()  # counter-clockwise = outward
    assert len(m.edges()) == 30720  # closed manifold: E = 3F/2
    hull = ConvexHull(v)
    assert len(hull.vertices) < 0.8 * len(v)  # many vertices lie in concavities
    r = np.linalg.norm(v, axis=1)
    assert r.min() > 0.7 and r.max() < 1.5 and r.max() - r.min() > 0.35


def test_analytic_normals_match_finite_differences():
    rng = np.random.default_rng(0)
    u = rng.normal(size=(50, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    p = u * S.surface_radius(u)[:, None]
    n = S.surface_normal(p)
    eps = 1e-6
    x = torch.as_tensor(p)
    grad = np.stack([
        ((S.implicit(x + eps * torch.eye(3, dtype=torch.float64)[k])
          - S.implicit(x - eps * torch.eye(3, dtype=torch.float64)[k])) / (2 * eps)).numpy()
        for k in range(3)
    ], 1)
    grad /= np.linalg.norm(grad, axis=1, keepdims=True)
    np.testing.assert_allclose(n, grad, atol=1e-6)


def test_trace_finds_first_root():
    rng = np.random.default_rng(1)
    o = torch.as_tensor(np.tile([[0.3, -3.5, 0.8]], (400, 1)))
    target = rng.uniform(-1.4, 1.4, size=(400, 3))
    d = torch.as_tensor(target) - o
    d = d / d.norm(dim=-1, keepdim=True)
    hit, t = S.trace_rays(o, d)
    assert 50 < int(hit.sum()) < 400  # both hits and misses
    p = o[hit] + t[hit, None] * d[hit]
    assert S.implicit(p).abs().max() < 1e-5
    # brute force: no sign change before t along hit rays, none at all along missed rays
    ts = torch.linspace(0, 8, 8001, dtype=torch.float64)
    sel = torch.arange(0, 400, 7)
    pts = o[sel, None, :] + ts[None, :, None] * d[sel, None, :]
    f = S.implicit(pts.reshape(-1, 3)).reshape(len(sel), -1)
    for j, i in enumerate(sel.tolist()):
        neg = torch.nonzero(f[j] < 0)
        if hit[i]:
            assert len(neg) and abs(float(ts[neg[0, 0]]) - float(t[i])) < 2e-3
        else:
            assert len(neg) == 0


def test_texture_is_colourful_and_high_contrast():
    m = S.default_mesh(5)
    alb = S.default_texture(m.vertices, m.vertex_normals())
    assert alb.shape == (10242, 3) and alb.dtype == np.float32
    assert alb.min() >= 0 and alb.max() <= 1
    assert len(np.unique(np.round(alb, 2), axis=0)) >= 8
    lum = alb.mean(1)
    assert lum.max() - lum.min() > 0.8  # ink vs paper
    # high frequency: neighbouring vertices often differ strongly
    e = m.edges()
    jumps = np.abs(alb[e[:, 0]] - alb[e[:, 1]]).max(1)
    assert (jumps > 0.3).mean() > 0.05


def _mesh_silhouette(mesh, K, c2w, res):
    w2c = np.linalg.inv(c2w)
    pc = mesh.vertices.astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    assert (pc[:, 2] > 0).all()
    uv = (pc @ K.T)[:, :2] / pc[:, 2:3]
    ys, xs = np.mgrid[0:res, 0:res]
    pix = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], 1)
    sil = np.zeros(len(pix), bool)
    tri = uv[mesh.faces]
    lo, hi = tri.min((0, 1)), tri.max((0, 1))
    keep = ((pix >= lo - 1) & (pix <= hi + 1)).all(1)
    sil_full = sil
    sil, pix = sil[keep], pix[keep]
    for s in range(0, len(tri), 512):
        a, b, c = tri[s:s + 512, 0], tri[s:s + 512, 1], tri[s:s + 512, 2]
        def cross(p0, p1, q):
            return (p1[:, None, 0] - p0[:, None, 0]) * (q[None, :, 1] - p0[:, None, 1]) - \
                   (p1[:, None, 1] - p0[:, None, 1]) * (q[None, :, 0] - p0[:, None, 0])
        w0, w1, w2 = cross(b, c, pix), cross(c, a, pix), cross(a, b, pix)
        inside = ((w0 >= 0) & (w1 >= 0) & (w2 >= 0)) | ((w0 <= 0) & (w1 <= 0) & (w2 <= 0))
        sil |= inside.any(0)
    sil_full[keep] = sil
    return sil_full.reshape(res, res)


def test_reference_render_matches_mesh_silhouette_and_is_deterministic():
    res = 64
    mesh = S.default_mesh(4)  # chord error ~1e-3, far below a pixel (~0.06)
    K = _K(res)
    for pos in ([0.5, -3.9, 0.6], [-2.0, 1.0, -3.2]):
        c2w = S.look_at_opencv(np.array(pos, dtype=np.float64))
        rgb, alpha = S.render_truth(K, c2w, res, res)
        assert rgb.shape == (res, res, 3) and alpha.shape == (res, res)
        sil = _mesh_silhouette(mesh, K, c2w, res)
        for a_mask in (alpha >= 0.5, alpha > 0):
            iou = (a_mask & sil).sum() / (a_mask | sil).sum()
            assert iou > 0.95, iou
        assert 0.1 < alpha.mean() < 0.6  # the object fills a good part of the frame
        assert ((alpha > 0) & (alpha < 1)).sum() > 20  # anti-aliased, soft edges
        np.testing.assert_allclose(rgb[alpha == 0], 1.0)  # white background
        rgb2, alpha2 = S.render_truth(K, c2w, res, res)
        # exact on purpose: determinism of one function called twice in one process on one machine
        np.testing.assert_array_equal(rgb, rgb2)
        np.testing.assert_array_equal(alpha, alpha2)
        black, _ = S.render_truth(K, c2w, res, res, background=(0, 0, 0))
        np.testing.assert_allclose(black + (1 - alpha[..., None]), rgb, atol=1e-5)
    # a camera looking away sees nothing
    away = S.look_at_opencv(np.array([0.0, -4.0, 0.0]), target=(0.0, -8.0, 0.0))
    _, a = S.render_truth(K, away, 16, 16)
    assert a.max() == 0


def test_small_scene_round_trip(small_scene):
    path, cache_root = small_scene
    assert os.path.basename(path) == "default_scene_v1_small"
    desc = json.load(open(os.path.join(path, "scene.json")))
    assert desc["params"]["resolution"] == 64 and desc["version"] == 1
    scene = load_blender(path, background=None)
    assert scene.mesh_path == os.path.join(path, "mesh.ply")
    mesh = load_mesh(scene.mesh_path)
    assert mesh.num_vertices == 2562 and desc["mesh"]["vertices"] == 2562
    np.testing.assert_allclose(mesh.vertices, S.default_mesh(4).vertices, atol=1e-6)
    tr, va, te = scene.split("train"), scene.split("val"), scene.split("test")
    assert (len(tr), len(va), len(te)) == (30, 4, 4)
    assert tr.images.shape == (30, 64, 64, 3) and tr.masks.shape == (30, 64, 64)
    np.testing.assert_allclose(tr.cameras.K[0], _K(64), rtol=1e-5)
    z = np.concatenate([s.cameras.centres[:, 2] for s in (tr, va, te)])
    assert (z > 0.5).any() and (z < -0.5).any()  # both hemispheres
    np.testing.assert_allclose(np.linalg.norm(tr.cameras.centres, axis=1), S.CAMERA_RADIUS, rtol=1e-5)
    dmin = np.linalg.norm(va.cameras.centres[:, None] - tr.cameras.centres[None], axis=-1).min()
    assert dmin > 0.05  # held-out views are not training views
    # the stored images are the reference renders of the stored cameras (8-bit rounding)
    rgb, alpha = S.render_truth(va.cameras.K[2], va.cameras.c2w[2], 64, 64, background=None,
                                    seed=0 * 100_003 + 10_000 + 2)
    png = read_image(os.path.join(path, "val", "r_2.png"))
    np.testing.assert_allclose(png[..., 3], alpha, atol=0.6 / 255)
    np.testing.assert_allclose(png[..., :3][alpha > 0], rgb[alpha > 0], atol=1e-3 + 0.6 / 255)
    # reused, not regenerated
    def boom(*a, **k):
        raise AssertionError("regenerated a complete cached scene")
    orig = S.make_default_scene
    S.make_default_scene = boom
    try:
        assert S.default_scene_dir(cache_root=cache_root, small=True) == path
    finally:
        S.make_default_scene = orig


def test_make_default_scene_is_deterministic(tmp_path, small_scene):
    path, _ = small_scene
    out = S.make_default_scene(str(tmp_path / "again"), **S.SMALL_SCENE_KWARGS)
    # byte equality on purpose: both scenes are generated in this process on this machine (the fixture
    # is not a file committed from another CPU), so the same code must give the same bytes
    for name in ("transforms_train.json", "transforms_test.json", "scene.json", "train/r_0.png",
                 "test/r_3.png", "mesh.ply"):
        with open(os.path.join(out, name), "rb") as a, open(os.path.join(path, name), "rb") as b:
            assert a.read() == b.read(), name


def test_cache_location(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert S._cache_base() == os.path.join(str(tmp_path / "xdg"), "neumesh")
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert S._cache_base() == os.path.join(os.path.expanduser("~"), ".cache", "neumesh")
    assert S._cache_base(str(tmp_path)) == str(tmp_path)
