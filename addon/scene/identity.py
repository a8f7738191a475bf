"""Vertex identity: which field vertex each mesh vertex is, carried through Blender's modelling tools.

When a field is attached to a mesh (Load field, New object, training), every vertex gets three point
attributes: ``neumesh_vid`` (the field vertex index), ``neumesh_rest`` (that vertex's rest position
in the field) and ``neumesh_key`` (the field's lineage key, ``nm.field_key``).
Blender keeps point attributes through Delete, Separate, Duplicate and Join, and interpolates them for
the vertices that Subdivide, Extrude or a Subdivision Surface modifier make; the renderer maps mesh
vertices to field vertices through them (``render.collect``) instead of by order:

- a vertex whose id and stored rest position match a vertex of the field *is* that vertex;
- any other vertex is new: it sits at its stored rest position and its codes are interpolated from
  the 4 nearest field vertices (``remap_field``).

A mesh that joins several fields holds several keys.  The object's own field file covers its own key;
every attached field is also recorded in the scene (``Scene.neumesh_fields``: key -> file), which is
where a joined-in object's field is found (Ctrl+J keeps only the active object's properties).
"""
from __future__ import annotations

import os

import bpy
from bpy.props import CollectionProperty, IntProperty, StringProperty

from ..runtime._np import np
from ..runtime import classes_factory, core
from ..runtime.errors import UserError
from . import props

ATTR_VID = "neumesh_vid"
ATTR_REST = "neumesh_rest"
ATTR_KEY = "neumesh_key"
ATTRS = (ATTR_VID, ATTR_REST, ATTR_KEY)


def key_of(field) -> int:
    return int(core.get().field_key(field))


def _attr(mesh, name, kind, domain="POINT"):
    a = mesh.attributes.get(name)
    if a is not None and (a.data_type != kind or a.domain != domain):
        mesh.attributes.remove(a)
        a = None
    return a or mesh.attributes.new(name=name, type=kind, domain=domain)


def write(obj, field) -> None:
    """Mark every vertex of ``obj``'s mesh as the field vertex of the same index (the mesh is the
    field's scaffold, in the field's vertex order)."""
    me = obj.data
    n = len(me.vertices)
    if n != field.num_vertices:
        raise UserError(f"'{obj.name}' has {n} vertices but its field has {field.num_vertices}")
    rest = np.ascontiguousarray(field.rest_vertices.detach().cpu().numpy(), np.float32)
    _attr(me, ATTR_VID, "INT").data.foreach_set("value", np.arange(n, dtype=np.int32))
    _attr(me, ATTR_REST, "FLOAT_VECTOR").data.foreach_set("vector", rest.ravel())
    _attr(me, ATTR_KEY, "INT").data.foreach_set("value", np.full(n, key_of(field), np.int32))
    me.update()


def read(mesh, raw: bool = False):
    """(vid (N,) int64, rest (N,3) float64, key (N,) int64) of a mesh, or None without the attributes.
    ``raw``: as stored (int32, float32), for cheap comparisons between frames."""
    attrs = mesh.attributes
    if any(attrs.get(a) is None for a in ATTRS):
        return None
    n = len(mesh.vertices)
    if any(attrs[a].domain != "POINT" for a in ATTRS) or any(len(attrs[a].data) != n for a in ATTRS):
        return None
    vid = np.empty(n, np.int32)
    key = np.empty(n, np.int32)
    rest = np.empty(n * 3, np.float32)
    attrs[ATTR_VID].data.foreach_get("value", vid)
    attrs[ATTR_KEY].data.foreach_get("value", key)
    attrs[ATTR_REST].data.foreach_get("vector", rest)
    if raw:
        return vid, rest.reshape(n, 3), key
    return vid.astype(np.int64), rest.reshape(n, 3).astype(np.float64), key.astype(np.int64)


# ---------------------------------------------------------------------------------- registry
class NeuMeshFieldRef(bpy.types.PropertyGroup):
    key: IntProperty(name="Key", description="Lineage key of the field (a hash of its scaffold and geometry)")
    path: StringProperty(name="File", subtype="FILE_PATH", description="The newest file of that field")


def register_field(scene, field, path: str) -> int:
    """Record ``path`` as the file of ``field``'s key in ``scene`` (newest wins); returns the key."""
    key = key_of(field)
    path = os.path.abspath(bpy.path.abspath(path))
    reg = scene.neumesh_fields
    for ref in reg:
        if ref.key == key:
            if ref.path != path:
                ref.path = path
            return key
    ref = reg.add()
    ref.key, ref.path = key, path
    return key


def lookup(scene, key: int) -> str | None:
    for ref in scene.neumesh_fields:
        if ref.key == int(key):
            return os.path.abspath(bpy.path.abspath(ref.path))
    return None


def attach(context, obj, field, path: str) -> None:
    """Attach ``field`` (file ``path``) to ``obj`` whose mesh is its scaffold: path, identity
    attributes, scene record."""
    props.set_field_path(obj, path)
    write(obj, field)
    register_field(context.scene, field, path)


# ---------------------------------------------------------------------------------- edits
def field_rows(obj, field, mesh_indices, what: str) -> np.ndarray:
    """The field vertices behind mesh vertices ``mesh_indices`` of ``obj`` (sorted, unique): through
    the identity attributes, or by order for a mesh without them (then the counts must match).
    New vertices (no field vertex of their own) are left out; vertices of another field joined into
    the object are refused."""
    idx = np.asarray(mesh_indices, np.int64)
    ident = read(obj.data)
    if ident is None:
        if len(obj.data.vertices) != field.num_vertices:
            raise UserError(f"'{obj.name}' has {len(obj.data.vertices)} vertices but its field has "
                                f"{field.num_vertices} and the mesh has no NeuMesh vertex ids to map them; "
                                "Load field on the original mesh again")
        return np.unique(idx)
    vid, rest, key = ident
    own = key_of(field)
    if (key[idx] != own).any():
        raise UserError(f"{what}: the selection includes vertices of another field joined into '{obj.name}'; "
                            "separate them (P) to edit that part")
    ids = core.get().resolve_ids(field, vid[idx], rest[idx])
    ids = np.unique(ids[ids >= 0])
    if len(ids) == 0:
        raise UserError(f"{what}: the selected vertices are all new (made by subdivision or extrusion) and "
                            "carry no codes of their own; include vertices of the original mesh")
    return ids


def vertex_ids(obj, field, mesh_indices) -> np.ndarray:
    """Field vertex id of each mesh vertex in ``mesh_indices`` (in order; -1 for a new vertex or one of
    another field)."""
    idx = np.asarray(mesh_indices, np.int64)
    ident = read(obj.data)
    if ident is None:
        return np.where(idx < field.num_vertices, idx, -1)
    vid, rest, key = ident
    ids = core.get().resolve_ids(field, vid[idx], rest[idx])
    ids[key[idx] != key_of(field)] = -1
    return ids


def mesh_vertices_of(obj, field, field_ids) -> np.ndarray:
    """Mesh vertices of ``obj`` that are the field vertices ``field_ids`` (every copy of a duplicated
    vertex; none for new vertices)."""
    ids = vertex_ids(obj, field, np.arange(len(obj.data.vertices)))
    return np.nonzero(np.isin(ids, np.asarray(field_ids)) & (ids >= 0))[0]


def corner_rows(obj, field, corner_vertices: np.ndarray):
    """(keep mask over corners, field vertex id per kept corner) for face corners given by mesh vertex."""
    ident = read(obj.data)
    cv = np.asarray(corner_vertices, np.int64)
    if ident is None:
        return np.ones(len(cv), bool), cv
    vid, rest, key = ident
    ids = core.get().resolve_ids(field, vid, rest)
    ids[key != key_of(field)] = -1
    out = ids[cv]
    keep = out >= 0
    return keep, out[keep]


classes = (NeuMeshFieldRef,)


register, unregister = classes_factory(classes, (
    (bpy.types.Scene, "neumesh_fields", lambda: CollectionProperty(type=NeuMeshFieldRef)),))
