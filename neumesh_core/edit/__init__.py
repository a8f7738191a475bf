"""Edits of trained fields without retraining (plain functions over vertex index sets, UVs, images).

Each edit returns an :class:`EditRecord` with the rows it changed, so callers can undo it exactly;
edited fields are saved beside the file they came from (:func:`save_edited`), never over it.
"""
from .files import edit_info, next_edit_path, parent_of, root_of, save_edited
from .record import EditRecord, as_vertex_ids

__all__ = ["EditRecord", "as_vertex_ids", "edit_info", "next_edit_path", "parent_of", "root_of", "save_edited"]
