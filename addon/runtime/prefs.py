"""Add-on preferences: dependency status, "Install dependencies", existing environment path."""
from __future__ import annotations

import os

import bpy
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty

from . import blas, core, deps, install, persist, text
from .jobs import redraw
from .settings import ADDON_ID, extra_paths, get_prefs

_status_cache: dict = {"statuses": None, "blas": None}


def refresh_paths_and_status(do_import=False):
    deps.configure_sys_path(extra_paths())
    _status_cache["statuses"] = deps.check_dependencies(do_import=do_import)
    if do_import:
        core.prepare_torch()   # torch may have been imported just now: its BLAS, the exit-scan guard
    return _status_cache["statuses"]


def _on_env_path(self, _context):
    refresh_paths_and_status()
    persist.changed()     # a `blender -b` started now must find the folder too


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
    device: EnumProperty(
        name="Device",
        description="Where the Rendered viewport and F12 render fields. Auto: an NVIDIA GPU when torch sees "
                    "one (a CUDA build of torch), else the CPU. Training and edits run on the CPU",
        items=[("AUTO", "Auto", "A CUDA GPU when torch sees one, else the CPU"),
               ("CPU", "CPU", "Always the CPU"),
               ("CUDA", "CUDA", "An NVIDIA GPU (needs a CUDA build of torch and a driver)")],
        default="AUTO",
    )
    show_log: BoolProperty(name="Show pip log", default=False)

    def draw(self, context):
        layout = self.layout
        note = persist.unsaved_note()
        if note:
            text.wrapped_label(layout, note, text.text_width(context), icon="ERROR", context=context)
        statuses = _status_cache["statuses"]
        if statuses is None:
            statuses = refresh_paths_and_status()
        box = layout.box()
        box.label(text="Python dependencies (Blender's Python %d.%d)" % __import__("sys").version_info[:2])
        width = text.text_width(context)
        for s in statuses:   # name | version or error; what an optional one is for on its own line
            split = box.split(factor=0.4)
            icon = "CHECKMARK" if s.found else ("ERROR" if s.required else "INFO")
            split.label(text=f"{s.dist}", icon=icon)
            split.label(text=s.version if s.found else s.error)
            if not s.found and not s.required:
                text.wrapped_label(box, f"for {used_by(s.dist)}", width, icon="BLANK1", context=context)
        miss = [s.dist for s in statuses if s.required and not s.found]
        if miss:
            box.label(text="Missing: " + ", ".join(miss) + ". Install them or set an existing environment.",
                      icon="ERROR")
        else:
            box.label(text="All required dependencies found.", icon="CHECKMARK")
        row = box.row()
        row.operator("neumesh.check_dependencies", icon="FILE_REFRESH")
        job = install.current_install()
        running = job is not None and job.running
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
            text.wrapped_label(box, f"pip: {job.state.lower()} {job.message}", text.text_width(context), icon=icon,
                               context=context)
            box.prop(self, "show_log")
            if self.show_log:
                col = box.column(align=True)
                for line in job.log_lines[-15:]:
                    col.label(text=line[:160])
        self._draw_speed(layout, context)
        row = layout.row()
        row.prop(self, "torch_threads")
        row.label(text=f"{core.wanted_threads()} in use" + (" (all cores)" if self.torch_threads == 0 else ""))
        layout.prop(self, "device")
        if "torch" in __import__("sys").modules:   # never import torch just to draw the preferences
            text.wrapped_label(layout, core.device_summary(), text.text_width(context), icon="BLANK1",
                               context=context)
        layout.prop(self, "preview_start")   # one a row: side by side their names are cut
        layout.prop(self, "preview_final")

    def _draw_speed(self, layout, context):
        """Box 'Speed': torch's matrix-multiply rate and BLAS in this Blender, with the remedy if slow."""
        st = _status_cache.get("blas")
        box = layout.box()
        if st is None:
            box.label(text="Speed: press 'Check dependencies' to measure torch in this Blender", icon="TIME")
            return
        width = text.text_width(context)
        if st["own"]:
            level = speed_level(st.get("gflops"))
            icon = {"fast": "CHECKMARK", "moderate": "INFO"}.get(level, "ERROR")
            text.wrapped_label(box, "Speed: " + speed_message(st), width, icon=icon)
            return
        text.wrapped_label(box, "Speed: " + speed_message(st), width, icon="ERROR")
        text.wrapped_label(box, "Start Blender with torch's BLAS preloaded (see docs/addon.md, 'Speed'):", width)
        text.wrapped_label(box, st["remedy"], width, icon="CONSOLE")
        box.operator("neumesh.copy_launcher", icon="COPYDOWN")


def used_by(dist: str) -> str:
    """The features that need distribution ``dist``, for the preferences' list ('optional' if none)."""
    feats = next((d[4] for d in deps.DEPENDENCIES if d[1] == dist), ())
    return ", ".join(deps.FEATURES.get(f, f) for f in feats) or "optional"


def draw_missing(layout, feature: str, context) -> bool:
    """Where ``feature`` (a key of ``deps.FEATURES``) lacks Python packages: a box naming them in full
    and a button that installs exactly those. Returns whether anything is missing."""
    missing = deps.missing_for(feature)
    if not missing:
        return False
    box = layout.box()
    text.wrapped_label(box, f"{deps.FEATURES.get(feature, feature)} needs {', '.join(missing)}",
                       text.text_width(context), icon="ERROR", context=context)
    job = install.current_install()
    row = box.row()
    row.enabled = job is None or not job.running
    op = row.operator("neumesh.install_dependencies", text=deps.install_label(missing), icon="IMPORT")
    op.packages = " ".join(missing)
    return True


def speed_status(measure: bool = True):
    """torch's BLAS in this Blender (see blas.py): which library its matrix multiplies call, the rate
    measured here, the launcher command when it is the slow one. None without torch."""
    import sys

    if "torch" not in sys.modules:
        return None
    st = blas.status(measure=measure)
    core.prepare_torch()  # measuring may have made torch import more modules
    _status_cache["blas"] = st
    return st


# The 2-core machine the figures of docs/benchmarks.md were measured on multiplies fp32 matrices at
# about 180 GFLOP/s (every results file records its own rate).  A rate is judged against it: from
# FAST_GFLOPS on, those figures hold; below SLOW_GFLOPS renders and training take several times
# longer (matrix multiplies are much of their work, not all of it).
REFERENCE_GFLOPS = 180.0
FAST_GFLOPS = 120.0
SLOW_GFLOPS = 40.0
REFERENCE_LEGO_S = 0.7


def speed_level(gflops) -> str:
    """"fast", "moderate" or "slow" for a measured matrix-multiply rate ("" when not measured)."""
    if gflops is None:
        return ""
    return "fast" if gflops >= FAST_GFLOPS else "moderate" if gflops >= SLOW_GFLOPS else "slow"


def speed_judgement(gflops) -> str:
    """What a measured matrix-multiply rate means for renders and training, and what to do when it is
    slow ('' when not measured)."""
    level = speed_level(gflops)
    if not level:
        return ""
    ref = f"the {REFERENCE_GFLOPS:.0f} GFLOP/s of the 2 cores the docs' figures come from"
    if level == "fast":
        return f"fast: about {ref} or more (a lego frame at 400x400 in ~{REFERENCE_LEGO_S:.1f} s)"
    times = REFERENCE_GFLOPS / max(float(gflops), 0.1)
    slower = (f"{times:.0f}x below {ref}: renders and training up to {times:.0f}x slower (a lego frame at "
              f"400x400 up to ~{REFERENCE_LEGO_S * times:.0f} s instead of ~{REFERENCE_LEGO_S:.1f} s)")
    if level == "moderate":
        return "moderate: " + slower
    return ("slow: " + slower + ". Other programs keep the CPU busy (try CPU threads 1 or 2 below, and "
            "measure again) or the CPU is small; a CUDA GPU (Device) renders many times faster")


def speed_message(st) -> str:
    """One sentence on torch's matrix-multiply speed in this Blender and what it means ('' before it
    was measured); the launcher command is not part of it (``st["remedy"]``)."""
    if not st:
        return ""
    rate = "" if st.get("gflops") is None else f" {st['gflops']:.0f} GFLOP/s"
    if st["own"]:
        foreign = st["rebind"].get("foreign") if st["rebind"].get("rebound") else None
        src = f" (rebound from {', '.join(os.path.basename(f) for f in foreign)})" if foreign else ""
        judged = speed_judgement(st.get("gflops"))
        return f"matrix multiply{rate} with torch's own BLAS{src}" + (f": {judged}" if judged else "")
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
                self.report({"WARNING" if speed_level(st.get("gflops")) == "slow" else "INFO"}, msg)
            else:
                self.report({"WARNING"}, f"{msg}. Start Blender as: {st['remedy']}")
        return {"FINISHED"}


class NEUMESH_OT_copy_launcher(bpy.types.Operator):
    """Copy the command that starts Blender with torch's own BLAS preloaded to the clipboard"""

    bl_idname = "neumesh.copy_launcher"
    bl_label = "Copy launcher command"

    def execute(self, context):
        st = _status_cache.get("blas") or {}
        cmd = st.get("remedy") or blas.preload_command()
        context.window_manager.clipboard = cmd
        self.report({"INFO"}, f"NeuMesh: copied: {cmd}")
        return {"FINISHED"}


class NEUMESH_OT_install_dependencies(bpy.types.Operator):
    """Install what Blender's Python lacks of torch 2.13, numpy, scipy, pykdtree, trimesh, safetensors,
    pillow, scikit-learn, scikit-image and xatlas, with Blender's own Python (pip), into a folder owned by
    the add-on (never a numpy over Blender's own). Needs network access (several hundred MB)"""

    bl_idname = "neumesh.install_dependencies"
    bl_label = "Install dependencies"

    wait: BoolProperty(default=False, options={"HIDDEN", "SKIP_SAVE"})
    packages: StringProperty(default="", options={"HIDDEN", "SKIP_SAVE"},
                             description="space-separated dependency names to install when missing "
                                         "(default: every missing one)")
    requirements: StringProperty(default="", options={"HIDDEN", "SKIP_SAVE"},
                                 description="space-separated pip arguments instead of the planned set")

    @classmethod
    def description(cls, context, props):
        if props is not None and props.packages:
            return f"Install {props.packages} with Blender's own Python into the add-on's folder"
        return cls.__doc__

    def execute(self, context):
        import shlex

        p = get_prefs()
        extra = shlex.split(p.pip_extra_args) if p is not None else []
        try:
            refresh_paths_and_status()
            if self.requirements.strip():
                reqs = shlex.split(self.requirements)
                keep_out = ["numpy"] if deps.own_numpy_version() else []
            else:
                wanted = self.packages.split() if self.packages.strip() else None
                reqs, keep_out = deps.install_plan(wanted, _status_cache["statuses"])
            if not reqs:
                self.report({"INFO"}, "NeuMesh: nothing to install; Blender's Python has "
                                      + (self.packages if self.packages.strip() else "every dependency"))
                return {"FINISHED"}
            target = deps.addon_deps_dir(ADDON_ID, create=True)
            job = install.start_install(target, reqs, extra, keep_out=keep_out)
        except Exception as exc:
            self.report({"ERROR"}, f"NeuMesh: cannot start pip: {exc}")
            return {"CANCELLED"}
        if self.wait or bpy.app.background:
            job.join()
            return self._finish(job)
        bpy.app.timers.register(_poll_install, first_interval=0.5)
        self.report({"INFO"}, f"NeuMesh: installing {' '.join(reqs)} in the background (see add-on preferences)")
        return {"FINISHED"}

    def _finish(self, job):
        refresh_paths_and_status()
        if job.state == "DONE":
            self.report({"INFO"}, "NeuMesh: " + job.message)
            return {"FINISHED"}
        self.report({"ERROR"}, "NeuMesh: dependency installation failed: " + job.message)
        return {"CANCELLED"}


def _poll_install():
    job = install.current_install()
    redraw(bpy.context)
    if job is None or not job.running:
        refresh_paths_and_status()
        redraw(bpy.context)
        return None
    return 0.5


classes = (NEUMESH_AP_preferences, NEUMESH_OT_check_dependencies, NEUMESH_OT_copy_launcher,
           NEUMESH_OT_install_dependencies)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()
    try:
        deps.configure_sys_path(extra_paths())
    except Exception:
        pass
    persist.schedule()    # just enabled (Install, the tick): saved so that `blender -b` has the engine


def unregister():
    _unregister_classes()
