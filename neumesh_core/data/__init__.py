"""Dataset readers. All return a :class:`Scene` (see scene.py); cameras are OpenCV c2w."""
from .cameras import Cameras, intrinsics_from_fov, opencv_to_opengl, opengl_to_opencv, pixel_rays
from .scene import ImageSet, Scene

__all__ = [
    "Cameras",
    "ImageSet",
    "Scene",
    "intrinsics_from_fov",
    "opencv_to_opengl",
    "opengl_to_opencv",
    "pixel_rays",
]
