"""The bake's target from the field's own density (neumesh_core/bake/extract.py) and texel colours from
the field's renders (neumesh_core/bake/project.py).

An untrained, deterministic dense-shell field (``conftest.textured_field``) on the 2,562-vertex blob:
its density fills the band within the field radius of the scaffold, so its surface lies about one
radius out from the blob and its colour is red for x > 0, blue elsewhere (the modification colour).
No training: the module runs in a few seconds."""
import numpy as np
import pytest
import torch

from neumesh_core.bake import ExtractConfig, ProjectConfig, density_grid, extract_surface, projected_colours
from neumesh_core.bake.surface import surface_offsets
from neumesh_core.errors import NeuMeshError
from neumesh_core.mesh import vertex_normals
from ..conftest import one_thread, textured_field


@pytest.fixture(scope="module")
def shell(blob_mesh):
    return textured_field(blob_mesh, interpolation="early")


def test_density_grid_matches_querying_every_node(shell):
    """The grid queries only nodes in (and one cell around) occupied cells; the reference queries all of
    them. Equal where queried; where skipped, the field's density is below any surface level."""
    r = shell.radius
    voxel = 0.8 * r
    with one_thread():
        vals, lo = density_grid(shell, voxel, chunk=5000)
        dims = vals.shape
        axes = [lo[i] + voxel * np.arange(dims[i]) for i in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
        with torch.no_grad():
            ref = np.concatenate([shell.sigma_fn(torch.from_numpy(grid[s:s + 65536]))[0].numpy()
                                  for s in range(0, len(grid), 65536)]).reshape(dims)
    queried = vals != 0
    assert queried.mean() < 0.9          # the mask skipped some of the box
    np.testing.assert_allclose(vals[queried], ref[queried], rtol=1e-4, atol=1e-4)
    lowest = -np.log(1 - min(ExtractConfig().levels)) / r
    assert ref[~queried].max() < lowest, (ref[~queried].max(), lowest)


def test_extract_surface_lies_on_the_fields_surface(shell, blob_mesh):
    r = shell.radius
    with one_thread():
        (V, F), info = extract_surface(shell, ExtractConfig(voxel=0.5, views=4, view_size=48))
        n = np.asarray(vertex_normals(V, F), np.float32)
        pick = np.random.default_rng(0).permutation(len(V))[:500]
        off = surface_offsets(shell, V[pick], n[pick], search=2.0, level=0.5, step=0.05)
        blob_off = surface_offsets(shell, blob_mesh.vertices[:500], np.asarray(
            vertex_normals(blob_mesh.vertices, blob_mesh.faces))[:500], search=2.0, level=0.5, step=0.05)
    assert info["level"] in ExtractConfig().levels and set(info["level_scores"]) == {
        f"{a:g}" for a in ExtractConfig().levels}
    assert info["faces"] == len(F) > 500 and F.max() < len(V)
    # the scaffold lies about a radius inside the surface; the extracted mesh on it
    assert np.nanmedian(np.abs(blob_off)) > 0.5 * r
    assert np.nanmedian(np.abs(off)) < 0.25 * r, np.nanmedian(np.abs(off)) / r
    # one fixed level: no calibration
    with one_thread():
        _, info1 = extract_surface(shell, ExtractConfig(voxel=0.8, level=0.5))
    assert info1["level"] == 0.5 and "level_scores" not in info1


def test_extract_and_project_configs_refuse_bad_values(shell):
    with pytest.raises(ValueError, match="opacity"):
        ExtractConfig(level=1.5)
    with pytest.raises(ValueError, match="voxel"):
        ExtractConfig(voxel=0)
    with pytest.raises(ValueError, match="views"):
        ProjectConfig(views=0)
    with pytest.raises(NeuMeshError, match="voxel"):
        density_grid(shell, 1e-4)          # far too many nodes: refused before any query


def test_projected_colours_see_the_field_and_skip_hidden_points(shell):
    """Points on the field's surface take its colour (red x > 0, blue x < 0); points hidden inside the
    mesh (behind its own faces from every view) get no weight."""
    with one_thread():
        (V, F), _ = extract_surface(shell, ExtractConfig(voxel=0.6, level=0.5))
        N = np.asarray(vertex_normals(V, F), np.float32)
        # the shell's density is a band: marching cubes meshes its outer and its inner wall; the outer
        # one (the component reaching farthest out) is what the cameras see
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        _, lab = connected_components(coo_matrix((np.ones(len(F) * 2), (np.r_[F[:, 0], F[:, 1]],
                                                                         np.r_[F[:, 1], F[:, 2]])),
                                                 shape=(len(V), len(V))), directed=False)
        outer_ids = np.nonzero(lab == lab[np.argmax(np.linalg.norm(V, axis=1))])[0]
        rng = np.random.default_rng(2)
        pick = outer_ids[rng.permutation(len(outer_ids))[:300]]
        inner = 0.3 * V[pick[:50]]                       # well inside the closed surface
        pts = np.concatenate([V[pick], inner])
        nrm = np.concatenate([N[pick], N[pick[:50]]])
        cols, w = projected_colours(shell, V, F, pts, nrm, ProjectConfig(views=12, size=64))
    outer, hidden = slice(0, 300), slice(300, 350)
    assert (w[hidden] == 0).all()
    seen = w[outer] > 0
    assert seen.mean() > 0.9
    x = pts[outer][:, 0]
    red = cols[outer][:, 0] - cols[outer][:, 2]
    far = seen & (np.abs(x) > 0.2 * np.abs(V[:, 0]).max())
    assert (np.sign(red[far]) == np.sign(x[far])).mean() > 0.95


@pytest.mark.parametrize("stop_at", [0.02, 0.07, 0.3])
def test_field_surface_bake_with_views_cancels_in_every_stage(shell, stop_at):
    """``mesh="field"`` + ``colours="views"`` (the add-on's default): progress rises through extraction
    (0-0.1: density grid, then the level's calibration renders) and projection (0.15-0.75, inside each
    view's render), and answering False in any of them raises Cancelled there, not at the end."""
    import neumesh_core as nm
    from neumesh_core.bake import bake_texture

    seen = []

    def progress(f):
        seen.append(float(f))
        return f < stop_at

    with one_thread(), pytest.raises(nm.Cancelled):
        bake_texture(shell, resolution=32, mesh="field", colours="views", vertex_colours=False,
                     extract=ExtractConfig(voxel=0.8, faces=300, views=2, view_size=32),
                     project=ProjectConfig(views=2, size=32), progress=progress)
    assert seen[-1] >= stop_at
    # stopped at the first answer past the point: inside the view's render (2 views span 0.15-0.45 and
    # 0.45-0.75; a render reports at 80% of its view's share), not at the view's end
    assert seen[-1] < stop_at + 0.1, seen[-3:]
    assert all(b >= a - 1e-9 for a, b in zip(seen, seen[1:])), "progress went backwards"


def test_bake_defaults_to_the_field_surface_with_projected_colours(shell):
    """By default ``bake_texture(field)`` bakes onto the field's own surface, decimated to
    FIELD_FACES x the scaffold's faces, with colours from the field's renders (the scaffold with rays is
    ``mesh=None, colours="rays"``)."""
    from neumesh_core.bake import bake_texture
    from neumesh_core.bake.texture import FIELD_FACES

    with one_thread():
        b = bake_texture(shell, resolution=32, vertex_colours=False, measure_texels=0,
                         project=ProjectConfig(views=2, size=32))
    assert b.info["mesh"] == "field" and "texels_unseen" in b.info and "fit" not in b.info
    target = FIELD_FACES * len(shell.faces)
    assert 0.8 * target <= b.info["mesh_faces"] <= 1.2 * target, (b.info["mesh_faces"], target)
