"""neumesh_core: NeuMesh++ neural radiance fields on mesh scaffolds (torch; no bpy).

Public API (see README.md): load_scene, load_mesh, create_field, train, save_field, load_field,
render_camera, evaluate, save_image, make_default_scene; edits: swap_texture, fill_texture,
paint_texture (nm.edit); semantics: nm.semantics; baking: bake_texture (nm.bake: decimate, save_bake);
scaffold building: build_scaffold, ScaffoldConfig; real captures: read_capture, training_photos,
undistorted_images, estimate_poses, frames_from_video; deformation: nm.deform (ArapSolver, arap);
devices: resolve_device. The add-on reaches the core only through these names.
"""
from __future__ import annotations

from .data.cameras import (Cameras, axis_to_ray_depth, intrinsics_from_fov, opencv_to_opengl, opengl_to_opencv,
                           pixel_rays, ray_to_axis_depth)
from .data.scene import ImageSet, Scene
from .errors import (CheckpointError, DataError, DeformError, EditError, NeuMeshError, NoSemanticsError,
                     PaintMissError, SelectionError, VertexMismatchError, WeightsUnavailableError)
from .mesh import Mesh, load_mesh, save_mesh
from .device import resolve_device
from .field.field import FieldConfig, NeuMeshField, create_field
from .field.remap import (field_key, remap_field, resolve_ids,  # remap_field: the add-on's topology edits
                          split_by_key, sub_triangles)
from .render.renderer import Cancelled, RenderOutput, RenderSettings, render_camera, render_rays
from .render.raster import depth_buffer
from .field.io import load_field, save_field
from .train.trainer import TrainConfig, TrainProgress, TrainResult, train
from .evaluate import evaluate
from .imageio import read_image, save_image, srgb_to_linear
from .data.loader import load_scene
from .data.synthetic import default_scene_dir, make_default_scene
from . import edit  # noqa: E402  (nm.edit: EditRecord, save_edited, ...)
from .edit import CornerUVs, fill_texture, paint_layer, paint_texture, swap_texture  # noqa: E402
from . import semantics  # noqa: E402  (nm.semantics: distill_semantics, select_region, extractors)
from . import bake  # noqa: E402  (nm.bake: bake_texture, decimate, save_bake)
from .bake import bake_texture  # noqa: E402
from .reconstruct import ScaffoldConfig, build_scaffold  # noqa: E402
from .data.capture import Capture, capture_object_box, training_photos, undistorted_images  # noqa: E402
from .data.loader import read_capture  # noqa: E402
from .reconstruct.poses import PosesConfig, PosesError, PosesProgress, PosesReport, estimate_poses  # noqa: E402
from .reconstruct.video import frames_from_video  # noqa: E402
from . import deform  # noqa: E402  (nm.deform: ArapSolver, arap)
from .data.frame import ObjectBox, SceneFrame, object_box, parse_box, scene_frame  # noqa: E402
from .field.background import (BackgroundModel, attach_background, background_for, background_of,  # noqa: E402
                               fit_background_for)
from .fit import capture_box, is_unmasked_capture, prepare_capture_field  # noqa: E402

__version__ = "0.1.0"


__all__ = [
    "Cameras", "ScaffoldConfig", "axis_to_ray_depth", "bake", "deform", "bake_texture", "build_scaffold",
    "depth_buffer", "field_key", "ray_to_axis_depth", "remap_field", "resolve_ids", "split_by_key", "sub_triangles",
    "Cancelled", "CheckpointError", "CornerUVs", "DataError", "DeformError", "EditError", "PaintMissError",
    "FieldConfig", "ImageSet", "Mesh", "NeuMeshError", "NeuMeshField", "NoSemanticsError", "RenderOutput",
    "RenderSettings", "Scene", "SelectionError", "TrainConfig", "TrainProgress", "TrainResult",
    "VertexMismatchError", "WeightsUnavailableError", "create_field", "default_scene_dir", "evaluate",
    "fill_texture", "intrinsics_from_fov", "load_field", "load_mesh", "load_scene", "make_default_scene",
    "opencv_to_opengl", "opengl_to_opencv", "paint_layer", "paint_texture", "pixel_rays", "read_image",
    "srgb_to_linear", "render_camera", "render_rays", "save_field", "save_image", "save_mesh", "swap_texture",
    "train", "Capture", "PosesConfig", "PosesError", "PosesProgress", "PosesReport", "estimate_poses",
    "frames_from_video", "read_capture", "capture_object_box", "training_photos", "undistorted_images", "ObjectBox",
    "SceneFrame", "object_box", "parse_box", "scene_frame", "BackgroundModel", "attach_background",
    "background_for", "background_of", "fit_background_for", "resolve_device", "capture_box", "is_unmasked_capture",
    "prepare_capture_field",
]
