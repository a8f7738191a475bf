"""Hold NeuMesh's Python threads still while the main thread runs an operator under a context override
(no bpy; thread-safe).

Blender 3.4 crashes when ``bpy.ops`` runs inside ``context.temp_override(...)`` while another Python
thread runs Python code: during the operator Blender looks context members up in the override's
dictionary from C, and it takes the GIL for that only when no thread holds it (``PyC_IsInterpreterActive``
asks whether *some* thread holds the GIL, not this one), so the lookup's temporary strings are made in
Python's allocator beside the other thread's objects and corrupt its heap. Measured in ``blender -b``:
an empty ``temp_override()`` around ``bpy.ops.object.location_clear()`` beside a thread that runs Python
segfaults within seconds (2 of 2 runs, and 2 of 2 with keyword overrides); the same loop without the
override ran 30 s without a crash. The viewport's preview thread and the jobs (training, edits) run
Python between their torch operations, so the add-on's own overridden operator calls (splitting an area
for the paint editor, closing it, starting the Texture Paint watcher) go through :func:`override`.

Worker threads enclose their work in :func:`worker` and call :func:`checkpoint` at safe points (each
progress callback: between chunks of rays or steps). :func:`held` closes the gate (a lock), waits until
every worker is parked at a checkpoint or has ended (at most ``timeout`` seconds: a worker inside one
long torch operation holds the GIL only between operations, so the call goes ahead after the wait),
runs the body, and opens the gate again. Nestable; the main thread never registers as a worker.
A parked worker blocks on the gate's lock itself, so it takes the GIL again only once the gate opens
(a thread waiting on a condition variable wakes up, and runs Python, whenever it is notified).
"""
from __future__ import annotations

import contextlib
import threading
import time

_mutex = threading.Lock()                 # guards _state
_gate = threading.Lock()                  # held by the main thread while an overridden operator runs
_state = {"closed": 0, "workers": 0, "parked": 0}
_owner = {"thread": None, "depth": 0}     # the thread inside held() (re-entrant for it)
_local = threading.local()


@contextlib.contextmanager
def worker():
    """Around a worker thread's Python work (a render, a job): :func:`held` waits for it."""
    if getattr(_local, "depth", 0):
        _local.depth += 1
        try:
            yield
        finally:
            _local.depth -= 1
        return
    _local.depth = 1
    with _mutex:
        _state["workers"] += 1
    try:
        yield
    finally:
        _local.depth = 0
        with _mutex:
            _state["workers"] -= 1


def checkpoint(max_wait: float = 5.0) -> None:
    """In a worker, at a safe point: while the gate is closed, wait here. The wait is a plain lock's
    acquire, which gives up the GIL before it blocks and takes it again only once the gate opens: a
    parked thread runs no Python while the operator runs (a condition variable's wake-ups would).
    Returns at once when the gate is open; never waits longer than ``max_wait`` seconds."""
    if not getattr(_local, "depth", 0) or not _state["closed"]:
        return
    with _mutex:
        _state["parked"] += 1
    try:
        if _gate.acquire(timeout=max_wait):
            _gate.release()
    finally:
        with _mutex:
            _state["parked"] -= 1


@contextlib.contextmanager
def held(timeout: float = 2.0):
    """Run the body while every worker is parked at a checkpoint (or after ``timeout`` seconds). Yields
    True when they all were. Only for the main thread (a worker calling it would wait for itself)."""
    me = threading.get_ident()
    if _owner["thread"] == me:   # nested
        _owner["depth"] += 1
        try:
            yield True
        finally:
            _owner["depth"] -= 1
        return
    _gate.acquire()
    _owner["thread"], _owner["depth"] = me, 1
    _state["closed"] = 1
    try:
        end = time.monotonic() + timeout
        while _state["parked"] < _state["workers"] - getattr(_local, "depth", 0) and time.monotonic() < end:
            time.sleep(0.001)
        quiet = _state["parked"] >= _state["workers"] - getattr(_local, "depth", 0)
        # a worker that has just counted itself is a few bytecodes from blocking on the gate: this
        # sleep hands it the GIL to get there
        time.sleep(0.002)
        yield quiet
    finally:
        _state["closed"] = 0
        _owner["thread"], _owner["depth"] = None, 0
        _gate.release()


@contextlib.contextmanager
def override(context, **members):
    """``context.temp_override(**members)`` with the workers held (:func:`held`): how the add-on (and
    the real-window test scripts) run an operator under a context override."""
    with held(), context.temp_override(**members):
        yield


def state() -> dict:
    """Workers registered and parked now, and whether the gate is closed (for tests and the log)."""
    with _mutex:
        return dict(_state)
