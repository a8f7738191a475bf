"""Shared by the scripts that run inside a real `blender` (test_real_blender*.py drive them).

    install_addon(zip_path) -> module name: installs the zip the way the running Blender takes it
    (legacy add-on before 4.2, extension from 4.2 on), enables it and saves the user preferences, so
    later `blender` processes with the same BLENDER_USER_* folders have it enabled.
    facts(**kw): prints one line 'NEUMESH_FACTS {json}' that the test reads back.
    viewport_engines() / preview_done(): the NeuMesh viewport engines, and whether the first one has
    drawn its preview's last (finest) pass.
"""
import json
import os
import sys

import addon_utils
import bpy

HERE = os.path.dirname(os.path.abspath(__file__))


def _record_faults():
    """On a crash (SIGSEGV, SIGABRT ...) write every thread's Python stack to $NEUMESH_FAULT_LOG (the
    tests set it), the crashing thread marked "Current thread", before Blender's own crash handler
    writes its report. Blender's report shows the stack of the thread that holds the GIL, which need
    not be the one that crashed."""
    path = os.environ.get("NEUMESH_FAULT_LOG")
    if not path:
        return None
    import faulthandler

    fh = open(path, "a")
    faulthandler.enable(fh, all_threads=True)
    return fh


_FAULT_FILE = _record_faults()   # kept open for the life of the process


def script_args():
    return sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []


def install_addon(zip_path):
    if bpy.app.version >= (4, 2, 0):
        bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
        module = "bl_ext.user_default.neumesh"
    else:
        bpy.ops.preferences.addon_install(filepath=zip_path, overwrite=True)
        module = "neumesh"
    addon_utils.enable(module, default_set=True)
    bpy.ops.wm.save_userpref()
    if HERE not in sys.path:
        sys.path.insert(0, HERE)
    return module


def addon_module(module=None):
    return sys.modules[module or ("bl_ext.user_default.neumesh" if bpy.app.version >= (4, 2, 0) else "neumesh")]


def facts(**kw):
    print("NEUMESH_FACTS " + json.dumps(kw, default=str), flush=True)


def viewport_engines():
    """The add-on's live viewport render engines."""
    return list(addon_module().render.engine._PollRedraw._engines)


def preview_done():
    """The viewport's NeuMesh preview has drawn its last (finest) pass (drawn, not only rendered)."""
    for e in viewport_engines():
        pv = getattr(e, "_preview", None)
        if pv is None or pv.busy or pv.latest is None or pv.latest[1] != pv.divisors[-1]:
            return False
        return getattr(e, "_texture_serial", None) == pv.latest[:2]
    return False


def register_open_copy(cls, suffix: str, opened: bool = True) -> None:
    """Register panel ``cls`` again as ``<name><suffix>`` without DEFAULT_CLOSED (Blender keeps a panel's
    open or closed state by its name once drawn; ``opened=False`` keeps its own), its parent renamed
    with the same suffix."""
    opts = next((c.__dict__["bl_options"] for c in cls.__mro__ if isinstance(c.__dict__.get("bl_options"), set)),
                set())
    attrs = {"bl_idname": cls.__name__ + suffix,
             "bl_options": set(opts) - {"DEFAULT_CLOSED"} if opened else set(opts)}
    parent = next((c.__dict__["bl_parent_id"] for c in cls.__mro__ if "bl_parent_id" in c.__dict__), "")
    if parent:
        attrs["bl_parent_id"] = parent + suffix
    bpy.utils.register_class(type(cls.__name__ + suffix, (cls,), attrs))


def paint_brush(scene, colour=(0.0, 1.0, 1.0), size: int = 25) -> None:
    """Texture Paint's brush for a real stroke: ``colour`` at full strength, ``size`` pixels, its own
    colour (not the unified one)."""
    ip = scene.tool_settings.image_paint
    ip.brush.color = colour
    ip.brush.strength = 1.0
    scene.tool_settings.unified_paint_settings.use_unified_color = False
    scene.tool_settings.unified_paint_settings.size = size
    ip.brush.size = size


def overridden(**kw):
    """``bpy.context.temp_override(**kw)`` with the add-on's Python threads held at a checkpoint
    (``runtime.quiet.override``): Blender 3.4 corrupts Python's heap when an operator runs under an
    override while another Python thread runs (the viewport's preview thread, a job)."""
    try:
        quiet = addon_module().runtime.quiet
    except (KeyError, AttributeError):   # the add-on is not loaded (yet)
        return bpy.context.temp_override(**kw)
    return quiet.override(bpy.context, **kw)
