"""Device selection, and the CUDA path checked against the CPU path (gsplat style: the CPU run is the
reference).  The CUDA tests skip where torch sees no GPU (CI); they run on a GPU machine with
``pytest tests/test_device.py``."""
import numpy as np
import pytest
import torch

import neumesh_core as nm
from neumesh_core.device import resolve_device
from neumesh_core.errors import NeuMeshError

from .conftest import textured_field

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (run on a GPU machine)")


def test_resolve_device_without_a_gpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(None) == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(NeuMeshError, match="--device cpu"):
        resolve_device("cuda")
    with pytest.raises(NeuMeshError, match="--device cpu"):
        resolve_device("cuda:1")
    with pytest.raises(NeuMeshError, match="unknown device 'tpu'"):
        resolve_device("tpu")


def test_cli_says_what_to_do_when_cuda_is_missing(monkeypatch, small_scene_dir, tmp_path, capsys):
    from neumesh_core.cli import main

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    rc = main(["train", "--data", small_scene_dir, "--out", str(tmp_path / "f.neumesh"), "--steps", "1",
               "--device", "cuda"])
    assert rc == 2
    assert "sees no CUDA GPU" in capsys.readouterr().err
    assert not (tmp_path / "f.neumesh").exists()


def _camera(scene):
    val = scene.split("val")
    return val.cameras.K[0], val.cameras.c2w[0], val.cameras.width, val.cameras.height


@cuda
def test_cuda_render_matches_cpu(blob_mesh, small_scene_dir):
    scene = nm.load_scene(small_scene_dir)
    f_cpu = textured_field(blob_mesh)
    f_gpu = textured_field(blob_mesh).to("cuda")
    assert f_gpu.rest_vertices.is_cuda and f_gpu.grid.occ.is_cuda
    # the CPU's KD-tree becomes the Triton index on the GPU (the hash grid without triton; no host round
    # trip per query), and back
    from neumesh_core.field.knn import HashGridIndex, KDTreeIndex
    from neumesh_core.kernels.knn import TritonKNNIndex, triton_available
    gpu_index = TritonKNNIndex if triton_available() else HashGridIndex
    assert isinstance(f_gpu.scaffold.index, gpu_index) and f_gpu.scaffold.index.n == f_gpu.num_vertices
    assert isinstance(textured_field(blob_mesh).to("cuda").to("cpu").scaffold.index, KDTreeIndex)
    a = nm.render_camera(f_cpu, *_camera(scene), background=(1.0, 1.0, 1.0))
    b = nm.render_camera(f_gpu, *_camera(scene), background=(1.0, 1.0, 1.0))
    assert a.opacity.max() > 0.5   # the view sees the object
    c = nm.render_camera(f_gpu, *_camera(scene), background=(1.0, 1.0, 1.0),
                         settings=nm.RenderSettings(skip_empty=False))
    assert np.abs(b.rgb - c.rgb).max() < 1e-4   # skipping empty pixels and distances on the GPU
    d = np.abs(a.rgb - b.rgb)
    assert d.mean() < 1e-3 and d.max() < 0.05, (d.mean(), d.max())


@cuda
def test_cuda_deformed_field_renders_like_the_cpu(blob_mesh, small_scene_dir):
    """set_vertices on the GPU: normals through the sparse face incidence, the index built on the
    worker thread, the grid rebuilt; the image matches the CPU's deformed render."""
    scene = nm.load_scene(small_scene_dir)
    f_cpu = textured_field(blob_mesh)
    f_gpu = textured_field(blob_mesh).to("cuda")
    v = f_cpu.rest_vertices * torch.tensor([1.15, 1.0, 0.9])
    f_cpu.set_vertices(v)
    f_gpu.set_vertices(v.cuda())
    assert f_gpu.scaffold.normals.is_cuda and f_gpu.to_rest.is_cuda
    assert torch.allclose(f_gpu.scaffold.normals.cpu(), f_cpu.scaffold.normals, atol=1e-5)
    a = nm.render_camera(f_cpu, *_camera(scene), background=(1.0, 1.0, 1.0))
    b = nm.render_camera(f_gpu, *_camera(scene), background=(1.0, 1.0, 1.0))
    d = np.abs(a.rgb - b.rgb)
    assert a.opacity.max() > 0.5 and d.mean() < 1e-3 and d.max() < 0.05, (d.mean(), d.max())


@cuda
def test_cuda_hashgrid_field_renders_like_the_cpu_kdtree(blob_mesh, small_scene_dir):
    from neumesh_core.field.knn import HashGridIndex

    scene = nm.load_scene(small_scene_dir)
    f_cpu = textured_field(blob_mesh)
    f_gpu = textured_field(blob_mesh, knn="hashgrid").to("cuda")   # moving the field moves its index
    assert isinstance(f_gpu.scaffold.index, HashGridIndex) and f_gpu.scaffold.index.v.is_cuda
    a = nm.render_camera(f_cpu, *_camera(scene), background=(1.0, 1.0, 1.0))
    b = nm.render_camera(f_gpu, *_camera(scene), background=(1.0, 1.0, 1.0))
    d = np.abs(a.rgb - b.rgb)
    assert a.opacity.max() > 0.5 and d.mean() < 1e-3 and d.max() < 0.05, (d.mean(), d.max())


@cuda
def test_cuda_random_draws_match_cpu(blob_mesh):
    """A CPU generator picks the same TV vertices and occupancy cells on either device."""
    f_cpu = textured_field(blob_mesh)
    f_gpu = textured_field(blob_mesh).to("cuda")
    tv = [f.tv_loss(64, generator=torch.Generator().manual_seed(3)).item() for f in (f_cpu, f_gpu)]
    assert tv[0] == pytest.approx(tv[1], rel=1e-4)
    for f in (f_cpu, f_gpu):
        f.grid.refresh(lambda x, f=f: f.query(x, with_rgb=False)[0], 0.01, max_cells=500,
                       generator=torch.Generator().manual_seed(4))
    seen_cpu = (f_cpu.grid.density >= 0).nonzero()
    seen_gpu = (f_gpu.grid.density >= 0).nonzero().cpu()
    assert len(seen_cpu) == 500 and torch.equal(seen_cpu, seen_gpu)


@cuda
def test_cuda_training_learns_and_saves_a_device_free_field(small_scene_dir, tmp_path):
    """The CPU test's pass mark (24 dB on held-out views after 300 x 1024 rays), on CUDA, with the
    coarse code levels, weight averaging and batch TV on; the saved field loads on the CPU and renders
    what the CUDA field renders."""
    from .train.test_trainer import _val_psnr

    scene = nm.load_scene(small_scene_dir)
    field = nm.create_field(nm.load_mesh(scene.mesh_path), device=resolve_device("cuda"))
    path = str(tmp_path / "f.neumesh")
    res = nm.train(field, scene, nm.TrainConfig(steps=300, rays_per_batch=1024, checkpoint_path=path,
                                                code_levels=2, average_from=0.5, tv_vertices="batch"))
    assert res.steps_done == 300 and res.averaged > 0
    assert field.geo_codes.is_cuda
    after = _val_psnr(field, scene)
    assert after > 24.0, after
    g = nm.load_field(path)                       # onto the CPU
    assert not g.geo_codes.is_cuda
    a = nm.render_camera(field, *_camera(scene), background=scene.background)
    b = nm.render_camera(g, *_camera(scene), background=scene.background)
    d = np.abs(a.rgb - b.rgb)
    assert d.mean() < 1e-3 and d.max() < 0.05, (d.mean(), d.max())
