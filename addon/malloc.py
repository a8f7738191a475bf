"""Keep freed large blocks for reuse where Blender's allocator is jemalloc (no bpy; Linux only).

Blender builds for Linux (Debian's 3.4 among them) link jemalloc, which then serves every malloc of
the process, torch's included. jemalloc puts allocations of ``opt.oversize_threshold`` (8 MiB) and
more in a dedicated arena and, when the default decay times are positive, gives that arena a decay
time of 0: every freed block is handed back to the kernel at once. A NeuMesh render allocates and
frees tens of such blocks per chunk of rays (per-sample features, neighbour tables), so each of
them is page-faulted in afresh (zero-filled by the kernel) every time: a render in that Blender
took 2-6x as long as in a plain Python (benchmarks/bench_addon.py, section f12).

:func:`tune` gives that arena the dirty decay time of the ordinary arenas (Blender 3.4: 4 s): freed
pages stay mapped for reuse and go back to the kernel once unused for that long, as for every other
allocation. The other arenas are not touched. ``NEUMESH_JEMALLOC_DECAY_MS`` overrides the time (-1:
never give them back; ``off``: leave jemalloc alone).
Nothing happens where malloc is not jemalloc (bpy from PyPI, plain Python, macOS, Windows).
"""
from __future__ import annotations

import ctypes
import os

ENV = "NEUMESH_JEMALLOC_DECAY_MS"
DECAY_MS = 10_000     # jemalloc's own default dirty decay

_report: dict | None = None


def _mallctl():
    """jemalloc's mallctl in this process's global scope, or None."""
    try:
        f = ctypes.CDLL(None).mallctl
    except (AttributeError, OSError):
        return None
    f.restype = ctypes.c_int
    f.argtypes = [ctypes.c_char_p, ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t), ctypes.c_void_p,
                  ctypes.c_size_t]
    return f


def _read(mallctl, name: str, ctype):
    v, n = ctype(), ctypes.c_size_t(ctypes.sizeof(ctype))
    err = mallctl(name.encode(), ctypes.byref(v), ctypes.byref(n), None, 0)
    return None if err else v.value


def _write(mallctl, name: str, value: int) -> int:
    v = ctypes.c_ssize_t(int(value))
    return mallctl(name.encode(), None, None, ctypes.byref(v), ctypes.sizeof(v))


def decay_times() -> dict:
    """{arena index: (dirty ms, muzzy ms)} of the arenas that exist (empty without jemalloc)."""
    m = _mallctl()
    if m is None:
        return {}
    out = {}
    n = _read(m, "arenas.narenas", ctypes.c_uint) or 0
    for i in range(n):
        d = _read(m, f"arena.{i}.dirty_decay_ms", ctypes.c_ssize_t)
        if d is not None:
            out[i] = (d, _read(m, f"arena.{i}.muzzy_decay_ms", ctypes.c_ssize_t))
    return out


def tune(decay_ms: int | None = None) -> dict:
    """Give jemalloc's oversize arena the dirty decay time of its ordinary arenas (what this Blender
    chose for every other allocation; ``DECAY_MS`` if that is not positive), or ``decay_ms`` /
    $NEUMESH_JEMALLOC_DECAY_MS. The other arenas are left as they are. Idempotent; returns a report:
    ``jemalloc`` (bool), ``arena`` (the oversize arena's index), ``before`` / ``after`` (its dirty
    and muzzy decay ms), ``oversize_threshold``, ``error``."""
    global _report
    if decay_ms is None and _report is not None:
        return _report
    env = os.environ.get(ENV, "").strip()
    rep = {"jemalloc": False, "arena": None, "before": None, "after": None, "oversize_threshold": None,
           "error": ""}
    m = _mallctl()
    version = None if m is None else _read(m, "version", ctypes.c_char_p)
    if version is None:
        _report = rep
        return rep
    rep["jemalloc"], rep["version"] = True, version.decode(errors="replace")
    if env.lower() == "off" and decay_ms is None:
        rep["error"] = f"{ENV}=off"
        _report = rep
        return rep
    try:
        thr = _read(m, "opt.oversize_threshold", ctypes.c_size_t)
        rep["oversize_threshold"] = thr
        huge = _read(m, "opt.narenas", ctypes.c_uint)   # the oversize arena comes after the automatic ones
        if not thr or huge is None:
            rep["error"] = "no oversize arena"
            _report = rep
            return rep
        # the oversize arena is made on the first allocation that size, with decay 0: make it now
        libc = ctypes.CDLL(None)
        libc.malloc.restype = ctypes.c_void_p
        libc.malloc.argtypes = [ctypes.c_size_t]
        libc.free.argtypes = [ctypes.c_void_p]
        p = libc.malloc(int(thr) + 4096)
        if p:
            libc.free(p)
        rep["arena"] = int(huge)
        rep["before"] = (_read(m, f"arena.{huge}.dirty_decay_ms", ctypes.c_ssize_t),
                         _read(m, f"arena.{huge}.muzzy_decay_ms", ctypes.c_ssize_t))
        if decay_ms is None:
            ordinary = _read(m, "arena.0.dirty_decay_ms", ctypes.c_ssize_t)
            decay_ms = int(env) if env.lstrip("-").isdigit() else (ordinary if ordinary and ordinary > 0
                                                                  else DECAY_MS)
        err = _write(m, f"arena.{huge}.dirty_decay_ms", int(decay_ms))
        if err:
            rep["error"] = f"mallctl arena.{huge}.dirty_decay_ms: error {err}"
        rep["after"] = (_read(m, f"arena.{huge}.dirty_decay_ms", ctypes.c_ssize_t),
                        _read(m, f"arena.{huge}.muzzy_decay_ms", ctypes.c_ssize_t))
    except Exception as exc:  # noqa: BLE001 - never fatal: renders just stay slower
        rep["error"] = f"{type(exc).__name__}: {exc}"
    _report = rep
    return rep


def report() -> dict | None:
    """What :func:`tune` did (None before it ran)."""
    return _report
