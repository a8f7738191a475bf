"""Lazy access to the torch core.

The zip built by build_addon.py vendors ``neumesh_core`` as a subpackage of the add-on; a development
checkout (add-on run from the repository) falls back to a top-level ``neumesh_core``.  Importing it
pulls in torch, so it only happens when something is trained or rendered, never at registration.
"""
from __future__ import annotations

import contextlib
import importlib
import importlib.util

_nm = None


class CoreUnavailable(RuntimeError):
    """The core (or one of its dependencies such as torch) cannot be imported. The message is meant to
    follow a "NeuMesh: " prefix (operators, the render engine and the viewport add it)."""


_WHAT_TO_DO = ("Open Edit > Preferences > Add-ons > NeuMesh and press 'Install dependencies', or set "
               "'Existing environment' to a site-packages folder that has torch 2.13 (numpy<2).")


def prepare_torch():
    """Run once torch has been imported, by the add-on or by anyone else (idempotent, cheap after the
    first call): point torch's BLAS calls at torch's own BLAS where Blender links a slow one
    (:mod:`blas`), and make torch's module-like objects safe for Blender's exit-time add-on scan."""
    import sys

    if "torch" not in sys.modules:
        return
    from . import blas

    blas.ensure()
    guard_torch_namespaces()


def all_cores() -> int:
    """The CPUs this process may run on (its affinity mask; os.cpu_count() where that is unknown)."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def wanted_threads() -> int:
    """torch threads from the add-on preference *CPU threads* (0, or no preferences: all cores)."""
    from . import settings

    n = settings.torch_threads()
    return n if n > 0 else all_cores()


def apply_threads(n: int | None = None) -> int:
    """Set torch's thread count for the calling thread's torch work (renders, training, edits) to ``n``
    or :func:`wanted_threads`, and return it. Blender may have started torch with another count (its
    own render threads, or 1), and an OpenMP thread keeps the count it had when it first ran torch
    work, so every thread that renders or trains calls this first. Cheap when nothing changes."""
    import torch

    n = int(n) if n else wanted_threads()
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return n


@contextlib.contextmanager
def torch_work(threads: int | None = None):
    """Around the torch work of a render, a training, a distillation or an edit, in the thread that
    does it: torch's thread count from the preferences (:func:`apply_threads`), and Blender's jemalloc
    keeps freed memory mapped meanwhile (:mod:`malloc`; previous decay times back afterwards)."""
    from . import malloc

    try:
        get()
        n = apply_threads(threads)
    except Exception:  # noqa: BLE001 - no torch: the work itself reports it
        n = None
    with malloc.retain():
        yield n


def render_device():
    """The torch device renders run on, from the preference *Device* (auto: CUDA when torch sees a GPU).

    Raises :class:`~.errors.UserError` saying what to do when CUDA is chosen and torch cannot use it.
    """
    from . import settings
    from .errors import UserError

    nm = get()
    choice = settings.device()
    try:
        return nm.resolve_device(choice)
    except nm.NeuMeshError as exc:
        import torch

        build = "a CPU-only build" if torch.version.cuda is None else f"a CUDA {torch.version.cuda} build"
        raise UserError(
            f"Device is CUDA, but torch {torch.__version__} ({build}) sees no NVIDIA GPU. In Edit > "
            "Preferences > Add-ons > NeuMesh > Device: choose Auto or CPU, or install a CUDA build of torch "
            "on a machine with an NVIDIA GPU and driver") from exc


def device_summary() -> str:
    """What torch in this Blender can render on, for the preferences (imports the core)."""
    try:
        import torch

        get()
    except Exception as exc:  # noqa: BLE001 - no torch: the dependency list says what to do
        return f"torch unavailable ({type(exc).__name__})"
    if torch.cuda.is_available():
        return f"CUDA GPU: {torch.cuda.get_device_name(0)} (torch {torch.__version__})"
    build = "a CPU-only build" if torch.version.cuda is None else f"CUDA {torch.version.cuda} build, no GPU seen"
    return f"no CUDA GPU (torch {torch.__version__}, {build}): renders on the CPU"


def _import():
    pkg = __package__.rpartition(".")[0] if __package__ else ""   # the add-on package (above runtime/)
    vendored = pkg + ".neumesh_core" if pkg else None
    if vendored and importlib.util.find_spec(vendored) is not None:
        return importlib.import_module(vendored)
    return importlib.import_module("neumesh_core")


def get():
    """Return the ``neumesh_core`` module or raise :class:`CoreUnavailable` with what to do."""
    global _nm
    if _nm is not None:
        return _nm
    from . import deps, settings

    try:
        deps.configure_sys_path(settings.extra_paths())
    except Exception:  # noqa: BLE001 - no Blender context
        pass
    missing = deps.missing_required()
    if missing:
        raise CoreUnavailable(
            "missing Python package(s) " + ", ".join(missing) + ": Blender's Python cannot import "
            + ("it" if len(missing) == 1 else "them") + ". " + _WHAT_TO_DO)
    try:
        _nm = _import()
    except ModuleNotFoundError as exc:
        missing = exc.name or str(exc)
        raise CoreUnavailable(
            f"missing Python package '{missing}': Blender's Python cannot import it. " + _WHAT_TO_DO) from exc
    except ImportError as exc:
        raise CoreUnavailable(
            f"the core cannot be imported: {exc}. The installed dependencies are probably broken or built for "
            "another Python; reinstall them from the add-on preferences."
        ) from exc
    prepare_torch()
    return _nm


_FOREIGN_NAMESPACE_TYPES = {"_Ops", "_OpNamespace", "_PyOpNamespace", "_Classes", "_ClassNamespace"}


def guard_torch_namespaces() -> int:
    """Make torch's module-like objects in sys.modules safe for Blender's add-on scan.

    Blender's ``addon_utils.disable_all()`` (run at exit) calls ``getattr(m, "__addon_enabled__")`` on
    every entry of sys.modules. torch registers module-like objects there (``torch.ops``,
    ``torch.classes``, ``torch._VF``, backend/config modules) whose ``__getattr__`` forwards to
    torch's C state: ``torch.ops`` answers *any* name with a new (truthy) namespace, so Blender tries
    to "unregister" it, and at exit (torch's C side torn down) such a lookup segfaults Blender 3.4.
    Setting the attribute to False short-circuits the lookup. Called after importing the core and
    after every render/training (torch imports some modules lazily). Returns how many were patched.
    """
    import sys
    import types

    n = 0
    # multiprocessing (imported by torch) aliases sys.modules["__mp_main__"] to the *current*
    # __main__; inside a `blender --python script.py` run that is Blender's temporary script module,
    # which Blender frees behind Python's back when the script ends -> the exit scan segfaults on it.
    mp = sys.modules.get("__mp_main__")
    if mp is not None and getattr(mp, "__name__", "") != "__mp_main__":
        sys.modules["__mp_main__"] = types.ModuleType("__mp_main__")
        n += 1
    for name, m in list(sys.modules.items()):
        if type(m) is types.ModuleType:
            continue
        if not (name.startswith("torch") or type(m).__name__ in _FOREIGN_NAMESPACE_TYPES):
            continue
        d = getattr(m, "__dict__", None)
        if isinstance(d, dict) and d.get("__addon_enabled__", None) is False:
            continue
        try:
            object.__setattr__(m, "__addon_enabled__", False)
            n += 1
        except Exception:  # noqa: BLE001
            pass
    return n


def require(feature: str) -> None:
    """Raise :class:`errors.UserError` naming, in full, the Python packages that ``feature`` (a key of
    ``deps.FEATURES``: "bake", "semantics", ...) needs and Blender's Python cannot import, before a job
    starts (a job would otherwise die in its thread on the first import)."""
    from . import deps
    from .errors import UserError

    missing = deps.missing_for(feature)
    if missing:
        raise UserError(deps.missing_message(feature, missing))


def available() -> bool:
    try:
        get()
        return True
    except CoreUnavailable:
        return False


def error_types():
    """Exception types from the core that carry user-facing messages (empty if core unavailable)."""
    try:
        nm = get()
    except CoreUnavailable:
        return ()
    names = ("NeuMeshError", "CheckpointError", "VertexMismatchError", "DataError", "Cancelled")
    return tuple(getattr(nm, n) for n in names if isinstance(getattr(nm, n, None), type))


class CoreNotes(list):
    """``with CoreNotes() as notes: <core calls>``: the warnings the core itself raises meanwhile (a
    ``UserWarning`` such as "17 of 67 frames have no image and were skipped") are kept in ``notes`` as
    plain messages instead of being printed with a Python source line, which reads like a crash; the
    caller reports them (a Blender report, a job's message). Warnings from elsewhere (torch, numpy)
    go on as usual. Other threads' warnings raised meanwhile are caught too (the warnings module keeps
    one state per process): those of the core among them are reported here, the rest go on."""

    def __enter__(self):
        import warnings

        self._cm = warnings.catch_warnings(record=True)
        self._records = self._cm.__enter__()
        warnings.simplefilter("always")
        return self

    def __exit__(self, *exc_info):
        import os
        import warnings

        self._cm.__exit__(*exc_info)
        # the core's files, and the add-on's (a core warning with stacklevel=2 names its caller)
        roots = [os.path.dirname(os.path.dirname(os.path.abspath(__file__))) + os.sep]
        if _nm is not None:
            roots.append(os.path.dirname(os.path.abspath(_nm.__file__)) + os.sep)
        for w in self._records:
            ours = os.path.abspath(w.filename).startswith(tuple(roots))
            if ours and issubclass(w.category, UserWarning):
                if str(w.message) not in self:
                    self.append(str(w.message))
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        return False
