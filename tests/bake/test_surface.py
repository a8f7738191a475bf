"""Where the field's surface is seen from a mesh, and moving a mesh onto it (neumesh_core/bake/surface.py).

An untrained, deterministic dense-shell field (``conftest.textured_field``) on the 2,562-vertex blob: its
density fills the band within the field radius of the scaffold, so its surface seen from outside lies
about one radius out from the blob.  No training: the module runs in a few seconds."""
import numpy as np
import pytest

from neumesh_core.bake import SurfaceFitConfig, fit_to_field, offset_stats, surface_offsets
from neumesh_core.bake.surface import render_disagreement, view_cameras
from neumesh_core.data.synthetic import default_mesh
from neumesh_core.mesh import vertex_normals
from ..conftest import one_thread, textured_field


@pytest.fixture(scope="module")
def shell(blob_mesh):
    return textured_field(blob_mesh, interpolation="early")


def _blob_points(mesh, count=400):
    n = np.asarray(vertex_normals(mesh.vertices, mesh.faces), np.float32)
    pick = np.random.default_rng(1).permutation(len(mesh.vertices))[:count]
    return mesh.vertices[pick].astype(np.float32), n[pick]


def test_surface_offsets_measure_the_distance_along_the_normal(shell, blob_mesh):
    p, n = _blob_points(blob_mesh)
    r = shell.radius
    with one_thread():
        off = surface_offsets(shell, p, n, search=2.0, level=0.5, step=0.05)
        moved = surface_offsets(shell, p + 0.4 * r * n, n, search=2.0, level=0.5, step=0.05)
        levels = surface_offsets(shell, p, n, search=2.0, level=[0.1, 0.5, 0.9], step=0.05)
    assert np.isfinite(off).all()
    # the dense band reaches about a radius out of the scaffold: the surface lies outside the blob
    assert 0.5 * r < np.median(off) < 1.05 * r, np.median(off) / r
    # moving the points out by 0.4 radii brings the surface 0.4 radii closer
    np.testing.assert_allclose(moved, off - 0.4 * r, atol=0.03 * r)
    # several levels from one pass: the same as one at a time for 0.5; a lower opacity lies farther out
    np.testing.assert_allclose(levels[:, 1], off, atol=1e-5)
    assert (levels[:, 0] >= levels[:, 1] - 1e-6).all() and (levels[:, 1] >= levels[:, 2] - 1e-6).all()
    assert (levels[:, 0] - levels[:, 2]).mean() > 0.01 * r
    # far from the field there is no surface: NaN, counted as not found
    far = surface_offsets(shell, p * 4.0, n, search=1.0)
    assert np.isnan(far).all()
    st = offset_stats(np.concatenate([off, far]), r)
    assert st["found"] == pytest.approx(0.5) and st["median_radii"] == pytest.approx(np.median(np.abs(off)) / r)


def test_fit_moves_a_mesh_onto_the_field_surface(shell):
    """A coarser blob inflated by 0.6 radii along its normals (so 0.4 radii inside the shell's outer
    surface, wherever) ends within a few hundredths of a radius of it."""
    r = shell.radius
    m = default_mesh(subdiv=3)
    n = np.asarray(vertex_normals(m.vertices, m.faces), np.float32)
    V = m.vertices + 0.6 * r * n
    with one_thread():
        fitted, info = fit_to_field(shell, V, m.faces, SurfaceFitConfig(level=0.5))
    assert fitted.shape == V.shape and np.isfinite(fitted).all()
    assert info["before"]["median_radii"] > 0.2
    assert info["after"]["median_radii"] < 0.05 and info["after"]["p90_radii"] < 0.1, info["after"]
    assert info["after"]["found"] == 1.0 and info["level"] == 0.5
    # the vertices moved along the normals (outwards here), not sideways
    d = fitted - V
    along = (d * n).sum(1)
    assert np.median(along) > 0.1 * r
    assert np.percentile(np.linalg.norm(d - along[:, None] * n, axis=1), 90) < 0.1 * r
    # the faces were fitted too, not only the vertices: a vertex-only fit leaves face centres farther
    with one_thread():
        _, vinfo = fit_to_field(shell, V, m.faces, SurfaceFitConfig(level=0.5, face_samples=0))
    assert vinfo["after"]["mean_radii"] >= info["after"]["mean_radii"] - 1e-3


def test_fit_calibrates_the_level_against_the_field_renders(shell):
    r = shell.radius
    m = default_mesh(subdiv=3)
    cfg = SurfaceFitConfig(level=None, levels=(0.05, 0.5, 0.95), views=3, view_size=48)
    with one_thread():
        fitted, info = fit_to_field(shell, m.vertices, m.faces, cfg)
    scores = info["level_scores"]
    assert set(scores) == {"0.05", "0.5", "0.95"}
    assert info["level"] == float(min(scores, key=scores.get))
    assert min(scores.values()) <= info["before_render_disagreement"]
    # the score is what it says: the field's own depth maps against themselves score 0, a mesh moved
    # two radii out scores worse than the fitted one
    cams = view_cameras(fitted, 3, 48)
    import neumesh_core as nm

    refs = []
    for K, c2w in cams:
        out = nm.render_camera(shell, K, c2w, 48, 48, background=None)
        refs.append(np.where(out.opacity >= 0.5, out.depth, np.inf))
    n = np.asarray(vertex_normals(fitted, m.faces), np.float32)
    assert render_disagreement(refs, fitted, m.faces, cams, 48, r) < \
        render_disagreement(refs, fitted + 2 * r * n, m.faces, cams, 48, r)
    for (K, c2w), ref in zip(cams, refs):   # the cameras look at the mesh: it fills part of each view
        assert 0.05 < np.isfinite(ref).mean() < 0.9


def test_fit_config_rejects_bad_values():
    with pytest.raises(ValueError):
        SurfaceFitConfig(level=1.0)
    with pytest.raises(ValueError):
        SurfaceFitConfig(levels=())
    with pytest.raises(ValueError):
        SurfaceFitConfig(face_samples=2)
    with pytest.raises(ValueError):
        SurfaceFitConfig(step=0)


def test_a_big_mesh_fits_a_subset_of_its_faces(shell):
    r = shell.radius
    m = default_mesh(subdiv=3)
    n = np.asarray(vertex_normals(m.vertices, m.faces), np.float32)
    V = m.vertices + 0.6 * r * n
    cap = len(V) + 3 * 100                         # the vertices and 100 of the 1,280 faces
    with one_thread():
        _, info = fit_to_field(shell, V, m.faces, SurfaceFitConfig(level=0.5, max_samples=cap))
    assert info["samples"] == cap
    assert info["after"]["median_radii"] < 0.05
