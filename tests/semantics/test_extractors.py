"""2D feature extractors: the weight-free default and the DINO ViT (random weights; local files only)."""
import os

import numpy as np
import pytest
import torch

import neumesh_core as nm
from neumesh_core.semantics.extractors import (ColourTextureExtractor, DinoExtractor, build_dino_model,
                                               find_dino_weights, make_extractor)


def _two_colour_image(h=48, w=64, shade=1.0):
    img = np.zeros((h, w, 3), np.float32)
    img[:, : w // 2] = np.array([0.8, 0.15, 0.1]) * shade
    img[:, w // 2:] = np.array([0.15, 0.3, 0.85]) * shade
    return img


def test_colour_texture_separates_colours_and_ignores_shading():
    ex = make_extractor()
    assert isinstance(ex, ColourTextureExtractor) and ex.name == "colour-texture"
    img = _two_colour_image()
    f = ex(img)
    assert f.shape[:2] == img.shape[:2] and f.dtype == np.float32 and np.isfinite(f).all()
    left, right = f[10:38, 2:16].reshape(-1, f.shape[-1]), f[10:38, 48:62].reshape(-1, f.shape[-1])
    spread = max(np.linalg.norm(left - left.mean(0), axis=1).max(), np.linalg.norm(right - right.mean(0), axis=1).max())
    gap = np.linalg.norm(left.mean(0) - right.mean(0))
    assert gap > 5 * spread
    # the same colours in shadow: chromaticity channels do not move, so the two sides stay apart by more
    # than the shadow moves either side
    g = ex(_two_colour_image(shade=0.6))
    shadow = np.linalg.norm(g[20, 10] - f[20, 10])
    assert gap > 2 * shadow
    assert np.array_equal(ex(img), f)   # deterministic (same process, same path)


def test_texture_separates_stripes_from_flat_of_the_same_mean_colour():
    h, w = 48, 96
    img = np.full((h, w, 3), 0.5, np.float32)
    stripes = (np.arange(w // 2) // 3) % 2 == 0
    img[:, : w // 2] = np.where(stripes[None, :, None], 0.8, 0.2)
    f = ColourTextureExtractor()(img)
    a, b = f[24, 12], f[24, 84]
    assert np.linalg.norm(a - b) > 0.1


def test_mask_keeps_the_background_out():
    img = _two_colour_image()
    mask = np.ones(img.shape[:2], np.float32)
    mask[:, :8] = 0
    img2 = img.copy()
    img2[:, :8] = 1.0                     # a different background behind the mask
    ex = make_extractor()
    a, b = ex(img, mask), ex(img2, mask)
    assert np.allclose(a[:, 16:], b[:, 16:], atol=1e-4)
    with pytest.raises(ValueError, match="mask shape"):
        ex(img, mask[:10])
    with pytest.raises(ValueError, match=r"\(H,W,3\)"):
        ex(img[..., 0])


def test_unknown_extractor_is_a_clear_error():
    with pytest.raises(ValueError, match="colour-texture"):
        make_extractor("resnet")
    with pytest.raises(ValueError, match="no weights"):
        make_extractor("colour-texture", weights="x.safetensors")


def test_missing_dino_weights_name_the_expected_file(tmp_path, monkeypatch):
    monkeypatch.setenv("NEUMESH_WEIGHTS", str(tmp_path / "w"))
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.delenv("HF_HUB_CACHE", raising=False)
    with pytest.raises(nm.WeightsUnavailableError) as e:
        make_extractor("dino-vits8")
    msg = str(e.value)
    assert os.path.join(str(tmp_path / "w"), "dino-vits8.safetensors") in msg
    assert "facebook/dino-vits8" in msg and "Nothing is downloaded" in msg
    with pytest.raises(nm.WeightsUnavailableError, match="does not exist"):
        make_extractor("dino-vits16", weights=str(tmp_path / "nope.safetensors"))


pytest.importorskip("transformers")   # the rest needs the [dino] extra (installed by setup.sh)


@pytest.mark.parametrize("name,patch,width", [("dino-vits16", 16, 384), ("dinov2-small", 14, 384)])
def test_dino_random_weights_give_patch_token_maps(name, patch, width):
    torch.manual_seed(0)
    ex = DinoExtractor(name, model=build_dino_model(name), image_size=2 * patch)
    f = ex(np.random.default_rng(0).random((40, 60, 3)).astype(np.float32))
    assert f.shape == (2, 3, width) and np.isfinite(f).all()
    assert np.allclose(np.linalg.norm(f, axis=-1), 1.0, atol=1e-5)


def test_dino_weights_load_from_the_weights_folder(tmp_path, monkeypatch):
    from safetensors.torch import save_file

    monkeypatch.setenv("NEUMESH_WEIGHTS", str(tmp_path))
    torch.manual_seed(1)
    model = build_dino_model("dino-vits16")
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(tmp_path / "dino-vits16.safetensors"))
    assert find_dino_weights("dino-vits16") == str(tmp_path / "dino-vits16.safetensors")
    img = np.random.default_rng(1).random((32, 32, 3)).astype(np.float32)
    loaded = make_extractor("dino-vits16", image_size=32)
    ref = DinoExtractor("dino-vits16", model=model, image_size=32)
    assert np.allclose(loaded(img), ref(img), atol=1e-5)
    # a file that does not fit the architecture is refused with a clear error
    save_file({"embeddings.cls_token": torch.zeros(1, 1, 8)}, str(tmp_path / "bad.safetensors"))
    with pytest.raises(nm.WeightsUnavailableError, match="does not fit"):
        make_extractor("dino-vits16", weights=str(tmp_path / "bad.safetensors"))
