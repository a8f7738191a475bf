"""One frame of the fields :func:`field_cache.collect` found, for the F12 engine, the viewport preview, the
render-to-image operator, painting and the benchmarks: ``nm.render_camera`` of the posed fields, its
passes (combined, depth, modification colour) and holdouts, in Blender's colour space.

Colour: a field reproduces the training images' pixel values, i.e. display-referred sRGB. Blender's
render result is scene-linear, so pixels are decoded with the sRGB transfer function before they are
handed to Blender; with the view transform 'Standard' (display sRGB, look None, exposure 0, gamma 1)
and dither 0 the saved PNG equals the core's own output (up to 8/16-bit quantisation).
"""
from __future__ import annotations

from dataclasses import dataclass

from ..runtime._np import np
from ..runtime import core
from ..scene import sync
from . import field_cache
from .field_cache import Item

# the last render_items call: seconds in nm.render_camera, in posing the fields, torch's threads
LAST_TIMINGS: dict = {}


def render_items(items: list[Item], K, c2w, width: int, height: int, transparent: bool = False,
                 progress=None, supersample: int = 1, background_model: bool = True) -> np.ndarray:
    """Render (H,W,4) float32 display-referred RGBA (sRGB-encoded like the field's training images).

    ``supersample``: S x S rays per pixel, averaged (anti-aliasing).
    Transparent: straight alpha = opacity, rgb composited on black (premultiplied).
    Otherwise: composited on white, alpha = 1.
    ``background_model``: a field trained on photos without masks renders the room its background model
    learned behind it (with Transparent: alpha is the frame's coverage); off: the object alone.
    """
    out = _render_out(items, K, c2w, width, height, transparent, progress, supersample,
                      background_model=background_model)
    if out is None:
        return _empty(width, height, transparent)
    return _rgba(out, width, height, transparent)


def render_items_surface(items: list[Item], K, c2w, width: int, height: int):
    """:func:`render_items` (opaque, on white) and the frame's (opacity, depth) (H,W) arrays: the
    surface a paint layer painted on this image lies on (None, None without fields)."""
    out = _render_out(items, K, c2w, width, height, False, None, 1)
    if out is None:
        return _empty(width, height, False), None, None
    return _rgba(out, width, height, False), np.asarray(out.opacity), np.asarray(out.depth)


def _render_out(items: list[Item], K, c2w, width: int, height: int, transparent: bool, progress,
                supersample: int, far=None, background_model: bool = True):
    """``nm.render_camera`` of the posed fields of ``items`` (None when there is none)."""
    nm = core.get()
    LAST_TIMINGS.clear()
    bg = (0.0, 0.0, 0.0) if transparent else (1.0, 1.0, 1.0)
    if not items:
        return None
    import time

    import torch

    with core.torch_work() as threads, field_cache.LOCK:
        t0 = time.perf_counter()
        device = core.render_device()   # the preference Device (auto: a CUDA GPU when torch sees one)
        posed = []
        for it in items:
            if it.field is None:
                field_cache.get_field(it.key, it.path)
            posed.append(field_cache.on_device(it, field_cache.posed_field(it), device))
        t1 = time.perf_counter()
        out = nm.render_camera(posed if len(posed) > 1 else posed[0], np.asarray(K, np.float32),
                               np.asarray(c2w, np.float32), int(width), int(height), background=bg,
                               settings=nm.RenderSettings(supersample=int(supersample),
                                                          background_model=bool(background_model)),
                               progress=progress,
                               far=far)
        t2 = time.perf_counter()
    LAST_TIMINGS.update(pose_s=t1 - t0, core_s=t2 - t1, torch_threads=torch.get_num_threads(),
                        threads_wanted=threads, device=str(device))
    core.guard_torch_namespaces()  # torch may have imported more modules lazily
    return out


@dataclass
class Passes:
    """One frame's render passes for Blender: ``combined`` (H,W,4) scene-linear premultiplied RGBA,
    ``z`` (H,W) distance along the camera axis (the Depth pass of Cycles/EEVEE; inf where empty),
    and ``mod`` (H,W,3) the rendered modification colour (premultiplied by opacity; a data pass)."""

    combined: np.ndarray
    z: np.ndarray
    mod: np.ndarray


def holdout_meshes(depsgraph) -> tuple[np.ndarray, np.ndarray] | None:
    """World-space (V,3) vertices and (F,3) triangles of every object that is a holdout in the
    depsgraph's view layer (Object properties > Visibility > Holdout, or a holdout collection), or
    None when there is none. Those objects occlude the field and leave transparent holes."""
    verts, tris, base = [], [], 0
    for ob in depsgraph.objects:
        if ob.type not in {"MESH", "CURVE", "SURFACE", "META", "FONT"}:
            continue
        if not field_cache.is_holdout(ob.original, depsgraph):
            continue
        me = ob.to_mesh()
        try:
            me.calc_loop_triangles()
            n, t = len(me.vertices), len(me.loop_triangles)
            if n == 0 or t == 0:
                continue
            v = np.empty(n * 3, np.float32)
            me.vertices.foreach_get("co", v)
            f = np.empty(t * 3, np.int64)
            me.loop_triangles.foreach_get("vertices", f)
        finally:
            ob.to_mesh_clear()
        verts.append(sync.to_world(v.reshape(-1, 3), ob.matrix_world))
        tris.append(f.reshape(-1, 3) + base)
        base += n
    if not verts:
        return None
    return np.concatenate(verts).astype(np.float64), np.concatenate(tris)


def holdout_z(depsgraph, K, c2w, width: int, height: int) -> np.ndarray | None:
    """(H,W) camera-axis distance of the nearest holdout surface at each pixel (inf: none), or None."""
    meshes = holdout_meshes(depsgraph)
    if meshes is None:
        return None
    return core.get().depth_buffer(meshes[0], meshes[1], K, c2w, width, height)


def render_passes(items: list[Item], K, c2w, width: int, height: int, transparent: bool = False,
                  progress=None, supersample: int = 1, occluder_z: np.ndarray | None = None,
                  background_model: bool = True) -> Passes:
    """The passes of one frame (see :class:`Passes`). ``occluder_z`` (H,W) camera-axis distances of
    holdout surfaces (inf: none): the field behind them is not sampled, and there the background is
    left out (alpha = the field's opacity in front of the holdout, even without Film > Transparent)."""
    nm = core.get()
    far = None if occluder_z is None else nm.axis_to_ray_depth(occluder_z, K)
    out = _render_out(items, K, c2w, width, height, transparent, progress, supersample, far, background_model)
    if out is None:
        rgba = _empty(width, height, transparent)
        z = np.full((height, width), np.inf, np.float32)
        mod = np.zeros((height, width, 3), np.float32)
        a = np.zeros((height, width), np.float32)
    else:
        rgba = _rgba(out, width, height, transparent)
        z = nm.ray_to_axis_depth(out.depth.reshape(height, width), K)
        mod = np.asarray(out.mod_colour, np.float32).reshape(height, width, 3)
        a = np.asarray(out.alpha, np.float32).reshape(height, width)
    combined = to_scene_linear(rgba, transparent)
    if occluder_z is not None:
        hold = np.isfinite(occluder_z)
        if not transparent and hold.any():   # the white background was added in display space
            premult = rgba[..., :3] - (1.0 - a[..., None])
            cut = to_scene_linear(np.concatenate([premult, a[..., None]], -1), True)
            combined[hold] = cut[hold]
        z = np.minimum(z, occluder_z.astype(np.float32))
    return Passes(combined.astype(np.float32), z.astype(np.float32), mod)


def _empty(width: int, height: int, transparent: bool) -> np.ndarray:
    img = np.zeros((height, width, 4), np.float32)
    if not transparent:
        img[:] = 1.0
    return img


def _rgba(out, width: int, height: int, transparent: bool) -> np.ndarray:
    rgb = np.asarray(out.rgb, dtype=np.float32).reshape(height, width, 3)
    alpha = np.asarray(out.alpha, dtype=np.float32).reshape(height, width, 1) if transparent else \
        np.ones((height, width, 1), np.float32)
    return np.concatenate([rgb, alpha], axis=-1)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, None)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def to_scene_linear(rgba: np.ndarray, transparent: bool) -> np.ndarray:
    """Display-referred RGBA from :func:`render_items` -> Blender scene-linear premultiplied RGBA."""
    srgb_to_linear = core.get().srgb_to_linear
    rgb, a = rgba[..., :3], rgba[..., 3:4]
    if transparent:
        straight = np.where(a > 1e-6, rgb / np.maximum(a, 1e-6), 0.0)
        lin = srgb_to_linear(np.clip(straight, 0.0, 1.0)) * a
    else:
        lin = srgb_to_linear(rgb)
    return np.concatenate([lin, a], axis=-1).astype(np.float32)


def scale_K(K, width, height, new_w, new_h):
    K = np.array(K, dtype=np.float32)
    K[0, :] *= new_w / float(width)
    K[1, :] *= new_h / float(height)
    return K
