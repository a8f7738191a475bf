"""Pure-torch occupancy grid: initialised from the scaffold, refined from densities during training.

The field has zero density farther than ``radius`` from every vertex, so the *mesh mask* (cells within
``radius`` of a vertex, a conservative box dilation of the vertex splat) bounds everything the marcher
needs to look at.  Training then prunes mesh-mask cells whose density stays below a threshold.
"""
from __future__ import annotations

import math
from typing import Callable, Optional

import torch
import torch.nn.functional as F

from ..device import draw_device


class OccupancyGrid:
    """A dense boolean grid over an axis-aligned box.

    aabb (2,3); resolution (3,) cells per axis (cubic cells); ``occ`` (X,Y,Z) bool; ``mesh_mask``
    the conservative mask from the scaffold; ``density`` an EMA of observed max densities (-1 = unseen).
    """

    def __init__(self, aabb: torch.Tensor, resolution, mesh_mask: torch.Tensor):
        self.aabb = aabb.float()
        self.resolution = torch.as_tensor(resolution, dtype=torch.long, device=aabb.device)
        self.mesh_mask = mesh_mask
        self.occ = mesh_mask.clone()
        self.density = torch.full(mesh_mask.shape, -1.0, device=aabb.device)
        self.cell = (self.aabb[1] - self.aabb[0]) / self.resolution.float()

    # ------------------------------------------------------------------ construction
    @staticmethod
    def _layout(vertices: torch.Tensor, radius: float, max_res: int):
        lo = vertices.min(0).values
        hi = vertices.max(0).values
        extent = (hi - lo).max().item() + 2 * radius
        cell = extent / max_res
        pad = radius + cell
        lo = lo - pad
        hi = hi + pad
        res = torch.clamp(torch.ceil((hi - lo) / cell), min=1).long()
        hi = lo + res.float() * cell
        return torch.stack([lo, hi]), res

    @staticmethod
    def _flat_index(ijk: torch.Tensor, res) -> torch.Tensor:
        """(...,3) in-range cell indices -> (...) index into the flattened (X,Y,Z) grid."""
        ry, rz = int(res[1]), int(res[2])
        return (ijk[..., 0] * ry + ijk[..., 1]) * rz + ijk[..., 2]

    @staticmethod
    def _splat(vertices: torch.Tensor, aabb: torch.Tensor, res: torch.Tensor):
        """(X,Y,Z) bool grid of the cells holding a vertex, and the per-axis cell size."""
        cell = (aabb[1] - aabb[0]) / res.float()
        ijk = torch.floor((vertices - aabb[0]) / cell).long()
        ijk = torch.minimum(torch.maximum(ijk, torch.zeros_like(ijk)), res - 1)
        rx, ry, rz = (int(v) for v in res.tolist())
        grid = torch.zeros(rx * ry * rz, dtype=torch.bool, device=vertices.device)
        grid[OccupancyGrid._flat_index(ijk, res)] = True
        return grid.view(rx, ry, rz), cell

    @staticmethod
    def mask_from_vertices(vertices: torch.Tensor, aabb: torch.Tensor, res: torch.Tensor,
                           radius: float) -> torch.Tensor:
        """Cells that can contain a point within ``radius`` of some vertex (box dilation, conservative).

        The dilation is separable: along each axis a cell is set when any cell within r cells of it is,
        computed as an OR of the 2r+1 shifted copies of the boolean grid (r is a few cells, so this
        reads the grid a few times; :func:`mask_from_vertices_reference` is the max-pool form)."""
        grid, cell = OccupancyGrid._splat(vertices, aabb, res)
        r_cells = [int(math.ceil(radius / float(c))) for c in cell.tolist()]
        for axis, r in enumerate(r_cells):
            n = grid.shape[axis]
            r = min(r, n - 1)
            if r <= 0:
                continue
            out = grid.clone()
            for s in range(1, r + 1):   # cell i takes cells i - s and i + s
                out.narrow(axis, s, n - s).logical_or_(grid.narrow(axis, 0, n - s))
                out.narrow(axis, 0, n - s).logical_or_(grid.narrow(axis, s, n - s))
            grid = out
        return grid

    @staticmethod
    def mask_from_vertices_reference(vertices: torch.Tensor, aabb: torch.Tensor, res: torch.Tensor,
                                     radius: float) -> torch.Tensor:
        """Plain reference of :meth:`mask_from_vertices`: 3D max pooling of the vertex splat."""
        grid, cell = OccupancyGrid._splat(vertices, aabb, res)
        rx, ry, rz = grid.shape
        grid = grid.float().view(1, 1, rx, ry, rz)
        r_cells = [int(math.ceil(radius / float(c))) for c in cell.tolist()]
        for axis, r in enumerate(r_cells):
            if r <= 0:
                continue
            k = [1, 1, 1]
            k[axis] = 2 * r + 1
            p = [0, 0, 0]
            p[axis] = r
            grid = F.max_pool3d(grid, kernel_size=tuple(k), stride=1, padding=tuple(p))
        return grid.view(rx, ry, rz) > 0.5

    @classmethod
    def from_vertices(cls, vertices: torch.Tensor, radius: float, max_res: int = 128) -> "OccupancyGrid":
        aabb, res = cls._layout(vertices, radius, max_res)
        return cls(aabb, res, cls.mask_from_vertices(vertices, aabb, res, radius))

    def rebuild_from_vertices(self, vertices: torch.Tensor, radius: float,
                              carried_points: Optional[torch.Tensor] = None) -> None:
        """Re-initialise for moved vertices (box and mesh mask recomputed; densities forgotten).

        ``carried_points``: centres of the cells that were occupied before the move, moved along with
        the surface; when given, occupancy is limited to their cells (dilated by one cell) within the new
        mesh mask, so pruning learnt in the rest pose survives a deformation.
        """
        max_res = int(self.resolution.max().item())
        aabb, res = self._layout(vertices, radius, max_res)
        self.__init__(aabb, res, self.mask_from_vertices(vertices, aabb, res, radius))
        if carried_points is not None:
            carried = self.mask_from_vertices(carried_points, aabb, res, float(self.cell.max()))
            self.occ = self.mesh_mask & carried

    def occupied_centres(self) -> torch.Tensor:
        """(C,3) centres of occupied cells."""
        return self.cell_centres(self.occ.reshape(-1).nonzero().squeeze(1))

    @property
    def refined(self) -> bool:
        """True once densities pruned anything below the mesh mask."""
        return bool((self.density >= 0).any()) and not torch.equal(self.occ, self.mesh_mask)

    # ------------------------------------------------------------------ state
    def state(self) -> dict:
        return {"aabb": self.aabb.clone(), "resolution": self.resolution.clone(),
                "mesh_mask": self.mesh_mask.clone(), "occ": self.occ.clone(), "density": self.density.clone()}

    def load_state(self, s: dict) -> None:
        self.aabb = s["aabb"].float().to(self.aabb.device)
        self.resolution = s["resolution"].long().to(self.aabb.device)
        self.cell = (self.aabb[1] - self.aabb[0]) / self.resolution.float()
        self.mesh_mask = s["mesh_mask"].bool().to(self.aabb.device)
        self.occ = s["occ"].bool().to(self.aabb.device)
        self.density = s["density"].float().to(self.aabb.device)

    def to(self, device) -> "OccupancyGrid":
        for name in ("aabb", "resolution", "mesh_mask", "occ", "density", "cell"):
            setattr(self, name, getattr(self, name).to(device))
        return self

    # ------------------------------------------------------------------ queries
    def lookup(self, points: torch.Tensor) -> torch.Tensor:
        """(...,3) points -> (...) bool occupancy (False outside the box)."""
        rel = (points - self.aabb[0]) / self.cell
        ijk = torch.floor(rel).long()
        inside = ((ijk >= 0) & (ijk < self.resolution)).all(-1)
        ijk = torch.minimum(torch.maximum(ijk, torch.zeros_like(ijk)), self.resolution - 1)
        return self.occ.reshape(-1)[self._flat_index(ijk, self.resolution)] & inside

    def cell_coordinates(self, origins: torch.Tensor, dirs: torch.Tensor):
        """Rays in the grid's cell coordinates: (g_o, g_d) with the point at distance t in the cell
        ``floor(g_o + g_d t)`` (:meth:`lookup_steps`)."""
        inv = 1.0 / self.cell
        return (origins - self.aabb[0]) * inv, dirs * inv

    def lookup_steps(self, g_o: torch.Tensor, g_d: torch.Tensor, ts: torch.Tensor) -> torch.Tensor:
        """Occupancy of the points at distances ``ts`` (R,W) along rays given in cell coordinates
        (:meth:`cell_coordinates`, (R,3) each) -> (R,W) bool.  Points outside the box read the nearest
        boundary cell (the marcher masks them by the ray's box interval).  The marcher's fast form of
        :meth:`lookup` (which is the reference): no world points, int32 cell indices."""
        res = self.resolution.to(torch.int32)
        ijk = torch.floor(g_o[:, None, :] + g_d[:, None, :] * ts[..., None]).to(torch.int32)
        ijk = torch.minimum(ijk.clamp_min_(0), res - 1)
        return self.occ.reshape(-1)[self._flat_index(ijk, res)]

    @staticmethod
    def _slab(origins: torch.Tensor, dirs: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor):
        """Entry/exit distances of rays (...,3) with boxes [lo, hi] (...,3), broadcast together (the
        slab test); exit < entry where a ray misses its box."""
        inv = 1.0 / torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
        t0 = (lo - origins) * inv
        t1 = (hi - origins) * inv
        return torch.minimum(t0, t1).max(-1).values, torch.maximum(t0, t1).min(-1).values

    def ray_aabb(self, origins: torch.Tensor, dirs: torch.Tensor):
        """Entry/exit distances of rays with the grid box; t_far < t_near where a ray misses."""
        return self._slab(origins, dirs, self.aabb[0], self.aabb[1])

    def camera_ranges(self, K, c2w, width: int, height: int, tile: int = 8):
        """Where each pixel's ray can meet an occupied cell: per-pixel distances (near, far), each
        (height*width,) float32 on the grid's device, with near > far (inf, -inf) for pixels whose rays
        meet no occupied cell -- or None when an occupied cell reaches behind the camera (no bound).

        Conservative screen-space splat: each occupied cell (of the grid max-pooled by a power of two
        while its cells stay under a tile on screen) is bounded by the sphere through its corners; the
        sphere's pixel box (interval arithmetic on x/z and y/z of the camera-aligned cube around it),
        widened by a pixel and rounded out to ``tile`` x ``tile`` tiles, takes the interval [distance
        to the centre - radius, distance + radius], and each tile keeps the smallest near and the
        largest far over its cells.  A point of a ray lies at distance t = |x - o|, so no occupied point
        of a pixel's ray lies outside its tile's interval (at any sub-pixel position of the ray).
        :meth:`camera_ranges_reference` is the exact per-ray form.  K (3,3) pixels (skew allowed),
        c2w (4,4) OpenCV.
        """
        dev = self.aabb.device
        K = torch.as_tensor(K, dtype=torch.float32, device=dev)
        c2w = torch.as_tensor(c2w, dtype=torch.float32, device=dev)
        R, o = c2w[:3, :3], c2w[:3, 3]
        tile = max(1, int(tile))
        tw, th = -(-width // tile), -(-height // tile)
        near = torch.full((th * tw,), float("inf"), device=dev)
        far = torch.full((th * tw,), float("-inf"), device=dev)
        # pool while a pooled cell stays within a tile on screen (seen from the box's nearest point)
        gap = float(torch.maximum(self.aabb[0] - o, o - self.aabb[1]).clamp_min(0).norm())
        depth = gap + 0.5 * float((self.aabb[1] - self.aabb[0]).norm())
        px = float(torch.maximum(K[0, 0].abs(), K[1, 1].abs())) * float(self.cell.max()) / max(depth, 1e-9)
        f = 1
        while 2 * f * px <= tile and 2 * f < int(self.resolution.max()):
            f *= 2
        centres, rho = self._pooled_cells(f)
        if len(centres):
            cam = (centres - o) @ R                             # (C,3) camera coordinates (OpenCV)
            z_lo = cam[:, 2] - rho
            if bool((z_lo <= 1e-6).any()):
                return None
            z_hi = cam[:, 2] + rho

            def ratio_bounds(c):   # min and max of (c +- rho) / z over z in [z_lo, z_hi] (z > 0)
                lo, hi = c - rho, c + rho
                return (torch.minimum(lo / z_lo, lo / z_hi), torch.maximum(hi / z_lo, hi / z_hi))

            (xa, xb), (ya, yb) = ratio_bounds(cam[:, 0]), ratio_bounds(cam[:, 1])
            fx, sk, cx, fy, cy = (float(K[0, 0]), float(K[0, 1]), float(K[0, 2]), float(K[1, 1]), float(K[1, 2]))
            # u = fx x/z + sk y/z + cx (fx, fy > 0): bound each term over its interval
            u_lo = fx * xa + torch.minimum(sk * ya, sk * yb) + cx
            u_hi = fx * xb + torch.maximum(sk * ya, sk * yb) + cx
            v_lo, v_hi = fy * ya + cy, fy * yb + cy
            on = (u_hi >= -1) & (u_lo <= width + 1) & (v_hi >= -1) & (v_lo <= height + 1)
            dist = cam.norm(dim=-1)
            c_near, c_far = (dist - rho).clamp_min(0), dist + rho
            u_lo, u_hi, v_lo, v_hi, c_near, c_far = (t[on] for t in (u_lo, u_hi, v_lo, v_hi, c_near, c_far))
            # tiles under the pixel box [floor(lo - 1), floor(hi + 1)], clipped to the image
            x0 = torch.div((u_lo - 1).floor().clamp(0, width - 1).long(), tile, rounding_mode="floor")
            x1 = torch.div((u_hi + 1).floor().clamp(0, width - 1).long(), tile, rounding_mode="floor")
            y0 = torch.div((v_lo - 1).floor().clamp(0, height - 1).long(), tile, rounding_mode="floor")
            y1 = torch.div((v_hi + 1).floor().clamp(0, height - 1).long(), tile, rounding_mode="floor")
            nx = x1 - x0 + 1
            cnt = nx * (y1 - y0 + 1)
            total = int(cnt.sum())
            if total:
                cid = torch.repeat_interleave(torch.arange(len(cnt), device=dev), cnt, output_size=total)
                within = torch.arange(total, device=dev) - (torch.cumsum(cnt, 0) - cnt)[cid]
                nxc = nx[cid]
                t_idx = (y0[cid] + torch.div(within, nxc, rounding_mode="floor")) * tw + x0[cid] + within % nxc
                near.scatter_reduce_(0, t_idx, c_near[cid], "amin")
                far.scatter_reduce_(0, t_idx, c_far[cid], "amax")
        # tiles -> pixels, widened by a small fraction of a cell against rounding at cell borders
        pad = 0.01 * float(self.cell.min())
        rows = torch.arange(height, device=dev) // tile
        cols = torch.arange(width, device=dev) // tile
        t_of_px = (rows[:, None] * tw + cols[None, :]).reshape(-1)
        return near[t_of_px] - pad, far[t_of_px] + pad

    def _pooled_cells(self, f: int):
        """Centres (C,3) of the occupied cells of the grid max-pooled by ``f``, and the radius of the
        sphere through a pooled cell's corners; cached until ``occ`` is replaced or written."""
        key = (id(self.occ), self.occ.data_ptr(), self.occ._version, f, self.aabb.data_ptr())
        cache = self.__dict__.setdefault("_pooled_cache", {})
        if cache.get("key") != key:
            cache.clear()
            cache["key"] = key
        if f not in cache:
            occ = self.occ
            if f > 1:
                occ = F.max_pool3d(occ[None, None].float(), f, f, ceil_mode=True)[0, 0] > 0
            ijk = occ.nonzero()
            size = self.cell * f
            lo = self.aabb[0] + ijk.float() * size
            hi = torch.minimum(lo + size, self.aabb[1])
            cache[f] = ((lo + hi) * 0.5, 0.5 * float(size.norm()) * 1.0001)
        return cache[f]

    def camera_ranges_reference(self, origins: torch.Tensor, dirs: torch.Tensor):
        """Exact per-ray form of :meth:`camera_ranges` (slab test of every ray against every occupied
        cell; small grids only): (near, far) (R,) of the cells each ray meets (inf, -inf where none)."""
        idx = self.occ.reshape(-1).nonzero().squeeze(1)
        lo = self.cell_centres(idx) - 0.5 * self.cell
        t_in, t_out = self._slab(origins[:, None], dirs[:, None], lo[None], (lo + self.cell)[None])
        t_in = t_in.clamp_min(0)
        hit = t_out >= t_in
        near = torch.where(hit, t_in, torch.full_like(t_in, float("inf"))).min(1).values
        far = torch.where(hit, t_out, torch.full_like(t_out, float("-inf"))).max(1).values
        return near, far

    def cell_centres(self, flat_idx: torch.Tensor) -> torch.Tensor:
        ry, rz = int(self.resolution[1]), int(self.resolution[2])
        i = torch.div(flat_idx, ry * rz, rounding_mode="floor")
        j = torch.div(flat_idx, rz, rounding_mode="floor") % ry
        k = flat_idx % rz
        return self.aabb[0] + (torch.stack([i, j, k], -1).float() + 0.5) * self.cell

    @property
    def occupied_fraction(self) -> float:
        return float(self.occ.float().mean())

    # ------------------------------------------------------------------ refresh
    @torch.no_grad()
    def refresh(self, sigma_fn: Callable[[torch.Tensor], torch.Tensor], step_size: float,
                alpha_threshold: float = 0.005, decay: float = 0.95, max_cells: Optional[int] = 65536,
                generator: Optional[torch.Generator] = None, chunk: int = 65536) -> None:
        """Update densities of (a random subset of) mesh-mask cells at jittered points; prune cells whose
        decayed max density gives an alpha below ``alpha_threshold`` over one marching step."""
        cand = self.mesh_mask.reshape(-1).nonzero().squeeze(1)
        if len(cand) == 0:
            return
        if max_cells is not None and len(cand) > max_cells:
            # draws come from the generator's device (a CPU generator gives the same cells on any device)
            pick = torch.randperm(len(cand), device=draw_device(generator, cand), generator=generator)
            cand = cand[pick[:max_cells].to(cand.device)]
        dens = self.density.reshape(-1)
        for s in range(0, len(cand), chunk):
            c = cand[s:s + chunk]
            jitter = torch.rand(len(c), 3, device=draw_device(generator, c), generator=generator).to(c.device) - 0.5
            x = self.cell_centres(c) + jitter * self.cell
            sigma = sigma_fn(x).float()
            old = dens[c]
            dens[c] = torch.where(old < 0, sigma, torch.maximum(old * decay, sigma))
        threshold = -math.log(1.0 - alpha_threshold) / step_size
        seen = self.density >= 0
        self.occ = self.mesh_mask & (~seen | (self.density > threshold))
