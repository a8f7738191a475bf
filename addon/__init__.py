"""NeuMesh for Blender: render, deform and train NeuMesh++ neural fields stored on mesh scaffolds.

Installs as a Blender 4.2+ extension (blender_manifest.toml) and as a legacy add-on (bl_info) on
older Blender. torch and the other dependencies are imported lazily (runtime/deps.py, runtime/core.py),
so the add-on registers without them and its preferences explain how to install them.  The rooms
(sub-packages) and what each may import: DEVELOPERS.md, "addon/".
"""

bl_info = {
    "name": "NeuMesh",
    "author": "NeuMesh for Blender developers",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "Render engine 'NeuMesh'; 3D View > Sidebar > NeuMesh",
    "description": "Neural radiance fields on mesh scaffolds (NeuMesh++): train, deform, render",
    "doc_url": "",
    "category": "Render",
}

from .runtime import deps  # noqa: E402

# dependency folders (NEUMESH_PYTHONPATH, the add-on's own pip folder) go on sys.path first
try:
    deps.configure_sys_path([deps.addon_deps_dir(__package__, create=False)])
except Exception as _exc:  # noqa: BLE001
    print(f"NeuMesh: dependency folder unavailable: {_exc}")

from . import bake, deform, edit, render, runtime, scene, semantics, train, ui  # noqa: E402

# each room registers its own modules; the order is the sidebar's order of panels, and a room's
# classes may use the properties of the rooms before it
_rooms = (runtime, scene, train, render, ui, edit, semantics, bake, deform)


def register():
    for room in _rooms:
        room.register()


def unregister():
    for room in reversed(_rooms):
        room.unregister()
