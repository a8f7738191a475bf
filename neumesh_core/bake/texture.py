"""Bake a field into a plain UV-textured mesh (a native asset for Blender's Cycles/EEVEE, OBJ, glTF).

The mesh is the scaffold in its *current* pose (``field.vertices``: edited and deformed), or any target
mesh lying near the field's surface (``mesh=``: e.g. a decimated copy, :func:`decimate`), unwrapped by
xatlas.  Each texel inside a chart gets its surface point and interpolated normal; the texel's colour is
what the field renders on a short ray that starts ``offset`` x radius outside the surface and looks
along -normal (volume rendering over at most 2 x offset, so the colour is the one a camera looking
straight at that spot sees, and a surface behind it is not reached).  With ``directions > 1`` the
colour is the mean over that many rays: -normal plus rays tilted by ``cone_deg`` around it (averages
view-dependent highlights out; see docs/baking.md for the measured effect).  Chart borders are dilated
by ``padding`` texels so bilinear sampling and mip-maps do not pull in the empty background.

The field's colour already holds the lighting of the photos: the baked texture is "baked light".
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field as dc_field
from typing import Callable, Optional

import numpy as np
import torch

from ..errors import NeuMeshError
from .simplify import decimate  # noqa: F401  (kept importable from here)
from .uv import dilate, texel_coverage, unwrap


@dataclass
class BakeResult:
    """A UV-textured copy of the field's scaffold in its current pose."""

    vertices: np.ndarray        # (M,3) float32 world positions (atlas vertices: seams split vertices)
    faces: np.ndarray           # (F,3) int32 indices into ``vertices`` (the mesh's faces, same order)
    uvs: np.ndarray             # (M,2) float32 in [0,1]; u right, v up (v=1 is the image's first row)
    vertex_index: np.ndarray    # (M,) int64: the mesh vertex each atlas vertex is a copy of (the
                                # field's vertex, or the target mesh's with ``mesh=``)
    texture: np.ndarray         # (H,W,3) float32 in [0,1], padded
    mask: np.ndarray            # (H,W) bool: texels inside a chart triangle
    vertex_colours: Optional[np.ndarray] = None   # (N,3) per mesh vertex (same rays at the vertices)
    seconds: float = 0.0
    info: dict = dc_field(default_factory=dict)

    @property
    def resolution(self) -> int:
        return int(self.texture.shape[0])


def _cancel(progress, fraction):
    if progress is not None and progress(float(fraction)) is False:
        from ..render.renderer import Cancelled

        raise Cancelled("baking cancelled; nothing was written")


def _tangent_dirs(n: torch.Tensor, count: int, cone_deg: float) -> list:
    """Unit view directions looking *into* the surface: -n, then count-1 tilted by cone_deg around it."""
    dirs = [-n]
    if count <= 1:
        return dirs
    ref = torch.where((n[:, 2].abs() < 0.9)[:, None], torch.tensor([0.0, 0.0, 1.0]), torch.tensor([1.0, 0.0, 0.0]))
    t1 = torch.nn.functional.normalize(torch.cross(n, ref, dim=1), dim=1)
    t2 = torch.cross(n, t1, dim=1)
    a = math.radians(cone_deg)
    for k in range(count - 1):
        phi = 2 * math.pi * k / (count - 1)
        d = -math.cos(a) * n + math.sin(a) * (math.cos(phi) * t1 + math.sin(phi) * t2)
        dirs.append(d)
    return dirs


@torch.no_grad()
def surface_colours(field, points, normals, offset: float = 1.0, directions: int = 1, cone_deg: float = 30.0,
                    chunk: int = 32768, progress: Optional[Callable[[float], bool]] = None,
                    span: tuple = (0.0, 1.0), return_found: bool = False):
    """(n,3) the field's colour at surface points seen along -normal (mean over ``directions`` rays).

    With ``return_found`` also (n,) bool: False where no ray met density and the point itself has no
    scaffold vertex within the field radius (its colour is then 0: the field is empty there)."""
    from ..render.renderer import RenderSettings, default_step
    from ..render.volume import composite
    from ..sampling.marcher import march_rays

    settings = RenderSettings()
    p = torch.as_tensor(np.asarray(points, np.float32))
    nrm = torch.nn.functional.normalize(torch.as_tensor(np.asarray(normals, np.float32)), dim=1)
    dev = field.geo_codes.device
    d0 = float(offset) * field.radius
    step = default_step(field, settings)
    out = torch.zeros(len(p), 3)
    found = torch.ones(len(p), dtype=torch.bool)
    n_total = max(1, len(p))
    for s in range(0, len(p), chunk):
        pc, nc = p[s:s + chunk], nrm[s:s + chunk]
        acc = torch.zeros(len(pc), 3)
        wsum = torch.zeros(len(pc))
        for d in _tangent_dirs(nc, directions, cone_deg):
            # start outside the surface along the normal, looking along d (into the surface)
            o = (pc - d * (d0 / torch.clamp((-d * nc).sum(1, keepdim=True), min=0.2))).to(dev)
            dd = d.to(dev)
            far = 2.0 * d0 / math.cos(math.radians(cone_deg)) if directions > 1 else 2.0 * d0
            smp = march_rays(o, dd, field.grid, field.sigma_fn, step, near=0.0, far=far,
                             window=settings.window, early_stop_eps=settings.early_stop_eps,
                             weight_threshold=settings.weight_threshold)
            if len(smp) == 0:
                continue
            _, rgb, _ = field.decode(smp.aux, dd[smp.ray_indices], with_rgb=True, with_sigma=False)
            c = composite(smp.ray_indices, smp.t_starts, smp.t_ends, smp.sigmas, {"rgb": rgb}, len(o))
            op = c["opacity"].cpu()
            atlas = getattr(field, "paint_atlas", None)
            if atlas is not None and not atlas.is_empty:   # texel paint bakes with the field's colour
                depth = torch.where(c["opacity"] > 1e-6, c["depth"] / c["opacity"].clamp_min(1e-6),
                                    torch.full_like(c["depth"], float("inf")))
                c["rgb"] = atlas.composite(field, o, dd, c["rgb"], c["opacity"], depth)
            acc += c["rgb"].cpu()
            wsum += op
        ok = wsum > 1e-3
        col = torch.zeros(len(pc), 3)
        col[ok] = acc[ok] / wsum[ok, None]
        # where no ray met density (a hole in the field), fall back to a point query on the surface
        if (~ok).any():
            x = (pc[~ok] + 0.3 * field.radius * nc[~ok]).to(dev)
            nb = field.neighbourhood(x)
            _, rgb, _ = field.decode(nb, (-nc[~ok]).to(dev), with_rgb=True, with_sigma=False)
            col[~ok] = rgb.cpu()
            miss = torch.zeros(len(pc), dtype=torch.bool)
            miss[~ok] = ~nb.valid.any(1).cpu()
            found[s:s + chunk] = ~miss
        out[s:s + chunk] = col.clamp(0, 1)
        _cancel(progress, span[0] + (span[1] - span[0]) * min(1.0, (s + chunk) / n_total))
    if return_found:
        return out.numpy(), found.numpy()
    return out.numpy()


def _target_mesh(field, mesh):
    """(vertices, faces, normals, label) of the mesh to bake onto: the scaffold in its current pose when
    ``mesh`` is None, else ``mesh`` (an ``nm.Mesh`` or a (vertices, faces) pair, world space)."""
    from ..mesh import vertex_normals

    if mesh is None:
        V = np.asarray(field.vertices, np.float32)
        F = field.faces.cpu().numpy().astype(np.int64)
        N = field.scaffold.normals.detach().cpu().numpy().astype(np.float32)
        return V, F, N, "scaffold"
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        V, F = mesh.vertices, mesh.faces
    else:
        V, F = mesh
    V = np.ascontiguousarray(np.asarray(V, np.float32).reshape(-1, 3))
    F = np.ascontiguousarray(np.asarray(F, np.int64).reshape(-1, 3))
    if len(V) < 3 or len(F) < 1:
        raise ValueError("the target mesh has no triangles")
    if F.min() < 0 or F.max() >= len(V):
        raise ValueError("the target mesh's face indices are out of range of its vertices")
    N = np.asarray(vertex_normals(V, F), np.float32)
    return V, F, N, "target"


FIELD_FACES = 0.2   # mesh="field" without an ExtractConfig: decimated to this x the scaffold's faces
                    # (finer gains nothing on lego, coarser loses: docs/baking.md, the experiment log)


def bake_texture(field, resolution: int = 1024, padding: int = 4, offset: Optional[float] = None,
                 directions: int = 1, cone_deg: float = 30.0, vertex_colours: bool = True, chunk: int = 32768,
                 progress: Optional[Callable[[float], bool]] = None, mesh="field", fit=None,
                 measure_texels: int = 65536, colours: str = "views", project=None,
                 extract=None) -> BakeResult:
    """Bake the field's view-independent appearance into a UV texture of a mesh.

    Defaults: ``mesh="field"`` decimated to ``FIELD_FACES`` x the scaffold's faces and
    ``colours="views"``, the bake closest to the field (figures in docs/benchmarks.md, "Baking lego");
    ``mesh=None, colours="rays"`` is the quicker scaffold bake.

    ``mesh``: the mesh to bake onto: None = the field's scaffold in its current pose (edited,
    deformed); else an ``nm.Mesh`` or (vertices, faces) in world space lying near the field's surface,
    e.g. a decimated copy of the scaffold (:func:`decimate`).  Each texel's ray starts ``offset`` field
    radii out along the mesh's normal and looks back along it over 2 x offset radii, so a mesh that
    lies off the field's surface by less than that still sees it.  Texels whose ray meets no density
    and that lie farther than a radius from every scaffold vertex (the field is empty there) are
    counted in ``info["missed_texels"]`` and filled from the nearest baked texels of their chart
    (dilation), or with the mean colour.
    ``resolution``: texture size (square); ``padding``: texels between charts and dilation of their
    borders; ``offset``: ray start outside the surface, in field radii; ``directions``/``cone_deg``: rays
    averaged per texel (1 = straight along -normal); ``vertex_colours``: also a colour per mesh vertex.
    ``mesh="field"``: a mesh extracted from the field's own density (marching cubes, then decimated:
    :func:`~neumesh_core.bake.extract.extract_surface` with ``extract``, an :class:`ExtractConfig`;
    None: the default config decimated to ``FIELD_FACES`` x the scaffold's face count; ``info["extract"]``).
    ``fit``: first move the mesh's vertices along their normals onto the surface the field renders
    (:func:`~neumesh_core.bake.surface.fit_to_field`; True = the default :class:`SurfaceFitConfig`, a
    config, or False to bake onto the mesh where it is; None = True except for ``mesh="field"``,
    which already lies on it).  The result's vertices are the moved ones.
    ``colours``: "rays" (each texel's short ray along -normal) or "views" (the field's renders from
    virtual cameras projected onto the texels that they see, :func:`~neumesh_core.bake.project.
    projected_colours` with ``project``, a :class:`ProjectConfig`; texels no view sees take their ray
    colour; ``info["texels_unseen"]``).
    ``offset`` None: 0.5 radii with ``fit`` (the rays stay short around the surface the mesh now lies
    on), else 1.
    ``measure_texels``: how many texels (a fixed random subset; 0 = none) measure how far the baked
    mesh lies from the field's surface along their normal: ``info["surface_offset"]``
    (:func:`~neumesh_core.bake.surface.offset_stats`: mean / median / p90 in world units and radii; the
    surface at the fit's opacity level, else 0.5).
    ``progress(fraction) -> False`` cancels (raises ``nm.Cancelled``).  Nothing in the field changes.
    """
    from .surface import offset_stats, surface_offsets

    t0 = time.perf_counter()
    resolution = int(resolution)
    if resolution < 16:
        raise ValueError(f"resolution must be at least 16, got {resolution}")
    if colours not in ("rays", "views"):
        raise ValueError(f"colours must be 'rays' or 'views', got {colours!r}")
    _cancel(progress, 0.0)
    V, F, N, label, fit_info, extract_info = _bake_mesh(field, mesh, fit, extract, progress)
    if offset is None:
        offset = 0.5 if fit_info is not None else 1.0
    t_unwrap = time.perf_counter()
    vmap, faces, uvs, info = unwrap(V, F, resolution, padding)
    info["unwrap_s"] = time.perf_counter() - t_unwrap
    if fit_info is not None:
        info["fit"] = fit_info
        info["fit_s"] = fit_info["seconds"]
    if extract_info is not None:
        info["extract"] = extract_info
        info["extract_s"] = extract_info["seconds"]
    info["mesh"] = label
    info["mesh_vertices"] = int(len(V))
    info["mesh_faces"] = int(len(F))
    _cancel(progress, 0.1)
    texel, pts, nrm = _texel_points(V, N, vmap, faces, uvs, resolution)
    info["texels"] = int(len(texel))
    if measure_texels and len(texel):
        pick = np.random.default_rng(0).permutation(len(texel))[:int(measure_texels)]
        level = fit_info["level"] if fit_info is not None else 0.5
        off = surface_offsets(field, pts[pick], nrm[pick], search=max(1.5, 1.5 * float(offset)), level=level)
        info["surface_offset"] = offset_stats(off, float(field.radius))
    _cancel(progress, 0.15)
    vspan = 0.1 if vertex_colours else 0.0
    rays = dict(offset=offset, directions=directions, cone_deg=cone_deg, chunk=chunk, progress=progress)
    cols, found = _texel_colours(field, V, F, pts, nrm, colours, project, rays, vspan, info)
    info["missed_texels"] = int((~found).sum())
    padded, mask, mean = _texture_image(texel, cols, found, resolution, padding)
    vc = None
    if vertex_colours:
        vc, vfound = surface_colours(field, V, N, offset, directions, cone_deg, chunk, progress,
                                     span=(0.85, 0.95), return_found=True)
        vc[~vfound] = mean
    res = BakeResult(vertices=V[vmap], faces=faces.astype(np.int32), uvs=uvs, vertex_index=vmap,
                     texture=padded, mask=mask, vertex_colours=vc, info=info)
    res.seconds = time.perf_counter() - t0
    res.info.update({"resolution": resolution, "padding": int(padding), "offset": float(offset),
                     "directions": int(directions), "cone_deg": float(cone_deg), "seconds": res.seconds})
    if progress is not None:
        progress(1.0)
    return res


def _bake_mesh(field, mesh, fit, extract, progress):
    """The mesh :func:`bake_texture` bakes onto, in world space: extracted from the field's density
    (``mesh="field"``), given, or the scaffold; moved onto the field's surface when ``fit`` says so.
    Returns (vertices, faces, normals, label, fit info or None, extract info or None)."""
    from .surface import SurfaceFitConfig, fit_to_field

    extract_info = None
    if isinstance(mesh, str):
        if mesh != "field":
            raise ValueError(f"mesh must be None, 'field', an nm.Mesh or (vertices, faces), got {mesh!r}")
        from .extract import ExtractConfig, extract_surface

        if extract is None:
            extract = ExtractConfig(faces=max(1, int(round(FIELD_FACES * len(field.faces)))))
        mesh, extract_info = extract_surface(field, extract, progress=None if progress is None else
                                             (lambda f: progress(0.1 * f)))
        if fit is None:
            fit = False
    V, F, N, label = _target_mesh(field, mesh)
    if extract_info is not None:
        label = "field"
    fit_info = None
    if fit is None:
        fit = True
    if fit is not False:
        cfg = fit if isinstance(fit, SurfaceFitConfig) else SurfaceFitConfig()
        V, fit_info = fit_to_field(field, V, F, cfg, progress=None if progress is None else
                                   (lambda f: progress(0.1 * f)))
        from ..mesh import vertex_normals

        N = np.asarray(vertex_normals(V, F), np.float32)
    return V, F, N, label, fit_info, extract_info


def _texel_points(V, N, vmap, faces, uvs, resolution: int):
    """The texels inside the atlas's triangles (flat ids), their surface points and interpolated
    normals (a face's own normal where the corners' normals cancel)."""
    texel, face, bary = texel_coverage(uvs, faces, resolution)
    corner = vmap[faces[face]]                      # (n,3) mesh vertex of each corner
    pts = (bary[..., None] * V[corner]).sum(1)
    nrm = (bary[..., None] * N[corner]).sum(1)
    bad = np.linalg.norm(nrm, axis=1) < 1e-8      # opposite normals cancelling: use the face normal
    if bad.any():
        fv = V[corner[bad]]
        nrm[bad] = np.cross(fv[:, 1] - fv[:, 0], fv[:, 2] - fv[:, 0])
    return texel, pts, nrm


def _texel_colours(field, V, F, pts, nrm, colours: str, project, rays: dict, vspan: float, info: dict):
    """The texels' colours and whether the field was found there: from the field's renders projected
    onto them ("views"; the texels no view sees from their rays) or from their rays ("rays")."""
    progress = rays["progress"]
    ray_args = (rays["offset"], rays["directions"], rays["cone_deg"], rays["chunk"], progress)
    if colours == "views":
        from .project import projected_colours

        t_proj = time.perf_counter()
        cols, wsum = projected_colours(field, V, F, pts, nrm, project, progress, span=(0.15, 0.75))
        unseen = wsum <= 0
        found = np.ones(len(pts), bool)
        if unseen.any():
            rc, rf = surface_colours(field, pts[unseen], nrm[unseen], *ray_args,
                                     span=(0.75, 0.95 - vspan), return_found=True)
            cols[unseen] = rc
            found[unseen] = rf
        info["texels_unseen"] = int(unseen.sum())
        info["project_s"] = time.perf_counter() - t_proj
        return cols, found
    return surface_colours(field, pts, nrm, *ray_args, span=(0.15, 0.95 - vspan), return_found=True)


def _texture_image(texel, cols, found, resolution: int, padding: int):
    """The texture: the texels' colours, chart borders dilated by ``padding`` texels, missed texels
    inside charts grown from their baked neighbours, the rest the mean colour.  Returns (image, mask of
    the texels inside charts, the mean colour)."""
    image = np.zeros((resolution * resolution, 3), np.float32)
    mask = np.zeros(resolution * resolution, bool)
    image[texel] = cols
    mask[texel] = True
    baked = np.zeros(resolution * resolution, bool)
    baked[texel[found]] = True
    image = image.reshape(resolution, resolution, 3)
    mask = mask.reshape(resolution, resolution)
    baked = baked.reshape(resolution, resolution)
    padded, grown = dilate(image, baked, max(1, padding))
    for _ in range(16):         # missed texels inside charts: grown from their baked neighbours too
        if not (mask & ~grown).any():
            break
        padded, grown = dilate(padded, grown, 4)
    mean = cols[found].mean(0) if found.any() else 0.0
    if (~grown).any():   # the rest of the image: the mean colour (keeps mip-maps from greying to black)
        padded[~grown] = mean
    return padded, mask, mean


def _replace(tmp: str, path: str) -> None:
    os.replace(tmp, path)


def save_bake(result: BakeResult, out_dir: str, name: str, glb: bool = True, protect=()) -> dict:
    """Write ``<name>.obj`` + ``<name>.mtl`` + ``<name>.png`` (+ ``<name>.glb`` with trimesh) in
    ``out_dir``.  Every file is written to a temporary name beside it and renamed, so a reader never
    sees half a file; paths in ``protect`` (e.g. the field file) are never written.  Returns the paths."""
    from ..imageio import save_image

    os.makedirs(out_dir, exist_ok=True)
    paths = {ext: os.path.join(out_dir, f"{name}.{ext}") for ext in ("obj", "mtl", "png")}
    if glb:
        paths["glb"] = os.path.join(out_dir, f"{name}.glb")
    guarded = {os.path.realpath(p) for p in protect}
    for p in paths.values():
        if os.path.realpath(p) in guarded:
            raise NeuMeshError(f"refusing to overwrite {p}: choose another --out folder or name")
    save_image(paths["png"], result.texture)   # atomic itself
    tmp = paths["mtl"] + ".tmp"
    with open(tmp, "w") as fh:
        fh.write(f"# NeuMesh bake\nnewmtl {name}\nKa 0 0 0\nKd 1 1 1\nKs 0 0 0\nillum 1\n"
                 f"map_Kd {name}.png\n")
    _replace(tmp, paths["mtl"])
    tmp = paths["obj"] + ".tmp"
    v, uv, f = result.vertices, result.uvs, result.faces.astype(np.int64) + 1
    with open(tmp, "w") as fh:
        fh.write(f"# NeuMesh bake: {len(v)} vertices, {len(f)} faces\nmtllib {name}.mtl\no {name}\n")
        np.savetxt(fh, v, fmt="v %.6f %.6f %.6f")
        np.savetxt(fh, uv, fmt="vt %.6f %.6f")
        fh.write(f"usemtl {name}\n")
        np.savetxt(fh, np.repeat(f, 2, axis=1), fmt="f %d/%d %d/%d %d/%d")
    _replace(tmp, paths["obj"])
    if glb:
        import trimesh
        from PIL import Image

        img = Image.fromarray((np.clip(result.texture, 0, 1) * 255 + 0.5).astype(np.uint8))
        mat = trimesh.visual.material.PBRMaterial(baseColorTexture=img, metallicFactor=0.0, roughnessFactor=1.0)
        mesh = trimesh.Trimesh(vertices=result.vertices, faces=result.faces, process=False,
                               visual=trimesh.visual.TextureVisuals(uv=result.uvs, material=mat))
        tmp = paths["glb"] + ".tmp"
        with open(tmp, "wb") as fh:
            fh.write(mesh.export(file_type="glb"))
        _replace(tmp, paths["glb"])
    return paths
