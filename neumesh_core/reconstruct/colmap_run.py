"""pycolmap, run the way poses and sparse points both run it: imported with a clear error, its own log
hidden unless asked for (:func:`colmap_log`), and a long call run in a helper thread with progress and
cancel (:func:`_run_stage`)."""
from __future__ import annotations

import contextlib
import threading
from typing import Callable, Optional

from ..errors import NeuMeshError


def import_pycolmap():
    try:
        import pycolmap
    except ImportError as exc:  # pragma: no cover - a declared dependency
        raise NeuMeshError("poses and sparse points need pycolmap: pip install pycolmap") from exc
    return pycolmap


@contextlib.contextmanager
def colmap_log(show: bool = False):
    """Inside the block pycolmap logs (glog, from C++ to fd 2) only errors, or everything with ``show``;
    the level before is restored after. glog's level is one for the whole process. Without pycolmap
    installed there is nothing to hide."""
    try:
        import pycolmap
    except ImportError:
        yield
        return
    logging = pycolmap.logging
    before = logging.minloglevel
    logging.minloglevel = min(before, int(logging.INFO)) if show else max(before, int(logging.ERROR))
    try:
        yield
    finally:
        logging.minloglevel = before


def _is_cancelled(token) -> bool:
    v = token.is_cancelled
    return bool(v() if callable(v) else v)


def _run_stage(fn, token, report: Callable[[], Optional[bool]]):
    """Run ``fn()`` in a helper thread; call ``report()`` here ~4x/s; False cancels through ``token``."""
    from ..errors import Cancelled

    box = {}

    def work():
        try:
            box["out"] = fn()
        except BaseException as exc:  # handed to the caller
            box["exc"] = exc

    t = threading.Thread(target=work, name="neumesh-poses", daemon=True)
    t.start()
    cancelled = False
    try:
        while t.is_alive():
            t.join(0.25)
            if not cancelled and report() is False:
                token.cancel()
                cancelled = True
    except BaseException:  # Ctrl-C (or a failing callback): stop pycolmap before leaving
        token.cancel()
        t.join(30)
        raise
    if cancelled or _is_cancelled(token):
        raise Cancelled("pose recovery cancelled; nothing usable was written")
    if "exc" in box:
        raise box["exc"]
    return box.get("out")
