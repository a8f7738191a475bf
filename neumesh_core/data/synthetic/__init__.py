"""The built-in default scene: a textured, non-convex "bumpy blob" and its ground-truth ray tracer.

Analytic surface (star-shaped around the origin): for a unit direction ``u`` the surface point is
``r(u) * u`` with ``r(u) = 1 + AMPLITUDE * bumps(u)`` and ``bumps`` a sum of smooth von Mises-Fisher
lobes ``c_k * exp(kappa_k * (u . d_k - 1))`` (positive lobes are hills, negative ones dents, so the
surface has concavities). Everything here (shape, texture, light, cameras) is fixed and deterministic.

* :func:`default_mesh` - icosphere whose vertices lie exactly on the analytic surface.
* :func:`default_texture` - a high-frequency solid texture (stripes/checker + stroke lettering).
* :func:`render_truth` - ray tracer of the analytic surface (Lipschitz-safe marching + bisection,
  analytic normals, Lambert + Blinn-Phong, 4 jittered samples per pixel).
* :func:`make_default_scene` / :func:`default_scene_dir` - write / cache it in NeRF-synthetic format.

Modules: :mod:`.shape` (surface, mesh) · :mod:`.texture` · :mod:`.tracer` (ground-truth ray tracer, light)
· :mod:`.scene` (camera rig, scene writer). Every name is importable from here.
"""
from __future__ import annotations

from .shape import (AMPLITUDE, _consts, _fibonacci_sphere, _radius_and_grad, _torch_single_thread, default_mesh,
                    icosphere, implicit, shape_bounds, surface_normal, surface_radius)
from .texture import default_texture
from .tracer import (AMBIENT, DIFFUSE, LIGHT_DIR, SHININESS, SPECULAR, _render_unpremultiplied, _sample_offsets,
                     render_truth, shade, trace_rays)
from .scene import (CAMERA_ANGLE_X, CAMERA_RADIUS, SCENE_VERSION, SMALL_SCENE_KWARGS, _cache_base, _is_complete,
                    _rotation, camera_positions, default_scene_dir, look_at_opencv, make_default_scene)


__all__ = ["AMBIENT", "AMPLITUDE", "CAMERA_ANGLE_X", "CAMERA_RADIUS", "DIFFUSE", "LIGHT_DIR", "SCENE_VERSION",
           "SHININESS", "SMALL_SCENE_KWARGS", "SPECULAR", "camera_positions", "default_mesh", "default_scene_dir",
           "default_texture", "icosphere", "implicit", "look_at_opencv", "make_default_scene", "render_truth",
           "shade", "shape_bounds", "surface_normal", "surface_radius", "trace_rays"]
