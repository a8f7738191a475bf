"""Edits of trained fields without retraining (plain functions over vertex index sets, UVs, images).

Each edit returns an :class:`EditRecord` with the rows it changed, so callers can undo it exactly;
edited fields are saved beside the file they came from (:func:`save_edited`), never over it.

- :func:`swap_texture`: a target region takes a source region's texture (alignment + code transfer);
  refused when the aligned source does not cover the target.  :func:`swap_alignment`: the same
  alignment and its fit figures without writing anything (a preview).
- :func:`fill_texture`: a template region's texture tiled over a target region through UV maps.
- :func:`paint_texture`: paint on one rendered view becomes surface paint (modification colours, or
  texels of a paint atlas: :func:`create_paint_atlas`, :func:`paint_atlas_from_view`); paint made in
  the atlas image elsewhere (Blender's Texture Paint) is recorded by :func:`paint_image_record`;
  :func:`paint_onto_source` carries paint on a remapped field onto the field it was remapped from.
"""
from .align import Similarity, arap_icp, initial_alignment, rigid_icp, umeyama
from .edited_files import edit_info, next_edit_path, parent_of, root_of, save_edited
from .fill import CornerUVs, FillConfig, fill_texture, planar_uvs
from .paint import PaintConfig, paint_fields, paint_layer, paint_onto_source, paint_texture
from .paint_atlas import AtlasRecord, create_paint_atlas, paint_atlas_from_view, paint_image_record
from .record import EditRecord, as_vertex_ids
from .fit_check import FitFigures, FitThresholds
from .swap import SwapAlignment, SwapConfig, swap_alignment, swap_texture
from .transfer import idw_neighbours

__all__ = ["AtlasRecord", "create_paint_atlas", "paint_atlas_from_view", "paint_image_record", "CornerUVs",
           "EditRecord", "FillConfig", "FitFigures", "FitThresholds", "PaintConfig", "Similarity", "SwapConfig",
           "arap_icp", "as_vertex_ids", "edit_info", "fill_texture", "idw_neighbours", "initial_alignment",
           "next_edit_path", "paint_fields", "paint_layer", "paint_onto_source", "paint_texture", "parent_of",
           "planar_uvs", "rigid_icp", "root_of", "save_edited",
           "SwapAlignment", "swap_alignment", "swap_texture", "umeyama"]
