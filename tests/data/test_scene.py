"""ImageSet storage: photos stay uint8 (masks uint8 or bool); the float accessors give what the float32
storage gave (the reference every old code path used)."""
import numpy as np
import pytest
import torch

from neumesh_core.data.cameras import Cameras, intrinsics_from_fov
from neumesh_core.data.scene import ImageSet, as_float


def _cams(n, h=6, w=8):
    K = np.repeat(intrinsics_from_fov(w, h, 0.8)[None], n, 0).astype(np.float32)
    return Cameras(K, np.repeat(np.eye(4, dtype=np.float32)[None], n, 0), w, h)


def _pair(n=3, h=6, w=8, mask_dtype=np.uint8):
    rng = np.random.default_rng(0)
    u8 = rng.integers(0, 256, (n, h, w, 3), dtype=np.uint8)
    m = rng.integers(0, 256, (n, h, w), dtype=np.uint8)
    if mask_dtype == np.bool_:
        m = m > 127
    ref_m = m.astype(np.float32) if mask_dtype == np.bool_ else m.astype(np.float32) / 255.0
    return (ImageSet(_cams(n, h, w), u8, m, ["a", "b", "c"][:n]),
            ImageSet(_cams(n, h, w), u8.astype(np.float32) / 255.0, ref_m, ["a", "b", "c"][:n]))


@pytest.mark.parametrize("mask_dtype", [np.uint8, np.bool_])
def test_float_accessors_match_the_float32_storage(mask_dtype):
    u8, ref = _pair(mask_dtype=mask_dtype)
    assert u8.images.nbytes * 4 == ref.images.nbytes
    for i in range(len(u8)):
        v = u8.float_view(i)
        assert v.dtype == np.float32 and v.shape == (6, 8, 3)
        np.testing.assert_allclose(v, ref.images[i], atol=1e-7)
        np.testing.assert_allclose(u8.float_mask(i), ref.masks[i], atol=1e-7)
    np.testing.assert_allclose(u8.float_images(), ref.images, atol=1e-7)
    np.testing.assert_allclose(u8.float_images([2, 0]), ref.images[[2, 0]], atol=1e-7)
    np.testing.assert_allclose(u8.float_masks([1]), ref.masks[[1]], atol=1e-7)
    sub = u8.subset([1, 2])
    assert sub.images.dtype == np.uint8 and sub.names == ["b", "c"]
    np.testing.assert_allclose(sub.float_view(0), ref.images[1], atol=1e-7)
    # float storage passes through unchanged (no copy)
    assert ref.float_images() is ref.images and ref.float_view(0).dtype == np.float32


def test_as_float_on_tensors_matches_numpy():
    u8, ref = _pair()
    t = as_float(torch.from_numpy(u8.images[:, 1:3, 2:5]))
    assert t.dtype == torch.float32
    np.testing.assert_allclose(t.numpy(), ref.images[:, 1:3, 2:5], atol=1e-7)
    b = as_float(torch.tensor([True, False]))
    assert b.tolist() == [1.0, 0.0]
    assert as_float(None) is None


def test_images_without_a_pixel_type_are_refused():
    cams = _cams(1)
    with pytest.raises(ValueError, match="uint8 or float"):
        ImageSet(cams, np.zeros((1, 6, 8, 3), np.int16))
    with pytest.raises(ValueError, match="masks must be uint8, bool or float"):
        ImageSet(cams, np.zeros((1, 6, 8, 3), np.uint8), np.zeros((1, 6, 8), np.int32))
