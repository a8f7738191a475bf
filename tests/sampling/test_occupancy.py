"""The occupancy grid's mesh mask: the shifted-OR dilation against the max-pool reference."""
import pytest
import torch

from neumesh_core.sampling.occupancy import OccupancyGrid


@pytest.mark.parametrize("radius", [0.0, 0.03, 0.11, 0.4, 5.0])
def test_mask_from_vertices_matches_max_pool_reference(radius):
    g = torch.Generator().manual_seed(0)
    verts = torch.rand(300, 3, generator=g) * torch.tensor([1.0, 0.6, 0.3])
    aabb = torch.tensor([[-0.1, -0.1, -0.1], [1.1, 0.7, 0.4]])
    res = torch.tensor([24, 16, 10])
    fast = OccupancyGrid.mask_from_vertices(verts, aabb, res, radius)
    ref = OccupancyGrid.mask_from_vertices_reference(verts, aabb, res, radius)
    assert fast.dtype == torch.bool and fast.shape == (24, 16, 10)
    assert torch.equal(fast, ref)      # booleans: exact
    # every cell holding a vertex is set, and a radius of zero dilates nothing
    assert int(fast.sum()) >= int(OccupancyGrid._splat(verts, aabb, res)[0].sum())
    if radius == 0.0:
        assert torch.equal(fast, OccupancyGrid._splat(verts, aabb, res)[0])


def test_grid_from_vertices_covers_every_point_within_the_radius():
    g = torch.Generator().manual_seed(1)
    verts = torch.rand(200, 3, generator=g)
    grid = OccupancyGrid.from_vertices(verts, 0.05, max_res=32)
    # points at most the radius away from a vertex fall in occupied cells
    d = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g), dim=1)
    pts = verts[torch.randint(0, 200, (2000,), generator=g)] + d * 0.05 * torch.rand(2000, 1, generator=g)
    assert bool(grid.lookup(pts).all())


def test_lookup_steps_matches_lookup_of_world_points():
    g = torch.Generator().manual_seed(2)
    verts = torch.rand(400, 3, generator=g)
    grid = OccupancyGrid.from_vertices(verts, 0.04, max_res=40)
    o = torch.tensor([[-1.0, 0.3, 0.4]]).repeat(64, 1) + 0.2 * torch.randn(64, 3, generator=g)
    d = torch.nn.functional.normalize(torch.tensor([1.0, 0.1, 0.05]) + 0.3 * torch.randn(64, 3, generator=g), dim=1)
    t_near, t_far = grid.ray_aabb(o, d)
    ts = t_near[:, None] + torch.rand(64, 50, generator=g) * (t_far - t_near).clamp_min(0)[:, None]
    ref = grid.lookup(o[:, None, :] + d[:, None, :] * ts[..., None])
    fast = grid.lookup_steps(*grid.cell_coordinates(o, d), ts)
    inside = (ts >= t_near[:, None]) & (ts < t_far[:, None])
    # the two round a point's cell coordinates differently (world point first, or not), so a point
    # within float rounding of a cell face may read the cell beside it: allow a handful
    assert fast.shape == ref.shape and int(inside.sum()) > 1000
    assert int((fast != ref)[inside].sum()) <= 3
    assert ref[inside].any() and (~ref[inside]).any()
