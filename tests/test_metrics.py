"""PSNR / SSIM / LPIPS (neumesh_core/metrics.py)."""
import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from neumesh_core import metrics as M
from neumesh_core.errors import WeightsUnavailableError


def test_psnr_known_values():
    gt = np.zeros((8, 8, 3), np.float32)
    assert M.psnr(gt + 0.1, gt) == pytest.approx(20.0, abs=1e-4)
    assert M.psnr(torch.full((8, 8, 3), 0.01), torch.zeros(8, 8, 3)) == pytest.approx(40.0, abs=1e-3)
    assert M.psnr(gt, gt) == math.inf
    pred = gt.copy()
    pred[:4] = 0.5  # error only in the top half
    mask = np.zeros((8, 8), np.float32)
    mask[4:] = 1
    assert M.psnr(pred, gt, mask) == math.inf
    assert M.psnr(pred, gt, 1 - mask) == pytest.approx(-10 * math.log10(0.25), abs=1e-4)
    assert M.masked_psnr(pred, gt, (1 - mask) * 0.9) == pytest.approx(-10 * math.log10(0.25), abs=1e-4)
    assert M.psnr(pred, gt) == pytest.approx(-10 * math.log10(0.125), abs=1e-4)
    with pytest.raises(ValueError):
        M.psnr(gt, gt[:4])


def test_ssim_matches_skimage():
    rng = np.random.default_rng(0)
    gt = rng.random((40, 50, 3)).astype(np.float32)
    gt = (gt + np.roll(gt, 1, 0) + np.roll(gt, 1, 1)) / 3  # some structure
    for noise in (0.02, 0.1, 0.3):
        pred = np.clip(gt + rng.normal(0, noise, gt.shape), 0, 1).astype(np.float32)
        ref = structural_similarity(pred, gt, channel_axis=-1, data_range=1.0, gaussian_weights=True,
                                    sigma=1.5, use_sample_covariance=False)
        assert M.ssim(pred, gt) == pytest.approx(ref, abs=1e-3)
        assert M.ssim(torch.as_tensor(pred), torch.as_tensor(gt)) == pytest.approx(ref, abs=1e-3)
    grey = gt[..., 0]
    ref = structural_similarity(grey * 0.8, grey, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                use_sample_covariance=False)
    assert M.ssim(grey * 0.8, grey) == pytest.approx(ref, abs=1e-3)
    assert M.ssim(gt, gt) == pytest.approx(1.0, abs=1e-9)


def test_masked_ssim_averages_the_map():
    rng = np.random.default_rng(1)
    gt = rng.random((32, 32, 3))
    pred = gt.copy()
    pred[:, 16:] = rng.random((32, 16, 3))  # right half is wrong
    left = np.zeros((32, 32))
    left[:, :8] = 1  # valid-region SSIM map covers columns 5..26 -> columns 5..7 are clean
    assert M.ssim(pred, gt, mask=left) == pytest.approx(1.0, abs=1e-9)
    assert M.ssim(pred, gt) < 0.7
    full = M.ssim(pred, gt, mask=np.ones((32, 32)))
    assert full == pytest.approx(M.ssim(pred, gt), abs=1e-12)


def test_lpips_unavailable_raises_with_instructions(tmp_path, monkeypatch):
    monkeypatch.setenv("NEUMESH_WEIGHTS", str(tmp_path / "none"))
    assert M.lpips_available() is False
    img = np.zeros((64, 64, 3), np.float32)
    with pytest.raises(WeightsUnavailableError) as ei:
        M.compute_lpips(img, img)
    msg = str(ei.value)
    assert str(tmp_path / "none") in msg and "alexnet-owt-7be5be79.pth" in msg and "alex.pth" in msg


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_network_with_local_weights(tmp_path, net):
    """The plain-torch network loads torchvision/lpips-layout state dicts (random values here)."""
    torch.manual_seed(0)
    backbone = {}
    for i, cin, cout, k, _, _ in M._CONV_LAYOUT[net]:
        backbone[f"features.{i}.weight"] = torch.randn(cout, cin, k, k) * (2.0 / (cin * k * k)) ** 0.5
        backbone[f"features.{i}.bias"] = torch.zeros(cout)
    lin = {f"lin{j}.model.1.weight": torch.rand(1, c, 1, 1) for j, c in enumerate(M._TAP_CHANNELS[net])}
    names = {"alex": ("alexnet-owt-7be5be79.pth", "alex.pth"), "vgg": ("vgg16-397923af.pth", "vgg.pth")}[net]
    torch.save(backbone, tmp_path / names[0])
    if net == "alex":
        torch.save(lin, tmp_path / names[1])
    else:
        from safetensors.torch import save_file

        save_file(lin, str(tmp_path / "lpips_vgg.safetensors"))
    assert M.lpips_available(str(tmp_path), net=net)
    rng = np.random.default_rng(0)
    size = 64 if net == "alex" else 32
    a = rng.random((size, size, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1).astype(np.float32)
    assert M.compute_lpips(a, a, cache_dir=str(tmp_path), net=net) == pytest.approx(0.0, abs=1e-7)
    d1 = M.compute_lpips(a, b, cache_dir=str(tmp_path), net=net)
    d2 = M.compute_lpips(a, 1 - a, cache_dir=str(tmp_path), net=net)
    assert 0 < d1 < d2
    batch = M.compute_lpips(np.stack([a, a]), np.stack([b, b]), cache_dir=str(tmp_path), net=net)
    assert batch == pytest.approx(d1, rel=1e-5)


def test_lpips_rejects_wrong_state_dict(tmp_path):
    torch.save({"foo": torch.zeros(1)}, tmp_path / "alexnet.pth")
    torch.save({"bar": torch.zeros(1)}, tmp_path / "alex.pth")
    with pytest.raises(WeightsUnavailableError, match="features.0.weight"):
        M.compute_lpips(np.zeros((64, 64, 3)), np.zeros((64, 64, 3)), cache_dir=str(tmp_path))


def test_shading_corrected_removes_smooth_gain_but_not_blur():
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(0)
    gt = rng.uniform(0.2, 0.8, (64, 64, 3)).astype(np.float32)
    mask = np.zeros((64, 64), np.float32)
    mask[8:56, 8:56] = 1
    yy, xx = np.mgrid[0:64, 0:64] / 64.0
    gain = (0.8 + 0.4 * xx * yy)[..., None]  # smooth shading change, as between two lightings
    shaded = np.clip(gt * gain, 0, 1).astype(np.float32)
    raw = M.masked_psnr(shaded, gt, mask)
    fixed = M.masked_psnr(M.shading_corrected(shaded, gt, mask, sigma=6), gt, mask)
    assert raw < 25 and fixed > raw + 10
    # blur is an error of detail, not of shading: the correction leaves it
    blurred = np.stack([gaussian_filter(gt[..., c], 1.5) for c in range(3)], -1).astype(np.float32)
    assert M.masked_psnr(M.shading_corrected(blurred, gt, mask, sigma=6), gt, mask) == pytest.approx(
        M.masked_psnr(blurred, gt, mask), abs=0.3)
    # outside the mask the prediction is untouched
    out = M.shading_corrected(shaded, gt, mask, sigma=6)
    assert np.array_equal(out[mask == 0], shaded[mask == 0])
    with pytest.raises(ValueError, match="no pixels"):
        M.shading_corrected(shaded, gt, np.zeros((64, 64)))
