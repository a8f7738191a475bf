"""``build_scaffold``: posed images (+ masks) -> triangle mesh scaffold, with a quality report."""
from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
import torch

from ..data.scene import ImageSet, Scene
from ..errors import Cancelled
from ..mesh import load_mesh
from ..data.views import ViewStack
from .config import METHODS, ScaffoldConfig, ScaffoldError, ScaffoldReport, _json_default  # noqa: F401 (re-exported)
from .hull import axes_meeting_point, carve_hull, common_view_volume, mask_sdf



def _resize_for_density(imgs: ImageSet, max_side: int) -> ImageSet:
    """Area-downsample images/masks by an integer factor so the longest side is <= max_side."""
    H, W = imgs.cameras.height, imgs.cameras.width
    f = int(math.ceil(max(H, W) / max(1, max_side)))
    if f <= 1:
        return imgs
    h, w = H // f, W // f
    # one view at a time: uint8 photos are converted per view, never all at full size as float
    im = np.stack([imgs.float_view(k)[:h * f, :w * f].reshape(h, f, w, f, 3).mean((1, 3))
                   for k in range(len(imgs))])
    ms = None
    if imgs.masks is not None:
        ms = np.stack([imgs.float_mask(k)[:h * f, :w * f].reshape(h, f, w, f).mean((1, 3))
                       for k in range(len(imgs))])
    cams = imgs.cameras.scaled(1.0 / f)
    from ..data.cameras import Cameras

    cams = Cameras(cams.K, cams.c2w, w, h)
    return ImageSet(cams, im.astype(np.float32), None if ms is None else ms.astype(np.float32))


def build_scaffold(scene_or_imageset, config: ScaffoldConfig | None = None,
                   progress: Callable[[str, float], object] | None = None,
                   log: Callable[[str], None] | None = None, box=None):
    """Reconstruct a mesh scaffold from posed images.

    scene_or_imageset: a :class:`Scene` (its "train" split, bbox, background and reference mesh are
    used) or an :class:`ImageSet` (no bbox: the volume seen by the cameras is used).
    box: the object box (``data.frame.ObjectBox``) of photos without masks: method "fusion" builds the
    surface in it (without it, the scene's bbox as an axis-aligned box).
    progress(stage, fraction) -> False cancels (raises Cancelled). Stages: "bounds", "hull",
    "density", "mesh", "metrics" ("fusion": "density", "depths", "fusion", "mesh", "metrics").
    log(str) receives human-readable details.
    Returns (Mesh, ScaffoldReport).  Raises ScaffoldError (a DataError) on unusable input.

    The stages are the functions below, in order: :func:`_choose_method`, :func:`_bounds`,
    :func:`_hull`, :func:`_carve_mvs` or :func:`_fit_density`, :func:`_extract_mesh`, :func:`_metrics`
    (method "fusion": :func:`_fused`).
    """
    cfg = config or ScaffoldConfig()
    if cfg.method not in METHODS:
        raise ValueError(f"ScaffoldConfig.method must be one of {METHODS}, got {cfg.method!r}")
    t_all = time.perf_counter()
    rep = ScaffoldReport(config=asdict(cfg))
    say = log or (lambda s: None)

    def check(stage: str, frac: float) -> None:
        if progress is not None and progress(stage, float(min(max(frac, 0.0), 1.0))) is False:
            raise Cancelled(f"scaffold cancelled during stage '{stage}'")

    src = _source(scene_or_imageset)
    images = src.images
    cams = images.cameras
    rep.num_views, rep.image_size = len(cams), (cams.width, cams.height)
    method = _choose_method(cfg, images, src.bbox, box, rep)
    if method == "fusion":
        return _fused(images, box, src.bbox, cfg, rep, check, say, t_all)

    views, lo, hi, min_views = _bounds(cams, src.bbox, cfg, rep, check, say)
    hull_grid = None
    if method in ("hull", "hull+mvs", "hull+density"):
        hull_grid, lo, hi = _hull(images, views, lo, hi, min_views, cfg, rep, check, say)
    rep.bbox = [lo.tolist(), hi.tolist()]

    # the signed field the surface is extracted from, on a grid (lo corner, voxel)
    field_vals, field_lo, field_voxel, px_per_voxel = None, None, None, 1.0
    if hull_grid is not None:
        field_vals, px_per_voxel = _hull_field(views, hull_grid, lo, hi)
        field_lo, field_voxel = hull_grid.lo, hull_grid.voxel
    if method == "hull+mvs":
        field_vals = _carve_mvs(images, views, hull_grid, field_vals, cfg, rep, check, say)
    if method in ("hull+density", "density"):
        field_vals, field_lo, field_voxel = _fit_density(images, hull_grid, px_per_voxel, lo, hi, field_vals,
                                                         field_lo, field_voxel, src.background, cfg, rep,
                                                         check, say)
    mesh = _extract_mesh(field_vals, field_lo, field_voxel, method, cfg, rep, check)
    _metrics(mesh, images, src.reference_mesh, cfg, rep, check)
    rep.timings["total"] = time.perf_counter() - t_all
    return mesh, rep


@dataclass
class _Source:
    """What build_scaffold takes from its input: the training images, the scene box (or None), the
    scene's background colour and its reference mesh (for the Chamfer metric)."""

    images: ImageSet
    bbox: np.ndarray | None = None
    background: object = None
    reference_mesh: str | None = None


def _source(scene_or_imageset) -> _Source:
    if isinstance(scene_or_imageset, Scene):
        scene = scene_or_imageset
        if "train" not in scene.splits:
            raise ScaffoldError(f"scene has no 'train' split (it has {sorted(scene.splits)}); "
                                "pass the ImageSet to use instead")
        bbox = None if scene.bbox is None else np.asarray(scene.bbox, np.float64).reshape(2, 3)
        return _Source(scene.split("train"), bbox, scene.background, scene.mesh_path)
    if isinstance(scene_or_imageset, ImageSet):
        return _Source(scene_or_imageset)
    raise TypeError("build_scaffold expects a Scene or an ImageSet")


def _choose_method(cfg: ScaffoldConfig, images: ImageSet, bbox, box, rep: ScaffoldReport) -> str:
    """The method to run ("auto" resolved by the masks), or a ScaffoldError that says what is missing."""
    N = len(images.cameras)
    if N < 3:
        raise ScaffoldError(
            f"only {N} view(s): a scaffold needs at least 3 posed views around the object "
            "(20+ recommended; 50-100 for good thin-structure recovery); add more images")
    has_masks = images.masks is not None
    method = cfg.method
    if method == "auto":
        method = "hull+mvs" if has_masks else "fusion"
        if has_masks and one_sided_capture(images.cameras):
            rep.notes.append("the cameras see the object from one side: the visual hull says little about "
                             "depth; multi-view stereo carves it (method 'hull+mvs')")
        if not has_masks:
            rep.notes.append("no masks/alpha in the data: the surface comes from the photos alone (a density grid "
                             "fitted with a background model, its depths fused); add masks for a visual hull")
    if method in ("hull", "hull+mvs", "hull+density") and not has_masks:
        raise ScaffoldError(f"method '{method}' needs masks (alpha for Blender data, mask/ for DTU) "
                            "but the images have none; add masks or use method 'density'")
    if method in ("density", "fusion") and bbox is None and box is None and not has_masks:
        raise ScaffoldError("no masks and no object box: cannot tell the object from the background; "
                            "provide masks (alpha / mask folder) or an object box (--box cx,cy,cz,sx,sy,sz)")
    rep.method = method
    return method


def _bounds(cams, bbox, cfg: ScaffoldConfig, rep: ScaffoldReport, check, say):
    """Stage "bounds": the box that enough views see (inside the scene box, or around the point the
    cameras look at).  Returns (views, lo, hi, min_views)."""
    t0 = time.perf_counter()
    check("bounds", 0.0)
    N = len(cams)
    views = ViewStack.from_cameras(cams)
    min_views = max(2, int(math.ceil(cfg.min_view_fraction * N)))
    if bbox is not None:
        dom_lo, dom_hi = bbox[0], bbox[1]
    else:
        c, r = axes_meeting_point(cams)
        dmin = float(np.linalg.norm(cams.centres - c[None], axis=1).min())
        half = 0.75 * dmin if dmin > 1e-6 else r
        dom_lo, dom_hi = c - half, c + half
    common, frac = common_view_volume(views, dom_lo, dom_hi, min_views)
    if common is None:
        raise ScaffoldError(
            f"the cameras do not see a common volume: no point of the scene box is in frame in at "
            f"least {min_views} of {N} views (min_view_fraction={cfg.min_view_fraction}); check that the "
            "poses belong to one capture of one object (and their convention), or lower min_view_fraction")
    rec_views = min(min_views, max(2, int(math.ceil(cfg.reconstruct_view_fraction * N))))
    if rec_views < min_views:  # the box of what fewer views see (the check above passed)
        common, frac = common_view_volume(views, dom_lo, dom_hi, rec_views)
    lo = np.maximum(common[0], dom_lo)
    hi = np.minimum(common[1], dom_hi)
    say(f"common view volume: {frac:.1%} of the domain; box {np.round(lo, 3).tolist()} - {np.round(hi, 3).tolist()}")
    check("bounds", 1.0)
    rep.timings["bounds"] = time.perf_counter() - t0
    return views, lo, hi, rec_views


def _hull(images: ImageSet, views, lo, hi, min_views: int, cfg: ScaffoldConfig, rep: ScaffoldReport, check, say):
    """Stage "hull": the visual hull carved from the masks, coarse first to find the object's box, then
    at ``cfg.hull_resolution`` in that box.  Returns (hull grid, the box it was carved in: lo, hi)."""
    t0 = time.perf_counter()
    check("hull", 0.0)
    cams = images.cameras
    tol = max(0, cfg.mask_tolerance)
    views.sdf = torch.from_numpy(mask_sdf(images.float_masks(), cfg.mask_threshold))[:, None]
    dil = cfg.hull_dilate_px
    if dil < 0:
        dil = float(np.clip(max(cams.width, cams.height) / 800.0, 0.1, 0.5))
    coarse = carve_hull(views, lo, hi, 48, tol, min_views, dilate_px=dil, start_res=48)
    inside = coarse.values > 0
    if not inside.any():
        raise ScaffoldError(
            "the masks carve away the whole volume: no point projects inside the masks of enough "
            f"views (tolerance {tol}); check mask polarity (object = white), camera poses, or raise "
            "mask_tolerance")
    ijk = np.argwhere(inside)
    margin = 2.5 * coarse.voxel
    tlo = coarse.lo + ijk.min(0) * coarse.voxel - margin
    thi = coarse.lo + ijk.max(0) * coarse.voxel + margin
    lo, hi = np.maximum(tlo, lo - margin), np.minimum(thi, hi + margin)
    check("hull", 0.1)
    hull_grid = carve_hull(views, lo, hi, cfg.hull_resolution, tol, min_views,
                           dilate_px=dil, start_res=48,
                           check=lambda f: check("hull", 0.1 + 0.9 * f))
    views.sdf = None
    occ = float((hull_grid.values > 0).mean())
    rep.hull = {"tolerance_views": tol, "dilate_px": dil, "min_views": min_views, "grid": list(hull_grid.dims),
                "voxel": hull_grid.voxel, "occupied_fraction": occ, "evaluations": hull_grid.evaluated}
    say(f"visual hull: grid {'x'.join(map(str, hull_grid.dims))}, voxel {hull_grid.voxel:.4f}, "
        f"{occ:.1%} inside, tolerance {tol} views")
    rep.timings["hull"] = time.perf_counter() - t0
    return hull_grid, lo, hi


def _hull_field(views, hull_grid, lo, hi):
    """The hull's signed distance in pixels in voxel units (clipped to +-6), and pixels per voxel at the
    box's centre."""
    focal = views.mean_focal()
    centre = torch.as_tensor(0.5 * (lo + hi), dtype=torch.float32)[None]
    depth = float(views.project(centre)[2].abs().mean().clamp_min(1e-6))
    px_per_voxel = hull_grid.voxel * focal / depth
    return np.clip(hull_grid.values / max(px_per_voxel, 1e-6), -6.0, 6.0), px_per_voxel


def _carve_mvs(images: ImageSet, views, hull_grid, field_vals, cfg: ScaffoldConfig, rep: ScaffoldReport, check,
               say):
    """Stage "mvs": multi-view stereo carves the hull's concavities; silhouettes stay covered."""
    from .mvs import MVSConfig, keep_silhouettes, refine_hull

    t0 = time.perf_counter()
    check("mvs", 0.0)
    mimgs = _resize_for_density(images, cfg.mvs_max_image_side)
    mres = refine_hull(mimgs, hull_grid, field_vals, cfg.mvs or MVSConfig(),
                       check=lambda f: check("mvs", f), log=say)
    seen = np.isfinite(mres.values)
    carved_vals = np.where(seen, np.minimum(field_vals, mres.values), field_vals)
    carved_vals, kept = keep_silhouettes(carved_vals, field_vals, hull_grid.lo, hull_grid.voxel,
                                         views, images.float_masks(), cfg.mask_threshold)
    carved = (field_vals > 0) & (carved_vals <= 0)
    n_hull = max(int((field_vals > 0).sum()), 1)
    say(f"mvs: carved {carved.sum() / n_hull:.1%} of the hull; {kept['restored_nodes']} nodes given back "
        f"to keep the silhouettes covered")
    rep.mvs = {**mres.stats, "carved_fraction_of_hull": float(carved.sum() / n_hull),
               "image_size": [mimgs.cameras.width, mimgs.cameras.height], "silhouettes": kept}
    rep.timings["mvs"] = time.perf_counter() - t0
    return carved_vals


def _fit_density(images: ImageSet, hull_grid, px_per_voxel: float, lo, hi, field_vals, field_lo, field_voxel,
                 background, cfg: ScaffoldConfig, rep: ScaffoldReport, check, say):
    """Stage "density": a density grid fitted to the photos (inside the hull when there is one, which
    it then cuts).  Returns the field (values, lo, voxel)."""
    from .density import fit_density

    t0 = time.perf_counter()
    check("density", 0.0)
    if hull_grid is not None:
        allowed = hull_grid.values > -3.0 * max(px_per_voxel, 1.0)
        init_inside = hull_grid.values > 0
        g_lo, g_vox = hull_grid.lo, hull_grid.voxel
    else:
        res = 96
        g_vox = float((hi - lo).max() / res)
        dims = [max(2, int(math.ceil((hi[i] - lo[i]) / g_vox)) + 1) for i in range(3)]
        allowed = np.ones(dims, bool)
        init_inside = np.zeros(dims, bool)
        g_lo = lo.astype(np.float32)
    dimgs = _resize_for_density(images, cfg.density_max_image_side)
    dres = fit_density(dimgs, allowed, init_inside, g_lo, g_vox,
                       resolutions=tuple(cfg.density_resolutions), iters=tuple(cfg.density_iters),
                       batch_rays=cfg.density_batch_rays, background=background,
                       use_masks=images.masks is not None, lr=cfg.density_lr, seed=cfg.seed,
                       check=lambda f: check("density", f), log=say)
    thr = -math.log(1.0 - cfg.density_iso_alpha)
    dfield = np.log(np.maximum(dres.sigma, 1e-6) / thr)
    if field_vals is not None:
        # bring the density field onto the hull grid and intersect (min) with the hull
        d_on_hull = torch.nn.functional.interpolate(
            torch.from_numpy(dfield.astype(np.float32))[None, None], size=tuple(field_vals.shape),
            mode="trilinear", align_corners=True)[0, 0].numpy()
        field_vals = np.minimum(field_vals, np.clip(d_on_hull, -6.0, 6.0))
    else:
        field_vals, field_lo, field_voxel = np.clip(dfield, -6.0, 6.0), dres.lo, dres.voxel
    rep.density = {"iterations": dres.iterations, "final_loss": dres.final_loss,
                   "final_psnr": dres.final_psnr, "rays_per_sec": dres.rays_per_sec,
                   "grid": list(dres.sigma.shape), "iso_sigma_per_voxel": thr,
                   "image_size": [dimgs.cameras.width, dimgs.cameras.height]}
    rep.timings["density"] = time.perf_counter() - t0
    return field_vals, field_lo, field_voxel


def _extract_mesh(field_vals, field_lo, field_voxel, method: str, cfg: ScaffoldConfig, rep: ScaffoldReport, check):
    """Stage "mesh": the field's zero level set at about ``cfg.target_vertices`` vertices."""
    from .meshing import extract_with_target

    t0 = time.perf_counter()
    check("mesh", 0.0)
    mesh, info = extract_with_target(field_vals.astype(np.float32), 0.0, field_lo, field_voxel,
                                     cfg.target_vertices, cfg.min_component_fraction,
                                     max_grid_nodes=int(cfg.max_mesh_grid) ** 3,
                                     check=lambda f: check("mesh", f))
    rep.meshing = info
    if mesh.num_vertices == 0 or len(mesh.faces) == 0:
        raise ScaffoldError(
            "the reconstructed surface has no faces: the occupancy is empty at this iso level. "
            + ("Lower density_iso_alpha or use method 'hull'; " if method != "hull" else "")
            + "check masks/poses, raise mask_tolerance or hull_dilate_px, or raise hull_resolution "
              "for very thin objects")
    _check_size(mesh, cfg, rep, "lower target_vertices (--vertices) or hull_resolution (--resolution)")
    rep.timings["mesh"] = time.perf_counter() - t0
    check("mesh", 1.0)
    return mesh


def _check_size(mesh, cfg: ScaffoldConfig, rep: ScaffoldReport, lower: str) -> None:
    """Refuse a scaffold over ``cfg.max_faces`` (saying what to ``lower``); record its size."""
    if len(mesh.faces) > cfg.max_faces:
        raise ScaffoldError(
            f"the scaffold has {len(mesh.faces)} faces (> max_faces={cfg.max_faces}); {lower}, or raise "
            "max_faces (--max-faces) if you want a scaffold this large (about 2 faces per vertex)")
    rep.num_vertices, rep.num_faces = int(mesh.num_vertices), int(len(mesh.faces))


def _metrics(mesh, images: ImageSet, reference_mesh, cfg: ScaffoldConfig, rep: ScaffoldReport, check) -> None:
    """Stage "metrics": silhouette IoU against the masks, Chamfer distance to the reference mesh."""
    t0 = time.perf_counter()
    if cfg.compute_iou and images.masks is not None:
        from .quality import silhouette_iou

        check("metrics", 0.0)
        iou = silhouette_iou(mesh, images.cameras, images.float_masks(), cfg.mask_threshold, cfg.iou_views or None)
        rep.silhouette_iou = {k: v for k, v in iou.items() if k != "per_view"}
        rep.silhouette_iou["worst_view"] = int(np.argmin(iou["per_view"])) if not cfg.iou_views else None
    if cfg.chamfer_samples and reference_mesh and os.path.isfile(reference_mesh):
        from .quality import chamfer_distance

        check("metrics", 0.5)
        ref = load_mesh(reference_mesh)
        ch = chamfer_distance(mesh, ref, cfg.chamfer_samples, seed=cfg.seed)
        diag = float(np.linalg.norm(ref.bbox()[1] - ref.bbox()[0]))
        ch["relative"] = ch["chamfer"] / max(diag, 1e-12)
        ch["reference"] = reference_mesh
        rep.chamfer = ch
    check("metrics", 1.0)
    rep.timings["metrics"] = time.perf_counter() - t0


def _fused(images: ImageSet, box, bbox, cfg: ScaffoldConfig, rep: ScaffoldReport, check, say, t_all: float):
    """Method "fusion" (``fusion.py``): the surface of photos without masks, inside ``box``."""
    from ..data.frame import ObjectBox
    from .fusion import build_fused_scaffold

    if box is None:
        box = ObjectBox.from_aabb(bbox)
    dimgs = _resize_for_density(images, cfg.density_max_image_side)
    built = build_fused_scaffold(dimgs, box, cfg, cfg.fusion, check=check, log=say)
    mesh = built.mesh
    rep.bbox = [box.aabb()[0].tolist(), box.aabb()[1].tolist()]
    rep.density, rep.fusion, rep.meshing = built.report["density"], built.report["fusion"], built.report["meshing"]
    rep.timings.update(built.report["timings"])
    rep.background = built.background
    if mesh.num_vertices == 0 or len(mesh.faces) == 0:
        raise ScaffoldError("the photos agree on no surface inside the object box: check that the box holds the "
                            "object (--box) and that the poses belong to the photos")
    _check_size(mesh, cfg, rep, "lower target_vertices (--vertices)")
    check("metrics", 1.0)
    rep.timings["total"] = time.perf_counter() - t_all
    return mesh, rep


def one_sided_capture(cams, threshold: float = 0.7) -> bool:
    """True when the views look at the object from one side (like DTU) rather than from all around
    (like NeRF-synthetic): the mean unit direction from the cameras' meeting point to the camera
    centres is long (~0 all around, ~0.5 for a hemisphere, ~0.9 for a 50-degree cone)."""
    c, _ = axes_meeting_point(cams)
    d = cams.centres.astype(np.float64) - c[None]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return bool(np.linalg.norm(d.mean(0)) > threshold)
