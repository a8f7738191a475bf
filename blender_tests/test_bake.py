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
    assert bpy.ops.neumesh.bake_material(resolution=128, shading=shading) == {"FINISHED"}
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
    # normal (issue 50: at most SurfaceFitConfig.search radii), so the baked mesh lies where the field renders
    shift = np.linalg.norm(co.reshape(-1, 3) - (src.reshape(-1, 3) + [1.5, 0, 0]), axis=1)
    assert shift.max() <= nm.bake.SurfaceFitConfig().search * field.radius + 1e-4, shift.max()
    uv = me.uv_layers.get(addon.edit.bake.UV_NAME)
    assert uv is not None
    uvs = np.empty(len(me.loops) * 2, np.float32)
    uv.data.foreach_get("uv", uvs)
    assert uvs.min() >= 0 and uvs.max() <= 1 and np.ptp(uvs) > 0.5
    # the per-vertex colour attribute (the same rays at the vertices)
    attr = me.color_attributes.get(addon.edit.bake.COLOR_NAME)
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
    assert uvnode.type == "UVMAP" and uvnode.uv_map == addon.edit.bake.UV_NAME
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
    assert bpy.ops.neumesh.bake_material(resolution=64, decimate=0.25) == {"FINISHED"}
    baked = bpy.context.active_object
    me = baked.data
    assert len(bpy.data.objects) == n_objects + 1 and len(bpy.data.meshes) == n_meshes + 1
    assert 0.15 * n_faces < len(me.polygons) < 0.35 * n_faces
    assert all(len(p.vertices) == 3 for p in me.polygons)
    assert len(obj.data.polygons) == n_faces
    uv = me.uv_layers.get(addon.edit.bake.UV_NAME)
    uvs = np.empty(len(me.loops) * 2, np.float32)
    uv.data.foreach_get("uv", uvs)
    assert uvs.min() >= 0 and uvs.max() <= 1
    attr = me.color_attributes.get(addon.edit.bake.COLOR_NAME)
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
    res = bake_texture(field, resolution=64, vertex_colors=False)
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
