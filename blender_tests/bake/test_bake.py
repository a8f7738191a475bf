"""Bake to material: the operator turns the active object's field, as it renders now, into a new object
with the UV map, a packed image of the bake and a Principled BSDF material; the field is untouched."""
from __future__ import annotations

import hashlib
import shutil

import bpy
import numpy as np
import pytest


def _load(trained_field, tmp_path):
    path = str(tmp_path / "A.neumesh")
    shutil.copy(trained_field, path)
    assert bpy.ops.neumesh.load_field(filepath=path, new_object=True) == {"FINISHED"}
    return bpy.context.active_object, path


def _links_to(node, socket_names):
    return [l.from_node for l in node.id_data.links if l.to_node == node and l.to_socket.name in socket_names]


@pytest.mark.parametrize("shading", ["EMISSION", "BASE_COLOR"])
def test_bake_material_creates_a_textured_object(addon, trained_field, tmp_path, shading):
    import neumesh_core as nm

    obj, path = _load(trained_field, tmp_path)
    obj.location.x = 1.5          # the bake follows the pose (world space)
    bpy.context.view_layer.update()
    digest = hashlib.sha256(open(path, "rb").read()).hexdigest()
    n_before = len(bpy.data.objects)
    assert bpy.ops.neumesh.bake_material(resolution=128, shading=shading, target="SCAFFOLD",
                                          colours="RAYS") == {"FINISHED"}
    assert len(bpy.data.objects) == n_before + 1
    baked = bpy.context.active_object
    assert baked is not obj and baked.name.startswith(obj.name) and baked.name.endswith("_baked")
    me = baked.data
    field = nm.load_field(path)
    assert len(me.vertices) == field.num_vertices and len(me.polygons) == len(field.faces)
    # world-space copy of the posed mesh: shifted by the object's location
    co = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    src = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.vertices.foreach_get("co", src)
    # the bake follows the pose (world space) and moves each vertex onto the field's surface along its
    # normal (at most SurfaceFitConfig.search radii), so the baked mesh lies where the field renders
    shift = np.linalg.norm(co.reshape(-1, 3) - (src.reshape(-1, 3) + [1.5, 0, 0]), axis=1)
    assert shift.max() <= nm.bake.SurfaceFitConfig().search * field.radius + 1e-4, shift.max()
    uv = me.uv_layers.get(addon.bake.material.UV_NAME)
    assert uv is not None
    uvs = np.empty(len(me.loops) * 2, np.float32)
    uv.data.foreach_get("uv", uvs)
    assert uvs.min() >= 0 and uvs.max() <= 1 and np.ptp(uvs) > 0.5
    # the per-vertex colour attribute (the same rays at the vertices)
    attr = me.color_attributes.get(addon.bake.material.COLOR_NAME)
    assert attr is not None and attr.domain == "POINT" and len(attr.data) == len(me.vertices)
    vc = np.empty(len(me.vertices) * 4, np.float32)
    attr.data.foreach_get("color", vc)
    assert vc.reshape(-1, 4)[:, :3].std() > 0.01
    # material: Principled BSDF fed by an image node that holds the bake, through the UV map
    mat = me.materials[0]
    nodes = mat.node_tree.nodes
    tex = nodes["NeuMesh baked texture"]
    img = tex.image
    assert img is not None and tuple(img.size) == (128, 128) and img.packed_file is not None
    px = np.empty(128 * 128 * 4, np.float32)
    img.pixels.foreach_get(px)
    px = px.reshape(128, 128, 4)
    assert px[..., :3].std() > 0.02                     # a texture, not a flat colour
    bsdf = next(n for n in nodes if n.type == "BSDF_PRINCIPLED")
    socket = ("Emission Color", "Emission") if shading == "EMISSION" else ("Base Color",)
    assert tex in _links_to(bsdf, socket)
    uvnode = _links_to(tex, ("Vector",))[0]
    assert uvnode.type == "UVMAP" and uvnode.uv_map == addon.bake.material.UV_NAME
    assert any(l.to_node.type == "OUTPUT_MATERIAL" for l in bsdf.outputs[0].links)
    # the field file and the source object are unchanged
    assert hashlib.sha256(open(path, "rb").read()).hexdigest() == digest
    assert addon.scene.props.field_abspath(obj) == path


def test_bake_material_needs_a_field(addon):
    bpy.ops.mesh.primitive_cube_add()
    with pytest.raises(RuntimeError, match="no NeuMesh field"):
        bpy.ops.neumesh.bake_material(resolution=64)


def test_bake_material_decimate_ratio(addon, trained_field, tmp_path):
    """Decimate ratio < 1: the bake goes onto a copy reduced by Blender's Decimate modifier; the
    temporary object is gone and the field's object keeps its mesh."""
    obj, path = _load(trained_field, tmp_path)
    n_faces, n_objects, n_meshes = len(obj.data.polygons), len(bpy.data.objects), len(bpy.data.meshes)
    assert bpy.ops.neumesh.bake_material(resolution=64, decimate=0.25, target="SCAFFOLD",
                                          colours="RAYS") == {"FINISHED"}
    baked = bpy.context.active_object
    me = baked.data
    assert len(bpy.data.objects) == n_objects + 1 and len(bpy.data.meshes) == n_meshes + 1
    assert 0.15 * n_faces < len(me.polygons) < 0.35 * n_faces
    assert all(len(p.vertices) == 3 for p in me.polygons)
    assert len(obj.data.polygons) == n_faces
    uv = me.uv_layers.get(addon.bake.material.UV_NAME)
    uvs = np.empty(len(me.loops) * 2, np.float32)
    uv.data.foreach_get("uv", uvs)
    assert uvs.min() >= 0 and uvs.max() <= 1
    attr = me.color_attributes.get(addon.bake.material.COLOR_NAME)
    assert attr is not None and len(attr.data) == len(me.vertices)
    img = me.materials[0].node_tree.nodes["NeuMesh baked texture"].image
    px = np.empty(64 * 64 * 4, np.float32)
    img.pixels.foreach_get(px)
    assert px.reshape(64, 64, 4)[..., :3].std() > 0.02
    # the decimated copy lies on the scaffold: every vertex within a small distance of the original's
    co = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    src = np.empty(len(obj.data.vertices) * 3, np.float32)
    obj.data.vertices.foreach_get("co", src)
    src = src.reshape(-1, 3)
    d = np.linalg.norm(co.reshape(-1, 3)[:, None] - src[None], axis=2).min(1)
    assert np.percentile(d, 95) < 0.1 * np.ptp(src, 0).max()


def test_baked_files_load_in_blender(trained_field, tmp_path):
    """The CLI's files (OBJ + MTL + PNG, GLB) import into Blender with their faces, UVs and texture."""
    import neumesh_core as nm
    from neumesh_core.bake import bake_texture, save_bake

    field = nm.load_field(trained_field)
    res = bake_texture(field, resolution=64, vertex_colours=False, mesh=None, colours="rays")
    paths = save_bake(res, str(tmp_path / "out"), "asset")
    n_faces = len(res.faces)
    assert bpy.ops.wm.obj_import(filepath=paths["obj"]) == {"FINISHED"}
    ob = bpy.context.selected_objects[0]
    assert len(ob.data.polygons) == n_faces and len(ob.data.uv_layers) == 1
    img = next(n.image for n in ob.data.materials[0].node_tree.nodes if n.type == "TEX_IMAGE")
    assert tuple(img.size) == (64, 64)
    bpy.ops.object.select_all(action="DESELECT")
    assert bpy.ops.import_scene.gltf(filepath=paths["glb"]) == {"FINISHED"}
    ob = next(o for o in bpy.context.selected_objects if o.type == "MESH")
    assert len(ob.data.polygons) == n_faces and len(ob.data.uv_layers) >= 1
    img = next(n.image for n in ob.data.materials[0].node_tree.nodes if n.type == "TEX_IMAGE")
    assert tuple(img.size) == (64, 64)


def _baked_arrays(obj):
    """The baked object as the core's rasteriser takes it, read back from Blender: one vertex per loop
    triangle corner (world space: the baked object has an identity transform), its UV, the image (row 0
    at the top) -- what Cycles/EEVEE would render with the emission material."""
    me = obj.data
    me.calc_loop_triangles()
    co = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    tri_loops = np.empty(len(me.loop_triangles) * 3, np.int32)
    me.loop_triangles.foreach_get("loops", tri_loops)
    loop_vert = np.empty(len(me.loops), np.int32)
    me.loops.foreach_get("vertex_index", loop_vert)
    uv = np.empty(len(me.loops) * 2, np.float32)
    me.uv_layers["NeuMesh bake"].data.foreach_get("uv", uv)
    img = me.materials[0].node_tree.nodes["NeuMesh baked texture"].image
    w, h = img.size
    px = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(px)
    verts = co.reshape(-1, 3)[loop_vert[tri_loops]]
    uvs = uv.reshape(-1, 2)[tri_loops]
    faces = np.arange(len(tri_loops), dtype=np.int64).reshape(-1, 3)
    return verts, faces, uvs, px.reshape(h, w, 4)[::-1, :, :3].copy()


def test_bake_field_surface_with_views_renders_like_the_field(addon, trained_field, tiny_dataset, tmp_path):
    """Target *Field surface* + Colours *Views* (the defaults) on the built-in scene (128 texels, 8 views of
    64 px): the new object is a mesh extracted from the field's density (not the scaffold); read back from
    Blender and rendered at the scene's test view (3x its 32 px) it matches the field's own render.

    Pass mark 18 dB.  Why so low a mark: the session's field is trained for 40 steps
    on 32 px photos, so its edges are soft, half-transparent shells an opaque mesh cannot show, and its
    colour is nearly flat (a flat texture of the bake's mean colour scores about the same; the texture's
    fidelity is measured on trained fields in tests/bake/ and benchmarks/bench/bench_bake.py).  What
    this field does show is the target: Scaffold + Rays (one click away) renders the same field at
    13.4 dB, because the field's surface lies about a radius off its scaffold; the pass mark asks the
    default (Field surface + Views) for 4 dB more than that."""
    import neumesh_core as nm
    from neumesh_core.metrics import psnr
    from neumesh_core.render.raster import render_textured_mesh

    obj, path = _load(trained_field, tmp_path)
    op = bpy.ops.neumesh.bake_material
    props = op.get_rna_type().properties
    assert props["target"].default == "FIELD" and props["colours"].default == "VIEWS"
    wm_props = bpy.types.WindowManager.bl_rna.properties
    assert wm_props["neumesh_bake_target"].default == "FIELD" and wm_props["neumesh_bake_colours"].default == "VIEWS"
    field = nm.load_field(path)
    cams = nm.load_scene(tiny_dataset).split("test").cameras
    K = np.array(cams.K[0], np.float64)
    K[:2] *= 3
    w, h = 3 * cams.width, 3 * cams.height
    ref = np.clip(nm.render_camera(field, K, cams.c2w[0], w, h).rgb, 0, 1)
    vals = {}
    for kw in (dict(views=8, view_size=64, field_decimate=0.5), dict(target="SCAFFOLD", colours="RAYS")):
        n_before = len(bpy.data.objects)
        bpy.context.view_layer.objects.active = obj
        assert op(resolution=128, **kw) == {"FINISHED"}
        assert len(bpy.data.objects) == n_before + 1
        baked = bpy.context.active_object
        if "target" not in kw:   # a new mesh: about field_decimate x the scaffold's faces
            assert len(baked.data.vertices) != field.num_vertices
            assert 0.2 * len(field.faces) < len(baked.data.polygons) <= 0.6 * len(field.faces)
        img, cov = render_textured_mesh(*_baked_arrays(baked), K, cams.c2w[0], w, h, supersample=2)
        assert cov.mean() > 0.1
        vals[kw.get("target", "FIELD")] = psnr(img, ref)
    print("baked vs field (dB):", {k: round(v, 2) for k, v in vals.items()})
    assert vals["FIELD"] > 18.0 and vals["FIELD"] > vals["SCAFFOLD"] + 4.0


def test_bake_cancelled_in_each_stage_leaves_nothing(addon, trained_field, tmp_path, monkeypatch):
    """Esc while the bake extracts the field's surface or projects its views: the job's progress
    callback answers False (what JobModal.modal's Esc does), the core stops in that stage and the
    operator creates no object, mesh, image or material."""
    obj, path = _load(trained_field, tmp_path)
    Job = addon.runtime.jobs.Job
    orig = Job.progress
    for stop_at in (0.05, 0.3):
        seen = []

        def progress(self, fraction, stop_at=stop_at, seen=seen):
            seen.append(float(fraction))
            if fraction >= stop_at:
                self.cancel()
            return orig(self, fraction)

        monkeypatch.setattr(Job, "progress", progress)
        counts = [len(c) for c in (bpy.data.objects, bpy.data.meshes, bpy.data.images, bpy.data.materials)]
        assert bpy.ops.neumesh.bake_material(resolution=64, views=4, view_size=64) == {"CANCELLED"}
        assert [len(c) for c in (bpy.data.objects, bpy.data.meshes, bpy.data.images,
                                 bpy.data.materials)] == counts
        assert stop_at <= seen[-1] < stop_at + 0.15, seen[-3:]   # stopped in that stage, not at the end
        assert bpy.context.active_object == obj


def test_field_surface_bake_names_its_missing_packages(addon, trained_field, tmp_path, monkeypatch):
    """Target Field surface needs marching cubes (scikit-image) and a decimator: where Blender's Python
    lacks them the operator says which to install before any work starts; Target Scaffold does not need
    them."""
    obj, _ = _load(trained_field, tmp_path)
    deps = addon.runtime.deps
    orig = deps.missing_for
    monkeypatch.setattr(deps, "missing_for", lambda f: ["scikit-image"] if f == "bake_field" else orig(f))
    n = len(bpy.data.objects)
    with pytest.raises(RuntimeError, match="scikit-image"):
        bpy.ops.neumesh.bake_material(resolution=64)
    assert len(bpy.data.objects) == n
    assert bpy.ops.neumesh.bake_material(resolution=64, target="SCAFFOLD", colours="RAYS") == {"FINISHED"}
