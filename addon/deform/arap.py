"""ARAP deform: pull a handle, the object bends as rigidly as possible, the field follows.

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
the live setup, like a modifier's *Apply as shape key*.  In the viewport a drag's solve runs in a
thread per object (the newest Empty transforms win; a timer writes the result), so the interface stays
live while a big scaffold solves; scripts and renders (``bpy.app.background``) solve in place.
While a Texture Paint stroke runs on the object (``paint_sync.stroke_running``) no solve is written:
Blender's projection paint reads the mesh evaluated when the stroke began, and a key written under the
stroke (a render or frame change that a script or timer starts) frees that mesh (Blender 3.4 then
segfaults at the stroke's next dab); the solve is written once the stroke has ended.
Undo and redo restore the Empties and the live shape key together, exactly (:mod:`.arap_undo`: each
write records the Empties' transforms it was solved for, and the shapes shown before drags are
kept).  The operators, settings and panel are in :mod:`.arap_ops`.
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict

import bpy
from bpy.app.handlers import persistent

from ..runtime._np import np
from ..runtime import core
from ..runtime.errors import UserError
from ..scene import sync
from ..edit import paint_sync

LIVE_KEY = "NeuMesh ARAP"
APPLIED_KEY = "ARAP pose"
SOLVED_FOR = "neumesh_arap_solved_for"   # on the shape keys' ID: digest of the Empties' transforms

_SOLVERS: dict = {}   # object name -> {"key": cache key, "preview"/"full": ArapSolver, "last": transforms,
#                                         "stale": solvers whose warm start an undo made wrong}
TIMINGS: dict = {}    # object name -> last solve's figures (setup_s, solve_s, write_s, mode)
_SHAPES: dict = {}    # object name -> OrderedDict(transforms digest -> (N,3) shape shown for them)
KEEP_SHAPES = 8       # shapes kept per object (undo/redo steps back to a shape shown before)


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


def _entry(obj, s, rest, full: bool, build: bool = True):
    """(entry, solver) of ``obj``'s cache; the solver is factorised here when missing and ``build``
    (else None: :func:`_factorise` builds it, e.g. in the drag thread)."""
    name = obj.name_full
    key = (len(rest), s.generation, s.anchor_group, s.handle_groups, s.preview_vertices,
           float(np.abs(rest).sum()))
    ent = _SOLVERS.get(name)
    if ent is None or ent["key"] != key:
        anchors, handles, names = read_groups(obj, s)
        if names != _list(s.handle_groups):
            raise UserError("the handle groups changed since ARAP deform was added: press Refresh")
        ent = _SOLVERS[name] = {"key": key, "groups": (anchors, handles), "last": None, "rest": rest,
                                "faces": sync.mesh_triangles(obj.data), "lock": threading.Lock()}
    which = "full" if full or s.preview_vertices == 0 or s.preview_vertices >= len(rest) else "preview"
    ent.setdefault("cfg", {})[which] = (0 if which == "full" else s.preview_vertices)
    if which not in ent and build:
        _factorise(name, ent, which)
    return ent, ent.get(which), which


def _factorise(name, ent, which):
    nm = core.get()
    anchors, handles = ent["groups"]
    with core.torch_work():
        solver = nm.deform.ArapSolver(ent["rest"], ent["faces"], anchors, handles,
                                      nm.deform.ArapConfig(cage_vertices=ent["cfg"][which]))
    ent[which] = solver
    TIMINGS.setdefault(name, {})[f"setup_{which}_s"] = solver.setup_seconds
    return solver


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


def _digest(moved: bytes) -> str:
    import hashlib

    return hashlib.sha1(moved).hexdigest()


def _write_live(obj, V: np.ndarray, moved: bytes) -> None:
    """The live shape key := ``V``, solved for the Empties' transforms ``moved``."""
    keys = obj.data.shape_keys
    kb = keys.key_blocks.get(LIVE_KEY) if keys else None
    if kb is None:
        kb = obj.shape_key_add(name=LIVE_KEY, from_mix=False)
        kb.value = 1.0
    kb.data.foreach_set("co", np.ascontiguousarray(V, np.float32).ravel())
    keys = obj.data.shape_keys
    keys[SOLVED_FOR] = _digest(moved)
    obj.data.update()


def _shown(obj):
    """(transforms digest, (N,3) shape) the live key shows now, or None."""
    keys = obj.data.shape_keys
    kb = keys.key_blocks.get(LIVE_KEY) if keys else None
    if kb is None or keys.get(SOLVED_FOR) is None:
        return None
    arr = np.empty(len(kb.data) * 3, np.float32)
    kb.data.foreach_get("co", arr)
    return str(keys[SOLVED_FOR]), arr.reshape(-1, 3)


def _remember(obj) -> None:
    """Keep the shape the live key shows now, so that an undo or redo back to its Empties' transforms
    shows it again exactly (the last KEEP_SHAPES per object)."""
    got = _shown(obj)
    if got is None:
        return
    shapes = _SHAPES.setdefault(obj.name_full, OrderedDict())
    shapes[got[0]] = got[1]
    shapes.move_to_end(got[0])
    while len(shapes) > KEEP_SHAPES:
        shapes.popitem(last=False)


def _unchanged(ent, moved, from_rest) -> bool:
    last = ent["last"]   # (transforms, solved from rest) of the last solve
    return last is not None and last[0] == moved and (last[1] or not from_rest)


def solve(obj, depsgraph=None, from_rest: bool = False, force: bool = False):
    """Re-solve ``obj``'s ARAP deform for the Empties' current transforms and write the live shape key,
    in this thread. ``from_rest``: a frame change / render (deterministic; *Frame iterations*); else a
    drag (warm start, *Iterations*, preview cage).  Returns the ArapResult, or None when nothing moved
    since the last solve (a frame change still re-solves a dragged pose from rest)."""
    s = obj.neumesh_arap
    t0 = time.perf_counter()
    M = handle_transforms(obj, s, depsgraph)
    ent, solver, which = _entry(obj, s, _rest(obj), full=from_rest and not s.cage_in_renders, build=False)
    moved = M.round(7).tobytes()
    if not force and _unchanged(ent, moved, from_rest):
        return None
    with ent["lock"]:
        solver = _ready(obj.name_full, ent, which)
        res = _solve_with(solver, M, s.frame_iterations if from_rest else s.iterations, from_rest)
    t1 = time.perf_counter()
    _write_live(obj, res.vertices, moved)
    ent["last"] = (moved, from_rest)
    TIMINGS.setdefault(obj.name_full, {}).update(
        mode="frame" if from_rest else "drag", solve_s=t1 - t0, write_s=time.perf_counter() - t1,
        move_to_preview_s=time.perf_counter() - t0, cage=solver.cage is not None)
    return res


def start(obj, depsgraph=None):
    """The first solve after *Add ARAP deform* / *Refresh*: with every Empty where it was made, the
    solution is the rest shape, written without solving (factorising waits for the first move);
    otherwise a solve from rest."""
    s = obj.neumesh_arap
    M = handle_transforms(obj, s, depsgraph)
    if not np.allclose(M, np.eye(4), atol=1e-7):
        return solve(obj, depsgraph, from_rest=True, force=True)
    rest = _rest(obj)
    ent, _solver, _which = _entry(obj, s, rest, full=True, build=False)
    moved = M.round(7).tobytes()
    _write_live(obj, rest, moved)
    ent["last"] = (moved, True)
    TIMINGS.setdefault(obj.name_full, {})["mode"] = "rest"
    return None


def _ready(name, ent, which):
    """The ``which`` solver of ``ent``, factorised when missing, its warm start forgotten when an undo
    restored another shape than its last solve (call under ``ent["lock"]``)."""
    solver = ent.get(which) or _factorise(name, ent, which)
    if which in ent.get("stale", ()):
        solver.reset()
        ent["stale"].discard(which)
    return solver


def _solve_with(solver, M, iterations, from_rest):
    nm = core.get()
    try:
        with core.torch_work():
            return solver.solve(solver.targets_from_transforms(M), iterations=iterations,
                                warm_start=not from_rest)
    except nm.DeformError as exc:
        raise UserError(str(exc)) from exc


# ------------------------------------------------------------------------ drags in a background thread
_DRAGS: dict = {}   # object name -> {"want": (M, t_seen, moved, iterations, epoch), "thread", "epoch",
#                                       "done": (V, t_seen, moved, solve_s, cage, epoch) or None}
_UNDO = {"busy": False}   # between undo_pre and undo_post (also redo): no solve may write


def drag(obj, depsgraph=None) -> bool:
    """A handle moved in the viewport: queue a solve in the object's drag thread (factorising first
    when needed); the newest transforms win, the result is written by a timer.  True when queued."""
    s = obj.neumesh_arap
    t_seen = time.perf_counter()
    M = handle_transforms(obj, s, depsgraph)
    ent, _solver, which = _entry(obj, s, _rest(obj), full=False, build=False)
    moved = M.round(7).tobytes()
    if _unchanged(ent, moved, False):
        return False
    name = obj.name_full
    d = _DRAGS.setdefault(name, {"thread": None, "done": None, "error": None, "epoch": 0})
    if d.get("want") is None and d["done"] is None and (d["thread"] is None or not d["thread"].is_alive()):
        _remember(obj)     # a drag begins: the shape before it, for the undo of the drag
    d["want"] = (M, t_seen, moved, s.iterations, d["epoch"])
    d["ent"], d["which"] = ent, which
    _start(name, d)
    if not bpy.app.timers.is_registered(_apply_drags):
        bpy.app.timers.register(_apply_drags, first_interval=0.02)
    return True


def _start(name, d) -> None:
    if d["thread"] is None or not d["thread"].is_alive():
        d["thread"] = threading.Thread(target=_drag_worker, args=(name, d["ent"], d["which"], d),
                                       daemon=True, name="neumesh-arap-drag")
        d["thread"].start()


def prepare_preview(obj) -> threading.Thread | None:
    """Factorise ``obj``'s drag solver in a background thread and solve it once at rest (a first solve
    without a previous one starts on a coarse cage, seconds on a big scaffold), so that the first drag
    waits for neither (started by *Add ARAP deform*); None when it is ready already."""
    s = obj.neumesh_arap
    ent, _solver, which = _entry(obj, s, _rest(obj), full=False, build=False)
    if ent.get(f"primed_{which}"):
        return None
    obj_name = obj.name_full

    def build():
        try:
            with ent["lock"]:
                solver = ent.get(which) or _factorise(obj_name, ent, which)
                if not ent.get(f"primed_{which}"):
                    _solve_with(solver, np.eye(4), 1, False)
                    ent[f"primed_{which}"] = True
        except Exception as exc:  # noqa: BLE001 - the first drag builds it again and reports
            print(f"NeuMesh ARAP '{obj_name}': {exc}")

    job = threading.Thread(target=build, daemon=True, name="neumesh-arap-prepare")
    job.start()
    ent["prepare"] = job
    return job


def _drag_worker(name, ent, which, d):
    try:
        while d.get("want") is not None:
            M, t_seen, moved, iters, epoch = d.pop("want")
            with ent["lock"]:
                t0 = time.perf_counter()
                solver = _ready(name, ent, which)
                res = _solve_with(solver, M, iters, False)
            d["done"] = (res.vertices, t_seen, moved, time.perf_counter() - t0, solver.cage is not None, epoch)
    except Exception as exc:  # noqa: BLE001 - reported by the timer, in the main thread
        d["error"] = exc


def _apply_drags(hold: bool = True):
    """Timer: write finished drag solves into their objects; keeps polling while a thread runs, and
    (``hold``) while a Texture Paint stroke runs on the object (the solve is written once it has ended)."""
    busy = False
    for name, d in list(_DRAGS.items()):
        done, d["done"] = d["done"], None
        obj = bpy.data.objects.get(name)
        if hold and done is not None and obj is not None and paint_sync.stroke_running(obj):
            d["done"], done = done, None
        if done is not None and done[-1] != d.get("epoch", 0):
            done = None            # solved for Empties an undo or redo has put back since
        if done is not None and obj is not None and name in _SOLVERS and not _UNDO["busy"]:
            V, t_seen, moved, solve_s, cage, _epoch = done
            _write_live(obj, V, moved)
            _SOLVERS[name]["last"] = (moved, False)
            TIMINGS.setdefault(name, {}).update(mode="drag", solve_s=solve_s, cage=cage,
                                                move_to_preview_s=time.perf_counter() - t_seen)
        if d.get("error") is not None:
            print(f"NeuMesh ARAP '{name}': {d.pop('error')}")
            d.pop("want", None)
        elif d.get("want") is not None:   # queued just as the thread finished its loop
            _start(name, d)
        busy = busy or (d["thread"] is not None and d["thread"].is_alive()) or d["done"] is not None
    return 0.02 if busy else None


def wait_for_drags(timeout: float = 600.0) -> None:
    """Block until every drag thread finished and its result is written (scripts, tests, benchmarks)."""
    end = time.perf_counter() + timeout
    while time.perf_counter() < end:
        for d in list(_DRAGS.values()):
            if d["thread"] is not None:
                d["thread"].join(max(0.0, end - time.perf_counter()))
        if _apply_drags(hold=False) is None:
            return


def _arap_objects(scene):
    return [o for o in scene.objects if o.type == "MESH" and o.neumesh_arap.enabled]


_HELD: set = set()   # objects whose frame-change solve waits for a Texture Paint stroke to end


def _run(scene, depsgraph, from_rest):
    for obj in _arap_objects(scene):
        if paint_sync.stroke_running(obj):
            # a write now would make the mesh evaluate anew under the stroke (Blender's projection paint
            # reads it through pointers taken when the stroke began): solved once the stroke has ended
            _HELD.add(obj.name_full)
            if not bpy.app.timers.is_registered(_after_stroke):
                bpy.app.timers.register(_after_stroke, first_interval=0.25)
            continue
        try:
            solve(obj, depsgraph, from_rest=from_rest)
        except Exception as exc:  # noqa: BLE001 - a handler must not raise; say why in the console
            print(f"NeuMesh ARAP '{obj.name}': {exc}")


def _after_stroke():
    """Timer: the frame-change solves held back while a Texture Paint stroke ran, once it has ended."""
    if paint_sync.stroke_running():
        return 0.25
    names = sorted(_HELD)
    _HELD.clear()
    for name in names:
        obj = bpy.data.objects.get(name)
        if obj is None or obj.type != "MESH" or not obj.neumesh_arap.enabled or _UNDO["busy"]:
            continue
        try:
            solve(obj, from_rest=True)
        except Exception as exc:  # noqa: BLE001 - a timer must not raise; say why in the console
            print(f"NeuMesh ARAP '{obj.name}': {exc}")
    return None


@persistent
def on_frame_change(scene, depsgraph=None):
    if not _UNDO["busy"]:
        _run(scene, depsgraph, from_rest=True)


@persistent
def on_depsgraph_update(scene, depsgraph=None):
    if depsgraph is None or _UNDO["busy"] or not _arap_objects(scene):
        return
    if not any(isinstance(u.id, bpy.types.Object) for u in depsgraph.updates):
        return
    if bpy.app.background:   # scripts and renders: solve here, the result is there when the call returns
        _run(scene, depsgraph, from_rest=False)
        return
    for obj in _arap_objects(scene):   # the viewport: the solve runs beside the interface
        try:
            drag(obj, depsgraph)
        except Exception as exc:  # noqa: BLE001
            print(f"NeuMesh ARAP '{obj.name}': {exc}")
