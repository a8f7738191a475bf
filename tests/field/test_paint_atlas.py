"""The paint atlas (neumesh_core/field/paint_atlas.py): the nearest-face lookup against a brute-force
reference, compositing in the render, following a deformation, and saving it with the field in a
versioned way (files without one load unchanged)."""
import json

import numpy as np
import pytest
import torch

import neumesh_core as nm
from neumesh_core.errors import CheckpointError, NeuMeshError
from neumesh_core.field.paint_atlas import (PaintAtlas, closest_faces_reference, closest_points_on_triangles)

from ..conftest import textured_field
from ..edit.helpers import camera

S = 48


@pytest.fixture(scope="module")
def blob3():
    from neumesh_core.data.synthetic import default_mesh

    return default_mesh(subdiv=3)


def _atlas(field, res=64, fill=None):
    """An atlas with planar UVs per vertex (x, y of the rest pose scaled into [0, 1])."""
    v = field.rest_vertices.numpy()
    uv = (v[:, :2] - v[:, :2].min(0)) / np.ptp(v[:, :2], 0).max()
    img = np.zeros((res, res, 4), np.float32)
    if fill is not None:
        img[:] = fill
    return PaintAtlas(uv[field.faces.numpy()], img, "given")


def test_closest_point_on_a_triangle_matches_dense_sampling():
    rng = np.random.default_rng(0)
    a, b, c = np.array([0.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0.2, 0.8, 0])
    # points around the triangle, above and below it: every Voronoi region (vertices, edges, face)
    p = rng.uniform([-0.6, -0.6, -0.5], [1.6, 1.4, 0.5], size=(400, 3))
    bary = closest_points_on_triangles(p, *(np.repeat(x[None], len(p), 0) for x in (a, b, c)))
    assert np.allclose(bary.sum(1), 1) and (bary >= -1e-9).all()
    x = bary @ np.stack([a, b, c])
    g = np.linspace(0, 1, 201)
    u, v = np.meshgrid(g, g)
    keep = (u + v) <= 1
    dense = a + u[keep, None] * (b - a) + v[keep, None] * (c - a)
    dmin = np.linalg.norm(p[:, None] - dense[None], axis=2).min(1)
    d = np.linalg.norm(p - x, axis=1)
    assert (d <= dmin + 1e-9).all() and np.allclose(d, dmin, atol=5e-3)


def test_closest_faces_match_the_reference(blob3):
    field = textured_field(blob3, interpolation="early")
    atlas = _atlas(field)
    rng = np.random.default_rng(1)
    v = field.vertices
    p = v[rng.integers(0, len(v), 150)] + rng.normal(0, 0.5 * field.radius, (150, 3))
    for pose in range(2):
        face, bary, dist = atlas.closest_faces(field, p)
        rf, rb, rd = closest_faces_reference(p, field.vertices, field.faces.numpy())
        np.testing.assert_allclose(dist, rd, atol=1e-7)
        same = face == rf                       # ties (a point nearest to a shared edge) may differ
        assert same.mean() > 0.9
        np.testing.assert_allclose(bary[same], rb[same], atol=1e-6)
        # the lookup follows the current pose (the centroid tree is rebuilt after set_vertices)
        field.set_vertices(field.vertices * np.array([1.2, 1.0, 0.9], np.float32))
        p = p * np.array([1.2, 1.0, 0.9])


def test_render_composites_the_paint_and_an_empty_atlas_changes_nothing(blob3):
    field = textured_field(blob3, interpolation="early")
    K, c2w = camera(20.0, size=S)
    ref = nm.render_camera(field, K, c2w, S, S)
    field.paint_atlas = _atlas(field)
    empty = nm.render_camera(field, K, c2w, S, S)
    np.testing.assert_allclose(empty.rgb, ref.rgb, atol=0)
    field.paint_atlas = _atlas(field, fill=(1.0, 0.0, 0.0, 1.0))      # everything painted opaque red
    red = nm.render_camera(field, K, c2w, S, S, background=(0, 1, 0))
    a = ref.opacity[..., None]
    np.testing.assert_allclose(red.rgb, a * np.array([1.0, 0, 0]) + (1 - a) * np.array([0, 1.0, 0]), atol=1e-5)
    field.paint_atlas = _atlas(field, fill=(0.0, 0.0, 1.0, 0.5))      # half-transparent blue over the field
    blue = nm.render_camera(field, K, c2w, S, S, background=None)
    plain = nm.render_camera(textured_field(blob3, interpolation="early"), K, c2w, S, S, background=None)
    np.testing.assert_allclose(blue.rgb, 0.5 * plain.rgb + 0.5 * plain.opacity[..., None] * np.array([0, 0, 1.0]),
                               atol=1e-5)


def test_paint_follows_a_rigid_motion(blob3):
    """The atlas is bound to the scaffold's faces: moving the field and the camera together renders the
    same picture."""
    field = textured_field(blob3, interpolation="early")
    atlas = _atlas(field, res=32)
    img = atlas.image.numpy()
    img[::2, :, :] = (1.0, 0.9, 0.0, 1.0)          # stripes
    atlas.changed()
    field.paint_atlas = atlas
    K, c2w = camera(40.0, size=S)
    a = nm.render_camera(field, K, c2w, S, S)
    shift = np.array([0.3, -0.2, 0.1], np.float32)
    field.set_vertices(field.vertices + shift)
    moved = c2w.copy()
    moved[:3, 3] += shift
    b = nm.render_camera(field, K, moved, S, S)
    assert np.abs(a.rgb - b.rgb).max() < 0.02
    assert np.abs(a.rgb - nm.render_camera(textured_field(blob3, interpolation="early"), K, c2w, S, S).rgb).max() > 0.2


def test_atlas_is_saved_with_the_field_and_older_files_load_unchanged(blob3, tmp_path):
    field = textured_field(blob3, interpolation="early")
    plain = tmp_path / "plain.neumesh"
    nm.save_field(field, str(plain))
    from safetensors import safe_open

    with safe_open(str(plain), "pt") as fh:
        assert not any(k.startswith("paint/") for k in fh.keys())
        assert "paint_atlas" not in json.loads(fh.metadata()["neumesh"])
    assert getattr(nm.load_field(str(plain)), "paint_atlas", None) is None
    atlas = _atlas(field, res=16)
    atlas.image[3, 5] = torch.tensor([0.2, 0.4, 0.6, 1.0])
    field.paint_atlas = atlas
    path = tmp_path / "painted.neumesh"
    nm.save_field(field, str(path))
    back = nm.load_field(str(path))
    assert back.paint_atlas is not None and back.paint_atlas.source == "given"
    np.testing.assert_allclose(back.paint_atlas.uv.numpy(), atlas.uv.numpy(), atol=0)
    np.testing.assert_allclose(back.paint_atlas.image.numpy(), atlas.image.numpy(), atol=0.5 / 255 + 1e-6)
    # a newer atlas version is refused with what to do; a header without its tensors is incomplete
    from safetensors.torch import load_file, save_file

    t = load_file(str(path))
    with safe_open(str(path), "pt") as fh:
        meta = json.loads(fh.metadata()["neumesh"])
    meta["paint_atlas"]["version"] = 99
    save_file(t, str(tmp_path / "newer.neumesh"), metadata={"neumesh": json.dumps(meta)})
    with pytest.raises(CheckpointError, match="update NeuMesh"):
        nm.load_field(str(tmp_path / "newer.neumesh"))
    meta["paint_atlas"]["version"] = 1
    del t["paint/image"]
    save_file(t, str(tmp_path / "cut.neumesh"), metadata={"neumesh": json.dumps(meta)})
    with pytest.raises(CheckpointError, match="incomplete"):
        nm.load_field(str(tmp_path / "cut.neumesh"))


def test_bad_atlases_are_refused(blob3):
    field = textured_field(blob3, interpolation="early")
    with pytest.raises(NeuMeshError):
        PaintAtlas(np.zeros((4, 3)), np.zeros((8, 8, 4)))
    with pytest.raises(NeuMeshError):
        PaintAtlas(np.zeros((4, 3, 2)), np.zeros((8, 8, 3)))
    with pytest.raises(NeuMeshError, match="topology"):
        PaintAtlas(np.zeros((4, 3, 2)), np.zeros((8, 8, 4))).closest_faces(field, np.zeros((1, 3)))


def test_grid_atlas_lays_faces_out_without_overlap(blob3):
    from neumesh_core.bake.uv import uv_pixels
    from neumesh_core.field.paint_atlas import grid_atlas
    from neumesh_core.render.raster import raster_triangles

    F = blob3.faces
    res = 128
    uv, cell = grid_atlas(F, res)
    assert uv.shape == (len(F), 3, 2) and uv.min() >= 0 and uv.max() <= 1
    # no texel centre lies in two triangles (strictly inside by 1e-4 barycentric)
    counts = np.zeros(res * res, np.int64)
    for _, px, _ in raster_triangles(uv_pixels(uv.reshape(-1, 2), res).reshape(-1, 3, 2), res, res, eps=-1e-4):
        np.add.at(counts, px, 1)
    assert counts.max() == 1 and (counts > 0).mean() > 0.15    # 4.9-texel cells, 1-texel gutters: 22%
    # most faces share their cell with a neighbour across an edge, the edge's UVs identical on both sides
    cells = np.floor(uv_pixels(uv.reshape(-1, 2), res).reshape(-1, 3, 2).mean(1) / cell).astype(int)
    key = cells[:, 0] * 100000 + cells[:, 1]
    _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    assert (cnt[inv] == 2).mean() > 0.6 and cnt.max() <= 2     # greedy matching: 74% paired
    f1, f2 = [np.nonzero(inv == inv[i])[0] for i in range(1)][0]
    shared = set(F[f1]) & set(F[f2])
    assert len(shared) == 2
    for v in shared:
        np.testing.assert_allclose(uv[f1][list(F[f1]).index(v)], uv[f2][list(F[f2]).index(v)], atol=0)
    with pytest.raises(NeuMeshError, match="larger resolution"):
        grid_atlas(F, 16)


def test_surface_offsets_move_the_lookup_surface_and_are_saved(blob3, tmp_path):
    field = textured_field(blob3, interpolation="early")
    base = _atlas(field)
    off = np.full(field.num_vertices, 0.5 * field.radius, np.float32)
    atlas = PaintAtlas(base.uv, base.image, "given", None, off)
    n = field.scaffold.normals.numpy()
    np.testing.assert_allclose(atlas.lookup_vertices(field), field.vertices + 0.5 * field.radius * n, atol=1e-6)
    # a point on the moved surface is at distance ~0 from it, but half a radius from the scaffold
    p = (field.vertices + 0.5 * field.radius * n)[:20]
    assert atlas.closest_faces(field, p)[2].max() < 1e-6
    assert base.closest_faces(field, p)[2].min() > 0.3 * field.radius
    field.paint_atlas = atlas
    nm.save_field(field, str(tmp_path / "f.neumesh"))
    back = nm.load_field(str(tmp_path / "f.neumesh")).paint_atlas
    np.testing.assert_allclose(back.offsets.numpy(), off, atol=0)
    with pytest.raises(NeuMeshError, match="offsets"):
        PaintAtlas(base.uv, base.image, "given", None, off[:5]).lookup_vertices(field)


def test_set_image_updates_the_sampled_paint_as_a_full_rebuild_does(blob3):
    """set_image (a paint program's pixels, a region at a time) updates the premultiplied copy the
    render samples texel by texel; the reference is the copy rebuilt from the whole image."""
    field = textured_field(blob3, interpolation="early")
    atlas = field.paint_atlas = _atlas(field, res=32)
    K, c2w = camera(20.0, size=S)
    plain = nm.render_camera(field, K, c2w, S, S).rgb
    rng = np.random.default_rng(3)
    px = rng.uniform(0, 1, (10, 12, 4)).astype(np.float32)
    px[..., 3] = np.where(px[..., 3] > 0.4, px[..., 3], 0.0)
    changed = atlas.set_image(px, (18, 28, 8, 20))
    assert len(changed) == int((np.abs(px).max(-1) > 0).sum())
    assert set((changed // 32).tolist()) <= set(range(18, 28)) and set((changed % 32).tolist()) <= set(range(8, 20))
    np.testing.assert_allclose(atlas.image.numpy()[18:28, 8:20], px, atol=0)
    uv = rng.uniform(0, 1, (500, 2))                    # (the view sees rows 14-32 of this atlas)
    fast = atlas.sample(uv)
    atlas.changed()                                        # the reference: rebuilt from the whole image
    np.testing.assert_allclose(fast, atlas.sample(uv), atol=1e-6)
    assert not atlas.is_empty
    painted = nm.render_camera(field, K, c2w, S, S).rgb
    # the same pixels again change nothing; clearing them brings the plain render back
    assert len(atlas.set_image(px, (18, 28, 8, 20))) == 0
    atlas.set_image(np.zeros((10, 12, 4), np.float32), (18, 28, 8, 20))
    assert atlas.is_empty
    np.testing.assert_allclose(nm.render_camera(field, K, c2w, S, S).rgb, plain, atol=1e-6)
    assert np.abs(painted - plain).max() > 0.05
    # set_texels (the changed texels known) writes the same image as set_image, its reference
    other = _atlas(field, res=32)
    yy, xx = np.mgrid[18:28, 8:20]
    got = other.set_texels((yy * 32 + xx).ravel(), px.reshape(-1, 4))
    np.testing.assert_array_equal(np.sort(got), np.sort(changed))
    atlas.set_image(px, (18, 28, 8, 20))
    np.testing.assert_allclose(other.image.numpy(), atlas.image.numpy(), atol=0)
    np.testing.assert_allclose(other.sample(uv), atlas.sample(uv), atol=1e-6)
    with pytest.raises(NeuMeshError, match="outside"):
        other.set_texels([32 * 32], [[0, 0, 0, 1]])
    with pytest.raises(NeuMeshError, match="RGBA values"):
        other.set_texels([1, 2], [[0, 0, 0, 1]])
    atlas.set_image(np.zeros((10, 12, 4), np.float32), (18, 28, 8, 20))
    with pytest.raises(NeuMeshError, match="outside"):
        atlas.set_image(px, (25, 35, 0, 12))
    with pytest.raises(NeuMeshError, match="resized"):
        atlas.set_image(px, (0, 12, 0, 10))
    with pytest.raises(NeuMeshError, match="NaN"):
        atlas.set_image(np.full((32, 32, 4), np.nan, np.float32))


def test_texels_written_while_another_thread_builds_the_sampled_copy_are_sampled_as_written(blob3, monkeypatch):
    """A paint program writes texels in one thread while a render builds the premultiplied copy it
    samples in another (the first render after the atlas was made; seconds at 4096^2): the build is
    held after reading the colours and before reading the alpha, the texels are written then, and every
    one is sampled as written, none with the colour from before the write and the alpha from after it
    (black paint).  A copy of the atlas samples its own image."""
    import copy
    import threading

    from neumesh_core.field import paint_copy

    res = 64
    atlas = _atlas(textured_field(blob3, interpolation="early"), res=res)
    read_colour, written = threading.Event(), threading.Event()
    plain = paint_copy.premultiply

    def held(rows):
        if rows.ndim == 3:                                 # the whole image: a build
            rgb = rows[..., :3] * rows[..., 3:]
            read_colour.set()
            assert written.wait(30)
            return np.concatenate([rgb, rows[..., 3:]], -1).astype(np.float16)
        return plain(rows)

    monkeypatch.setattr(paint_copy, "premultiply", held)
    render = threading.Thread(target=lambda: atlas.is_empty)
    render.start()
    assert read_colour.wait(30)
    yy, xx = np.mgrid[10:20, 30:50]
    texels = (yy * res + xx).ravel()
    cyan = np.tile(np.float32([0.0, 1.0, 1.0, 1.0]), (len(texels), 1))
    assert len(atlas.set_texels(texels, cyan)) == len(texels)
    written.set()
    render.join(30)
    assert not render.is_alive()
    monkeypatch.setattr(paint_copy, "premultiply", plain)
    uv = np.stack([(xx.ravel() + 0.5) / res, 1.0 - (yy.ravel() + 0.5) / res], 1)   # texel centres
    assert not atlas.is_empty
    np.testing.assert_allclose(atlas.sample(uv), cyan, atol=1e-3)
    twin = copy.deepcopy(atlas)
    np.testing.assert_allclose(twin.sample(uv), cyan, atol=1e-3)
    twin.set_texels(texels, np.zeros_like(cyan))
    assert twin.is_empty and not atlas.is_empty
