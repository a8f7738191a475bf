"""Blender state -> numpy: evaluated world-space vertices, triangles, vertex-group selections, UVs.

All arrays are built with ``foreach_get`` (no per-vertex Python loop except vertex groups, which the
RNA API exposes per vertex only).
"""
from __future__ import annotations

from ..runtime._np import np

# Modifiers that can add, remove, merge or reorder vertices. A field is stored per scaffold vertex, so
# any of these between the field's mesh and the render would pair codes with the wrong vertices.
TOPOLOGY_MODIFIERS = {
    "SUBSURF", "MULTIRES", "REMESH", "DECIMATE", "TRIANGULATE", "BOOLEAN", "ARRAY", "BEVEL", "BUILD",
    "EDGE_SPLIT", "MASK", "MIRROR", "SCREW", "SKIN", "SOLIDIFY", "WELD", "WIREFRAME", "EXPLODE",
    "OCEAN", "PARTICLE_INSTANCE", "NODES", "MESH_TO_VOLUME", "VOLUME_TO_MESH",
}
# Of those, the ones that never touch vertex count/order when the count still matches.
_ORDER_SAFE_WHEN_COUNT_MATCHES = {"TRIANGULATE", "NODES", "EDGE_SPLIT", "BUILD"}


class TopologyError(RuntimeError):
    """Evaluated mesh does not have the field's vertices (count or order)."""


def mesh_vertices(mesh) -> np.ndarray:
    n = len(mesh.vertices)
    arr = np.empty(n * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", arr)
    return arr.reshape(n, 3)


def to_world(verts: np.ndarray, matrix_world) -> np.ndarray:
    M = np.asarray([list(r) for r in matrix_world], dtype=np.float64)
    out = verts.astype(np.float64) @ M[:3, :3].T + M[:3, 3]
    return out.astype(np.float32)


def mesh_triangles(mesh) -> np.ndarray:
    """(F,3) int64 triangles (quads/ngons split with Blender's loop triangulation; no new vertices)."""
    mesh.calc_loop_triangles()
    n = len(mesh.loop_triangles)
    tri = np.empty(n * 3, dtype=np.int32)
    mesh.loop_triangles.foreach_get("vertices", tri)
    return tri.reshape(n, 3).astype(np.int64)


def rest_world_vertices(obj) -> np.ndarray:
    """The object's own (undeformed, no modifiers/shape keys evaluation) vertices in world space."""
    return to_world(mesh_vertices(obj.data), obj.matrix_world)


def topology_modifiers(obj, for_render: bool = True) -> list:
    """Enabled modifiers of ``obj`` that can change vertex count/order."""
    out = []
    for m in obj.modifiers:
        enabled = m.show_render if for_render else m.show_viewport
        if enabled and m.type in TOPOLOGY_MODIFIERS:
            out.append(m)
    return out


def _describe(mods) -> str:
    return ", ".join(f"'{m.name}' ({m.type.replace('_', ' ').title()})" for m in mods)


def evaluated_world_vertices(obj, depsgraph, expected_count: int | None = None,
                             for_render: bool = True) -> np.ndarray:
    """World-space vertex positions of ``obj`` after modifiers/shape keys/armature/physics for the
    depsgraph's frame. Raises :class:`TopologyError` naming the responsible modifier when the evaluated
    mesh cannot carry the field (vertex count differs, or a generating modifier is active)."""
    obj_eval = obj.evaluated_get(depsgraph)
    mesh = obj_eval.data
    tmp = None
    if mesh is None or not hasattr(mesh, "vertices"):
        tmp = obj_eval.to_mesh()
        mesh = tmp
    try:
        verts = mesh_vertices(mesh)
    finally:
        if tmp is not None:
            obj_eval.to_mesh_clear()
    if expected_count is not None:
        mods = topology_modifiers(obj, for_render)
        if len(verts) != expected_count:
            if mods:
                raise TopologyError(
                    f"object '{obj.name}': modifier {_describe(mods)} changes the mesh topology "
                    f"({len(verts)} evaluated vertices, the NeuMesh field has {expected_count}); "
                    f"disable or remove it (deforming modifiers such as Armature, Lattice, Shape keys are fine)")
            raise TopologyError(
                f"object '{obj.name}' has {len(verts)} evaluated vertices but its NeuMesh field has "
                f"{expected_count}; the mesh was edited (vertices added or deleted) after the field was "
                f"trained. Use the mesh the field was trained on")
        unsafe = [m for m in mods if m.type not in _ORDER_SAFE_WHEN_COUNT_MATCHES]
        if unsafe:
            raise TopologyError(
                f"object '{obj.name}': modifier {_describe(unsafe)} can reorder or regenerate vertices; "
                f"NeuMesh fields need the original vertex order. Disable or remove it")
    M = obj_eval.matrix_world
    return to_world(verts, M)


def vertex_group_indices(obj, group_name: str, min_weight: float = 0.0) -> np.ndarray:
    """Indices (int64, ascending) of vertices in vertex group ``group_name`` with weight > min_weight."""
    vg = obj.vertex_groups.get(group_name)
    if vg is None:
        raise KeyError(f"object '{obj.name}' has no vertex group '{group_name}'")
    gi = vg.index
    out = []
    for v in obj.data.vertices:
        for g in v.groups:
            if g.group == gi and g.weight > min_weight:
                out.append(v.index)
                break
    return np.asarray(out, dtype=np.int64)


def vertex_group_weights(obj, group_name: str) -> np.ndarray:
    """(V,) float32 weights of a vertex group (0 for vertices not in it)."""
    vg = obj.vertex_groups.get(group_name)
    if vg is None:
        raise KeyError(f"object '{obj.name}' has no vertex group '{group_name}'")
    gi = vg.index
    w = np.zeros(len(obj.data.vertices), dtype=np.float32)
    for v in obj.data.vertices:
        for g in v.groups:
            if g.group == gi:
                w[v.index] = g.weight
    return w


def selected_vertex_indices(mesh) -> np.ndarray:
    n = len(mesh.vertices)
    sel = np.empty(n, dtype=bool)
    mesh.vertices.foreach_get("select", sel)
    return np.nonzero(sel)[0].astype(np.int64)


def uv_loops(mesh, name: str | None = None) -> np.ndarray:
    """(L,2) float32 per-loop UVs of layer ``name`` (active layer if None)."""
    layer = mesh.uv_layers.get(name) if name else mesh.uv_layers.active
    if layer is None:
        raise KeyError(f"mesh '{mesh.name}' has no UV layer" + (f" '{name}'" if name else ""))
    n = len(mesh.loops)
    uv = np.empty(n * 2, dtype=np.float32)
    layer.data.foreach_get("uv", uv)
    return uv.reshape(n, 2)


def uv_vertices(mesh, name: str | None = None) -> np.ndarray:
    """(V,2) float32 per-vertex UVs (mean over the vertex's loops; seams average)."""
    uv = uv_loops(mesh, name)
    n = len(mesh.loops)
    vi = np.empty(n, dtype=np.int32)
    mesh.loops.foreach_get("vertex_index", vi)
    V = len(mesh.vertices)
    acc = np.zeros((V, 2), dtype=np.float64)
    cnt = np.zeros(V, dtype=np.float64)
    np.add.at(acc, vi, uv)
    np.add.at(cnt, vi, 1.0)
    return (acc / np.maximum(cnt, 1.0)[:, None]).astype(np.float32)


def new_mesh_object(name: str, vertices: np.ndarray, faces: np.ndarray, collection=None):
    """Create a mesh object from (V,3)/(F,3) arrays with foreach_set (fast for 100k+ vertices)."""
    import bpy

    vertices = np.ascontiguousarray(vertices, dtype=np.float32).reshape(-1, 3)
    faces = np.ascontiguousarray(faces, dtype=np.int32).reshape(-1, 3)
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(vertices))
    me.vertices.foreach_set("co", vertices.ravel())
    me.loops.add(faces.size)
    me.loops.foreach_set("vertex_index", faces.ravel())
    me.polygons.add(len(faces))
    me.polygons.foreach_set("loop_start", np.arange(0, faces.size, 3, dtype=np.int32))
    if bpy.app.version < (3, 6, 0):  # loop_total is derived (read-only) from 3.6 on
        me.polygons.foreach_set("loop_total", np.full(len(faces), 3, dtype=np.int32))
    me.update(calc_edges=True)
    me.validate(clean_customdata=False)
    obj = bpy.data.objects.new(name, me)
    (collection or bpy.context.scene.collection).objects.link(obj)
    return obj
