"""Keep freed memory mapped while NeuMesh works, where Blender's allocator is jemalloc (no bpy; Linux).

Blender builds for Linux (Debian's 3.4 among them) link jemalloc, which then serves every malloc of
the process, torch's included. jemalloc hands freed pages back to the kernel on a timer ("decay":
Blender 3.4 sets 4 s dirty / 0 s muzzy; allocations of 8 MiB and more live in an arena with 0 s,
i.e. at once). A NeuMesh render allocates and frees hundreds of MB per chunk of rays, so pages are
returned and page-faulted in again (zero-filled by the kernel) all the time; a render that keeps its
pages is faster than one under Blender's decay settings, and than plain Python's glibc malloc
(benchmarks/bench/bench_addon.py times the two interleaved).

:func:`retain` is a context manager around torch work (renders, training, edits): on entering, every
arena (the oversize one made first if need be) and the default for new ones get decay -1 (freed pages
stay mapped and are reused); when the last user leaves, the previous times are put back, so Blender
returns the memory as before once NeuMesh is idle. ``NEUMESH_JEMALLOC=off`` leaves jemalloc alone.
Nothing happens where malloc is not jemalloc (bpy from PyPI, plain Python, macOS, Windows).
"""
from __future__ import annotations

import contextlib
import ctypes
import os
import threading

ENV = "NEUMESH_JEMALLOC"
_KINDS = ("dirty", "muzzy")
_LOCK = threading.Lock()
_state = {"depth": 0, "saved": None}
_report: dict | None = None
_fn = []


def _mallctl():
    """jemalloc's mallctl in this process's global scope, or None."""
    if _fn:
        return _fn[0]
    f = None
    try:
        f = ctypes.CDLL(None).mallctl
        f.restype = ctypes.c_int
        f.argtypes = [ctypes.c_char_p, ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t), ctypes.c_void_p,
                      ctypes.c_size_t]
        if _read(f, "version", ctypes.c_char_p) is None:
            f = None
    except (AttributeError, OSError):
        f = None
    _fn.append(f)
    return f


def _read(mallctl, name: str, ctype):
    v, n = ctype(), ctypes.c_size_t(ctypes.sizeof(ctype))
    err = mallctl(name.encode(), ctypes.byref(v), ctypes.byref(n), None, 0)
    return None if err else v.value


def _write(mallctl, name: str, value: int) -> int:
    v = ctypes.c_ssize_t(int(value))
    return mallctl(name.encode(), None, None, ctypes.byref(v), ctypes.sizeof(v))


def available() -> bool:
    """malloc is jemalloc here."""
    return _mallctl() is not None


def decay_times() -> dict:
    """{arena index: (dirty ms, muzzy ms)} of the arenas that exist (empty without jemalloc)."""
    m = _mallctl()
    if m is None:
        return {}
    out = {}
    for i in range(_read(m, "arenas.narenas", ctypes.c_uint) or 0):
        d = _read(m, f"arena.{i}.dirty_decay_ms", ctypes.c_ssize_t)
        if d is not None:
            out[i] = (d, _read(m, f"arena.{i}.muzzy_decay_ms", ctypes.c_ssize_t))
    return out


def _defaults(m):
    return tuple(_read(m, f"arenas.{k}_decay_ms", ctypes.c_ssize_t) for k in _KINDS)


def _make_oversize_arena(m):
    """The oversize arena is made on the first allocation of that size (with decay 0): make it now."""
    thr = _read(m, "opt.oversize_threshold", ctypes.c_size_t)
    if thr:
        libc = ctypes.CDLL(None)
        libc.malloc.restype = ctypes.c_void_p
        libc.malloc.argtypes = [ctypes.c_size_t]
        libc.free.argtypes = [ctypes.c_void_p]
        p = libc.malloc(int(thr) + 4096)
        if p:
            libc.free(p)
    return thr


def _set_all(m, times: dict, default: tuple) -> list:
    errors = []
    for k, v in zip(_KINDS, default):
        if v is not None and _write(m, f"arenas.{k}_decay_ms", v):
            errors.append(f"arenas.{k}_decay_ms")
    for i in decay_times():
        for k, v in zip(_KINDS, times.get(i, default)):
            if v is not None and _write(m, f"arena.{i}.{k}_decay_ms", v):
                errors.append(f"arena.{i}.{k}_decay_ms")
    return errors


def _enter():
    global _report
    m = _mallctl()
    if m is None or os.environ.get(ENV, "").strip().lower() == "off":
        return
    with _LOCK:
        _state["depth"] += 1
        if _state["depth"] > 1:
            return
        try:
            thr = _make_oversize_arena(m)
            saved = (decay_times(), _defaults(m))
            _state["saved"] = saved
            errors = _set_all(m, {}, (-1, -1))
            _report = {"jemalloc": True, "oversize_threshold": thr, "before": saved[0], "default_before": saved[1],
                       "during": decay_times(), "error": ", ".join(errors)}
        except Exception as exc:  # noqa: BLE001 - never fatal: renders just stay slower
            _report = {"jemalloc": True, "error": f"{type(exc).__name__}: {exc}"}


def _exit():
    m = _mallctl()
    if m is None:
        return
    with _LOCK:
        if _state["depth"] == 0:
            return
        _state["depth"] -= 1
        if _state["depth"] or _state["saved"] is None:
            return
        times, default = _state["saved"]
        _state["saved"] = None
        try:
            errors = _set_all(m, times, default)
            if _report is not None:
                _report["after"] = decay_times()
                if errors:
                    _report["error"] = (_report.get("error", "") + " restore: " + ", ".join(errors)).strip()
        except Exception as exc:  # noqa: BLE001
            if _report is not None:
                _report["error"] = f"restore: {type(exc).__name__}: {exc}"


@contextlib.contextmanager
def retain():
    """Inside: jemalloc keeps freed pages for reuse (see the module docstring); nestable, thread-safe."""
    _enter()
    try:
        yield
    finally:
        _exit()


def report() -> dict | None:
    """The last :func:`retain`: decay times before, during and after (None before one ran, or
    without jemalloc)."""
    return _report
