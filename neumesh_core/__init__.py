"""neumesh_core: NeuMesh++ neural radiance fields on mesh scaffolds (torch; no bpy).

Public API (see README.md): load_scene, load_mesh, create_field, train, save_field, load_field,
render_camera, evaluate, save_image, make_default_scene; edits: swap_texture, fill_texture,
paint_texture (nm.edit); semantics: nm.semantics.
"""
from __future__ import annotations

from .data.cameras import Cameras, intrinsics_from_fov, opencv_to_opengl, opengl_to_opencv, pixel_rays
from .data.scene import ImageSet, Scene
from .errors import (CheckpointError, DataError, EditError, NeuMeshError, NoSemanticsError, SelectionError,
                     VertexMismatchError, WeightsUnavailableError)
from .mesh import Mesh, load_mesh, save_mesh
from .field.field import FieldConfig, NeuMeshField
from .render.renderer import Cancelled, RenderOutput, RenderSettings, render_camera, render_rays
from .train.checkpoint import load_field, save_field
from .train.trainer import TrainConfig, TrainProgress, TrainResult, train
from .evaluate import evaluate
from .imageio import read_image, save_image
from .data.loader import load_scene
from .data.synthetic import default_scene_dir, make_default_scene
from . import edit  # noqa: E402  (nm.edit: EditRecord, save_edited, ...)
from .edit import CornerUVs, fill_texture, paint_layer, paint_texture, swap_texture  # noqa: E402
from . import semantics  # noqa: E402  (nm.semantics: distill_semantics, select_region, extractors)
# --- public names the Blender add-on uses (issue 46; the lead merges this block with the core's) ---
from . import bake  # noqa: E402  (nm.bake: bake_texture, decimate, save_bake)
from .bake import bake_texture  # noqa: E402
from .field.remap import field_key, remap_field, resolve_ids  # noqa: E402
from .render.raster import depth_buffer  # noqa: E402
from .data.cameras import axis_to_ray_depth, ray_to_axis_depth  # noqa: E402
from .scaffold.build import ScaffoldConfig, build_scaffold  # noqa: E402
# --- end of the add-on's public names ---

__version__ = "0.1.0"


def create_field(mesh: Mesh, config: FieldConfig | None = None, device="cpu") -> NeuMeshField:
    """A new, untrained field on ``mesh`` (vertex order is the field's vertex order)."""
    return NeuMeshField(mesh, config or FieldConfig()).to(device)


__all__ = [
    "Cameras", "Cancelled", "CheckpointError", "CornerUVs", "DataError", "EditError", "FieldConfig", "ImageSet",
    "Mesh", "NeuMeshError", "NeuMeshField", "NoSemanticsError", "RenderOutput", "RenderSettings", "Scene",
    "SelectionError", "TrainConfig", "TrainProgress", "TrainResult", "VertexMismatchError",
    "WeightsUnavailableError", "create_field", "default_scene_dir", "evaluate", "fill_texture",
    "intrinsics_from_fov", "load_field", "load_mesh", "load_scene", "make_default_scene", "opencv_to_opengl",
    "opengl_to_opencv", "paint_layer", "paint_texture", "pixel_rays", "read_image", "render_camera", "render_rays",
    "save_field", "save_image", "save_mesh", "swap_texture", "train",
    # the add-on's public names (issue 46)
    "ScaffoldConfig", "axis_to_ray_depth", "bake", "bake_texture", "build_scaffold", "depth_buffer", "field_key",
    "ray_to_axis_depth", "remap_field", "resolve_ids",
]
