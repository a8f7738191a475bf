"""*Install dependencies*: ``<Blender's python> -m pip install --target <the add-on's folder> ...`` in a
background :class:`jobs.Job` (Blender's UI stays responsive). What is installed comes from
:func:`deps.install_plan`: only what the running Blender lacks, and never a numpy over Blender's own.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys

from . import deps
from .jobs import Job


class InstallJob(Job):
    """pip in a thread; poll ``state`` (RUNNING, DONE, ERROR), ``message`` and ``log_lines``.
    ``keep_out``: distributions removed from the target after pip ran (see :func:`deps.install_plan`)."""

    uses_torch = False

    def __init__(self, target: str, requirements, extra_args=(), python: str | None = None, keep_out=()):
        super().__init__("pip")
        self.target = target
        self.requirements = list(requirements)
        self.extra_args = list(extra_args)
        self.keep_out = list(keep_out)
        self.python = python or python_executable()
        self.log_lines: list[str] = []
        self.returncode = None

    @property
    def command(self) -> list[str]:
        return [self.python, "-m", "pip", "install", "--no-input", "--disable-pip-version-check",
                "--upgrade", "--target", self.target, *self.extra_args, *self.requirements]

    def _log(self, line):
        self.log_lines.append(line.rstrip())
        del self.log_lines[:-200]

    def run(self):
        if not self.requirements:
            self.message = "nothing to install: Blender's Python has every dependency"
            return None
        os.makedirs(self.target, exist_ok=True)
        env = dict(os.environ)
        env["PYTHONNOUSERSITE"] = "1"
        env.pop("PYTHONPATH", None)
        if not _has_pip(self.python, env):
            self._log("pip is missing; running ensurepip")
            r = subprocess.run([self.python, "-m", "ensurepip", "--upgrade"], env=env, capture_output=True, text=True)
            self._log(r.stdout + r.stderr)
            if r.returncode != 0:
                raise RuntimeError("Blender's Python has no pip and ensurepip failed; install pip for "
                                   f"{self.python} or point the add-on to an existing environment")
        self._log("$ " + " ".join(self.command))
        proc = subprocess.Popen(self.command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for line in proc.stdout:
            self._log(line)
        self.returncode = proc.wait()
        if self.returncode != 0:
            tail = " | ".join(line for line in self.log_lines[-4:] if line.strip())
            raise RuntimeError(f"pip failed (exit {self.returncode}): {tail}")
        removed = remove_distributions(self.target, self.keep_out)
        if removed:
            self._log("removed from the folder (Blender's own copy is used): " + ", ".join(removed))
        deps.configure_sys_path([self.target])
        self.message = f"installed {' '.join(self.requirements)} into {self.target}"
        return self.target

    def _main(self):
        super()._main()
        if self.state == "ERROR":
            self._log("ERROR: " + self.message)


def remove_distributions(target: str, names) -> list[str]:
    """Delete distributions ``names`` (their packages, ``.libs`` and ``.dist-info``) from a pip
    ``--target`` folder; returns what was removed."""
    removed = []
    if not names or not os.path.isdir(target):
        return removed
    mods = {n.lower().replace("-", "_") for n in names}
    for entry in sorted(os.listdir(target)):
        low = entry.lower()
        if not any(low in (m, m + ".libs") or (low.startswith(m + "-") and low.endswith(".dist-info"))
                   for m in mods):
            continue
        full = os.path.join(target, entry)
        if os.path.isdir(full):
            shutil.rmtree(full, ignore_errors=True)
        else:
            os.remove(full)
        removed.append(entry)
    return removed


def python_executable() -> str:
    """Blender's own Python interpreter (sys.executable is it since Blender 2.91)."""
    exe = sys.executable
    if exe and os.path.basename(exe).lower().startswith("python"):
        return exe
    # very old Blender: sys.executable is blender itself
    import bpy  # noqa: F401

    return getattr(bpy.app, "binary_path_python", exe)


def _has_pip(python, env) -> bool:
    r = subprocess.run([python, "-c", "import pip"], env=env, capture_output=True)
    return r.returncode == 0


_install_job: InstallJob | None = None


def current_install() -> InstallJob | None:
    return _install_job


def start_install(target, requirements, extra_args=(), keep_out=()) -> InstallJob:
    global _install_job
    if _install_job is not None and _install_job.running:
        raise RuntimeError("an installation is already running")
    _install_job = InstallJob(target, requirements, extra_args, keep_out=keep_out).start()
    return _install_job
