"""The add-on's own error type.

:class:`UserError`: an operator cannot start with what the scene holds (no field, a missing vertex
group or UV map, a missing Python package, a camera missing...). The message says what to do; nothing
was changed. Errors of the core (``neumesh_core.NeuMeshError`` and its subclasses, such as
``nm.EditError`` when an edit's input is bad) reach the user through :func:`core.error_types`; the
add-on never defines a second class for a meaning the core already has.
"""
from __future__ import annotations


class UserError(RuntimeError):
    """An operator cannot start; the message says what to do. Nothing was changed."""
