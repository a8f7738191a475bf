"""Baking a field into a UV-textured mesh (neumesh_core/bake.py) and the numpy rasteriser that checks it.

One field is trained briefly on the small built-in scene (diffuse-dominated, 64 px) and baked once at
256 texels (module fixtures, ~12 s together on one thread)."""
import hashlib
import importlib.util
import os

import numpy as np
import pytest

import neumesh_core as nm
from neumesh_core.bake import BakeResult, bake_texture, dilate, save_bake, texel_coverage, uv_pixels
from neumesh_core.metrics import psnr
from neumesh_core.render.raster import raster_triangles, render_textured_mesh
from ..conftest import one_thread


@pytest.fixture(scope="module")
def trained(small_scene_dir, blob_mesh):
    """200 steps x 512 rays on the small scene with the 2,562-vertex blob as scaffold (~10 s)."""
    scene = nm.load_scene(small_scene_dir)
    field = nm.create_field(blob_mesh, nm.FieldConfig(interpolation="early"))
    with one_thread():
        nm.train(field, scene, nm.TrainConfig(steps=200, rays_per_batch=512, log_every=50))
    field.eval()
    return field, scene


@pytest.fixture(scope="module")
def baked(trained):
    field, _ = trained
    with one_thread():
        return bake_texture(field, resolution=256, mesh=None, colours="rays")


def _overlap_counts(uvs, faces, resolution):
    """How many chart triangles cover each texel centre, counting only centres strictly inside a
    triangle (by 1e-4 barycentric), so that texels on an edge two triangles share count once."""
    counts = np.zeros(resolution * resolution, np.int64)
    for _, px, _ in raster_triangles(uv_pixels(uvs, resolution)[faces], resolution, resolution, eps=-1e-4):
        np.add.at(counts, px, 1)
    return counts


def test_baked_render_matches_field_render(trained, baked):
    """The bake (256 texels, raster 2x2 supersampled) scores at least 29 dB (mean PSNR) against the
    field's render of the 4 held-out views (64 px); a flat texture of the mean colour scores >5 dB below."""
    field, scene = trained
    test = scene.split("test")
    cams = test.cameras
    vals = []
    with one_thread():
        refs = [np.clip(nm.render_camera(field, cams.K[i], cams.c2w[i], cams.width, cams.height).rgb, 0, 1)
                for i in range(len(test))]
    for i, ref in enumerate(refs):
        img, cov = render_textured_mesh(baked.vertices, baked.faces, baked.uvs, baked.texture, cams.K[i],
                                        cams.c2w[i], cams.width, cams.height, supersample=2)
        assert cov.mean() > 0.2
        vals.append(psnr(img, ref))
    print("baked vs field PSNR per view:", [round(v, 2) for v in vals])
    assert np.mean(vals) > 29.0
    # and it is the field's texture that does it: a flat grey texture scores far below
    flat = np.full_like(baked.texture, float(baked.texture[baked.mask].mean()))
    img, _ = render_textured_mesh(baked.vertices, baked.faces, baked.uvs, flat, cams.K[0], cams.c2w[0],
                                  cams.width, cams.height, supersample=2)
    assert psnr(img, refs[0]) < vals[0] - 5


def test_atlas_charts_do_not_overlap(trained, baked):
    field, _ = trained
    res = baked.resolution
    assert baked.texture.shape == (res, res, 3) and baked.mask.shape == (res, res)
    assert baked.uvs.min() >= 0 and baked.uvs.max() <= 1
    assert len(baked.faces) == len(field.faces)
    np.testing.assert_array_equal(baked.vertex_index[baked.faces], field.faces.numpy())
    counts = _overlap_counts(baked.uvs, baked.faces, res)
    assert (counts >= 1).mean() > 0.3, "the atlas uses too little of the texture"
    assert counts.max() == 1, f"{int((counts > 1).sum())} texels covered by two chart triangles"
    # the check can fail: the same atlas with one face's UVs copied onto another's does overlap
    faces = baked.faces.copy()
    big = int(np.argmax(np.abs(np.cross(*(np.diff(uv_pixels(baked.uvs, res)[faces], axis=1).transpose(1, 0, 2))))))
    extra = np.concatenate([faces, faces[big:big + 1]])
    assert _overlap_counts(baked.uvs, extra, res).max() == 2


def test_padding_fills_the_border_around_charts(baked):
    """Texels within the padding of a chart hold chart colours (dilated), not the background fill."""
    res = baked.resolution
    m = baked.mask
    pm = np.pad(m, 1)
    near = np.zeros_like(m)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            near |= pm[dy:dy + res, dx:dx + res]
    ring = near & ~m
    assert ring.sum() > 100
    # a ring texel is the mean of chart texels next to it: within the range of its chart neighbours
    tex = baked.texture
    ys, xs = np.nonzero(ring)
    for y, x in list(zip(ys, xs))[:: max(1, len(ys) // 200)]:
        win = (slice(max(0, y - 1), y + 2), slice(max(0, x - 1), x + 2))
        vals = tex[win][m[win]]
        assert np.all(tex[y, x] >= vals.min(0) - 1e-5) and np.all(tex[y, x] <= vals.max(0) + 1e-5)
    _, grown = dilate(np.zeros((9, 9, 3), np.float32), np.zeros((9, 9), bool), 2)
    assert not grown.any()
    one = np.zeros((9, 9, 3), np.float32)
    one[4, 4] = (0.2, 0.4, 0.6)
    mk = np.zeros((9, 9), bool)
    mk[4, 4] = True
    img, grown = dilate(one, mk, 2)
    assert grown.sum() == 25 and np.allclose(img[2:7, 2:7], (0.2, 0.4, 0.6))
    assert res == 256


def test_bake_follows_the_current_pose(trained, baked):
    """A rigidly moved field bakes the moved mesh with the same colours (the field is equivariant)."""
    import copy

    field, _ = trained
    moved = copy.deepcopy(field)
    shift = np.array([0.4, -0.2, 0.3], np.float32)
    moved.set_vertices(np.asarray(field.vertices) + shift)
    with one_thread():
        res = bake_texture(moved, resolution=64, padding=2, fit=False, mesh=None, colours="rays")
    np.testing.assert_allclose(res.vertices, np.asarray(moved.vertices)[res.vertex_index], atol=1e-6)
    diff = np.abs(res.vertex_colours - baked.vertex_colours)
    assert np.percentile(diff, 95) < 0.03, float(np.percentile(diff, 95))
    # fitted onto the field's surface (one level, no calibration): the moved bake's mesh is the
    # original's moved by the same shift
    from neumesh_core.bake import SurfaceFitConfig

    cfg = SurfaceFitConfig(level=0.1)
    with one_thread():
        a = bake_texture(field, resolution=32, padding=2, fit=cfg, vertex_colours=False, measure_texels=0, mesh=None,
                         colours="rays")
        b = bake_texture(moved, resolution=32, padding=2, fit=cfg, vertex_colours=False, measure_texels=0, mesh=None,
                         colours="rays")
    moved_by = np.zeros((field.num_vertices, 3))
    moved_by[b.vertex_index] = b.vertices
    ref = np.zeros((field.num_vertices, 3))
    ref[a.vertex_index] = a.vertices
    err = np.linalg.norm(moved_by - ref - shift, axis=1)
    assert np.percentile(err, 99) < 0.02 * field.radius, float(np.percentile(err, 99))
    assert np.abs(ref - np.asarray(field.vertices)).max() > 0.02 * field.radius   # the fit did move it


def test_bake_cancel(trained):
    field, _ = trained
    seen = []

    def progress(f):
        seen.append(f)
        return f < 0.12

    with pytest.raises(nm.Cancelled):
        bake_texture(field, resolution=64, progress=progress, mesh=None, colours="rays")
    assert seen and seen[-1] >= 0.12


def test_texel_coverage_texels_are_unique(baked):
    texel, face, bary = texel_coverage(baked.uvs, baked.faces, baked.resolution)
    assert len(np.unique(texel)) == len(texel) == int(baked.mask.sum())
    assert np.all(bary >= -1e-6) and np.allclose(bary.sum(1), 1)


def test_cli_bake_writes_loadable_files_and_leaves_the_field(trained, tmp_path):
    import trimesh

    from neumesh_core.cli import main

    field, _ = trained
    fpath = tmp_path / "blob.neumesh"
    nm.save_field(field, str(fpath))
    digest = hashlib.sha256(fpath.read_bytes()).hexdigest()
    out = tmp_path / "baked"
    with one_thread():
        assert main(["bake", "--field", str(fpath), "--out", str(out), "--resolution", "64", "--target", "scaffold",
                     "--colours", "rays"]) == 0
    names = sorted(os.listdir(out))
    assert names == ["blob.glb", "blob.mtl", "blob.obj", "blob.png"], names
    assert hashlib.sha256(fpath.read_bytes()).hexdigest() == digest
    m = trimesh.load(str(out / "blob.obj"), process=False, force="mesh")
    assert len(m.faces) == len(field.faces)
    assert m.visual.uv is not None and len(m.visual.uv) == len(m.vertices)
    assert m.visual.material.image is not None and m.visual.material.image.size == (64, 64)
    g = trimesh.load(str(out / "blob.glb"), force="mesh")
    assert len(g.faces) == len(field.faces) and g.visual.uv is not None
    # an output named like the field is refused, the field stays
    from neumesh_core.bake import BakeResult

    r = BakeResult(vertices=np.zeros((3, 3), np.float32), faces=np.array([[0, 1, 2]], np.int32),
                   uvs=np.zeros((3, 2), np.float32), vertex_index=np.arange(3), texture=np.zeros((4, 4, 3)),
                   mask=np.ones((4, 4), bool))
    with pytest.raises(nm.NeuMeshError):
        save_bake(r, str(tmp_path), "blob", glb=False, protect=(str(tmp_path / "blob.png"),))


def test_raster_textured_quads_z_buffer_and_uv_convention():
    """Two camera-facing quads: the nearer one hides the farther; its texture's top half (v up, the
    image's first rows) appears at the top of the picture (OpenCV camera: y down)."""
    K = np.array([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]])
    c2w = np.eye(4)
    quad = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)   # y down in camera
    # near quad: half-size 0.5 at z=3 (8.3 px); far quad: half-size 1 at z=5 (10 px), drawn first
    v = np.concatenate([quad + [0, 0, 5], quad * 0.5 + [0, 0, 3]])
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    uv = np.concatenate([np.full((4, 2), (0.95, 0.5)),                       # far quad: the grey column
                         np.array([[0, 1], [0.5, 1], [0.5, 0], [0, 0]])])    # camera-top edge -> v = 1
    tex = np.full((8, 8, 3), 0.5, np.float32)
    tex[:4, :6] = (1, 0, 0)      # first rows (v near 1): red
    tex[4:, :6] = (0, 0, 1)      # blue
    rgb, cov = render_textured_mesh(v, f, uv, tex, K, c2w, 64, 64, background=(0, 1, 0))
    assert np.allclose(rgb[26, 30], (1, 0, 0)) and np.allclose(rgb[38, 30], (0, 0, 1))
    assert np.allclose(rgb[32, 41], 0.5) and np.allclose(rgb[23, 32], 0.5)   # the far quad around it
    assert np.allclose(rgb[1, 1], (0, 1, 0)) and cov[1, 1] == 0
    assert abs(cov.sum() - 20 * 20) < 45
    ss, cs = render_textured_mesh(v, f, uv, tex, K, c2w, 64, 64, background=(0, 1, 0), supersample=3)
    assert abs(cs.sum() - 20 * 20) < 15 and np.allclose(ss[26, 30], (1, 0, 0))


def _mean_psnr_vs_field(field, scene, b):
    test = scene.split("test")
    cams = test.cameras
    vals = []
    with one_thread():
        for i in range(len(test)):
            ref = np.clip(nm.render_camera(field, cams.K[i], cams.c2w[i], cams.width, cams.height).rgb, 0, 1)
            img, _ = render_textured_mesh(b.vertices, b.faces, b.uvs, b.texture, cams.K[i], cams.c2w[i],
                                          cams.width, cams.height, supersample=2)
            vals.append(psnr(img, ref))
    return float(np.mean(vals))


def test_bake_onto_a_coarser_target_mesh(trained):
    """A 642-vertex blob (the scaffold has 2,562) lies within the field radius of the field's surface:
    its texel rays still find the field: 29 dB against the field's render (a little below the scaffold's
    own bake: the coarser silhouette)."""
    from neumesh_core.data.synthetic import default_mesh

    field, scene = trained
    target = default_mesh(subdiv=3)
    with one_thread():
        b = bake_texture(field, resolution=128, mesh=target, fit=False, colours="rays")
    assert b.info["mesh"] == "target" and b.info["missed_texels"] == 0
    assert b.info["mesh_vertices"] == 642 and b.info["mesh_faces"] == len(b.faces) == 1280
    np.testing.assert_array_equal(b.vertex_index[b.faces], target.faces)
    np.testing.assert_allclose(b.vertices, target.vertices[b.vertex_index], atol=1e-6)
    assert b.vertex_colours.shape == (642, 3)
    assert _overlap_counts(b.uvs, b.faces, 128).max() == 1
    val = _mean_psnr_vs_field(field, scene, b)
    print("coarse target: baked vs field PSNR", round(val, 2))
    assert val > 29.0
    # (vertices, faces) pairs work too and give the same atlas
    with one_thread():
        b2 = bake_texture(field, resolution=32, mesh=(target.vertices, target.faces), vertex_colours=False,
                          colours="rays")
    assert len(b2.faces) == 1280 and b2.vertex_colours is None


def test_bake_target_far_from_the_field_is_filled_not_black(trained):
    """A target 3x the blob's size lies far outside the field: every texel misses, is counted, and the
    texture holds no black holes (filled with the field's mean colour / neighbours)."""
    from neumesh_core.data.synthetic import default_mesh

    field, _ = trained
    far = default_mesh(subdiv=1)
    far.vertices = far.vertices * 3.0
    with one_thread():
        b = bake_texture(field, resolution=32, mesh=far, colours="rays")
    assert b.info["missed_texels"] == b.info["texels"] > 0
    assert np.isfinite(b.texture).all()
    with pytest.raises(ValueError):
        bake_texture(field, resolution=32, mesh=(far.vertices, np.array([[0, 1, 99]])), colours="rays")


def test_decimate(blob_mesh, monkeypatch):
    import sys

    from neumesh_core.bake import decimate

    v, f = decimate(blob_mesh.vertices, blob_mesh.faces, 1.0)
    assert len(f) == len(blob_mesh.faces)
    with pytest.raises(ValueError):
        decimate(blob_mesh.vertices, blob_mesh.faces, 0.0)
    monkeypatch.setitem(sys.modules, "fast_simplification", None)     # not installed: libigl's collapse
    monkeypatch.setitem(sys.modules, "igl", None)
    with pytest.raises(nm.NeuMeshError, match="fast-simplification"):    # neither: says what to install
        decimate(blob_mesh.vertices, blob_mesh.faces, 0.5)
    monkeypatch.delitem(sys.modules, "igl")
    outs = []
    if importlib.util.find_spec("igl") is not None:
        outs.append(decimate(blob_mesh.vertices, blob_mesh.faces, 0.25))
    monkeypatch.undo()
    if importlib.util.find_spec("fast_simplification") is not None:
        outs.append(decimate(blob_mesh.vertices, blob_mesh.faces, 0.25))
    if not outs:
        pytest.skip("neither fast-simplification nor libigl installed")
    for v, f in outs:
        assert 0.2 * len(blob_mesh.faces) < len(f) < 0.3 * len(blob_mesh.faces)
        assert f.max() < len(v)
        # the decimated vertices stay on the blob (within a small fraction of its size)
        r = np.linalg.norm(v[:, None] - blob_mesh.vertices[None], axis=2).min(1)
        assert np.percentile(r, 95) < 0.05 * np.ptp(blob_mesh.vertices, 0).max()


def test_cli_bake_onto_a_given_mesh(trained, tmp_path):
    import trimesh

    from neumesh_core.cli import main
    from neumesh_core.data.synthetic import default_mesh

    field, _ = trained
    fpath = tmp_path / "blob.neumesh"
    nm.save_field(field, str(fpath))
    target = default_mesh(subdiv=2)
    mpath = tmp_path / "target.ply"
    nm.save_mesh(target, str(mpath))
    out = tmp_path / "baked"
    with one_thread():
        assert main(["bake", "--field", str(fpath), "--out", str(out), "--resolution", "32", "--mesh",
                     str(mpath), "--views", "4", "--view-size", "64"]) == 0
    m = trimesh.load(str(out / "blob.obj"), process=False, force="mesh")
    assert len(m.faces) == len(target.faces)
    g = trimesh.load(str(out / "blob.glb"), force="mesh")
    assert len(g.faces) == len(target.faces) and g.visual.uv is not None


def test_bake_moves_an_offset_mesh_onto_the_field(trained):
    """A coarse blob inflated by 0.6 field radii bakes the field's colours at the wrong places where it
    is; moved onto the field's surface first (the default) it scores like the scaffold's own bake: pass
    marks 29 dB against the field's render (96 px) and +5 dB over the bake where it is.  The bake
    reports how far its mesh lies from the field's surface."""
    from neumesh_core.data.synthetic import default_mesh
    from neumesh_core.mesh import vertex_normals

    field, scene = trained
    m = default_mesh(subdiv=3)
    V = m.vertices + 0.6 * field.radius * np.asarray(vertex_normals(m.vertices, m.faces))
    with one_thread():
        off = bake_texture(field, resolution=128, mesh=(V, m.faces), fit=False, vertex_colours=False,
                           colours="rays")
        on = bake_texture(field, resolution=128, mesh=(V, m.faces), vertex_colours=False, colours="rays")
    p_off, p_on = _mean_psnr_vs_field(field, scene, off), _mean_psnr_vs_field(field, scene, on)
    print(f"inflated target: {p_off:.2f} dB where it is, {p_on:.2f} dB fitted (level {on.info['fit']['level']})")
    assert p_on > 29.0 and p_on > p_off + 5.0
    assert off.info["surface_offset"]["median_radii"] > 0.3
    assert on.info["surface_offset"]["median_radii"] < 0.1 and on.info["surface_offset"]["found"] > 0.99
    assert on.info["fit"]["after"]["median_radii"] < on.info["fit"]["before"]["median_radii"]
    assert "fit" not in off.info


def test_bake_onto_the_fields_own_surface_with_projected_colours(trained, baked):
    """mesh='field' extracts the target from the field's density (marching cubes, no decimation here)
    and colours='views' takes the texel colours from the field's renders.  On this smooth blob, whose
    scaffold already lies on the field's surface, the scaffold's ray bake stays closer than the coarse
    marching-cubes mesh (voxel 0.6 radii) with colours from 16 renders of 96 px: pass marks 27 dB and
    2 dB above the same mesh with a flat texture of its mean colour
    (the texture carries the field's pattern).  Bad values are refused."""
    from neumesh_core.bake import ExtractConfig, ProjectConfig

    field, scene = trained
    with one_thread():
        b = bake_texture(field, resolution=256, mesh="field", colours="views",
                         extract=ExtractConfig(voxel=0.6, views=4, view_size=48),
                         project=ProjectConfig(views=16, size=96))
    assert b.info["mesh"] == "field" and "fit" not in b.info
    ex = b.info["extract"]
    assert ex["faces"] == b.info["mesh_faces"] == len(b.faces) and ex["level"] in ExtractConfig().levels
    assert 0 <= b.info["texels_unseen"] < 0.5 * b.info["texels"]
    val = _mean_psnr_vs_field(field, scene, b)
    ref = _mean_psnr_vs_field(field, scene, baked)
    flat = BakeResult(vertices=b.vertices, faces=b.faces, uvs=b.uvs, vertex_index=b.vertex_index, mask=b.mask,
                      texture=np.full_like(b.texture, float(b.texture[b.mask].mean())))
    val_flat = _mean_psnr_vs_field(field, scene, flat)
    print("field surface + projected colours vs field:", round(val, 2), "scaffold rays:", round(ref, 2),
          "flat texture:", round(val_flat, 2))
    assert val > 27.0 and val > val_flat + 2.0
    with pytest.raises(ValueError, match="colours"):
        bake_texture(field, resolution=32, colours="normals", mesh=None)
    with pytest.raises(ValueError, match="mesh"):
        bake_texture(field, resolution=32, mesh="scaffold-please", colours="rays")


def test_cli_bake_onto_the_field_surface_with_projected_colours(trained, tmp_path):
    """`neumesh bake` bakes onto the field's surface (decimated to 0.2 x the scaffold's faces) with colours
    from its views by default and writes the files; --target field with --mesh is refused."""
    import trimesh

    from neumesh_core.cli import main

    field, _ = trained
    fpath = tmp_path / "blob.neumesh"
    nm.save_field(field, str(fpath))
    out = tmp_path / "baked"
    with one_thread():
        assert main(["bake", "--field", str(fpath), "--out", str(out), "--resolution", "64", "--no-glb",
                     "--views", "4", "--view-size", "48"]) == 0
    m = trimesh.load(str(out / "blob.obj"), process=False, force="mesh")
    assert 0.15 * len(field.faces) < len(m.faces) < 0.25 * len(field.faces) and m.visual.uv is not None
    with pytest.raises(SystemExit, match="--target field"):
        main(["bake", "--field", str(fpath), "--out", str(out), "--target", "field", "--mesh", str(fpath)])
