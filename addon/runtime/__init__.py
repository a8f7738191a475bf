"""runtime: what the add-on needs to run at all: Python dependencies (deps, install), preferences
(settings, prefs), the lazy core import and torch's thread count (core), the BLAS and allocator
work-arounds for Blender's own libraries (blas, malloc), the one background-job class (jobs), the
error type (errors) and text that fits the sidebar (text). Imports nothing from the other rooms."""
from __future__ import annotations

from . import prefs

_modules = (prefs,)


def modules_factory(modules):
    """(register, unregister) of a room: each module's register() in order; unregister() in reverse,
    going on past a module that fails (the others must still go)."""
    def register():
        for m in modules:
            m.register()

    def unregister():
        for m in reversed(modules):
            try:
                m.unregister()
            except Exception as exc:  # noqa: BLE001 - keep unregistering the rest
                print(f"NeuMesh: unregister {m.__name__}: {exc}")

    return register, unregister


def classes_factory(classes, properties=()):
    """(register, unregister) of a module's bpy classes and the properties it adds to Blender types:
    ``properties`` = ``((owner, name, make), ...)``, ``make()`` building the property once the classes
    are registered (``PointerProperty(type=...)`` needs its class registered first)."""
    import bpy

    register_classes, unregister_classes = bpy.utils.register_classes_factory(classes)

    def register():
        register_classes()
        for owner, name, make in properties:
            setattr(owner, name, make())

    def unregister():
        for owner, name, _make in reversed(properties):
            if hasattr(owner, name):
                delattr(owner, name)
        unregister_classes()

    return register, unregister


register, unregister = modules_factory(_modules)
