"""The fused renderer (neumesh_core/kernels/fused.py, fused_kernel.py) against the torch render_rays:
early and post interpolation, at rest and deformed; its march against the torch marcher; the path
choice; the ahead-of-time build for a GPU.

Without a GPU the kernels run in Triton's interpreter (tests/kernels/helpers.py); with a GPU
(benchmarks/gpu_check.sh) compiled on CUDA."""
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from .helpers import DEVICE, ROOT, scene  # first: sets TRITON_INTERPRET, skips without triton  # isort: skip
import neumesh_core as nm
from neumesh_core.errors import NeuMeshError
from neumesh_core.metrics import psnr

from ..conftest import textured_field


@pytest.mark.parametrize("interpolation", ["early", "post"])
@pytest.mark.parametrize("deformed", [False, True], ids=["rest", "deformed"])
def test_fused_render_matches_the_torch_render(interpolation, deformed):
    field, K, c2w = scene(interpolation, deformed)
    w = h = 12
    far = None
    if deformed:   # a holdout in front of part of the field (per-pixel far distances)
        far = np.full((h, w), np.inf, np.float32)
        far[:, : w // 2] = 5.0
    ref = nm.render_camera(field, K, c2w, w, h, settings=nm.RenderSettings(backend="torch"), far=far)
    out = nm.render_camera(field, K, c2w, w, h, settings=nm.RenderSettings(backend="triton"), far=far)
    assert ref.opacity.max() > 0.9 and ref.opacity.min() < 0.1   # the view sees the object and around it
    assert psnr(out.rgb, ref.rgb) >= 50.0, psnr(out.rgb, ref.rgb)
    assert np.abs(out.opacity - ref.opacity).max() < 1e-3
    assert np.abs(out.mod_colour - ref.mod_colour).max() < 1e-3
    hit = ref.opacity > 1e-3
    assert np.array_equal(np.isfinite(out.depth), np.isfinite(ref.depth))
    assert np.abs(out.depth[hit] - ref.depth[hit]).max() < 1e-3
    assert abs(out.n_samples - ref.n_samples) <= max(2, ref.n_samples // 100)
    if interpolation == "early" and not deformed:   # whole rays through the grid's box (no ray ranges)
        whole = nm.render_camera(field, K, c2w, w, h, settings=nm.RenderSettings(backend="triton", skip_empty=False))
        assert psnr(whole.rgb, ref.rgb) >= 50.0


def test_backend_choice_and_errors():
    from neumesh_core.data.synthetic import default_mesh
    from neumesh_core.kernels.fused import supported, use_triton

    field = textured_field(default_mesh(subdiv=1), "early")
    with pytest.raises(ValueError, match="backend"):
        nm.RenderSettings(backend="cuda")
    # the CPU default stays the torch path
    assert not use_triton(nm.RenderSettings(), [field], "cpu")
    assert not use_triton(nm.RenderSettings(backend="torch"), [field], DEVICE)
    # what the kernel does not cover falls back under "auto" and is an error under "triton"
    assert supported(field) is None
    two = textured_field(default_mesh(subdiv=1), "early")
    two.add_decoder(textured_field(default_mesh(subdiv=1), "early", seed=1).rad_decoders[0].apply(
        lambda m: torch.nn.init.normal_(m.weight) if isinstance(m, torch.nn.Linear) else None))
    assert "decoders" in supported(two)
    assert not use_triton(nm.RenderSettings(), [two], "cuda")
    with pytest.raises(NeuMeshError, match="backend='auto'"):
        use_triton(nm.RenderSettings(backend="triton"), [two], DEVICE)
    assert not use_triton(nm.RenderSettings(backend="auto"), [field, field], "cuda")


def test_half_precision_products_stay_close_to_the_reference(monkeypatch):
    """precision="fp16": the decoders' products with operands rounded to half precision (tensor cores
    on a GPU), fp32 sums.  Rounding shows (the image is not the fp32 one) but stays far under what an
    eye sees; an unknown precision is refused before anything runs."""
    from neumesh_core.kernels import fused as ft

    field, K, c2w = scene("post", False)
    ref = nm.render_camera(field, K, c2w, 12, 12, settings=nm.RenderSettings(backend="torch"))
    fp32 = nm.render_camera(field, K, c2w, 12, 12, settings=nm.RenderSettings(backend="triton"))
    monkeypatch.setitem(ft.KERNEL_OPTIONS, "precision", "fp16")
    half = nm.render_camera(field, K, c2w, 12, 12, settings=nm.RenderSettings(backend="triton"))
    assert psnr(half.rgb, ref.rgb) >= 50.0, psnr(half.rgb, ref.rgb)
    assert abs(half.n_samples - ref.n_samples) <= max(2, ref.n_samples // 100)
    if DEVICE == "cpu":   # the interpreter rounds the operands too: the images differ, a little
        assert 0 < np.abs(half.rgb - fp32.rgb).max() < 1e-3
    monkeypatch.setitem(ft.KERNEL_OPTIONS, "precision", "fp64")
    with pytest.raises(ValueError, match="precision"):
        nm.render_camera(field, K, c2w, 12, 12, settings=nm.RenderSettings(backend="triton"))


def test_the_kernel_builds_for_a_gpu_ahead_of_time(tmp_path):
    """Every schedule must compile for a real GPU, not only run in the interpreter: an sm_90 build (no
    GPU needed; Triton's own ptxas) of the default (static, early, fp32), of refill + post + bent +
    fp16 and of the training's march (samples out, jitter).  Once a restructured loop ran in the
    interpreter and failed in Triton 3.6's layout passes."""
    pytest.importorskip("triton.backends.nvidia")
    code = ("import sys, neumesh_core as nm\n"
            "from neumesh_core.kernels import fused as ft\n"
            "for kw in ({}, dict(schedule='refill', interpolation='post', deformed=True, precision='fp16'),\n"
            "           dict(march=True, jitter=True)):\n"
            "    k = ft.compile_for(nm.FieldConfig(), 90, **kw)\n"
            "    assert len(k.asm['cubin']) > 10000, kw\n"
            "print('built')\n")
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    env["TRITON_CACHE_DIR"] = str(tmp_path)   # a real build, not a cached one
    env["PYTHONPATH"] = os.pathsep.join([ROOT, env.get("PYTHONPATH", "")])
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0 and "built" in run.stdout, run.stderr[-3000:]
    if DEVICE == "cpu":   # this process imported triton in interpreter mode: a clear error, no crash
        from neumesh_core.kernels import fused as ft

        with pytest.raises(RuntimeError, match="TRITON_INTERPRET"):
            ft.compile_for(nm.FieldConfig(), 90)


def test_knn_early_out_and_ray_order_render_the_same_image(monkeypatch):
    from neumesh_core.kernels import fused as ft

    field, K, c2w = scene("early", True)
    st = nm.RenderSettings(backend="triton")
    full = nm.render_camera(field, K, c2w, 12, 12, settings=st)
    monkeypatch.setitem(ft.KERNEL_OPTIONS, "knn_early_out", True)
    out = nm.render_camera(field, K, c2w, 12, 12, settings=st)
    assert full.opacity.max() > 0.9 and out.n_samples == full.n_samples
    assert np.abs(out.rgb - full.rgb).max() < 1e-6 and np.abs(out.opacity - full.opacity).max() < 1e-6
    # rays handed over in rows instead of 8 x 4 tiles: other blocks, the same pixels
    monkeypatch.setitem(ft.KERNEL_OPTIONS, "ray_order", "rows")
    rows = nm.render_camera(field, K, c2w, 12, 12, settings=st)
    assert rows.n_samples == full.n_samples and np.abs(rows.rgb - full.rgb).max() < 1e-6


def test_refill_schedule_renders_what_the_static_one_does(monkeypatch):
    """The refill schedule: persistent programs whose lanes take the next ray from a shared counter as
    soon as theirs finishes.  With 16-ray blocks and 2 programs each lane renders several of the 144
    rays, in an order that depends on when the others finish; every ray must still come out as the
    torch reference renders it."""
    from neumesh_core.kernels import fused as ft

    field, K, c2w = scene("early", True)
    ref = nm.render_camera(field, K, c2w, 12, 12, settings=nm.RenderSettings(backend="torch"))
    monkeypatch.setitem(ft.KERNEL_OPTIONS, "schedule", "refill")
    monkeypatch.setitem(ft.KERNEL_OPTIONS, "block", 16)
    monkeypatch.setitem(ft.KERNEL_OPTIONS, "programs_per_sm", 1)
    out = nm.render_camera(field, K, c2w, 12, 12, settings=nm.RenderSettings(backend="triton"))
    assert ref.opacity.max() > 0.9 and ref.opacity.min() < 0.1
    assert psnr(out.rgb, ref.rgb) >= 50.0, psnr(out.rgb, ref.rgb)
    assert np.abs(out.opacity - ref.opacity).max() < 1e-3
    assert np.abs(out.mod_colour - ref.mod_colour).max() < 1e-3
    assert abs(out.n_samples - ref.n_samples) <= max(2, ref.n_samples // 100)
    if DEVICE == "cpu":   # the interpreter: 2 programs of 16 lanes for 144 rays, so lanes were refilled
        assert ft.refill_programs("cpu", 9, 1) == 2
    monkeypatch.setitem(ft.KERNEL_OPTIONS, "schedule", "wavefront")
    with pytest.raises(ValueError, match="schedule"):
        nm.render_camera(field, K, c2w, 12, 12, settings=nm.RenderSettings(backend="triton"))


@pytest.mark.parametrize("interpolation,deformed,jitter", [("early", False, True), ("post", True, False)],
                         ids=["early-rest-jitter", "post-bent"])
def test_fused_march_keeps_the_torch_marchers_samples(interpolation, deformed, jitter):
    """march_rays_fused (the kernel without colours) against its reference, the torch marcher with the
    field's sigma_fn: the same kept samples (rays, positions, with the training's per-ray jitter), the
    same densities and the same neighbours, with either schedule; a ray that keeps more samples than
    MARCH_SLOTS makes the chunk run again with room for it."""
    from neumesh_core.data.cameras import pixel_rays
    from neumesh_core.kernels import fused as ft
    from neumesh_core.render.renderer import default_step
    from neumesh_core.sampling.marcher import march_rays

    field, K, c2w = scene(interpolation, deformed)
    o, d = pixel_rays(K, c2w, 12, 12, device=DEVICE)
    jit = torch.rand(len(o), generator=torch.Generator().manual_seed(3)).to(DEVICE) if jitter else None
    step = default_step(field, nm.RenderSettings())
    ref = march_rays(o, d, field.grid, field.sigma_fn, step, jitter=jit)
    out = ft.march_rays_fused(field, o, d, step, jitter=jit)
    assert len(ref) > 80 and out.n_rays == ref.n_rays
    assert torch.equal(out.ray_indices, ref.ray_indices)
    assert torch.allclose(out.t_starts, ref.t_starts, atol=1e-6) and torch.allclose(out.t_ends, ref.t_ends, atol=1e-6)
    assert torch.allclose(out.sigmas, ref.sigmas, rtol=1e-4, atol=1e-5)
    assert torch.equal(out.aux.idx, ref.aux.idx) and torch.equal(out.aux.valid, ref.aux.valid)
    assert torch.allclose(out.aux.w, ref.aux.w, atol=1e-5) and torch.allclose(out.aux.p, ref.aux.p, atol=1e-5)
    # room for 2 samples a ray: the launch is repeated with room for the longest ray, the same samples
    longest = int(torch.bincount(ref.ray_indices).max())
    assert longest > 2
    # the refill schedule (lanes take new rays as theirs end) stores each ray's samples in its own slots
    refill = ft.march_rays_fused(field, o, d, step, jitter=jit, schedule="refill", block=16, programs_per_sm=1)
    assert torch.equal(refill.ray_indices, out.ray_indices) and torch.equal(refill.t_starts, out.t_starts)
    assert torch.equal(refill.aux.idx, out.aux.idx)
    old = ft.MARCH_SLOTS
    try:
        ft.MARCH_SLOTS = 2
        again = ft.march_rays_fused(field, o, d, step, jitter=jit)
    finally:
        ft.MARCH_SLOTS = old
    assert torch.equal(again.ray_indices, out.ray_indices) and torch.equal(again.t_starts, out.t_starts)


def test_a_training_step_marches_with_the_kernel_and_decodes_with_torch():
    """render_rays(train=True) with backend "triton": the kernel marches (jittered), the torch decoders
    decode the kept samples with autograd; the loss and every gradient are the torch path's."""
    from neumesh_core.data.cameras import pixel_rays
    from neumesh_core.kernels import fused as ft
    from neumesh_core.render.renderer import render_rays

    field, K, c2w = scene("early", False)
    o, d = pixel_rays(K, c2w, 12, 12, device=DEVICE)
    jit = torch.rand(len(o), generator=torch.Generator().manual_seed(4)).to(DEVICE)
    target = torch.rand(len(o), 3, generator=torch.Generator().manual_seed(5)).to(DEVICE)
    grads = []
    for backend in ("torch", "triton"):
        field.zero_grad(set_to_none=True)
        out = render_rays(field, o, d, background=torch.ones(3, device=DEVICE), train=True, jitter=jit,
                          settings=nm.RenderSettings(backend=backend), vertex_ids=True)
        loss = (out["rgb"] - target).square().mean()
        loss.backward()
        grads.append((float(loss.detach()), out["n_samples"], out["vertex_ids"][0],
                      {n: p.grad.detach().to_dense().clone() for n, p in field.named_parameters()
                       if p.grad is not None}))
    (l_ref, n_ref, v_ref, g_ref), (l_out, n_out, v_out, g_out) = grads
    assert n_out == n_ref > 80 and torch.equal(v_out, v_ref)
    assert abs(l_out - l_ref) < 1e-6 * max(1.0, abs(l_ref))
    assert g_ref.keys() == g_out.keys() and {"geo_codes", "tex_codes"} <= set(g_ref)
    for name in g_ref:
        assert torch.allclose(g_out[name], g_ref[name], rtol=1e-3, atol=1e-6), name
    # the plain render still takes the whole kernel; "auto" on the CPU keeps the torch marcher
    assert ft.use_triton(nm.RenderSettings(backend="triton"), [field], DEVICE)
    assert not ft.use_triton(nm.RenderSettings(backend="triton"), [field], DEVICE, train=True)
    assert ft.use_fused_march(nm.RenderSettings(backend="triton"), field, DEVICE)
    assert not ft.use_fused_march(nm.RenderSettings(), field, "cpu")
