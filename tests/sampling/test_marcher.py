import numpy as np
import torch

from neumesh_core.data.cameras import intrinsics_from_fov, pixel_rays
from neumesh_core.render.volume import composite, composite_reference
from neumesh_core.sampling.marcher import march_rays, march_rays_reference
from neumesh_core.sampling.occupancy import OccupancyGrid

from ..conftest import textured_field


def _camera(res=24):
    K = intrinsics_from_fov(0.9, res, res)
    c2w = np.eye(4, dtype=np.float32)
    c2w[2, 3] = -3.5
    return pixel_rays(K, c2w, res, res)


def test_grid_mask_is_conservative(blob_mesh):
    v = torch.as_tensor(blob_mesh.vertices)
    r = 0.08
    grid = OccupancyGrid.from_vertices(v, r, 64)
    g = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(20000, 3, generator=g), dim=-1)
    pts = v[torch.randint(0, len(v), (20000,), generator=g)] + dirs * r * torch.rand(20000, 1, generator=g)
    assert grid.lookup(pts).all()
    assert grid.occupied_fraction < 0.6
    assert not grid.lookup(torch.tensor([[50.0, 0, 0]])).any()


def test_marching_matches_dense_reference(blob_mesh):
    """Grid skipping + early termination + weight pruning vs every step composited per ray."""
    f = textured_field(blob_mesh)
    o, d = _camera()
    step = f.radius * 0.25
    s = march_rays(o, d, f.grid, f.sigma_fn, step)
    with torch.no_grad():
        _, rgb, _ = f.decode(s.aux, d[s.ray_indices])
    out = composite(s.ray_indices, s.t_starts, s.t_ends, s.sigmas, {"rgb": rgb}, len(o))

    t_near, t_far = f.grid.ray_aabb(o, d)
    t_near = torch.floor(t_near.clamp_min(0) / step) * step  # same anchoring as the marcher
    ref = march_rays_reference(o, d, t_near, t_far, step)
    x = ref.positions(o, d)
    with torch.no_grad():
        sig, rgb_r, _ = f.query(x, d[ref.ray_indices])
    rr = composite_reference(ref.ray_indices, ref.t_starts, ref.t_ends, sig, {"rgb": rgb_r}, len(o))
    assert rr["opacity"].max() > 0.9 and rr["opacity"].min() < 0.1  # the blob is in view, with background
    assert torch.allclose(out["opacity"], rr["opacity"], atol=2e-3)
    assert torch.allclose(out["rgb"], rr["rgb"], atol=3e-3)
    assert len(s) < 0.5 * len(ref)  # the grid and early stop actually skip work


def test_refresh_prunes_empty_cells(blob_mesh):
    f = textured_field(blob_mesh)
    with torch.no_grad():
        f.geo_decoder[-1].bias.fill_(-30.0)  # a field with no density anywhere
    before = f.grid.occupied_fraction
    f.grid.refresh(lambda x: f.query(x, with_rgb=False)[0], f.radius * 0.25, max_cells=None)
    assert before > 0 and f.grid.occupied_fraction == 0.0
