"""ARAP deform (issue 52): pull a handle, the object bends as rigidly as possible, the field follows.

The artist marks an *Anchor* vertex group (stays) and one or more *Handle* groups (every group whose name
starts with "Handle"), and presses *Add ARAP deform*: one Empty per handle group appears at the group's
centroid, parented to the object.  Moving, rotating or scaling an Empty (G/R/S, keyframes, drivers)
re-solves the deformation from the rest positions (the Basis shape key) and the Empties' transforms, and
writes it into the shape key "NeuMesh ARAP" (absolute positions, value 1).  The field follows because the
render engine reads the evaluated mesh, shape keys included; nothing in the mesh itself changes, so
removing the setup (or the key) gives the rest shape back.

When it solves: on every depsgraph update that moved an Empty (a drag: warm-started from the previous
solve, *Iterations* per move, on the *Preview* cage when set) and on every frame change (solved from rest
with *Frame iterations*, on the full mesh unless *Cage in renders* is on), so `blender -b -a` renders a
keyframed animation, and the same frame always gives the same shape.  The solver (the factorised system)
is cached per object and rebuilt when the groups, the Basis or the resolution change (*Refresh* re-reads
the vertex groups).  *Apply as shape key* bakes the current pose into a shape key "ARAP pose" and removes
the live setup, like a modifier's *Apply as shape key*.
"""
from __future__ import annotations

import time

import bpy
from bpy.app.handlers import persistent
from bpy.props import BoolProperty, IntProperty, PointerProperty, StringProperty

from ..runtime._np import np
from ..runtime import classes_factory, core
from ..runtime.errors import UserError
from ..scene import sync
from .base import EditSubPanel

LIVE_KEY = "NeuMesh ARAP"
APPLIED_KEY = "ARAP pose"

_SOLVERS: dict = {}   # object name -> {"key": cache key, "preview"/"full": ArapSolver, "last": transforms}
TIMINGS: dict = {}    # object name -> last solve's figures (setup_s, solve_s, write_s, mode)


class NeuMeshArapSettings(bpy.types.PropertyGroup):
    enabled: BoolProperty(name="ARAP deform", default=False)
    anchor_group: StringProperty(name="Anchor group", default="Anchor")
    handle_prefix: StringProperty(name="Handle groups", default="Handle",
                                  description="Every vertex group whose name starts with this is a handle")
    handle_groups: StringProperty(default="", options={"HIDDEN"})   # "\n"-joined, in the Empties' order
    handle_empties: StringProperty(default="", options={"HIDDEN"})  # "\n"-joined Empty names
    centroids: StringProperty(default="", options={"HIDDEN"})       # flat floats, local rest centroids
    preview_vertices: IntProperty(
        name="Preview", default=30000, min=0, soft_max=200000,
        description="Solve on a cage of about this many vertices while dragging and carry the result to "
                    "every vertex (0: the full mesh). Smaller is faster")
    iterations: IntProperty(name="Iterations", default=4, min=1, max=100,
                            description="Local-global iterations per move while dragging")
    frame_iterations: IntProperty(name="Frame iterations", default=30, min=1, max=500,
                                  description="Iterations of a solve from rest on a frame change or render")
    cage_in_renders: BoolProperty(name="Cage in renders", default=False,
                                  description="Solve frame changes and renders on the preview cage too")
    generation: IntProperty(default=0, options={"HIDDEN"})   # bumped by Refresh: rebuild the solver


# ------------------------------------------------------------------------------------------ state
def _list(s: str) -> list:
    return [x for x in s.split("\n") if x]


def _rest(obj) -> np.ndarray:
    keys = obj.data.shape_keys
    if keys is None:
        return sync.mesh_vertices(obj.data).astype(np.float64)
    basis = keys.reference_key
    arr = np.empty(len(basis.data) * 3, np.float32)
    basis.data.foreach_get("co", arr)
    return arr.reshape(-1, 3).astype(np.float64)


def read_groups(obj, s):
    """(anchors, [handle index arrays], [handle group names]); UserError with what to do when they are
    missing, empty or overlap."""
    if obj.vertex_groups.get(s.anchor_group) is None:
        raise UserError(f"'{obj.name}' has no vertex group '{s.anchor_group}': in Edit Mode select the "
                        "vertices that must stay, Object Data > Vertex Groups > +, name it "
                        f"'{s.anchor_group}' and Assign")
    names = [g.name for g in obj.vertex_groups if g.name.startswith(s.handle_prefix) and g.name != s.anchor_group]
    if not names:
        raise UserError(f"'{obj.name}' has no handle group: make a vertex group named "
                        f"'{s.handle_prefix}' (or '{s.handle_prefix}.001', ...) with the vertices to move")
    anchors = sync.vertex_group_indices(obj, s.anchor_group)
    handles = []
    for n in names:
        h = sync.vertex_group_indices(obj, n)
        if len(h) == 0:
            raise UserError(f"vertex group '{n}' has no vertices: assign the vertices to move, or delete it")
        both = np.intersect1d(h, anchors)
        if len(both):
            raise UserError(f"{len(both)} vertices are in both '{s.anchor_group}' and '{n}': a vertex stays "
                            "or moves, not both; remove them from one group")
        for m, other in zip(names, handles):
            if len(np.intersect1d(h, other)):
                raise UserError(f"vertex groups '{m}' and '{n}' share vertices: each handle vertex "
                                "follows one Empty; remove the shared ones from one group")
        handles.append(h)
    return anchors, handles, names


def _entry(obj, s, rest, full: bool):
    """The cached solver of ``obj`` (built when missing or out of date)."""
    nm = core.get()
    name = obj.name_full
    key = (len(rest), s.generation, s.anchor_group, s.handle_groups, s.preview_vertices,
           float(np.abs(rest).sum()))
    ent = _SOLVERS.get(name)
    if ent is None or ent["key"] != key:
        anchors, handles, names = read_groups(obj, s)
        if names != _list(s.handle_groups):
            raise UserError("the handle groups changed since ARAP deform was added: press Refresh")
        ent = _SOLVERS[name] = {"key": key, "groups": (anchors, handles), "last": None}
    which = "full" if full or s.preview_vertices == 0 or s.preview_vertices >= len(rest) else "preview"
    if which not in ent:
        anchors, handles = ent["groups"]
        cfg = nm.deform.ArapConfig(cage_vertices=0 if which == "full" else s.preview_vertices)
        with core.torch_work():
            ent[which] = nm.deform.ArapSolver(rest, sync.mesh_triangles(obj.data),
                                              anchors, handles, cfg)
        TIMINGS.setdefault(name, {})[f"setup_{which}_s"] = ent[which].setup_seconds
    return ent, ent[which]


def handle_transforms(obj, s, depsgraph=None) -> np.ndarray:
    """(G,4,4) object-space transforms of the handle groups: W^-1 E T(-c) for each Empty E (identity
    while the Empty sits where it was created)."""
    def world(o):
        o = o.evaluated_get(depsgraph) if depsgraph is not None else o
        return np.asarray([list(r) for r in o.matrix_world], np.float64)

    Winv = np.linalg.inv(world(obj))
    c = np.asarray([float(x) for x in s.centroids.split()], np.float64).reshape(-1, 3)
    out = []
    for en, ci in zip(_list(s.handle_empties), c):
        e = bpy.data.objects.get(en)
        if e is None:
            raise UserError(f"the ARAP handle Empty '{en}' was deleted: press Refresh to make it again")
        T = np.eye(4)
        T[:3, 3] = -ci
        out.append(Winv @ world(e) @ T)
    return np.stack(out)


def _write_live(obj, V: np.ndarray) -> None:
    keys = obj.data.shape_keys
    kb = keys.key_blocks.get(LIVE_KEY) if keys else None
    if kb is None:
        kb = obj.shape_key_add(name=LIVE_KEY, from_mix=False)
        kb.value = 1.0
    kb.data.foreach_set("co", np.ascontiguousarray(V, np.float32).ravel())
    obj.data.update()


def solve(obj, depsgraph=None, from_rest: bool = False, force: bool = False):
    """Re-solve ``obj``'s ARAP deform for the Empties' current transforms and write the live shape key.
    ``from_rest``: a frame change / render (deterministic; *Frame iterations*); else a drag (warm start,
    *Iterations*, preview cage).  Returns the ArapResult, or None when nothing moved since the last solve."""
    s = obj.neumesh_arap
    t0 = time.perf_counter()
    M = handle_transforms(obj, s, depsgraph)
    rest = _rest(obj)
    ent, solver = _entry(obj, s, rest, full=from_rest and not s.cage_in_renders)
    moved = M.round(7).tobytes()
    last = ent["last"]   # (transforms, solved from rest) of the last solve
    if not force and last is not None and last[0] == moved and (last[1] or not from_rest):
        return None   # nothing moved (a frame change still re-solves a dragged pose from rest)
    nm = core.get()
    try:
        with core.torch_work():
            res = solver.solve(solver.targets_from_transforms(M),
                               iterations=s.frame_iterations if from_rest else s.iterations,
                               warm_start=not from_rest)
    except nm.DeformError as exc:
        raise UserError(str(exc)) from exc
    t1 = time.perf_counter()
    _write_live(obj, res.vertices)
    ent["last"] = (moved, from_rest)
    TIMINGS.setdefault(obj.name_full, {}).update(
        mode="frame" if from_rest else "drag", solve_s=t1 - t0, write_s=time.perf_counter() - t1,
        cage=solver.cage is not None)
    return res


def _arap_objects(scene):
    return [o for o in scene.objects if o.type == "MESH" and o.neumesh_arap.enabled]


def _run(scene, depsgraph, from_rest):
    for obj in _arap_objects(scene):
        try:
            solve(obj, depsgraph, from_rest=from_rest)
        except Exception as exc:  # noqa: BLE001 - a handler must not raise; say why in the console
            print(f"NeuMesh ARAP '{obj.name}': {exc}")


@persistent
def on_frame_change(scene, depsgraph=None):
    _run(scene, depsgraph, from_rest=True)


@persistent
def on_depsgraph_update(scene, depsgraph=None):
    if depsgraph is None or not _arap_objects(scene):
        return
    if not any(isinstance(u.id, bpy.types.Object) for u in depsgraph.updates):
        return
    _run(scene, depsgraph, from_rest=False)


# -------------------------------------------------------------------------------------- operators
def _active_mesh(context):
    obj = context.active_object
    if obj is None or obj.type != "MESH":
        raise UserError("select the mesh object to deform (the one with the Anchor and Handle groups)")
    return obj


def _make_empties(context, obj, s, handles, names) -> None:
    rest = _rest(obj)
    old = _list(s.handle_empties)
    empties, cents = [], []
    for n, h in zip(names, handles):
        c = rest[h].mean(0)
        ename = f"{obj.name} {n}"
        e = bpy.data.objects.get(ename) if ename in old else None
        if e is None:
            e = bpy.data.objects.new(ename, None)
            e.empty_display_type = "SPHERE"
            e.empty_display_size = max(float(np.ptp(rest, 0).max()) * 0.05, 1e-3)
            (obj.users_collection[0] if obj.users_collection else context.scene.collection).objects.link(e)
            e.parent = obj
            e.matrix_parent_inverse.identity()
            e.location = c
        empties.append(e.name)
        cents.extend(float(x) for x in c)
    for en in old:
        if en not in empties and bpy.data.objects.get(en) is not None:
            bpy.data.objects.remove(bpy.data.objects[en])
    s.handle_groups, s.handle_empties = "\n".join(names), "\n".join(empties)
    s.centroids = " ".join(f"{x:.9g}" for x in cents)


class _ArapOperator:
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        try:
            return self.run(context)
        except UserError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}


class NEUMESH_OT_arap_add(_ArapOperator, bpy.types.Operator):
    """Deform the active object as rigidly as possible: the 'Anchor' group stays, each 'Handle' group
    follows its Empty (move, rotate, scale or keyframe it)"""

    bl_idname, bl_label = "neumesh.arap_add", "Add ARAP deform"

    def run(self, context):
        obj = _active_mesh(context)
        if obj.mode != "OBJECT":
            bpy.ops.object.mode_set(mode="OBJECT")
        s = obj.neumesh_arap
        _anchors, handles, names = read_groups(obj, s)
        if obj.data.shape_keys is None:
            obj.shape_key_add(name="Basis", from_mix=False)
        _make_empties(context, obj, s, handles, names)
        s.enabled = True
        s.generation += 1
        _SOLVERS.pop(obj.name_full, None)
        solve(obj, context.evaluated_depsgraph_get(), from_rest=True, force=True)
        self.report({"INFO"}, f"ARAP deform: {len(names)} handle Empt{'y' if len(names) == 1 else 'ies'} "
                              f"({', '.join(names)}); move them with G/R/S")
        return {"FINISHED"}


class NEUMESH_OT_arap_refresh(_ArapOperator, bpy.types.Operator):
    """Read the Anchor and Handle groups again (after editing them) and re-solve"""

    bl_idname, bl_label = "neumesh.arap_refresh", "Refresh"

    def run(self, context):
        return NEUMESH_OT_arap_add.run(self, context)


def _remove_setup(obj) -> None:
    s = obj.neumesh_arap
    for en in _list(s.handle_empties):
        if bpy.data.objects.get(en) is not None:
            bpy.data.objects.remove(bpy.data.objects[en])
    keys = obj.data.shape_keys
    if keys and keys.key_blocks.get(LIVE_KEY) is not None:
        obj.shape_key_remove(keys.key_blocks[LIVE_KEY])
    s.enabled = False
    s.handle_groups = s.handle_empties = s.centroids = ""
    _SOLVERS.pop(obj.name_full, None)


class NEUMESH_OT_arap_apply(_ArapOperator, bpy.types.Operator):
    """Bake the current ARAP pose into a shape key ('ARAP pose') and remove the live deform and its
    Empties"""

    bl_idname, bl_label = "neumesh.arap_apply", "Apply as shape key"

    def run(self, context):
        obj = _active_mesh(context)
        keys = obj.data.shape_keys
        kb = keys.key_blocks.get(LIVE_KEY) if keys else None
        if not obj.neumesh_arap.enabled or kb is None:
            raise UserError(f"'{obj.name}' has no ARAP deform to apply: press Add ARAP deform first")
        arr = np.empty(len(kb.data) * 3, np.float32)
        kb.data.foreach_get("co", arr)
        new = obj.shape_key_add(name=APPLIED_KEY, from_mix=False)
        new.data.foreach_set("co", arr)
        new.value = 1.0
        _remove_setup(obj)
        obj.data.update()
        self.report({"INFO"}, f"ARAP pose applied as shape key '{new.name}'")
        return {"FINISHED"}


class NEUMESH_OT_arap_remove(_ArapOperator, bpy.types.Operator):
    """Remove the ARAP deform (its shape key and Empties): the object goes back to its rest shape"""

    bl_idname, bl_label = "neumesh.arap_remove", "Remove"

    def run(self, context):
        obj = _active_mesh(context)
        _remove_setup(obj)
        obj.data.update()
        return {"FINISHED"}


class NEUMESH_PT_arap(EditSubPanel, bpy.types.Panel):
    bl_label = "ARAP deform"

    def draw_edit(self, context, col, obj):
        s = obj.neumesh_arap
        col.prop_search(s, "anchor_group", obj, "vertex_groups", text="Anchor")
        col.prop(s, "handle_prefix", text="Handles")
        col.prop(s, "preview_vertices")
        row = col.row(align=True)
        row.prop(s, "iterations")
        row.prop(s, "frame_iterations", text="Frame")
        col.prop(s, "cage_in_renders")
        if not s.enabled:
            col.operator("neumesh.arap_add", icon="MOD_MESHDEFORM")
            return
        t = TIMINGS.get(obj.name_full, {})
        if "solve_s" in t:
            col.label(text=f"Last solve {t['solve_s']:.2f} s ({'cage' if t.get('cage') else 'full'})")
        row = col.row(align=True)
        row.operator("neumesh.arap_refresh", icon="FILE_REFRESH")
        row.operator("neumesh.arap_remove", icon="X")
        col.operator("neumesh.arap_apply", icon="SHAPEKEY_DATA")


classes = (NeuMeshArapSettings, NEUMESH_OT_arap_add, NEUMESH_OT_arap_refresh, NEUMESH_OT_arap_apply,
           NEUMESH_OT_arap_remove, NEUMESH_PT_arap)
_register, _unregister = classes_factory(
    classes, ((bpy.types.Object, "neumesh_arap", lambda: PointerProperty(type=NeuMeshArapSettings)),))
_HANDLERS = ((bpy.app.handlers.frame_change_post, on_frame_change),
             (bpy.app.handlers.depsgraph_update_post, on_depsgraph_update))


def register():
    _register()
    for lst, fn in _HANDLERS:
        if fn not in lst:
            lst.append(fn)


def unregister():
    for lst, fn in _HANDLERS:
        if fn in lst:
            lst.remove(fn)
    _SOLVERS.clear()
    _unregister()
