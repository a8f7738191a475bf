"""Data stored in the .blend: the field file of an object, the add-on's scene settings."""
from __future__ import annotations

import os

import bpy
from bpy.app.handlers import persistent
from bpy.props import BoolProperty, EnumProperty, IntProperty, PointerProperty, StringProperty


def field_abspath(obj) -> str:
    """Absolute path of the field file of ``obj`` ('' if none). '//' paths resolve against the .blend."""
    p = getattr(getattr(obj, "neumesh", None), "field_path", "") or ""
    if not p.strip():
        return ""
    return os.path.normpath(bpy.path.abspath(p))


def has_field(obj) -> bool:
    return obj is not None and obj.type == "MESH" and bool(getattr(obj.neumesh, "field_path", "").strip()) \
        and obj.neumesh.enabled


def set_field_path(obj, path: str):
    """Store ``path`` on ``obj``; relative to the .blend ('//...') when the .blend has been saved."""
    path = os.path.abspath(bpy.path.abspath(path))
    obj.neumesh.field_path = _maybe_relative(path, bpy.data.filepath)


def _maybe_relative(abspath: str, blend_path: str) -> str:
    if not blend_path:
        return abspath
    try:
        return bpy.path.relpath(abspath, start=os.path.dirname(blend_path))
    except ValueError:  # other drive on Windows
        return abspath


# Blender 4.5+ warns about '//' paths unless the property declares it supports them
_REL = {"options": {"PATH_SUPPORTS_BLEND_RELATIVE"}} if bpy.app.version >= (4, 5, 0) else {}


class NeuMeshObjectSettings(bpy.types.PropertyGroup):
    field_path: StringProperty(
        name="Field file", description="NeuMesh field (.neumesh) rendered on this mesh's vertices",
        subtype="FILE_PATH", default="", **_REL,
    )
    enabled: BoolProperty(name="Render field", description="Render this object's field with NeuMesh",
                          default=True)


class NeuMeshSceneSettings(bpy.types.PropertyGroup):
    dataset_path: StringProperty(name="Dataset", subtype="DIR_PATH", default="", **_REL,
                                 description="NeRF-synthetic (transforms_*.json) or DTU (cameras.npz) folder")
    downscale: IntProperty(name="Downscale", default=1, min=1, max=16,
                           description="Divide the dataset image resolution by this")
    scaffold_method: EnumProperty(
        name="Scaffold method",
        items=[("auto", "Auto", "Visual hull carved by stereo with masks, photometric density "
                                "without"),
               ("hull", "Visual hull", "Fastest; needs masks / alpha"),
               ("hull+mvs", "Hull + stereo", "Hull, then multi-view stereo carves concavities and depth"),
               ("hull+density", "Hull + density", "Hull, then a density grid carves concavities"),
               ("density", "Density", "Photometric density only (no masks needed)")],
        default="auto",
    )
    scaffold_vertices: IntProperty(name="Scaffold vertices", default=100_000, min=0, max=5_000_000,
                                   description="Vertex count the scaffold is resampled to (0 = grid's own)")
    train_steps: IntProperty(name="Steps", default=2000, min=1, max=10_000_000)
    train_object: PointerProperty(name="Mesh", type=bpy.types.Object,
                                  poll=lambda self, o: o.type == "MESH",
                                  description="Mesh object (scaffold) whose field is trained")
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
    viewport_preview: BoolProperty(name="Progressive viewport", default=True,
                                   description="Rendered viewport shading draws low-resolution previews first")


@persistent
def _save_pre(*args):
    """Before saving: store field paths relative to the .blend's new location ('//...')."""
    target = ""
    for a in args:
        if isinstance(a, str) and a:
            target = a
    if not target:
        target = bpy.data.filepath
    if not target:
        return
    old = bpy.data.filepath
    for obj in bpy.data.objects:
        s = getattr(obj, "neumesh", None)
        if s is None or not s.field_path.strip():
            continue
        p = s.field_path
        if p.startswith("//"):
            if not old:
                continue
            p = os.path.normpath(bpy.path.abspath(p, start=os.path.dirname(old)))
        new = _maybe_relative(os.path.abspath(p), target)
        if new != s.field_path:
            s.field_path = new


classes = (NeuMeshObjectSettings, NeuMeshSceneSettings)


def register():
    for c in classes:
        bpy.utils.register_class(c)
    bpy.types.Object.neumesh = PointerProperty(type=NeuMeshObjectSettings)
    bpy.types.Scene.neumesh = PointerProperty(type=NeuMeshSceneSettings)
    if _save_pre not in bpy.app.handlers.save_pre:
        bpy.app.handlers.save_pre.append(_save_pre)


def unregister():
    if _save_pre in bpy.app.handlers.save_pre:
        bpy.app.handlers.save_pre.remove(_save_pre)
    del bpy.types.Scene.neumesh
    del bpy.types.Object.neumesh
    for c in reversed(classes):
        bpy.utils.unregister_class(c)
