"""Bake a field into a plain UV-textured mesh (docs/baking.md).

``texture``: the texels and their colours (:func:`bake_texture`, :func:`save_bake`, :func:`decimate`);
``uv``: the UV atlas (:func:`unwrap`, :func:`texel_coverage`, :func:`dilate`); ``surface``: where the
field's surface is seen from a mesh, and moving the mesh onto it before baking (:func:`fit_to_field`,
:func:`surface_offsets`).
"""
from .extract import ExtractConfig, density_grid, extract_surface
from .project import ProjectConfig, projected_colours
from .simplify import decimate
from .surface import SurfaceFitConfig, fit_to_field, offset_stats, surface_offsets
from .texture import BakeResult, bake_texture, save_bake, surface_colours
from .uv import dilate, texel_coverage, unwrap, uv_pixels

__all__ = ["BakeResult", "ExtractConfig", "ProjectConfig", "SurfaceFitConfig", "density_grid", "extract_surface",
           "projected_colours", "bake_texture", "decimate", "dilate", "fit_to_field", "offset_stats",
           "save_bake", "surface_colours", "surface_offsets", "texel_coverage", "unwrap", "uv_pixels"]
