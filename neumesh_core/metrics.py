"""Image quality metrics: PSNR, SSIM (Gaussian 11x11, sigma 1.5) and LPIPS (local weights only).

Inputs are images in [0,1]: numpy arrays or torch tensors shaped (H,W), (H,W,C) or (N,H,W,C).
Results are Python floats. Nothing here downloads anything: LPIPS reads weights from a local cache
(``$NEUMESH_WEIGHTS`` or ``~/.cache/neumesh/weights``) and raises :class:`WeightsUnavailableError`
naming the files to put there when they are missing.
"""
from __future__ import annotations

import math
import os
import threading

import numpy as np
import torch
import torch.nn.functional as F

from .errors import WeightsUnavailableError


def _t(x) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.detach().to("cpu", torch.float64)
    return torch.as_tensor(np.asarray(x, dtype=np.float64))


def _nhwc(x: torch.Tensor) -> torch.Tensor:
    if x.ndim == 2:
        return x[None, :, :, None]
    if x.ndim == 3:
        return x[None]
    if x.ndim == 4:
        return x
    raise ValueError(f"expected an image (H,W), (H,W,C) or a batch (N,H,W,C), got shape {tuple(x.shape)}")


def _pair(pred, gt):
    p, g = _t(pred), _t(gt)
    if p.shape != g.shape:
        raise ValueError(f"pred and gt shapes differ: {tuple(p.shape)} vs {tuple(g.shape)}")
    return _nhwc(p), _nhwc(g)


def _mask_nhw(mask, like: torch.Tensor) -> torch.Tensor:
    m = _t(mask)
    if m.ndim == like.ndim and m.shape[-1] == 1:
        m = m[..., 0]
    if m.ndim == 2:
        m = m[None]
    if m.ndim == 4 and m.shape[-1] == 1:
        m = m[..., 0]
    if tuple(m.shape) != tuple(like.shape[:3]) and not (m.shape[0] == 1 and m.shape[1:] == like.shape[1:3]):
        raise ValueError(f"mask shape {tuple(_t(mask).shape)} does not match images {tuple(like.shape)}")
    return m.expand(like.shape[0], -1, -1)


def _mse_to_psnr(mse: float) -> float:
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


def psnr(pred, gt, mask=None) -> float:
    """Peak signal-to-noise ratio (dB) for data range 1: -10 log10(MSE).

    With ``mask`` ((H,W) or (N,H,W) weights in [0,1]) the MSE is the mask-weighted mean over pixels
    and channels. Identical images give ``inf``.
    """
    p, g = _pair(pred, gt)
    se = (p - g) ** 2
    if mask is None:
        return _mse_to_psnr(float(se.mean()))
    m = _mask_nhw(mask, p)
    w = float(m.sum()) * p.shape[-1]
    if w <= 0:
        raise ValueError("psnr: the mask selects no pixels")
    return _mse_to_psnr(float((se * m[..., None]).sum()) / w)


def masked_psnr(pred, gt, mask, threshold: float = 0.5) -> float:
    """PSNR over foreground pixels only (``mask > threshold``), e.g. the DTU object masks."""
    p, _ = _pair(pred, gt)
    m = (_mask_nhw(mask, p) > threshold).to(torch.float64)
    return psnr(pred, gt, m)


def shading_corrected(pred, gt, mask, sigma: float = 16.0) -> np.ndarray:
    """``pred`` (H,W,3) with its low-frequency colour corrected towards ``gt`` inside ``mask``.

    Diagnostic, never a headline metric: the mask-normalised Gaussian blurs (``sigma`` px) of gt and
    pred give a smooth per-pixel, per-channel gain gt_low / pred_low that the prediction is multiplied
    by.  Errors that are only shading or exposure (lighting that changes with the camera, as in DTU)
    disappear; blur, misalignment and wrong texture stay.  Pixels outside the mask are left as they are.
    """
    from scipy.ndimage import gaussian_filter

    p = np.asarray(pred, np.float64)
    g = np.asarray(gt, np.float64)
    if p.shape != g.shape or p.ndim != 3:
        raise ValueError(f"shading_corrected: pred {p.shape} and gt {g.shape} must both be (H,W,C)")
    m = (np.asarray(mask) > 0.5).astype(np.float64)
    if m.shape != p.shape[:2]:
        raise ValueError(f"shading_corrected: mask {m.shape} does not match the image {p.shape[:2]}")
    if not m.any():
        raise ValueError("shading_corrected: the mask selects no pixels")
    norm = np.maximum(gaussian_filter(m, sigma), 1e-6)
    out = p.copy()
    for c in range(p.shape[2]):
        lo_g = gaussian_filter(g[..., c] * m, sigma) / norm
        lo_p = gaussian_filter(p[..., c] * m, sigma) / norm
        out[..., c] = np.where(m > 0, np.clip(p[..., c] * lo_g / np.maximum(lo_p, 1e-3), 0.0, 1.0), p[..., c])
    return out.astype(np.float32)


def _gaussian_window(size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim_map(pred, gt, window: int = 11, sigma: float = 1.5, data_range: float = 1.0) -> torch.Tensor:
    """Per-pixel SSIM (N,H-window+1,W-window+1), averaged over channels ('valid' filtering)."""
    p, g = _pair(pred, gt)
    n, h, w, c = p.shape
    if h < window or w < window:
        raise ValueError(f"ssim: images must be at least {window}x{window}, got {w}x{h}")
    k1 = _gaussian_window(window, sigma)
    kern = (k1[:, None] * k1[None, :]).expand(c, 1, window, window).contiguous()
    x = p.permute(0, 3, 1, 2)
    y = g.permute(0, 3, 1, 2)

    def filt(z):
        return F.conv2d(z, kern, groups=c)

    mu_x, mu_y = filt(x), filt(y)
    sxx = filt(x * x) - mu_x**2
    syy = filt(y * y) - mu_y**2
    sxy = filt(x * y) - mu_x * mu_y
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return s.mean(1)


def ssim(pred, gt, mask=None, window: int = 11, sigma: float = 1.5) -> float:
    """Structural similarity (Wang et al. 2004) with an 11x11 Gaussian window (sigma 1.5),
    K1=0.01, K2=0.03, data range 1; the SSIM map is averaged over the valid region (same as
    ``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1)``). With ``mask`` the map is averaged with the mask
    (cropped to the valid region) as weights."""
    s = ssim_map(pred, gt, window, sigma)
    if mask is None:
        return float(s.mean())
    p, _ = _pair(pred, gt)
    m = _mask_nhw(mask, p)
    r = window // 2
    m = m[:, r : r + s.shape[1], r : r + s.shape[2]]
    if float(m.sum()) <= 0:
        raise ValueError("ssim: the mask selects no pixels away from the image border")
    return float((s * m).sum() / m.sum())


# ---------------------------------------------------------------------------------------------
# LPIPS
# ---------------------------------------------------------------------------------------------
_BACKBONE_FILES = {
    "alex": ["alexnet.safetensors", "alexnet-owt-7be5be79.pth", "alexnet.pth"],
    "vgg": ["vgg16.safetensors", "vgg16-397923af.pth", "vgg16.pth"],
}
_LIN_FILES = {
    "alex": ["lpips_alex.safetensors", "lpips_alex.pth", "alex.pth"],
    "vgg": ["lpips_vgg.safetensors", "lpips_vgg.pth", "vgg.pth"],
}
# torchvision `features` conv indices and the LPIPS taps (ReLU outputs) for each backbone
_CONV_LAYOUT = {
    # (index, in, out, kernel, stride, padding)
    "alex": [(0, 3, 64, 11, 4, 2), (3, 64, 192, 5, 1, 2), (6, 192, 384, 3, 1, 1), (8, 384, 256, 3, 1, 1),
             (10, 256, 256, 3, 1, 1)],
    "vgg": [(0, 3, 64, 3, 1, 1), (2, 64, 64, 3, 1, 1), (5, 64, 128, 3, 1, 1), (7, 128, 128, 3, 1, 1),
            (10, 128, 256, 3, 1, 1), (12, 256, 256, 3, 1, 1), (14, 256, 256, 3, 1, 1),
            (17, 256, 512, 3, 1, 1), (19, 512, 512, 3, 1, 1), (21, 512, 512, 3, 1, 1),
            (24, 512, 512, 3, 1, 1), (26, 512, 512, 3, 1, 1), (28, 512, 512, 3, 1, 1)],
}
_TAP_CHANNELS = {"alex": [64, 192, 384, 256, 256], "vgg": [64, 128, 256, 512, 512]}
_LPIPS_CACHE: dict = {}
_LPIPS_LOCK = threading.Lock()


def weights_dir(cache_dir=None) -> str:
    """Local weights folder: ``cache_dir``, else ``$NEUMESH_WEIGHTS``, else ``~/.cache/neumesh/weights``."""
    if cache_dir is not None:
        return os.fspath(cache_dir)
    env = os.environ.get("NEUMESH_WEIGHTS")
    return env if env else os.path.join(os.path.expanduser("~"), ".cache", "neumesh", "weights")


def _find(folder: str, names: list[str]):
    for n in names:
        p = os.path.join(folder, n)
        if os.path.isfile(p):
            return p
    return None


def _missing_message(folder: str, net: str) -> str:
    return (
        f"LPIPS ({net}) weights are not in {folder}. Nothing is downloaded automatically: copy "
        f"the torchvision {net} backbone state dict as one of {_BACKBONE_FILES[net]} and the LPIPS "
        f"linear-layer state dict (from the `lpips` package: lpips/weights/v0.1/{net}.pth) as one of "
        f"{_LIN_FILES[net]} into that folder (or set $NEUMESH_WEIGHTS to a folder holding them)"
    )


def lpips_available(cache_dir=None, net: str = "alex") -> bool:
    """True when both LPIPS weight files for ``net`` ('alex' or 'vgg') are in the local cache."""
    if net not in _BACKBONE_FILES:
        raise ValueError(f"net must be 'alex' or 'vgg', got {net!r}")
    folder = weights_dir(cache_dir)
    return _find(folder, _BACKBONE_FILES[net]) is not None and _find(folder, _LIN_FILES[net]) is not None


def _load_state(path: str) -> dict:
    try:
        if path.endswith(".safetensors"):
            from safetensors.torch import load_file

            sd = load_file(path)
        else:
            sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise WeightsUnavailableError(
            f"could not read weights file {path}: {exc}; replace it with a valid state dict"
        ) from exc
    if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
        sd = sd["state_dict"]
    if not isinstance(sd, dict):
        raise WeightsUnavailableError(f"{path} does not hold a state dict; replace it with a valid one")
    return sd


class LPIPS(torch.nn.Module):
    """LPIPS v0.1 (Zhang et al. 2018) in plain torch: frozen backbone taps -> unit-normalised
    channel features -> squared difference -> learned 1x1 linear layer -> spatial mean -> sum."""

    def __init__(self, net: str = "alex"):
        super().__init__()
        if net not in _CONV_LAYOUT:
            raise ValueError(f"net must be 'alex' or 'vgg', got {net!r}")
        self.net = net
        self.convs = torch.nn.ModuleDict(
            {str(i): torch.nn.Conv2d(cin, cout, k, s, p) for i, cin, cout, k, s, p in _CONV_LAYOUT[net]}
        )
        self.lins = torch.nn.ModuleList(torch.nn.Conv2d(c, 1, 1, bias=False) for c in _TAP_CHANNELS[net])
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))

    def load_weights(self, backbone: dict, lin: dict, source: str = "") -> None:
        sd = {}
        for i, *_ in _CONV_LAYOUT[self.net]:
            for part in ("weight", "bias"):
                key = next((k for k in (f"features.{i}.{part}", f"{i}.{part}", f"net.features.{i}.{part}")
                            if k in backbone), None)
                if key is None:
                    raise WeightsUnavailableError(
                        f"backbone weights {source} lack features.{i}.{part}; expected a torchvision {self.net} "
                        "state dict"
                    )
                sd[f"convs.{i}.{part}"] = backbone[key]
        for j in range(len(_TAP_CHANNELS[self.net])):
            key = next((k for k in (f"lin{j}.model.1.weight", f"lin{j}.weight", f"lins.{j}.model.1.weight",
                                    f"lins.{j}.weight") if k in lin), None)
            if key is None:
                raise WeightsUnavailableError(
                    f"LPIPS linear weights {source} lack lin{j}.model.1.weight; expected the lpips v0.1 {self.net}.pth"
                )
            sd[f"lins.{j}.weight"] = lin[key]
        try:
            self.load_state_dict(sd, strict=False)
        except RuntimeError as exc:
            raise WeightsUnavailableError(f"LPIPS weights {source} have the wrong shapes: {exc}") from exc

    def _taps(self, x: torch.Tensor) -> list:
        taps = []
        if self.net == "alex":
            x = F.relu(self.convs["0"](x)); taps.append(x)  # noqa: E702
            x = F.max_pool2d(x, 3, 2)
            x = F.relu(self.convs["3"](x)); taps.append(x)  # noqa: E702
            x = F.max_pool2d(x, 3, 2)
            x = F.relu(self.convs["6"](x)); taps.append(x)  # noqa: E702
            x = F.relu(self.convs["8"](x)); taps.append(x)  # noqa: E702
            x = F.relu(self.convs["10"](x)); taps.append(x)  # noqa: E702
            return taps
        blocks = [[0, 2], [5, 7], [10, 12, 14], [17, 19, 21], [24, 26, 28]]
        for b, idx in enumerate(blocks):
            if b:
                x = F.max_pool2d(x, 2, 2)
            for i in idx:
                x = F.relu(self.convs[str(i)](x))
            taps.append(x)
        return taps

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """a, b: (N,3,H,W) in [-1,1]. Returns (N,) distances."""
        fa = self._taps((a - self.shift) / self.scale)
        fb = self._taps((b - self.shift) / self.scale)
        total = 0.0
        for lin, xa, xb in zip(self.lins, fa, fb):
            na = xa / (xa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            nb = xb / (xb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((na - nb) ** 2).mean(dim=(2, 3))
        return total.view(-1)


def load_lpips(cache_dir=None, net: str = "alex") -> LPIPS:
    """The LPIPS network with weights from the local cache (cached per folder). No downloads."""
    folder = weights_dir(cache_dir)
    key = (os.path.abspath(folder), net)
    with _LPIPS_LOCK:
        if key in _LPIPS_CACHE:
            return _LPIPS_CACHE[key]
        if net not in _BACKBONE_FILES:
            raise ValueError(f"net must be 'alex' or 'vgg', got {net!r}")
        bb_path, lin_path = _find(folder, _BACKBONE_FILES[net]), _find(folder, _LIN_FILES[net])
        if bb_path is None or lin_path is None:
            raise WeightsUnavailableError(_missing_message(folder, net))
        model = LPIPS(net)
        model.load_weights(_load_state(bb_path), _load_state(lin_path), source=f"{bb_path} / {lin_path}")
        model.eval().requires_grad_(False)
        _LPIPS_CACHE[key] = model
        return model


def compute_lpips(pred, gt, cache_dir=None, net: str = "alex") -> float:
    """LPIPS distance between images in [0,1] ((H,W,3) or (N,H,W,3)); mean over the batch.

    Raises :class:`WeightsUnavailableError` (saying which files to put where) when the weights are
    not in the local cache.
    """
    model = load_lpips(cache_dir, net)
    p, g = _pair(pred, gt)
    if p.shape[-1] != 3:
        raise ValueError(f"compute_lpips needs RGB images (...,3), got {p.shape[-1]} channels")
    a = (p.permute(0, 3, 1, 2).float() * 2 - 1).contiguous()
    b = (g.permute(0, 3, 1, 2).float() * 2 - 1).contiguous()
    with torch.no_grad():
        return float(model(a, b).mean())
