"""NeuMesh for Blender: render, deform and train NeuMesh++ neural fields stored on mesh scaffolds.

Installs as a Blender 4.2+ extension (blender_manifest.toml) and as a legacy add-on (bl_info) on
older Blender. torch and the other dependencies are imported lazily (see deps.py / core.py), so the
add-on registers without them and its preferences explain how to install them.
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

import bpy  # noqa: E402

from . import deps  # noqa: E402

# dependency folders (NEUMESH_PYTHONPATH, the add-on's own pip folder) go on sys.path first
try:
    deps.configure_sys_path([deps.addon_deps_dir(__package__, create=False)])
except Exception as _exc:  # noqa: BLE001
    print(f"NeuMesh: dependency folder unavailable: {_exc}")

from . import bake, colour, composite, edits, engine, identity, operators, paint, prefs, props, semantics, texture_edit, ui  # noqa: E402,E501

_modules = (prefs, props, identity, operators, composite, engine, colour, ui, edits, texture_edit, paint, semantics, bake)   # edits first: the others' panels are its children


def register():
    for m in _modules:
        m.register()


def unregister():
    for m in reversed(_modules):
        try:
            m.unregister()
        except Exception as exc:  # keep unregistering the rest
            print(f"NeuMesh: unregister {m.__name__}: {exc}")
