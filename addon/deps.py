"""Python dependencies of the add-on: where they live, whether they import, how to install them.

torch is far too large to bundle, so the add-on never imports it at registration time.  It is looked
up, in this order, in:

1. folders listed in the environment variable ``NEUMESH_PYTHONPATH`` (``os.pathsep`` separated),
2. the "Existing environment" folder of the add-on preferences (a ``site-packages`` directory),
3. the add-on's own dependency folder, filled by "Install dependencies" (pip with Blender's Python).

Each is put at the *front* of ``sys.path`` so the pinned versions win over anything else on the path.
Nothing in this module needs bpy except :func:`addon_deps_dir` (which asks Blender for a user folder).
"""
from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import os
import subprocess
import sys
import threading
import time

ENV_VAR = "NEUMESH_PYTHONPATH"

# (import name, distribution name, required, pip requirement)
DEPENDENCIES = (
    ("torch", "torch", True, "torch==2.13.0"),
    ("numpy", "numpy", True, "numpy<2"),
    ("safetensors", "safetensors", True, "safetensors"),
    ("PIL", "pillow", True, "pillow"),
    ("scipy", "scipy", False, "scipy"),
    ("pykdtree", "pykdtree", False, "pykdtree"),
    ("trimesh", "trimesh", False, "trimesh"),
    ("sklearn", "scikit-learn", False, "scikit-learn"),    # semantic selection (DBSCAN)
    ("skimage", "scikit-image", False, "scikit-image"),    # semantic distillation (superpixels)
    ("xatlas", "xatlas", False, "xatlas"),                 # Bake to material (UV atlas)
    ("pycolmap", "pycolmap", False, "pycolmap>=4"),        # COLMAP folders, Poses from Photos
    ("cv2", "opencv-python-headless", False, "opencv-python-headless<4.12"),  # lens undistortion, video frames
)
PIP_REQUIREMENTS = tuple(d[3] for d in DEPENDENCIES)

_added_paths: list[str] = []


def python_tag() -> str:
    return "py%d%d" % sys.version_info[:2]


def addon_deps_dir(package: str | None = None, create: bool = False) -> str:
    """Folder the add-on owns for pip-installed packages (per Python version)."""
    import bpy

    package = package or __package__
    base = None
    fn = getattr(bpy.utils, "extension_path_user", None)
    if fn is not None and package and package.startswith("bl_ext."):
        try:
            base = fn(package, path="", create=create)
        except Exception:  # not an extension (legacy install) or no writable user dir
            base = None
    if not base:
        base = bpy.utils.user_resource("SCRIPTS", path=os.path.join("addons_data", "neumesh"), create=create)
    path = os.path.join(base, "site-packages-" + python_tag())
    if create:
        os.makedirs(path, exist_ok=True)
    return path


def env_paths() -> list[str]:
    raw = os.environ.get(ENV_VAR, "")
    return [p for p in raw.split(os.pathsep) if p.strip()]


def configure_sys_path(extra: list[str] | tuple[str, ...] = ()) -> list[str]:
    """Put the dependency folders at the front of sys.path (idempotent). Returns the folders used.

    Folders that do not exist are skipped. Previously added folders that are no longer wanted
    (e.g. the preference changed) are removed again.
    """
    wanted: list[str] = []
    for p in list(env_paths()) + [e for e in extra if e]:
        p = os.path.abspath(os.path.expanduser(p))
        if os.path.isdir(p) and p not in wanted:
            wanted.append(p)
    for p in list(_added_paths):
        if p not in wanted and p in sys.path:
            sys.path.remove(p)
        if p not in wanted:
            _added_paths.remove(p)
    for p in reversed(wanted):
        if p in sys.path:
            sys.path.remove(p)
        sys.path.insert(0, p)
        if p not in _added_paths:
            _added_paths.append(p)
    importlib.invalidate_caches()
    return wanted


class DepStatus:
    __slots__ = ("name", "dist", "required", "found", "version", "location", "error")

    def __init__(self, name, dist, required):
        self.name, self.dist, self.required = name, dist, required
        self.found = False
        self.version = ""
        self.location = ""
        self.error = ""

    def __repr__(self):
        return f"DepStatus({self.name!r}, found={self.found}, version={self.version!r}, error={self.error!r})"


def check_dependencies(do_import: bool = False) -> list[DepStatus]:
    """Status of every dependency.

    do_import=False only locates the module and reads its installed version (cheap, safe in draw()).
    do_import=True really imports it (catches broken installs, e.g. an ABI mismatch).
    """
    importlib.invalidate_caches()
    out = []
    for name, dist, required, _req in DEPENDENCIES:
        st = DepStatus(name, dist, required)
        try:
            mod = sys.modules.get(name)
            spec = None if mod is not None else importlib.util.find_spec(name)
            if mod is None and spec is None:
                st.error = "not found"
                out.append(st)
                continue
            st.location = os.path.dirname(getattr(mod, "__file__", None) or (spec.origin if spec else "") or "")
            if do_import and mod is None:
                mod = importlib.import_module(name)
            ver = getattr(mod, "__version__", None) if mod is not None else None
            if not ver:
                try:
                    ver = importlib.metadata.version(dist)
                except Exception:
                    ver = "?"
            st.version = str(ver)
            st.found = True
        except Exception as exc:  # broken install: report, never raise into the UI
            st.found = False
            st.error = f"{type(exc).__name__}: {exc}"
        out.append(st)
    if do_import and "torch" in sys.modules:
        _torch_imported()
    return out


def _torch_imported():
    """torch was just imported here: the add-on's post-import steps (core.prepare_torch: torch's own
    BLAS, and the guard without which Blender 3.x segfaults at exit). Skipped when this file is loaded
    on its own, outside the add-on package."""
    if not __package__:
        return
    core = importlib.import_module(__package__ + ".core")
    core.prepare_torch()


def missing_required(statuses=None) -> list[str]:
    statuses = statuses if statuses is not None else check_dependencies()
    return [s.dist for s in statuses if s.required and not s.found]


# --------------------------------------------------------------------------------------------------
# pip install into the add-on's folder, in a background thread (Blender's UI stays responsive)

class InstallJob:
    """Runs ``<sys.executable> -m pip install --target DIR ...`` in a thread; poll ``state``."""

    def __init__(self, target: str, requirements=PIP_REQUIREMENTS, extra_args=(), python: str | None = None):
        self.target = target
        self.requirements = list(requirements)
        self.extra_args = list(extra_args)
        self.python = python or python_executable()
        self.state = "PENDING"  # RUNNING, DONE, ERROR
        self.message = ""
        self.log_lines: list[str] = []
        self.returncode = None
        self.started = time.time()
        self._thread = threading.Thread(target=self._run, name="neumesh-pip", daemon=True)

    @property
    def command(self) -> list[str]:
        return [self.python, "-m", "pip", "install", "--no-input", "--disable-pip-version-check",
                "--upgrade", "--target", self.target, *self.extra_args, *self.requirements]

    def start(self) -> "InstallJob":
        self.state = "RUNNING"
        self._thread.start()
        return self

    def join(self, timeout=None):
        self._thread.join(timeout)
        return self

    def _log(self, line):
        self.log_lines.append(line.rstrip())
        del self.log_lines[:-200]

    def _run(self):
        try:
            os.makedirs(self.target, exist_ok=True)
            env = dict(os.environ)
            env["PYTHONNOUSERSITE"] = "1"
            env.pop("PYTHONPATH", None)
            if not _has_pip(self.python, env):
                self._log("pip is missing; running ensurepip")
                r = subprocess.run([self.python, "-m", "ensurepip", "--upgrade"], env=env,
                                   capture_output=True, text=True)
                self._log(r.stdout + r.stderr)
                if r.returncode != 0:
                    raise RuntimeError("Blender's Python has no pip and ensurepip failed; install pip for "
                                       f"{self.python} or point the add-on to an existing environment")
            self._log("$ " + " ".join(self.command))
            proc = subprocess.Popen(self.command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                    text=True)
            for line in proc.stdout:
                self._log(line)
            self.returncode = proc.wait()
            if self.returncode != 0:
                tail = " | ".join(l for l in self.log_lines[-4:] if l.strip())
                raise RuntimeError(f"pip failed (exit {self.returncode}): {tail}")
            configure_sys_path([self.target])
            self.state = "DONE"
            self.message = f"installed into {self.target}"
        except Exception as exc:
            self.state = "ERROR"
            self.message = str(exc)
            self._log("ERROR: " + str(exc))


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


def start_install(target, requirements=PIP_REQUIREMENTS, extra_args=()) -> InstallJob:
    global _install_job
    if _install_job is not None and _install_job.state == "RUNNING":
        raise RuntimeError("an installation is already running")
    _install_job = InstallJob(target, requirements, extra_args).start()
    return _install_job
