"""2D segmenters for selection: ``segmenter(field, camera, (x, y)) -> (H,W) bool`` region of the click.

* :class:`FeatureSegmenter` ("features", weight-free, the default): renders the field's semantic
  features for the view (at most ``max_side`` pixels along the longer side, then upsampled) and takes
  the connected region of pixels whose feature has a cosine similarity >= ``threshold`` with the
  clicked pixel's.
* :class:`SamSegmenter` ("sam"): Segment Anything (Hugging Face ``transformers``' SamModel, an optional
  dependency) prompted with the click on the field's colour render; weights from a local folder or file
  (``$NEUMESH_WEIGHTS/sam-vit-base/`` or the Hugging Face cache), never downloaded.
"""
from __future__ import annotations

import glob
import os
from typing import Optional

import numpy as np

from ..errors import SelectionError, WeightsUnavailableError


def _scaled_camera(K, width, height, max_side):
    s = min(1.0, float(max_side) / max(width, height))
    w, h = max(1, int(round(width * s))), max(1, int(round(height * s)))
    K2 = np.array(K, np.float32)
    K2[0] *= w / width
    K2[1] *= h / height
    return K2, w, h


class FeatureSegmenter:
    """Connected region of similar rendered semantic features around the click (weight-free)."""

    name = "features"

    def __init__(self, threshold: float = 0.75, max_side: int = 96, min_opacity: float = 0.5):
        self.threshold = float(threshold)
        self.max_side = int(max_side)
        self.min_opacity = float(min_opacity)

    def __call__(self, field, camera, pixel) -> np.ndarray:
        from scipy.ndimage import label

        from ..render.renderer import render_camera

        K, c2w, width, height = camera
        K2, w, h = _scaled_camera(K, width, height, self.max_side)
        out = render_camera(field, K2, c2w, w, h, background=None, semantics=True)
        sem = out.sem / np.maximum(np.linalg.norm(out.sem, axis=-1, keepdims=True), 1e-12)
        x = min(w - 1, int(pixel[0] * w / width))
        y = min(h - 1, int(pixel[1] * h / height))
        if out.opacity[y, x] < self.min_opacity:
            return np.zeros((height, width), bool)
        sim = sem @ sem[y, x]
        ok = (sim >= self.threshold) & (out.opacity >= self.min_opacity)
        lab, _ = label(ok)
        region = lab == lab[y, x]
        if (w, h) != (width, height):
            iy = np.minimum((np.arange(height) + 0.5) * h / height, h - 1).astype(int)
            ix = np.minimum((np.arange(width) + 0.5) * w / width, w - 1).astype(int)
            region = region[iy][:, ix]
        return region


SAM_MODELS = {"sam-vit-base": "facebook/sam-vit-base", "sam-vit-large": "facebook/sam-vit-large",
              "sam-vit-huge": "facebook/sam-vit-huge"}


def find_sam_weights(name: str = "sam-vit-base", weights: Optional[str] = None) -> str:
    """Folder holding config.json + model.safetensors of a Hugging Face SAM repository (a local copy);
    :class:`WeightsUnavailableError` naming the expected folder otherwise."""
    from .extractors import _hf_cache_dirs, _weights_dir

    if name not in SAM_MODELS:
        raise ValueError(f"unknown SAM model {name!r}; known: {', '.join(SAM_MODELS)}")
    repo = SAM_MODELS[name]
    cands = [os.path.expanduser(weights)] if weights else [os.path.join(_weights_dir(), name)]
    if not weights:
        for hub in _hf_cache_dirs():
            cands += sorted(glob.glob(os.path.join(hub, "models--" + repo.replace("/", "--"), "snapshots", "*")))
    for c in cands:
        if os.path.isfile(os.path.join(c, "config.json")) and (
                os.path.isfile(os.path.join(c, "model.safetensors"))
                or os.path.isfile(os.path.join(c, "pytorch_model.bin"))):
            return c
    raise WeightsUnavailableError(
        f"no local weights for the SAM segmenter {name}: expected a folder {cands[0]} holding config.json and "
        f"model.safetensors of the Hugging Face repository {repo}. Nothing is downloaded: copy them there on a "
        f"machine with internet (set $NEUMESH_WEIGHTS for another folder), or use the weight-free "
        f"segmenter 'features'.")


class SamSegmenter:
    """Segment Anything prompted with the click on the field's colour render (the mask with the best
    predicted IoU)."""

    name = "sam"

    def __init__(self, name: str = "sam-vit-base", weights: Optional[str] = None, model=None, processor=None):
        if model is None:
            folder = find_sam_weights(name, weights)
            try:
                from transformers import SamModel, SamProcessor
            except ImportError as exc:
                raise ImportError("the SAM segmenter needs the 'transformers' package: pip install "
                                  "'neumesh[dino]', or use the weight-free segmenter 'features'") from exc
            model = SamModel.from_pretrained(folder, local_files_only=True)
            processor = SamProcessor.from_pretrained(folder, local_files_only=True)
        self.model = model.eval()
        self.processor = processor

    def __call__(self, field, camera, pixel) -> np.ndarray:
        import torch

        from ..render.renderer import render_camera

        K, c2w, width, height = camera
        out = render_camera(field, K, c2w, width, height, background=(1.0, 1.0, 1.0))
        img = (np.clip(out.rgb, 0, 1) * 255).astype(np.uint8)
        inputs = self.processor(img, input_points=[[[float(pixel[0]), float(pixel[1])]]], return_tensors="pt")
        with torch.no_grad():
            res = self.model(**inputs)
        masks = self.processor.image_processor.post_process_masks(
            res.pred_masks, inputs["original_sizes"], inputs["reshaped_input_sizes"])[0][0]
        best = int(res.iou_scores[0, 0].argmax())
        return masks[best].numpy().astype(bool)


def make_segmenter(name: str, **kwargs):
    """A segmenter by name: "features" (weight-free) or "sam" (local weights)."""
    if name == "features":
        return FeatureSegmenter(**kwargs)
    if name == "sam":
        return SamSegmenter(**kwargs)
    raise SelectionError(f"unknown 2D segmenter {name!r}; use 'features' (weight-free) or 'sam'")
