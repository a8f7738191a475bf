"""Add-on preferences: dependency status, "Install dependencies", existing environment path."""
from __future__ import annotations

import os

import bpy
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty

from . import deps

ADDON_ID = __package__  # "neumesh" (legacy add-on) or "bl_ext.<repo>.neumesh" (extension)

_status_cache: dict = {"statuses": None, "blas": None}


def get_prefs():
    """The add-on preferences, or None when the add-on is not enabled through the preferences."""
    try:
        addon = bpy.context.preferences.addons.get(ADDON_ID)
    except Exception:
        return None
    return addon.preferences if addon is not None else None


def extra_paths() -> list[str]:
    """Dependency folders from the preferences: the existing environment first, then our own folder."""
    out = []
    p = get_prefs()
    if p is not None and p.env_path.strip():
        out.append(bpy.path.abspath(p.env_path.strip()))
    try:
        own = deps.addon_deps_dir(ADDON_ID, create=False)
        if os.path.isdir(own):
            out.append(own)
    except Exception:
        pass
    return out


def refresh_paths_and_status(do_import=False):
    deps.configure_sys_path(extra_paths())
    _status_cache["statuses"] = deps.check_dependencies(do_import=do_import)
    return _status_cache["statuses"]


def _on_env_path(self, _context):
    refresh_paths_and_status()


class NEUMESH_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_ID

    env_path: StringProperty(
        name="Existing environment",
        description="A site-packages folder of a Python 3.%d environment that already has torch 2.13 and "
                    "numpy<2 (added to sys.path in front of everything else)" % __import__("sys").version_info[1],
        subtype="DIR_PATH", default="", update=_on_env_path,
    )
    pip_extra_args: StringProperty(
        name="Extra pip arguments",
        description="Added to the pip command, e.g. '--extra-index-url https://download.pytorch.org/whl/cpu' "
                    "to get the CPU build of torch",
        default="",
    )
    torch_threads: IntProperty(
        name="CPU threads",
        description="torch threads for rendering, training and edits (0: all cores). On a machine busy with "
                    "other work, fewer threads can be faster",
        default=0, min=0, max=1024,
    )
    preview_start: EnumProperty(
        name="Preview starts at", description="Resolution of the first viewport preview pass",
        items=[("8", "1/8", ""), ("4", "1/4", ""), ("2", "1/2", ""), ("1", "Full", "")], default="8",
    )
    preview_final: EnumProperty(
        name="Preview ends at", description="Resolution of the last viewport preview pass",
        items=[("4", "1/4", ""), ("2", "1/2", ""), ("1", "Full", "")], default="2",
    )
    show_log: BoolProperty(name="Show pip log", default=False)

    def draw(self, context):
        layout = self.layout
        statuses = _status_cache["statuses"]
        if statuses is None:
            statuses = refresh_paths_and_status()
        box = layout.box()
        box.label(text="Python dependencies (Blender's Python %d.%d)" % __import__("sys").version_info[:2])
        for s in statuses:
            row = box.row()
            icon = "CHECKMARK" if s.found else ("ERROR" if s.required else "INFO")
            what = s.version if s.found else (s.error + ("" if s.required else " (optional)"))
            row.label(text=f"{s.dist}", icon=icon)
            row.label(text=what)
        miss = [s.dist for s in statuses if s.required and not s.found]
        if miss:
            box.label(text="Missing: " + ", ".join(miss) + ". Install them or set an existing environment.",
                      icon="ERROR")
        else:
            box.label(text="All required dependencies found.", icon="CHECKMARK")
        row = box.row()
        row.operator("neumesh.check_dependencies", icon="FILE_REFRESH")
        job = deps.current_install()
        running = job is not None and job.state == "RUNNING"
        sub = row.row()
        sub.enabled = not running
        sub.operator("neumesh.install_dependencies", icon="IMPORT")
        try:
            box.label(text="Install folder: " + deps.addon_deps_dir(ADDON_ID, create=False))
        except Exception as exc:
            box.label(text=f"Install folder unavailable: {exc}", icon="ERROR")
        box.prop(self, "pip_extra_args")
        box.prop(self, "env_path")
        if job is not None:
            icon = {"RUNNING": "SORTTIME", "DONE": "CHECKMARK", "ERROR": "ERROR"}.get(job.state, "INFO")
            box.label(text=f"pip: {job.state.lower()} {job.message}", icon=icon)
            box.prop(self, "show_log")
            if self.show_log:
                col = box.column(align=True)
                for line in job.log_lines[-15:]:
                    col.label(text=line[:160])
        self._draw_speed(layout, context)
        row = layout.row()
        row.prop(self, "torch_threads")
        from . import core

        row.label(text=f"{core.wanted_threads()} in use" + (" (all cores)" if self.torch_threads == 0 else ""))
        row = layout.row()
        row.prop(self, "preview_start")
        row.prop(self, "preview_final")

    def _draw_speed(self, layout, context):
        """Box 'Speed': torch's matrix-multiply rate and BLAS in this Blender, with the remedy if slow."""
        from . import text

        st = _status_cache.get("blas")
        box = layout.box()
        if st is None:
            box.label(text="Speed: press 'Check dependencies' to measure torch in this Blender", icon="TIME")
            return
        width = text.text_width(context)
        if st["own"]:
            text.wrapped_label(box, "Speed: " + speed_message(st), width, icon="CHECKMARK")
            return
        text.wrapped_label(box, "Speed: " + speed_message(st), width, icon="ERROR")
        text.wrapped_label(box, "Start Blender with torch's BLAS preloaded (see docs/addon.md, 'Speed'):", width)
        text.wrapped_label(box, st["remedy"], width, icon="CONSOLE")
        box.operator("neumesh.copy_launcher", icon="COPYDOWN")


def speed_status(measure: bool = True):
    """torch's BLAS in this Blender (see blas.py): which library its matrix multiplies call, the rate
    measured here, the launcher command when it is the slow one. None without torch."""
    import sys

    if "torch" not in sys.modules:
        return None
    from . import blas, core

    st = blas.status(measure=measure)
    core.prepare_torch()  # measuring may have made torch import more modules
    _status_cache["blas"] = st
    return st


def speed_message(st) -> str:
    """One sentence on torch's matrix-multiply speed in this Blender ('' before it was measured); the
    launcher command is not part of it (``st["remedy"]``)."""
    if not st:
        return ""
    rate = "" if st.get("gflops") is None else f" {st['gflops']:.0f} GFLOP/s"
    if st["own"]:
        foreign = st["rebind"].get("foreign") if st["rebind"].get("rebound") else None
        src = f" (rebound from {', '.join(os.path.basename(f) for f in foreign)})" if foreign else ""
        return f"matrix multiply{rate} with torch's own BLAS{src}"
    return (f"matrix multiply{rate} on {os.path.basename(st['sgemm'])}, the slow BLAS this Blender links: "
            "renders and training run several times slower")


class NEUMESH_OT_check_dependencies(bpy.types.Operator):
    """Import every dependency, report versions, and measure torch's matrix-multiply speed in this
    Blender (a Blender that links a slow BLAS makes NeuMesh several times slower)"""

    bl_idname = "neumesh.check_dependencies"
    bl_label = "Check dependencies"

    def execute(self, context):
        statuses = refresh_paths_and_status(do_import=True)
        miss = [s.dist for s in statuses if s.required and not s.found]
        for s in statuses:
            if not s.found and s.error and s.error != "not found":
                self.report({"WARNING"}, f"NeuMesh: {s.dist}: {s.error}")
        if miss:
            self.report({"WARNING"}, "NeuMesh: missing " + ", ".join(miss))
            return {"FINISHED"}
        self.report({"INFO"}, "NeuMesh: " + ", ".join(f"{s.dist} {s.version}" for s in statuses if s.found))
        st = speed_status(measure=True)
        if st is not None:
            msg = "NeuMesh: " + speed_message(st)
            if st["own"]:
                self.report({"INFO"}, msg)
            else:
                self.report({"WARNING"}, f"{msg}. Start Blender as: {st['remedy']}")
        return {"FINISHED"}


class NEUMESH_OT_copy_launcher(bpy.types.Operator):
    """Copy the command that starts Blender with torch's own BLAS preloaded to the clipboard"""

    bl_idname = "neumesh.copy_launcher"
    bl_label = "Copy launcher command"

    def execute(self, context):
        from . import blas

        st = _status_cache.get("blas") or {}
        cmd = st.get("remedy") or blas.preload_command()
        context.window_manager.clipboard = cmd
        self.report({"INFO"}, f"NeuMesh: copied: {cmd}")
        return {"FINISHED"}


class NEUMESH_OT_install_dependencies(bpy.types.Operator):
    """Install torch 2.13, numpy<2, scipy, pykdtree, trimesh, safetensors and pillow with Blender's own
    Python (pip) into a folder owned by the add-on. Needs network access (several hundred MB)"""

    bl_idname = "neumesh.install_dependencies"
    bl_label = "Install dependencies"

    wait: BoolProperty(default=False, options={"HIDDEN", "SKIP_SAVE"})
    requirements: StringProperty(default="", options={"HIDDEN", "SKIP_SAVE"},
                                 description="space-separated requirements (default: the pinned set)")

    def execute(self, context):
        import shlex

        prefs = get_prefs()
        extra = shlex.split(prefs.pip_extra_args) if prefs is not None else []
        reqs = shlex.split(self.requirements) if self.requirements.strip() else list(deps.PIP_REQUIREMENTS)
        try:
            target = deps.addon_deps_dir(ADDON_ID, create=True)
            job = deps.start_install(target, reqs, extra)
        except Exception as exc:
            self.report({"ERROR"}, f"NeuMesh: cannot start pip: {exc}")
            return {"CANCELLED"}
        if self.wait or bpy.app.background:
            job.join()
            return self._finish(job)
        bpy.app.timers.register(_poll_install, first_interval=0.5)
        self.report({"INFO"}, "NeuMesh: installing dependencies in the background (see add-on preferences)")
        return {"FINISHED"}

    def _finish(self, job):
        refresh_paths_and_status()
        if job.state == "DONE":
            self.report({"INFO"}, "NeuMesh: " + job.message)
            return {"FINISHED"}
        self.report({"ERROR"}, "NeuMesh: dependency installation failed: " + job.message)
        return {"CANCELLED"}


def _poll_install():
    job = deps.current_install()
    _redraw_preferences()
    if job is None or job.state != "RUNNING":
        refresh_paths_and_status()
        _redraw_preferences()
        return None
    return 0.5


def _redraw_preferences():
    try:
        for win in bpy.context.window_manager.windows:
            for area in win.screen.areas:
                if area.type == "PREFERENCES":
                    area.tag_redraw()
    except Exception:
        pass


classes = (NEUMESH_AP_preferences, NEUMESH_OT_check_dependencies, NEUMESH_OT_copy_launcher,
           NEUMESH_OT_install_dependencies)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()
    try:
        deps.configure_sys_path(extra_paths())
    except Exception:
        pass


def unregister():
    _unregister_classes()
