"""The Triton neighbour search (neumesh_core/kernels/knn.py) against its torch reference
(knn_radius_reference), and as the field's own neighbour index.

Without a GPU the kernel runs in Triton's interpreter (tests/kernels/helpers.py); with a GPU
(benchmarks/gpu_check.sh) compiled on CUDA."""
import numpy as np
import pytest
import torch

from .helpers import DEVICE, scene  # first: sets TRITON_INTERPRET, skips without triton  # isort: skip
import neumesh_core as nm
from neumesh_core.field.knn import knn_radius_reference
from neumesh_core.kernels import knn as knn_triton

from ..conftest import textured_field


@pytest.mark.parametrize("cells_per_radius", [1, 2])
def test_knn_kernel_matches_the_reference(cells_per_radius):
    g = torch.Generator().manual_seed(0)
    verts = torch.rand(1500, 3, generator=g)
    pts = torch.rand(300, 3, generator=g) * 1.4 - 0.2        # some outside the vertices' box
    pts[0] = torch.tensor([5.0, 5.0, 5.0])                   # nothing within the radius
    r = 0.12
    index = knn_triton.TritonKNNIndex(verts.to(DEVICE), 4, r, block=64 if DEVICE == "cuda" else 512,
                                      cells_per_radius=cells_per_radius)
    idx, dist = index.query(pts.to(DEVICE))
    ref_i, ref_d = knn_radius_reference(pts, verts, 4, r)
    idx, dist = idx.cpu(), dist.cpu()
    assert torch.equal(torch.isinf(dist), torch.isinf(ref_d))
    assert (idx == -1).equal(ref_i == -1) and bool((idx[0] == -1).all())
    assert (ref_i >= 0).sum() > 400 and (ref_i == -1).sum() > 30   # both cases are exercised
    fin = torch.isfinite(ref_d)
    assert torch.allclose(dist[fin], ref_d[fin], atol=1e-6)
    assert torch.equal(idx, ref_i)   # random positions: no ties


@pytest.mark.parametrize("cells_per_radius", [1, 2])
def test_knn_early_out_finds_the_same_neighbours(cells_per_radius):
    """early_out merges only the candidates nearer than a row's worst key: dense vertices (~40 within
    the radius of a point, so most rounds need fewer than K merges) must give the reference's keys."""
    g = torch.Generator().manual_seed(1)
    verts = torch.rand(6000, 3, generator=g)
    pts = torch.rand(200, 3, generator=g)
    r = 0.12
    grid = knn_triton.TritonHashGrid(verts.to(DEVICE), r, cells_per_radius)
    idx, dist = knn_triton.knn_radius_triton(pts.to(DEVICE), grid, 4, block=64 if DEVICE == "cuda" else 256,
                                             early_out=True)
    ref_i, ref_d = knn_radius_reference(pts, verts, 4, r)
    assert (ref_i >= 0).all()
    assert torch.equal(idx.cpu(), ref_i) and torch.allclose(dist.cpu(), ref_d, atol=1e-6)


def test_cells_are_read_nearest_first():
    for c, centre in ((1, 13), (2, 62)):
        order = knn_triton.cell_order(c)
        s = 2 * c + 1
        assert sorted(order.tolist()) == list(range(s ** 3)) and order[0].item() == centre
        o = order.long()
        length = (o // (s * s) - c) ** 2 + ((o // s) % s - c) ** 2 + (o % s - c) ** 2
        assert bool((length[1:] >= length[:-1]).all())


def test_knn_kernel_with_fewer_vertices_than_k_and_a_huge_box():
    verts = torch.tensor([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [1e3, 0.0, 0.0]])   # a sparse, wide box
    pts = torch.tensor([[0.01, 0.0, 0.0], [999.99, 0.0, 0.0], [500.0, 0.0, 0.0]])
    grid = knn_triton.TritonHashGrid(verts.to(DEVICE), 0.1)
    assert np.prod(grid.dims) <= knn_triton.MAX_TABLE_CELLS
    idx, dist = knn_triton.knn_radius_triton(pts.to(DEVICE), grid, 4)
    ref_i, ref_d = knn_radius_reference(pts, verts, 4, 0.1)
    assert torch.equal(idx.cpu(), ref_i) and torch.allclose(dist.cpu(), ref_d, atol=1e-6, equal_nan=True)


def test_triton_neighbour_index_serves_the_torch_path():
    """FieldConfig(knn="triton"): the field's own neighbour queries (the torch marcher, edits, the
    occupancy refresh) answered by the Triton kernel; on a GPU "auto" gives it too.  The same render as
    the KD-tree's, and make_index names it."""
    from neumesh_core.data.synthetic import default_mesh
    from neumesh_core.field.knn import make_index

    verts = torch.rand(800, 3, generator=torch.Generator().manual_seed(6))
    index = make_index(verts.to(DEVICE), 4, 0.15, "triton")
    assert isinstance(index, knn_triton.TritonKNNIndex)
    pts = torch.rand(100, 3, generator=torch.Generator().manual_seed(7))
    idx, dist = index.query(pts.to(DEVICE))
    ref_i, ref_d = knn_radius_reference(pts, verts, 4, 0.15)
    assert torch.equal(idx.cpu(), ref_i) and torch.allclose(dist.cpu(), ref_d, atol=1e-6, equal_nan=True)
    if DEVICE == "cuda":
        assert isinstance(make_index(verts.cuda(), 4, 0.15, "auto"), knn_triton.TritonKNNIndex)
    mesh = default_mesh(subdiv=2)
    kd = textured_field(mesh, "early", grid_resolution=32).to(DEVICE)
    tr = textured_field(mesh, "early", grid_resolution=32, knn="triton").to(DEVICE)
    assert isinstance(tr.scaffold.index, knn_triton.TritonKNNIndex)
    _, K, c2w = scene("early", False)
    st = nm.RenderSettings(backend="torch")
    a = nm.render_camera(kd, K, c2w, 12, 12, settings=st)
    b = nm.render_camera(tr, K, c2w, 12, 12, settings=st)
    assert a.opacity.max() > 0.9 and a.n_samples == b.n_samples
    assert np.abs(a.rgb - b.rgb).max() < 1e-5
