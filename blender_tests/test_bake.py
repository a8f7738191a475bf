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
    np.testing.assert_allclose(co.reshape(-1, 3), src.reshape(-1, 3) + [1.5, 0, 0], atol=1e-5)
    uv = me.uv_layers.get(addon.bake.UV_NAME)
    assert uv is not None
    uvs = np.empty(len(me.loops) * 2, np.float32)
    uv.data.foreach_get("uv", uvs)
    assert uvs.min() >= 0 and uvs.max() <= 1 and np.ptp(uvs) > 0.5
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
    assert uvnode.type == "UVMAP" and uvnode.uv_map == addon.bake.UV_NAME
    assert any(l.to_node.type == "OUTPUT_MATERIAL" for l in bsdf.outputs[0].links)
    # the field file and the source object are unchanged
    assert hashlib.sha256(open(path, "rb").read()).hexdigest() == digest
    assert addon.props.field_abspath(obj) == path


def test_bake_material_needs_a_field(addon):
    bpy.ops.mesh.primitive_cube_add()
    with pytest.raises(RuntimeError, match="no NeuMesh field"):
        bpy.ops.neumesh.bake_material(resolution=64)
