"""Blender cameras <-> pinhole K / OpenCV c2w (numpy only; no torch).

Blender's ``matrix_world`` of a camera is OpenGL-style (x right, y up, looking down -z); the core
wants OpenCV (x right, y down, z forward): ``c2w_cv = c2w_gl @ diag(1,-1,-1,1)``.

Intrinsics are read from Blender's own projection matrix (``Object.calc_matrix_camera``), so sensor
fit, lens, shift and pixel aspect are all honoured exactly the way Blender projects:

    fx = W/2 * P[0][0]      cx = W/2 * (1 - P[0][2])
    fy = H/2 * P[1][1]      cy = H/2 * (1 + P[1][2])
"""
from __future__ import annotations

from ..runtime._np import np



def gl_to_cv():
    """diag(1,-1,-1,1): flips y and z (OpenGL camera axes <-> OpenCV camera axes)."""
    return np.diag([1.0, -1.0, -1.0, 1.0])


class CameraError(RuntimeError):
    pass


def render_size(scene) -> tuple[int, int]:
    r = scene.render
    return (max(1, int(r.resolution_x * r.resolution_percentage / 100)),
            max(1, int(r.resolution_y * r.resolution_percentage / 100)))


def border_rect(scene, width: int, height: int) -> tuple[int, int, int, int]:
    """The part of the ``width`` x ``height`` frame that a render fills: (column, row, w, h) with rows
    counted from the top; the whole frame unless Output > Format > Render Region (border) is on.
    Blender truncates ``border * size`` to whole pixels (``disprect`` in render_init_from_main)."""
    r = scene.render
    if not r.use_border:
        return 0, 0, int(width), int(height)
    x0, x1 = int(r.border_min_x * width), int(r.border_max_x * width)
    y0, y1 = int(r.border_min_y * height), int(r.border_max_y * height)   # from the bottom
    if x1 - x0 < 1 or y1 - y0 < 1:
        raise CameraError("the render region (border) is smaller than one pixel: widen it "
                          "(Ctrl+B in the camera view) or switch Output > Format > Render Region off")
    return x0, int(height) - y1, x1 - x0, y1 - y0


def crop_K(K, column: int, row: int) -> np.ndarray:
    """The intrinsics of the sub-image that starts at (column, row) of the image of ``K``."""
    Kc = np.array(K, dtype=np.float32)
    Kc[0, 2] -= column
    Kc[1, 2] -= row
    return Kc


def k_from_projection(P, width: int, height: int) -> np.ndarray:
    P = np.asarray(P, dtype=np.float64).reshape(4, 4)
    if abs(P[3, 3]) > 1e-9 or abs(P[3, 2] + 1.0) > 1e-6:
        raise CameraError("orthographic projection: NeuMesh renders perspective cameras only")
    K = np.eye(3)
    K[0, 0] = 0.5 * width * P[0, 0]
    K[0, 2] = 0.5 * width * (1.0 - P[0, 2])
    K[1, 1] = 0.5 * height * P[1, 1]
    K[1, 2] = 0.5 * height * (1.0 + P[1, 2])
    return K.astype(np.float32)


def c2w_from_matrix_world(matrix_world) -> np.ndarray:
    """OpenCV c2w from a Blender camera matrix_world (scale removed, rotation orthonormalised)."""
    M = np.asarray(matrix_world, dtype=np.float64).reshape(4, 4)
    R = M[:3, :3]
    # remove any object scale: polar decomposition via SVD keeps the nearest rotation
    U, _, Vt = np.linalg.svd(R)
    Rn = U @ Vt
    if np.linalg.det(Rn) < 0:
        raise CameraError("camera has a negative scale (mirrored); remove it")
    out = np.eye(4)
    out[:3, :3] = Rn
    out[:3, 3] = M[:3, 3]
    return (out @ gl_to_cv()).astype(np.float32)


def camera_K_c2w(cam_obj, scene, depsgraph=None, width=None, height=None):
    """K (3,3), c2w (4,4, OpenCV), width, height of a Blender camera object for ``scene``'s render size."""
    if cam_obj is None or cam_obj.type != "CAMERA":
        raise CameraError("no camera: set the scene camera (Scene properties > Camera)")
    if cam_obj.data.type != "PERSP":
        raise CameraError(f"camera '{cam_obj.name}' is {cam_obj.data.type.lower()}; NeuMesh renders "
                          "perspective cameras only")
    if width is None or height is None:
        width, height = render_size(scene)
    r = scene.render
    kw = dict(x=int(width), y=int(height), scale_x=float(r.pixel_aspect_x), scale_y=float(r.pixel_aspect_y))
    if depsgraph is None:
        import bpy

        depsgraph = bpy.context.evaluated_depsgraph_get()
    obj_eval = cam_obj.evaluated_get(depsgraph) if depsgraph is not None else cam_obj
    P = obj_eval.calc_matrix_camera(depsgraph, **kw)
    K = k_from_projection([list(row) for row in P], width, height)
    c2w = c2w_from_matrix_world([list(row) for row in obj_eval.matrix_world])
    return K, c2w, int(width), int(height)


def viewport_K_c2w(region, rv3d):
    """K, c2w, width, height for a 3D viewport region (perspective views and camera view)."""
    if not rv3d.is_perspective:
        raise CameraError("orthographic viewport: switch to a perspective view (numpad 5) or the camera")
    w, h = int(region.width), int(region.height)
    K = k_from_projection([list(r) for r in rv3d.window_matrix], w, h)
    view_inv = np.linalg.inv(np.asarray([list(r) for r in rv3d.view_matrix], dtype=np.float64))
    return K, c2w_from_matrix_world(view_inv), w, h


def set_camera_from_K(cam_obj, K, c2w_cv, width: int, height: int, sensor_width=36.0):
    """Configure a Blender camera (data + matrix_world) to match pinhole K and an OpenCV c2w.

    Sensor fit is HORIZONTAL with a 36 mm sensor, so lens = fx * 36 / W. Shifts are in units of the
    image width (Blender's convention for a horizontal fit). fy != fx cannot be expressed per camera
    (pixel aspect is per scene): returns the relative mismatch so callers can warn.
    """
    import mathutils

    K = np.asarray(K, dtype=np.float64)
    cam = cam_obj.data
    cam.type = "PERSP"
    cam.sensor_fit = "HORIZONTAL"
    cam.sensor_width = sensor_width
    cam.lens = float(K[0, 0] * sensor_width / width)
    cam.shift_x = float((0.5 * width - K[0, 2]) / width)
    cam.shift_y = float((K[1, 2] - 0.5 * height) / width)
    c2w_gl = np.asarray(c2w_cv, dtype=np.float64) @ gl_to_cv()
    cam_obj.matrix_world = mathutils.Matrix(c2w_gl.tolist())
    return abs(K[1, 1] - K[0, 0]) / max(abs(K[0, 0]), 1e-9)
