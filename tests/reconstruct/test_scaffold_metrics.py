"""Silhouette rasteriser and Chamfer distance of the scaffold package (exact, small cases)."""
import numpy as np
import pytest
import trimesh

from neumesh_core.data.cameras import Cameras
from neumesh_core.mesh import Mesh
from neumesh_core.reconstruct.quality import chamfer_distance, rasterize_silhouette, silhouette_iou


def _look_at(eye, target=(0, 0, 0), up=(0, 0, 1)):
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, (0, 1, 0))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
    return m.astype(np.float32)


def _brute_force(v2d, faces, w, h):
    """Per-pixel point-in-triangle test (pixel centres, edges inclusive)."""
    ys, xs = np.mgrid[0:h, 0:w]
    p = np.stack([xs + 0.5, ys + 0.5], -1).reshape(-1, 2)
    out = np.zeros(len(p), bool)
    for f in faces:
        a, b, c = v2d[f]
        d = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        if abs(d) < 1e-14:
            continue
        s = np.sign(d)
        e = []
        for p0, p1 in ((a, b), (b, c), (c, a)):
            e.append(s * ((p1[0] - p0[0]) * (p[:, 1] - p0[1]) - (p1[1] - p0[1]) * (p[:, 0] - p0[0])) >= 0)
        out |= e[0] & e[1] & e[2]
    return out.reshape(h, w)


def test_rasterizer_matches_brute_force():
    rng = np.random.default_rng(3)
    w, h = 40, 30
    K = np.array([[30.0, 0, w / 2], [0, 30.0, h / 2], [0, 0, 1]], np.float32)
    c2w = np.eye(4, dtype=np.float32)  # camera at origin looking down +z
    # random triangles of all sizes (some partly off-screen) at depth 2..4
    n = 60
    centres = np.c_[rng.uniform(-1.5, 1.5, (n, 2)), rng.uniform(2, 4, n)]
    size = rng.choice([0.02, 0.1, 0.5, 1.5], n)[:, None, None]
    verts = (centres[:, None, :] + rng.normal(size=(n, 3, 3)) * size).reshape(-1, 3)
    verts[:, 2] = np.abs(verts[:, 2]) + 0.5
    faces = np.arange(3 * n).reshape(n, 3)
    sil = rasterize_silhouette(verts, faces, K, c2w, w, h)
    uv = (verts / verts[:, 2:3]) @ K.T.astype(np.float64)
    ref = _brute_force(uv[:, :2], faces, w, h)
    assert sil.shape == (h, w)
    assert sil.sum() > 50  # the case is not trivial
    mismatch = (sil != ref).sum()
    assert mismatch <= 2, f"{mismatch} pixels differ from the brute-force rasteriser"


def test_sphere_silhouette_iou_matches_disk():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.5)
    mesh = Mesh(sphere.vertices, sphere.faces)
    w = h = 64
    f = 80.0
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], np.float32)
    eyes = [(3, 0, 0), (0, 3, 0.5), (-2, -2, 1)]
    c2w = np.stack([_look_at(e) for e in eyes])
    cams = Cameras(K, c2w, w, h)
    masks = []
    for e in eyes:
        d = np.linalg.norm(e)
        r_px = f * 0.5 / np.sqrt(d * d - 0.25)  # projected radius of a sphere (tangent cone)
        ys, xs = np.mgrid[0:h, 0:w] + 0.5
        masks.append(((xs - w / 2) ** 2 + (ys - h / 2) ** 2 <= r_px ** 2).astype(np.float32))
    res = silhouette_iou(mesh, cams, np.stack(masks))
    assert res["mean"] > 0.97 and res["min"] > 0.96
    # a shifted mesh must score clearly lower: the metric can fail
    shifted = Mesh(mesh.vertices + np.array([0, 0, 0.25], np.float32), mesh.faces)
    assert silhouette_iou(shifted, cams, np.stack(masks))["mean"] < 0.8


def test_chamfer_distance():
    a = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    ma = Mesh(a.vertices, a.faces)
    same = chamfer_distance(ma, ma, 20000)
    assert same["chamfer"] < 0.02  # sampling noise only
    mb = Mesh(a.vertices * 1.1, a.faces)
    ch = chamfer_distance(ma, mb, 20000)
    assert ch["chamfer"] == pytest.approx(0.1, abs=0.02)
    assert ch["accuracy"] > 0.08 and ch["completeness"] > 0.08


def test_mesh_cleanup_helpers():
    from neumesh_core.reconstruct.meshing import clean_mesh, keep_large_components, midpoint_subdivide

    s = trimesh.creation.icosphere(subdivisions=2)
    m = Mesh(s.vertices, s.faces)
    d = midpoint_subdivide(m)
    assert len(d.faces) == 4 * len(m.faces)
    assert d.num_vertices == m.num_vertices + len(m.edges())
    # duplicate + degenerate faces and an unreferenced vertex are removed
    v = np.vstack([m.vertices, [[9, 9, 9]]])
    f = np.vstack([m.faces, m.faces[:3, ::-1], [[0, 0, 1]]])
    c = clean_mesh(Mesh(v, f))
    assert len(c.faces) == len(m.faces) and c.num_vertices == m.num_vertices
    # a tiny floater is dropped, the big component kept
    small = trimesh.creation.icosphere(subdivisions=0, radius=0.01)
    both = Mesh(np.vstack([m.vertices, small.vertices + 3]), np.vstack([m.faces, small.faces + m.num_vertices]))
    k, n_found, n_kept = keep_large_components(both, min_fraction=0.1)
    assert (n_found, n_kept) == (2, 1) and len(k.faces) == len(m.faces)
