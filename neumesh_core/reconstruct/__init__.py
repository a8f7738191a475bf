"""Mesh scaffold from posed images: visual hull -> density grid -> marching cubes -> clean-up.

    from neumesh_core.reconstruct import build_scaffold, ScaffoldConfig
    mesh, report = build_scaffold(scene, ScaffoldConfig(target_vertices=200_000))
"""
from .build import Cancelled, ScaffoldConfig, ScaffoldError, ScaffoldReport, build_scaffold
from .quality import chamfer_distance, rasterize_silhouette, silhouette_iou

__all__ = [
    "Cancelled",
    "ScaffoldConfig",
    "ScaffoldError",
    "ScaffoldReport",
    "build_scaffold",
    "chamfer_distance",
    "rasterize_silhouette",
    "silhouette_iou",
]
