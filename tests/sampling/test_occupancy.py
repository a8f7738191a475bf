"""The occupancy grid: the mesh mask (shifted-OR dilation against the max-pool reference), step
lookups, and the per-pixel ray ranges of a camera against their exact per-ray reference."""
import numpy as np
import pytest
import torch

from neumesh_core.data.cameras import pixel_rays
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


def _look_at(eye, target=(0.5, 0.3, 0.15)):
    from neumesh_core.data.synthetic import look_at_opencv

    return np.asarray(look_at_opencv(np.asarray(eye, np.float64), np.asarray(target, np.float64)), np.float32)


@pytest.mark.parametrize("tile", [1, 4, 8])
@pytest.mark.parametrize("eye", [(2.5, -1.5, 1.2), (0.5, 0.3, 3.0), (-0.8, 1.9, -0.6)])
def test_camera_ranges_hold_every_occupied_cell_a_ray_meets(tile, eye):
    """The splatted per-pixel interval contains the exact one (a slab test of each ray against every
    occupied cell), at the centre and at sub-pixel positions, with skew and a non-square image; pixels
    whose rays meet nothing may be dropped, no other."""
    g = torch.Generator().manual_seed(3)
    verts = torch.rand(150, 3, generator=g) * torch.tensor([1.0, 0.6, 0.3])
    grid = OccupancyGrid.from_vertices(verts, 0.05, max_res=24)
    grid.occ &= torch.rand(grid.occ.shape, generator=g) > 0.3      # a pruned grid, holes included
    w, h = 37, 29
    K = np.array([[40.0, 1.5, 17.0], [0.0, 44.0, 15.5], [0.0, 0.0, 1.0]], np.float32)
    c2w = _look_at(eye)
    near, far = grid.camera_ranges(K, c2w, w, h, tile)
    assert near.shape == far.shape == (w * h,)
    live = near <= far
    assert 0 < int(live.sum()) < w * h or tile > 1
    for off in [(0.5, 0.5), (0.02, 0.97), (0.9, 0.1)]:
        o, d = pixel_rays(K, c2w, w, h, offset=off)
        r_near, r_far = grid.camera_ranges_reference(o, d)
        hit = r_near <= r_far
        assert int(hit.sum()) > 20
        assert bool(live[hit].all())
        assert bool((near[hit] <= r_near[hit]).all()) and bool((far[hit] >= r_far[hit]).all())
    if tile == 1:   # per pixel, the bound is not loose: most dropped pixels are really empty
        assert int(live.sum()) < 2 * int(hit.sum()) + 40


def test_camera_ranges_give_up_when_the_camera_is_inside_the_occupied_cells():
    g = torch.Generator().manual_seed(4)
    grid = OccupancyGrid.from_vertices(torch.rand(300, 3, generator=g), 0.1, max_res=16)
    K = np.array([[30.0, 0, 16], [0, 30.0, 16], [0, 0, 1]], np.float32)
    assert grid.camera_ranges(K, _look_at((0.5, 0.5, 0.5), (2.0, 0.5, 0.5)), 32, 32) is None
    # an empty grid: every pixel is empty
    grid.occ[:] = False
    near, far = grid.camera_ranges(K, _look_at((3.0, 0.5, 0.5), (0.5, 0.5, 0.5)), 32, 32)
    assert bool((near > far).all())
