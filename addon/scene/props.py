"""Data stored in the .blend: the field file of an object, the add-on's scene settings."""
from __future__ import annotations

import os

import bpy
from bpy.app.handlers import persistent
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from ..runtime.errors import UserError
from ..runtime.jobs import redraw


def field_abspath(obj) -> str:
    """Absolute path of the field file of ``obj`` ('' if none). '//' paths resolve against the .blend;
    when that file does not exist but the location recorded at the last save does, that one (a .blend
    saved to another folder by a Blender that does not tell add-ons where, see :func:`_save_pre`)."""
    s = getattr(obj, "neumesh", None)
    p = getattr(s, "field_path", "") or ""
    if not p.strip():
        return ""
    path = os.path.normpath(bpy.path.abspath(p))
    if not os.path.isfile(path):
        saved = _saved_location(s)
        if saved:
            return saved
    return path


def _saved_location(s) -> str:
    """The absolute location recorded with the path the object still has ('' when the path was changed
    since, or the file is not there either)."""
    saved = getattr(s, "field_path_saved", "")
    if saved and s.field_path == getattr(s, "field_path_saved_as", None) and os.path.isfile(saved):
        return saved
    return ""


def _record(s, abspath: str, path: str | None = None):
    """Set the field path (if ``path``) and remember where it leads (``abspath``), for _saved_location."""
    if path is not None and s.field_path != path:
        s.field_path = path
    if s.field_path_saved != abspath:
        s.field_path_saved = abspath
    if s.field_path_saved_as != s.field_path:
        s.field_path_saved_as = s.field_path


def missing_field_message(obj) -> str:
    """What to say when the field file of ``obj`` is missing: the path as the user wrote it ('//' kept)
    and, for a '//' path, what it is relative to."""
    p = obj.neumesh.field_path.strip()
    msg = f"object '{obj.name}': field file not found: {p}"
    if p.startswith("//"):
        if not bpy.data.filepath:
            msg += (" ('//' means the folder of the .blend file, and this .blend has not been saved: save it "
                    "in the folder the path is relative to, or choose the field file again)")
        else:
            msg += f" (= {os.path.normpath(bpy.path.abspath(p))})"
    return msg


def field_path_of(obj) -> str:
    """The object's field file (absolute); :class:`UserError` when it has none or it is missing."""
    if obj is None or obj.type != "MESH":
        raise UserError("select a mesh object that carries a NeuMesh field")
    path = field_abspath(obj)
    if not path:
        raise UserError(f"object '{obj.name}' has no NeuMesh field; load or train one first")
    if not os.path.isfile(path):
        raise UserError(missing_field_message(obj))
    return path


def has_field(obj) -> bool:
    return obj is not None and obj.type == "MESH" and bool(getattr(obj.neumesh, "field_path", "").strip()) \
        and obj.neumesh.enabled


def set_field_path(obj, path: str):
    """Store ``path`` on ``obj``; relative to the .blend ('//...') when the .blend has been saved."""
    path = os.path.abspath(bpy.path.abspath(path))
    _record(obj.neumesh, path, _maybe_relative(path, bpy.data.filepath))


EDITS_SUFFIX = "_neumesh"


def edits_folder(chosen: str, blend_path: str) -> str:
    """The folder edited field files are written to (pure: no Blender state, nothing created).

    ``chosen``: the scene's *Edits folder* as the artist set it ('' = the default; '//' = relative to
    the .blend); ``blend_path``: the saved .blend ('' when unsaved).  The default is a folder named
    after the .blend beside it (``scene.blend`` -> ``scene_neumesh/``), so an edit never writes into the
    folder a field was read from unless the artist chose that folder.  :class:`UserError` saying what to
    do when neither a folder was chosen nor the .blend saved."""
    chosen = (chosen or "").strip()
    blend = (blend_path or "").strip()
    if chosen.startswith("//"):
        if not blend:
            raise UserError(f"the Edits folder '{chosen}' is relative to the .blend ('//'), which is not saved; "
                            "save the .blend first, or choose an absolute Edits folder (Edit field panel)")
        return os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(blend)), chosen[2:]))
    if chosen:
        return os.path.normpath(os.path.abspath(os.path.expanduser(chosen)))
    if not blend:
        raise UserError("edits are saved beside the .blend, in a folder named after it, and this .blend is not "
                        "saved: save the .blend first, or choose an Edits folder (Edit field panel)")
    stem = os.path.splitext(os.path.basename(blend))[0] or "untitled"
    return os.path.join(os.path.dirname(os.path.abspath(blend)), stem + EDITS_SUFFIX)


def scene_edits_folder(scene=None) -> str:
    """:func:`edits_folder` of ``scene`` (default: the current one) and the open .blend."""
    scene = scene or bpy.context.scene
    return edits_folder(getattr(scene.neumesh, "edits_dir", ""), bpy.data.filepath)


def _maybe_relative(abspath: str, blend_path: str) -> str:
    if not blend_path:
        return abspath
    try:
        return bpy.path.relpath(abspath, start=os.path.dirname(blend_path))
    except ValueError:  # other drive on Windows
        return abspath


# Blender 4.5+ warns about '//' paths unless the property declares it supports them
_REL = {"options": {"PATH_SUPPORTS_BLEND_RELATIVE"}} if bpy.app.version >= (4, 5, 0) else {}


def _tag_object(self, _context):
    """A changed field path or switch: re-evaluate the object, so a Rendered viewport redraws."""
    try:
        self.id_data.update_tag()
    except Exception:  # noqa: BLE001 - e.g. while the file is being written
        pass


class NeuMeshObjectSettings(bpy.types.PropertyGroup):
    field_path: StringProperty(
        name="Field file", description="NeuMesh field (.neumesh) rendered on this mesh's vertices",
        subtype="FILE_PATH", default="", update=_tag_object, **_REL,
    )
    enabled: BoolProperty(name="Render field", description="Render this object's field with NeuMesh",
                          default=True, update=_tag_object)
    # where field_path_saved_as (the field path as it was then) led when it was set or the .blend was
    # last saved; used while the path is unchanged and does not resolve (see _save_pre)
    field_path_saved: StringProperty(name="Field file at last save", default="", options={"HIDDEN"})
    field_path_saved_as: StringProperty(name="Field path at last save", default="", options={"HIDDEN"})


class NeuMeshSceneSettings(bpy.types.PropertyGroup):
    dataset_path: StringProperty(name="Dataset", subtype="DIR_PATH", default="", **_REL,
                                 description="NeRF-synthetic (transforms_*.json), DTU (cameras.npz), COLMAP "
                                             "(sparse/0 + images) or transforms.json folder")
    downscale: IntProperty(name="Downscale", default=1, min=1, max=16,
                           description="Divide the dataset image resolution by this")
    scaffold_method: EnumProperty(
        name="Scaffold method",
        description="How the scaffold (the mesh the field is stored on; every vertex keeps the learned codes "
                    "of the surface around it) is built from the dataset's photos",
        items=[("auto", "Auto", "Visual hull carved by stereo with masks, photometric density "
                                "without"),
               ("hull", "Visual hull", "Fastest; needs masks / alpha"),
               ("hull+mvs", "Hull + stereo", "Hull, then multi-view stereo carves concavities and depth"),
               ("hull+density", "Hull + density", "Hull, then a density grid carves concavities"),
               ("density", "Density", "Photometric density only (no masks needed)")],
        default="auto",
    )
    scaffold_vertices: IntProperty(name="Scaffold vertices", default=100_000, min=0, max=5_000_000,
                                   description="Vertex count the scaffold (the mesh the field is stored on) is "
                                               "resampled to: more vertices hold finer detail and cost memory "
                                               "and time (0 = the grid's own count)")
    capture_source: StringProperty(name="Photos or video", subtype="FILE_PATH", default="", **_REL,
                                   description="A folder of photos of the object, or a video file, whose "
                                               "camera poses are estimated (needs pycolmap and opencv)")
    capture_fps: FloatProperty(name="Frames per second", default=2.0, min=0.1, max=30.0,
                               description="Frames kept per second of a video (the sharpest of each interval)")
    train_steps: IntProperty(name="Steps", default=2000, min=1, max=10_000_000)
    train_object: PointerProperty(name="Mesh", type=bpy.types.Object,
                                  poll=lambda self, o: o.type == "MESH",
                                  description="The scaffold: the mesh whose field is trained (every vertex "
                                              "keeps the learned codes of the surface around it)")
    composite_scene: PointerProperty(
        name="Field scene", type=bpy.types.Scene,
        description="The companion scene that renders this scene's NeuMesh fields with the NeuMesh engine, "
                    "Z-combined with this scene's render in the compositor (Composite with Scene)")
    edits_dir: StringProperty(name="Edits folder", subtype="DIR_PATH", default="", **_REL,
                              description="Where edits write their field files (<name>.edit-NNN.neumesh). Empty: "
                                          "beside the .blend, in a folder named after it (<blend name>_neumesh)")
    output_dir: StringProperty(name="Output folder", subtype="DIR_PATH", default="//neumesh_renders/", **_REL)
    render_cameras: EnumProperty(
        name="Cameras", items=[("ACTIVE", "Scene camera", "Render the scene camera"),
                               ("DATASET", "Dataset cameras", "Render every camera of the imported dataset")],
        default="ACTIVE",
    )
    render_samples: IntProperty(name="Anti-aliasing", default=1, min=1, max=4,
                                description="Final renders (F12, Render to images) average S x S rays per "
                                            "pixel: smoother edges and fine texture, S^2 times the render "
                                            "time. The viewport uses 1")
    render_background: BoolProperty(
        name="Background", default=True,
        description="Fields trained on photos without masks: render the room their background model learned "
                    "behind the object (a photo-like frame). Off: the object alone; with Film > Transparent "
                    "its alpha is the object's own opacity")
    train_background: BoolProperty(
        name="Background model", default=True,
        description="Photos without masks: learn the room outside the NeuMesh Box with a background model, "
                    "so the field keeps only the object (off: the field explains the whole photo)")
    viewport_preview: BoolProperty(name="Progressive viewport", default=True,
                                   description="Rendered viewport shading draws low-resolution previews first")
    photo_colour_set: BoolProperty(name="Photo colours set", default=False, options={"HIDDEN"},
                                   description="The view transform was set to 'Standard' when NeuMesh was "
                                               "first chosen as this scene's render engine")


def _objects_with_field_paths():
    for obj in bpy.data.objects:
        s = getattr(obj, "neumesh", None)
        if s is not None and s.field_path.strip():
            yield obj, s


@persistent
def _save_pre(*args):
    """Before saving: store field paths relative to the .blend's new location ('//...'), and each
    file's absolute location in ``field_path_saved``.

    Blender 4.x/5.x pass the path being written. Blender 3.x passes nothing (its save_pre gets
    ``(None, None)``), so a Save As to another folder cannot be told from a plain save there: the
    '//' path is kept relative to the folder it was made for, and the absolute location saved beside
    it repairs it when the file is opened from the new folder (:func:`_load_post`) or rendered
    (:func:`field_abspath`). After any save, :func:`_save_post` makes the paths in memory relative to
    where the file now is."""
    target = ""
    for a in args:
        if isinstance(a, str) and a:
            target = a
    for _obj, s in _objects_with_field_paths():
        p = s.field_path
        if p.startswith("//") and not bpy.data.filepath:
            continue  # relative to nothing yet; nothing to record
        abspath = os.path.normpath(bpy.path.abspath(p)) if p.startswith("//") else os.path.abspath(p)
        if not os.path.isfile(abspath):
            abspath = _saved_location(s) or abspath
        _record(s, abspath, _maybe_relative(abspath, target) if target else None)


@persistent
def _save_post(*_args):
    """After saving (and after Save Copy, which leaves the open file where it was): field paths in
    memory relative to where the .blend now is, pointing at the files :func:`_save_pre` recorded."""
    _relink(only_missing=False)


@persistent
def _load_post(*_args):
    """After opening a .blend: a '//' field path that does not resolve from the file's folder, whose
    location recorded at the last save exists, is made relative to the new folder (a Save As to
    another folder in Blender 3.x, see :func:`_save_pre`). The sidebar is redrawn once the file's
    windows exist (else its panels overlap until the mouse moves over them)."""
    _relink(only_missing=True)
    if not bpy.app.background:
        bpy.app.timers.register(_redraw_after_load, first_interval=0.1)


def _redraw_after_load():
    redraw(bpy.context)
    return None


def _relink(only_missing: bool):
    if not bpy.data.filepath:
        return
    for obj, s in _objects_with_field_paths():
        saved, p = _saved_location(s), s.field_path
        if not saved:
            continue
        if only_missing and (not p.startswith("//") or os.path.isfile(bpy.path.abspath(p))):
            continue
        new = _maybe_relative(saved, bpy.data.filepath)
        if new != p:
            _record(s, saved, new)
            if only_missing:
                print(f"NeuMesh: object '{obj.name}': field path {p} does not resolve from this .blend's "
                      f"folder; using {new} ({saved}), where the file was when the .blend was saved")


classes = (NeuMeshObjectSettings, NeuMeshSceneSettings)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()
    bpy.types.Object.neumesh = PointerProperty(type=NeuMeshObjectSettings)
    bpy.types.Scene.neumesh = PointerProperty(type=NeuMeshSceneSettings)
    for handlers, fn in _HANDLERS():
        if fn not in handlers:
            handlers.append(fn)


def _HANDLERS():
    h = bpy.app.handlers
    return ((h.save_pre, _save_pre), (h.save_post, _save_post), (h.load_post, _load_post))


def unregister():
    for handlers, fn in _HANDLERS():
        if fn in handlers:
            handlers.remove(fn)
    del bpy.types.Scene.neumesh
    del bpy.types.Object.neumesh
    _unregister_classes()
