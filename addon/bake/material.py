"""Bake to material: turn the active object's field (as it renders now: edited, deformed) into a plain
Blender object with a UV map, an image texture and a Principled BSDF material, for Cycles, EEVEE and
export (glTF, FBX, OBJ).

``target``: ``FIELD`` (default) bakes onto a mesh the core extracts from the field's own density
(marching cubes, decimated to ``field_decimate`` x the scaffold's faces): it lies where the field
renders; ``SCAFFOLD`` onto the field's scaffold in its current pose (quicker).
``colours``: ``VIEWS`` (default) gives each texel the colour the field's renders from ``views``
virtual cameras show there; ``RAYS`` the colour one short ray along the texel's normal sees (quicker).
The core (``neumesh_core.bake.bake_texture``) unwraps the target with xatlas (docs/baking.md).  That
colour already holds the lighting of the photos the field was trained on, so the material offers two ways to use it
(``shading``):

* ``EMISSION`` (default): the texture drives the Principled BSDF's emission at strength 1 and the base
  colour is black: the object looks like the field whatever the scene's lights (with the *Standard*
  view transform, Cycles and EEVEE reproduce the texture's colours; AgX/Filmic tone-map them).
* ``BASE_COLOR``: the texture is the base colour: the object takes the scene's lights, on top of the
  light already baked into the texture (shadows and highlights of the photos stay).

The new object is built from the field's vertices in world space (identity transform); the field and
the original object are not changed.  ``decimate`` < 1 bakes onto a lighter copy instead: the posed
scaffold goes through Blender's own Decimate modifier (collapse, triangulated) on a temporary object,
and the bake's texel rays start on that mesh's surface along its normal (docs/baking.md).  Invoked
from the UI the bake runs in a thread (progress in the status bar, Esc cancels); from a script it
blocks.
"""
from __future__ import annotations

import warnings

import bpy
from bpy.props import EnumProperty, FloatProperty, IntProperty

from ..runtime._np import np
from ..runtime import classes_factory, core, prefs
from ..render import field_cache
from ..runtime.errors import UserError
from ..runtime.jobs import Job, JobModal
from ..scene import sync
from ..scene.props import field_path_of
from ..edit.base import EditSubPanel, edit_copy

SHADING_ITEMS = (
    ("EMISSION", "Emission", "Texture as emission (strength 1), black base colour: looks like the field "
                             "under any lighting"),
    ("BASE_COLOR", "Base colour", "Texture as base colour: lit by the scene, on top of the photos' light "
                                  "baked into it"),
)
TARGET_ITEMS = (
    ("FIELD", "Field surface", "Bake onto a new mesh extracted from the field's own density (marching "
                               "cubes, decimated): lies where the field renders, so part edges match; costs a "
                               "density grid and marching cubes first; matches the field's renders more "
                               "closely than the scaffold"),
    ("SCAFFOLD", "Scaffold", "Bake onto the field's scaffold as it is posed now (optionally decimated): "
                             "quickest, keeps the scaffold's topology, but sits up to a radius off the "
                             "field's surface, so part edges come out a few pixels off"),
)
COLOUR_ITEMS = (
    ("VIEWS", "Views", "Texel colours from the field's renders on virtual cameras around the object (the "
                       "colour the field shows there; averages highlights); costs one render per view"),
    ("RAYS", "Rays", "Texel colours from one short ray along each texel's normal: quickest, a little "
                     "less faithful at part edges"),
)
UV_NAME = "NeuMesh bake"
COLOR_NAME = "NeuMesh bake colour"   # UV maps are attributes too (Blender 3.5+): names must differ


def _input(node, *names):
    """The first of ``names`` that ``node`` has as an input (names changed between Blender 3 and 4)."""
    for n in names:
        if n in node.inputs:
            return node.inputs[n]
    return None


def make_material(name: str, image, shading: str, uv_name: str = UV_NAME):
    mat = bpy.data.materials.new(name)
    with warnings.catch_warnings():   # Blender 5: materials always use nodes; the setter is deprecated
        warnings.simplefilter("ignore", DeprecationWarning)
        mat.use_nodes = True
    nt = mat.node_tree
    nodes, links = nt.nodes, nt.links
    bsdf = next((n for n in nodes if n.type == "BSDF_PRINCIPLED"), None) or nodes.new("ShaderNodeBsdfPrincipled")
    tex = nodes.new("ShaderNodeTexImage")
    tex.name = tex.label = "NeuMesh baked texture"
    tex.image = image
    tex.interpolation = "Linear"
    tex.location = (bsdf.location.x - 400, bsdf.location.y)
    uv = nodes.new("ShaderNodeUVMap")
    uv.uv_map = uv_name
    uv.location = (tex.location.x - 250, tex.location.y)
    links.new(uv.outputs["UV"], tex.inputs["Vector"])
    if shading == "EMISSION":
        links.new(tex.outputs["Color"], _input(bsdf, "Emission Color", "Emission"))
        _input(bsdf, "Emission Strength").default_value = 1.0
        _input(bsdf, "Base Color").default_value = (0.0, 0.0, 0.0, 1.0)
        spec = _input(bsdf, "Specular IOR Level", "Specular")
        if spec is not None:
            spec.default_value = 0.0
    else:
        links.new(tex.outputs["Color"], _input(bsdf, "Base Color"))
    _input(bsdf, "Roughness").default_value = 1.0
    mat["neumesh_shading"] = shading
    return mat


def make_image(name: str, texture: np.ndarray):
    """A Blender image (sRGB, packed into the .blend) holding ``texture`` (H,W,3) display-referred."""
    h, w = texture.shape[:2]
    img = bpy.data.images.new(name, width=w, height=h, alpha=False)
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = np.clip(texture, 0, 1)
    img.pixels.foreach_set(np.ascontiguousarray(rgba[::-1]).ravel())   # Blender's row 0 is the bottom
    img.update()
    try:
        img.pack()
    except Exception as exc:  # noqa: BLE001 - still usable in this session; saving the .blend may lose it
        print(f"NeuMesh: could not pack the baked image '{name}': {exc}")
    return img


def decimated_mesh(vertices: np.ndarray, faces: np.ndarray, ratio: float):
    """(vertices (V',3) float32, faces (F',3) int64): the mesh through Blender's Decimate modifier
    (collapse, ``ratio`` of the faces, triangulated) on a temporary object, which is removed again."""
    tmp = sync.new_mesh_object("NeuMesh decimate (temporary)", vertices, faces)
    data = tmp.data
    try:
        mod = tmp.modifiers.new("NeuMesh decimate", "DECIMATE")
        mod.decimate_type = "COLLAPSE"
        mod.ratio = float(ratio)
        mod.use_collapse_triangulate = True
        bpy.context.view_layer.update()
        ev = tmp.evaluated_get(bpy.context.evaluated_depsgraph_get())
        me = ev.to_mesh()
        try:
            me.calc_loop_triangles()
            v = np.empty(len(me.vertices) * 3, np.float32)
            me.vertices.foreach_get("co", v)
            t = np.empty(len(me.loop_triangles) * 3, np.int32)
            me.loop_triangles.foreach_get("vertices", t)
        finally:
            ev.to_mesh_clear()
    finally:
        bpy.data.objects.remove(tmp)
        bpy.data.meshes.remove(data)
        bpy.context.view_layer.update()   # else the view layer keeps a stale entry for the removed object
    return v.reshape(-1, 3), t.reshape(-1, 3).astype(np.int64)


def build_object(name: str, result, shading: str, collection=None):
    """The baked object: the baked mesh's vertices (world space: the field's, or the decimated copy's),
    its faces, UV map ``UV_NAME``, the image and the material; a per-vertex colour attribute when the
    bake has vertex colours."""
    n_field = int(result.vertex_index.max()) + 1 if len(result.vertex_index) else 0
    verts = np.zeros((n_field, 3), np.float32)
    verts[result.vertex_index] = result.vertices
    faces = result.vertex_index[result.faces]
    obj = sync.new_mesh_object(name, verts, faces, collection)
    me = obj.data
    uv = me.uv_layers.new(name=UV_NAME)
    uv.data.foreach_set("uv", np.ascontiguousarray(result.uvs[result.faces].reshape(-1), np.float32))
    if result.vertex_colours is not None and hasattr(me, "color_attributes"):
        attr = me.color_attributes.new(COLOR_NAME, "FLOAT_COLOR", "POINT")
        rgba = np.ones((n_field, 4), np.float32)
        rgba[:, :3] = core.get().srgb_to_linear(result.vertex_colours[:n_field])
        attr.data.foreach_set("color", rgba.ravel())
    img = make_image(f"{name}_texture", result.texture)
    mat = make_material(f"{name}_material", img, shading)
    me.materials.append(mat)
    me.polygons.foreach_set("use_smooth", np.ones(len(me.polygons), bool))
    me.update()
    obj["neumesh_baked_from"] = result.info.get("field_path", "")
    return obj


class NEUMESH_OT_bake_material(JobModal, bpy.types.Operator):
    """Bake the active object's field, as it renders now (edited and deformed), into a new object with
    a UV map, an image texture and a Principled BSDF material (for Cycles, EEVEE and export)"""

    bl_idname = "neumesh.bake_material"
    bl_label = "Bake to material"
    bl_options = {"REGISTER", "UNDO"}
    edit_label = "baking"

    resolution: IntProperty(name="Texture size", default=1024, min=64, max=8192,
                            description="Width and height of the baked texture in pixels")
    shading: EnumProperty(name="Shading", items=SHADING_ITEMS, default="EMISSION")
    directions: IntProperty(name="Rays per texel", default=1, min=1, max=16,
                            description="1: look straight at each texel along its normal; more: average "
                                        "over a 30-degree cone (softens view-dependent highlights)")
    decimate: FloatProperty(name="Decimate ratio", default=1.0, min=0.001, max=1.0, precision=3,
                            description="Bake onto a copy of the scaffold reduced by Blender's Decimate "
                                        "modifier to this fraction of its faces (1 = the scaffold itself)")
    target: EnumProperty(name="Target", items=TARGET_ITEMS, default="FIELD")
    field_decimate: FloatProperty(name="Faces", default=0.2, min=0.001, max=1.0, precision=3,
                                  description="Field surface: the extracted mesh is decimated to this fraction "
                                              "of the scaffold's face count (fewer: lighter asset, quicker "
                                              "unwrap, rounder part edges)")
    colours: EnumProperty(name="Colours", items=COLOUR_ITEMS, default="VIEWS")
    views: IntProperty(name="Views", default=48, min=1, max=256,
                       description="Views colours: virtual cameras around the object (more: fewer texels "
                                   "left to the ray colour, one field render each)")
    view_size: IntProperty(name="View size", default=512, min=16, max=4096,
                           description="Views colours: width and height of each render in pixels")

    def _start(self, context):
        obj = context.active_object
        try:
            path = field_path_of(obj)
            nm = core.get()
            core.require("bake")
            if self.target == "FIELD":
                core.require("bake_field")
            field, _ = field_cache.object_field(obj, context.evaluated_depsgraph_get())
            field = edit_copy(field)      # posed as it renders now; the thread works on its own copy
        except (UserError, core.CoreUnavailable, ValueError) as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return None
        except Exception as exc:  # noqa: BLE001 - topology errors, missing files...
            self.report({"ERROR"}, f"NeuMesh: bake failed: {exc}")
            return None
        res, dirs = int(self.resolution), int(self.directions)
        self._source = (obj.name_full, path)
        colours = "views" if self.colours == "VIEWS" else "rays"
        project = nm.bake.ProjectConfig(views=int(self.views), size=int(self.view_size))
        mesh = extract = None
        if self.target == "FIELD":
            mesh = "field"
            extract = nm.bake.ExtractConfig(faces=max(1, int(round(self.field_decimate * len(field.faces)))))
        elif self.decimate < 1.0:
            try:
                mesh = decimated_mesh(np.asarray(field.vertices, np.float32), field.faces.cpu().numpy(),
                                      self.decimate)
            except Exception as exc:  # noqa: BLE001 - modifier failures
                self.report({"ERROR"}, f"NeuMesh: decimating the scaffold failed: {exc}")
                return None
            if len(mesh[1]) == 0:
                self.report({"ERROR"}, f"NeuMesh: a decimate ratio of {self.decimate:g} leaves no faces; "
                                       "raise it")
                return None

        def run(progress):
            r = nm.bake_texture(field, resolution=res, directions=dirs, progress=progress, mesh=mesh,
                                extract=extract, colours=colours, project=project)
            r.info["field_path"] = path
            return r
        return Job("bake", run)

    def _finish(self, context, job):
        if job.cancelled:
            self.report({"WARNING"}, "NeuMesh: bake cancelled; nothing was created")
            return {"CANCELLED"}
        if job.error is not None:
            self.report({"ERROR"}, f"NeuMesh: bake: {job.error}")
            return {"CANCELLED"}
        name, _ = self._source
        coll = output_collection(context)
        obj = build_object(f"{name}_baked", job.result, self.shading, coll)
        for o in context.view_layer.objects:
            o.select_set(False)
        obj.select_set(True)
        context.view_layer.objects.active = obj
        r = job.result
        self.report({"INFO"}, f"NeuMesh: baked '{name}' into '{obj.name}' ({r.resolution}x{r.resolution} "
                              f"texture, {r.info.get('charts', 0)} charts, {len(r.faces)} faces, "
                              f"{r.seconds:.1f} s)")
        so = r.info.get("surface_offset") or {}
        if "median_radii" in so:
            self.report({"INFO"}, f"NeuMesh: the baked mesh lies {so['median_radii']:.2f} field radii (median) "
                                  "from the field's surface")
        if r.info.get("missed_texels"):
            self.report({"WARNING"}, f"NeuMesh: {r.info['missed_texels']} texels lie farther than the field "
                                     "radius from the field (filled from their neighbours)")
        return {"FINISHED"}


def output_collection(context):
    """Where a baked object goes: the artist's active collection (Outliner) in the scene they work in;
    the scene's own collection when that one is excluded, hidden from render (the field objects' edit
    collection after Composite with Scene) or not part of the scene."""
    scene = context.scene
    lc = context.view_layer.active_layer_collection
    coll = lc.collection if lc is not None else None
    if coll is None or lc.exclude or coll.hide_render or coll is scene.collection:
        return scene.collection
    return coll


class NEUMESH_PT_bake(EditSubPanel, bpy.types.Panel):
    bl_label = "Bake to material"

    def draw_edit(self, context, col, obj):
        s = context.window_manager
        prefs.draw_missing(col, "bake", context)
        if s.neumesh_bake_target == "FIELD":
            prefs.draw_missing(col, "bake_field", context)
        col.prop(s, "neumesh_bake_resolution")
        col.prop(s, "neumesh_bake_target", text="")
        if s.neumesh_bake_target == "FIELD":
            col.prop(s, "neumesh_bake_field_decimate")
        else:
            col.prop(s, "neumesh_bake_decimate")
        col.prop(s, "neumesh_bake_colours", text="")
        if s.neumesh_bake_colours == "VIEWS":
            col.prop(s, "neumesh_bake_views")
        col.prop(s, "neumesh_bake_shading", text="")
        op = col.operator("neumesh.bake_material", icon="RENDER_RESULT")
        op.resolution = s.neumesh_bake_resolution
        op.target = s.neumesh_bake_target
        op.decimate = s.neumesh_bake_decimate
        op.field_decimate = s.neumesh_bake_field_decimate
        op.colours = s.neumesh_bake_colours
        op.views = s.neumesh_bake_views
        op.shading = s.neumesh_bake_shading


classes = (NEUMESH_OT_bake_material, NEUMESH_PT_bake)


WM = bpy.types.WindowManager
register, unregister = classes_factory(classes, (
    (WM, "neumesh_bake_resolution", lambda: IntProperty(
        name="Texture size", default=1024, min=64, max=8192, description="Baked texture width and height (pixels)")),
    (WM, "neumesh_bake_shading", lambda: EnumProperty(name="Shading", items=SHADING_ITEMS, default="EMISSION")),
    (WM, "neumesh_bake_target", lambda: EnumProperty(name="Target", items=TARGET_ITEMS, default="FIELD")),
    (WM, "neumesh_bake_field_decimate", lambda: FloatProperty(
        name="Faces", default=0.2, min=0.001, max=1.0, precision=3,
        description="Field surface: decimate the extracted mesh to this fraction of the scaffold's face count")),
    (WM, "neumesh_bake_colours", lambda: EnumProperty(name="Colours", items=COLOUR_ITEMS, default="VIEWS")),
    (WM, "neumesh_bake_views", lambda: IntProperty(
        name="Views", default=48, min=1, max=256,
        description="Views colours: virtual cameras around the object (one field render each)")),
    (WM, "neumesh_bake_decimate", lambda: FloatProperty(
        name="Decimate ratio", default=1.0, min=0.001, max=1.0, precision=3,
        description="Bake onto a copy of the scaffold reduced by Blender's Decimate modifier to this fraction "
                    "of its faces (1 = the scaffold itself)")),
))
