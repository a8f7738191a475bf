"""Dataset readers. All return a :class:`Scene` (see scene.py); cameras are OpenCV c2w."""
from .cameras import Cameras, intrinsics_from_fov, opencv_to_opengl, opengl_to_opencv, pixel_rays
from .scene import ImageSet, Scene
from .capture import Capture, capture_object_box, scene_from_capture, undistorted_images
from .loader import read_capture
from .undistort import Lens

__all__ = [
    "Cameras",
    "Capture",
    "Lens",
    "capture_object_box",
    "read_capture",
    "scene_from_capture",
    "undistorted_images",
    "ImageSet",
    "Scene",
    "intrinsics_from_fov",
    "opencv_to_opengl",
    "opengl_to_opencv",
    "pixel_rays",
]
