"""2D feature extractors: image (H,W,3) float in [0,1] -> feature map (h,w,C) float32.

Semantic distillation (:mod:`.distill`) only needs this interface (:class:`FeatureExtractor`), so
extractors are pluggable.  Two are built in:

* :class:`ColourTextureExtractor` ("colour-texture", the default): needs no downloaded weights.  Per
  pixel it computes colour in CIELAB at several blur scales and orientation-free texture statistics
  (local contrast, gradient energy and anisotropy of the structure tensor) at the same scales, then
  averages every channel over SLIC superpixels (scikit-image), so each superpixel - a patch of one
  colour and texture - gets one feature.  It separates parts that differ in colour or texture, not
  parts that differ in meaning only.
* :class:`DinoExtractor` ("dino-vits8", "dino-vits16", "dino-vitb8", "dino-vitb16", "dinov2-small",
  "dinov2-base"): a self-supervised ViT's patch tokens.  The architecture is Hugging Face
  ``transformers``' ViT / DINOv2 (an optional dependency: ``pip install 'neumesh[dino]'``); the
  weights are read from a local file or folder, never downloaded (see :func:`find_dino_weights`).
  (timm's ViT would do as well, but every timm release imports torchvision at import time, and the
  torchvision wheel on PyPI does not load beside the pinned CPU torch.)

:func:`make_extractor` builds one by name; :func:`default_extractor_name` is "colour-texture".
"""
from __future__ import annotations

import glob
import os
from dataclasses import asdict, dataclass
from typing import Optional, Sequence

import numpy as np

from ..errors import WeightsUnavailableError


class FeatureExtractor:
    """Interface: ``extractor(image, mask=None) -> (h, w, C) float32``.

    ``image`` (H,W,3) float in [0,1]; ``mask`` (H,W) in [0,1] (foreground) when the data has one.
    The feature map covers the whole image (h/H = w/W need not be 1); callers resample it.
    """

    name = "extractor"

    def __call__(self, image: np.ndarray, mask: Optional[np.ndarray] = None) -> np.ndarray:
        image = np.asarray(image, np.float32)
        if image.ndim != 3 or image.shape[2] < 3:
            raise ValueError(f"{self.name}: expected an (H,W,3) image, got shape {image.shape}")
        if mask is not None:
            mask = np.asarray(mask, np.float32)
            if mask.shape != image.shape[:2]:
                raise ValueError(f"{self.name}: mask shape {mask.shape} does not match the image "
                                 f"{image.shape[:2]}")
        out = self.extract(np.clip(image[..., :3], 0.0, 1.0), mask)
        return np.ascontiguousarray(out, dtype=np.float32)

    def extract(self, image: np.ndarray, mask: Optional[np.ndarray]) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def info(self) -> dict:
        """JSON-friendly description (stored in the field file's header)."""
        return {"name": self.name}


# ----------------------------------------------------------------------------------------- weight-free
@dataclass
class ColourTextureConfig:
    """Settings of :class:`ColourTextureExtractor`.

    ``scales``: Gaussian scales as fractions of the image's shorter side (so a 64 px and a 400 px
    image of the same view give comparable features); ``superpixel_size``: mean superpixel edge in
    pixels (SLIC's n_segments = H*W / size^2); ``compactness``: SLIC's; ``colour_weight`` /
    ``lightness_weight`` / ``texture_weight`` scale the channel groups (lightness mostly follows
    shading, so it counts less than hue and chroma).
    """

    scales: Sequence[float] = (0.0, 0.015, 0.04)
    superpixel_size: float = 4.0
    compactness: float = 10.0
    colour_weight: float = 1.0
    lightness_weight: float = 0.35
    texture_weight: float = 1.0
    max_side: int = 256            # larger images are area-downscaled to this first (the map is resampled anyway)
    embed_dim: int = 0             # random Fourier features of the pooled descriptor (0: the raw descriptor)
    bandwidth: float = 0.5         # their Gaussian kernel's width, in descriptor units
    embed_seed: int = 0


def _blur(x: np.ndarray, sigma: float, mask: Optional[np.ndarray]) -> np.ndarray:
    """Gaussian blur of (H,W[,C]); with a mask, normalised convolution (background does not bleed in)."""
    from scipy.ndimage import gaussian_filter

    if sigma <= 0:
        return x
    sig = (sigma, sigma) + ((0,) if x.ndim == 3 else ())
    if mask is None:
        return gaussian_filter(x, sig, mode="nearest")
    m = mask if x.ndim == 2 else mask[..., None]
    num = gaussian_filter(x * m, sig, mode="nearest")
    den = gaussian_filter(np.broadcast_to(m, x.shape).astype(np.float32), sig, mode="nearest")
    return np.where(den > 1e-3, num / np.maximum(den, 1e-3), x)


class ColourTextureExtractor(FeatureExtractor):
    """The weight-free default (see the module docstring)."""

    name = "colour-texture"

    def __init__(self, config: Optional[ColourTextureConfig] = None):
        self.config = config or ColourTextureConfig()

    def info(self) -> dict:
        return {"name": self.name, **{k: list(v) if isinstance(v, tuple) else v
                                      for k, v in asdict(self.config).items()}}

    def pixel_features(self, image: np.ndarray, mask: Optional[np.ndarray] = None) -> np.ndarray:
        """(H,W,C) per-pixel descriptor before superpixel pooling.

        Per scale: lightness (CIELAB L), hue and chroma (CIELAB a, b), chromaticity (r, g of the
        encoded RGB divided by their sum: unchanged when the light gets brighter or darker, so shading
        does not move it), and texture: local contrast over local mean (also shading-invariant) and the
        structure tensor's anisotropy (stripes vs dots vs flat).
        """
        from scipy.ndimage import binary_erosion, sobel
        from skimage.color import rgb2lab

        cfg = self.config
        h, w = image.shape[:2]
        fg = None if mask is None else (mask > 0.5).astype(np.float32)
        lab = rgb2lab(image).astype(np.float32)
        L = lab[..., 0] / 100.0
        ab = lab[..., 1:] / 60.0
        chroma = (image[..., :2] / np.maximum(image.sum(-1, keepdims=True), 0.05) - 1.0 / 3.0) * 3.0
        gx, gy = sobel(L, 1), sobel(L, 0)
        if fg is not None:   # gradients that reach into the background describe the silhouette, not texture
            inner = binary_erosion(fg > 0, iterations=1)
            gx, gy = gx * inner, gy * inner
        chans = []
        for frac in cfg.scales:
            s = float(frac) * min(h, w)
            chans.append(cfg.lightness_weight * cfg.colour_weight * _blur(L, s, fg)[..., None])
            chans.append(cfg.colour_weight * _blur(ab, s, fg))
            chans.append(cfg.colour_weight * _blur(chroma, s, fg))
            # texture in a window ~2x the scale: contrast relative to brightness, and anisotropy
            t = max(1.0, 2.0 * s)
            mu = _blur(L, t, fg)
            contrast = np.sqrt(np.maximum(_blur(L * L, t, fg) - mu * mu, 0.0)) / (mu + 0.1)
            jxx, jyy, jxy = _blur(gx * gx, t, fg), _blur(gy * gy, t, fg), _blur(gx * gy, t, fg)
            aniso = np.sqrt((jxx - jyy) ** 2 + 4 * jxy ** 2) / np.maximum(jxx + jyy, 1e-6)
            chans.append(cfg.texture_weight * np.stack([contrast, 0.5 * aniso], -1))
        return np.concatenate(chans, -1).astype(np.float32)

    def superpixels(self, image: np.ndarray) -> np.ndarray:
        """(H,W) int labels of SLIC superpixels (grid-initialised; the mask is applied when pooling,
        which is several times faster than SLIC's masked k-means initialisation)."""
        from skimage.segmentation import slic

        h, w = image.shape[:2]
        n = max(4, int(round(h * w / self.config.superpixel_size ** 2)))
        return slic(image, n_segments=n, compactness=self.config.compactness, start_label=0,
                    channel_axis=-1).astype(np.int64)

    def extract(self, image: np.ndarray, mask: Optional[np.ndarray]) -> np.ndarray:
        h, w = image.shape[:2]
        s = min(1.0, self.config.max_side / max(h, w))
        if s < 1.0:
            from skimage.transform import resize

            size = (max(1, int(round(h * s))), max(1, int(round(w * s))))
            image = resize(image, size + (3,), anti_aliasing=True).astype(np.float32)
            mask = None if mask is None else resize(mask, size, anti_aliasing=True).astype(np.float32)
        feats = self.pixel_features(image, mask)
        labels = self.superpixels(image)
        n = int(labels.max()) + 1
        flat = labels.reshape(-1)
        # mean over each superpixel's foreground pixels (all of them without a mask)
        wgt = np.ones(flat.shape, np.float64) if mask is None else (mask.reshape(-1) > 0.5).astype(np.float64)
        count = np.bincount(flat, weights=wgt, minlength=n)
        pooled = np.stack([np.bincount(flat, weights=feats[..., c].reshape(-1) * wgt, minlength=n)
                           for c in range(feats.shape[-1])], -1) / np.maximum(count, 1e-9)[:, None]
        out = self.embed(pooled)[labels]
        if mask is not None:   # pixels of superpixels without foreground keep their own feature
            empty = (count <= 0)[labels]
            out[empty] = self.embed(feats[empty].astype(np.float64))
        return out.astype(np.float32)

    def embed(self, desc: np.ndarray) -> np.ndarray:
        """Random Fourier features (Rahimi & Recht) of descriptors (P,D): unit-length vectors whose dot
        products approximate the Gaussian kernel exp(-|a-b|^2 / (2 bandwidth^2)), so cosine similarity
        of the output measures descriptor distance (and no part's feature sits near the origin)."""
        cfg = self.config
        if cfg.embed_dim <= 0:
            return desc
        rng = np.random.default_rng(cfg.embed_seed)
        W = rng.normal(0.0, 1.0 / cfg.bandwidth, size=(desc.shape[1], cfg.embed_dim))
        b = rng.uniform(0.0, 2 * np.pi, size=cfg.embed_dim)
        return np.sqrt(2.0 / cfg.embed_dim) * np.cos(desc @ W + b)


# ----------------------------------------------------------------------------------------- DINO ViT
# name -> (Hugging Face repository, family, hidden size, layers, heads, mlp width, patch size)
DINO_MODELS = {
    "dino-vits8": ("facebook/dino-vits8", "vit", 384, 12, 6, 1536, 8),
    "dino-vits16": ("facebook/dino-vits16", "vit", 384, 12, 6, 1536, 16),
    "dino-vitb8": ("facebook/dino-vitb8", "vit", 768, 12, 12, 3072, 8),
    "dino-vitb16": ("facebook/dino-vitb16", "vit", 768, 12, 12, 3072, 16),
    "dinov2-small": ("facebook/dinov2-small", "dinov2", 384, 12, 6, 1536, 14),
    "dinov2-base": ("facebook/dinov2-base", "dinov2", 768, 12, 12, 3072, 14),
}
_WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin")
_IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
_IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)


def _weights_dir() -> str:
    from ..metrics import weights_dir

    return weights_dir()


def _hf_cache_dirs() -> list:
    out = []
    if os.environ.get("HF_HUB_CACHE"):
        out.append(os.environ["HF_HUB_CACHE"])
    hf_home = os.environ.get("HF_HOME") or os.path.join(os.path.expanduser("~"), ".cache", "huggingface")
    out.append(os.path.join(hf_home, "hub"))
    return out


def dino_weight_candidates(name: str, weights: Optional[str] = None) -> list:
    """The paths searched, in order, for the weights of DINO model ``name``."""
    if name not in DINO_MODELS:
        raise ValueError(f"unknown DINO model {name!r}; known: {', '.join(DINO_MODELS)}")
    repo = DINO_MODELS[name][0]
    if weights:
        w = os.path.expanduser(os.fspath(weights))
        return [os.path.join(w, f) for f in _WEIGHT_FILES] if os.path.isdir(w) else [w]
    d = _weights_dir()
    cands = [os.path.join(d, f"{name}.safetensors"), os.path.join(d, f"{name}.bin")]
    cands += [os.path.join(d, name, f) for f in _WEIGHT_FILES]
    for hub in _hf_cache_dirs():
        snap = os.path.join(hub, "models--" + repo.replace("/", "--"), "snapshots")
        for f in _WEIGHT_FILES:
            cands += sorted(glob.glob(os.path.join(snap, "*", f)))
    return cands


def find_dino_weights(name: str, weights: Optional[str] = None) -> str:
    """Path of a local weights file for DINO model ``name``, or :class:`WeightsUnavailableError`
    naming the expected file and where to put it.  Nothing is downloaded.

    Searched: ``weights`` (a file, or a folder holding model.safetensors / pytorch_model.bin) when
    given; else ``$NEUMESH_WEIGHTS/<name>.safetensors`` (default folder ~/.cache/neumesh/weights),
    ``$NEUMESH_WEIGHTS/<name>/model.safetensors`` and the Hugging Face hub cache
    (``$HF_HOME/hub/models--facebook--<model>/snapshots/*/``).
    """
    cands = dino_weight_candidates(name, weights)
    for c in cands:
        if os.path.isfile(c):
            return c
    repo = DINO_MODELS[name][0]
    if weights:
        where = f"{weights} does not exist" if not os.path.exists(os.path.expanduser(weights)) else \
            f"{weights} holds none of {', '.join(_WEIGHT_FILES)}"
        raise WeightsUnavailableError(f"DINO weights for {name}: {where}. Point --weights at the "
                                      f"model.safetensors of the Hugging Face repository {repo}.")
    d = _weights_dir()
    raise WeightsUnavailableError(
        f"no local weights for the DINO extractor {name}: expected {os.path.join(d, name + '.safetensors')} "
        f"(or {os.path.join(d, name, 'model.safetensors')}, or the Hugging Face cache of {repo}). "
        f"Nothing is downloaded: on a machine with internet get model.safetensors from the Hugging Face "
        f"repository {repo}, copy it there (set $NEUMESH_WEIGHTS to use another folder), or use the "
        f"weight-free extractor 'colour-texture'.")


def _transformers():
    try:
        import transformers  # noqa: F401
    except ImportError as exc:
        raise ImportError(
            "the DINO extractor needs the 'transformers' package (ViT / DINOv2 architectures): "
            "pip install 'neumesh[dino]' (or pip install transformers), or use the weight-free "
            "extractor 'colour-texture'") from exc
    import transformers

    return transformers


def build_dino_model(name: str):
    """The architecture of DINO model ``name`` with random weights (transformers ViTModel/Dinov2Model)."""
    if name not in DINO_MODELS:
        raise ValueError(f"unknown DINO model {name!r}; known: {', '.join(DINO_MODELS)}")
    tf = _transformers()
    _, family, hidden, layers, heads, mlp, patch = DINO_MODELS[name]
    if family == "vit":
        cfg = tf.ViTConfig(hidden_size=hidden, num_hidden_layers=layers, num_attention_heads=heads,
                           intermediate_size=mlp, patch_size=patch, image_size=224, qkv_bias=True,
                           layer_norm_eps=1e-6)
        model = tf.ViTModel(cfg, add_pooling_layer=False)
    else:
        cfg = tf.Dinov2Config(hidden_size=hidden, num_hidden_layers=layers, num_attention_heads=heads,
                              mlp_ratio=mlp // hidden, patch_size=patch, image_size=518)
        model = tf.Dinov2Model(cfg)
    return model.eval()


def load_state_dict_file(path: str) -> dict:
    """Tensors of a .safetensors file, or of a torch file read with ``weights_only=True`` (no code runs)."""
    import torch

    if path.endswith(".safetensors"):
        from safetensors.torch import load_file

        return load_file(path)
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001
        raise WeightsUnavailableError(f"{path} is not a readable weights file ({exc})") from exc
    if isinstance(sd, dict) and "state_dict" in sd and isinstance(sd["state_dict"], dict):
        sd = sd["state_dict"]
    return sd


def load_dino_weights(model, path: str) -> None:
    """Load a Hugging Face ViTModel/Dinov2Model state dict (``vit.``/``dinov2.`` prefixes and pooler
    entries are ignored) into ``model``; a clear error when it does not fit the architecture."""
    sd = load_state_dict_file(path)
    clean = {}
    for k, v in sd.items():
        for pre in ("vit.", "dinov2.", "model."):
            if k.startswith(pre):
                k = k[len(pre):]
        if k.startswith(("pooler.", "classifier.", "head.")):
            continue
        clean[k] = v
    own = model.state_dict()
    missing = [k for k in own if k not in clean]
    unexpected = [k for k in clean if k not in own]
    wrong = [k for k in own if k in clean and tuple(clean[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or wrong:
        raise WeightsUnavailableError(
            f"{path} does not fit this architecture ({len(missing)} missing, {len(unexpected)} unexpected, "
            f"{len(wrong)} misshapen entries, e.g. {(wrong + missing + unexpected)[:3]}); is it the "
            "model.safetensors of the matching Hugging Face DINO repository?")
    model.load_state_dict(clean, strict=True)


class DinoExtractor(FeatureExtractor):
    """Patch tokens of a DINO / DINOv2 ViT (last layer, class token dropped), L2-normalised.

    ``weights``: a file or folder (default: searched by :func:`find_dino_weights`); ``model``: an
    already built ``transformers`` model to use as is (tests use random weights).  ``image_size``: the
    shorter image side fed to the ViT (rounded to whole patches; the position embeddings are
    interpolated).
    """

    def __init__(self, name: str = "dino-vits8", weights: Optional[str] = None, image_size: int = 224,
                 model=None, threads: Optional[int] = None):
        if name not in DINO_MODELS:
            raise ValueError(f"unknown DINO model {name!r}; known: {', '.join(DINO_MODELS)}")
        self.name = name
        self.image_size = int(image_size)
        self.patch = DINO_MODELS[name][6]
        self.weights_path = None
        if model is None:
            # the weights first: a missing file is reported even where transformers is not installed
            self.weights_path = find_dino_weights(name, weights)
            model = build_dino_model(name)
            load_dino_weights(model, self.weights_path)
        self.model = model.eval()

    def info(self) -> dict:
        return {"name": self.name, "image_size": self.image_size, "weights": self.weights_path}

    def extract(self, image: np.ndarray, mask: Optional[np.ndarray]) -> np.ndarray:
        import torch
        import torch.nn.functional as F

        h, w = image.shape[:2]
        s = self.image_size / min(h, w)
        gh = max(1, int(round(h * s / self.patch)))
        gw = max(1, int(round(w * s / self.patch)))
        x = torch.from_numpy((image - _IMAGENET_MEAN) / _IMAGENET_STD).permute(2, 0, 1)[None]
        x = F.interpolate(x, size=(gh * self.patch, gw * self.patch), mode="bilinear", align_corners=False,
                          antialias=True)
        kwargs = {"interpolate_pos_encoding": True} if DINO_MODELS[self.name][1] == "vit" else {}
        with torch.no_grad():
            tokens = self.model(pixel_values=x, **kwargs).last_hidden_state[0]
        patches = tokens[tokens.shape[0] - gh * gw:]   # drop the class (and register) tokens
        patches = F.normalize(patches, dim=-1)
        return patches.reshape(gh, gw, -1).numpy()


# ----------------------------------------------------------------------------------------- registry
EXTRACTORS = ("colour-texture",) + tuple(DINO_MODELS)


def default_extractor_name() -> str:
    """The weight-free extractor: always available, needs nothing downloaded."""
    return "colour-texture"


def make_extractor(name: Optional[str] = None, weights: Optional[str] = None, **kwargs) -> FeatureExtractor:
    """An extractor by name (see :data:`EXTRACTORS`); None gives the default ("colour-texture")."""
    name = name or default_extractor_name()
    if name in ("colour-texture", "color-texture"):
        if weights:
            raise ValueError("the colour-texture extractor has no weights; drop --weights")
        return ColourTextureExtractor(ColourTextureConfig(**kwargs) if kwargs else None)
    if name in DINO_MODELS:
        return DinoExtractor(name, weights=weights, **kwargs)
    raise ValueError(f"unknown feature extractor {name!r}; choose one of {', '.join(EXTRACTORS)}")
