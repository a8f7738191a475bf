"""read_image / save_image / resize_image / srgb_to_linear."""
import os

import numpy as np
import pytest
from PIL import Image

from neumesh_core.errors import DataError
from neumesh_core.imageio import read_image, resize_image, save_image, srgb_to_linear


def test_png_round_trip_rgba_and_rgb(tmp_path):
    rng = np.random.default_rng(0)
    rgba = rng.random((7, 9, 4)).astype(np.float32)
    p = tmp_path / "sub" / "dir" / "a.png"  # folders are created
    save_image(str(p), rgba)
    back = read_image(str(p))
    assert back.shape == (7, 9, 4) and back.dtype == np.float32
    np.testing.assert_allclose(back, rgba, atol=0.5 / 255 + 1e-6)
    save_image(str(tmp_path / "b.png"), (rgba[..., :3] * 255).astype(np.uint8))
    assert read_image(str(tmp_path / "b.png")).shape == (7, 9, 3)
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".tmp")]  # no temporaries left


def test_save_clips_and_rejects_bad_shapes(tmp_path):
    save_image(str(tmp_path / "c.png"), np.array([[[-1.0, 0.5, 2.0]]], dtype=np.float32))
    np.testing.assert_allclose(read_image(str(tmp_path / "c.png"))[0, 0], [0, 128 / 255, 1], atol=1e-6)
    with pytest.raises(ValueError):
        save_image(str(tmp_path / "d.png"), np.zeros((4, 4, 5)))


def test_read_16bit_and_grey(tmp_path):
    a16 = (np.arange(12, dtype=np.uint16).reshape(3, 4) * 5000).astype(np.uint16)
    Image.fromarray(a16).save(tmp_path / "g16.png")
    g = read_image(str(tmp_path / "g16.png"))
    assert g.shape == (3, 4, 1)
    np.testing.assert_allclose(g[..., 0], a16 / 65535.0, atol=1e-6)
    Image.fromarray(np.full((2, 2), 51, np.uint8)).save(tmp_path / "g8.png")
    np.testing.assert_allclose(read_image(str(tmp_path / "g8.png")), 0.2, atol=1e-6)


def test_jpg_and_errors(tmp_path):
    save_image(str(tmp_path / "x.jpg"), np.full((8, 8, 3), 0.5, np.float32))
    assert abs(float(read_image(str(tmp_path / "x.jpg")).mean()) - 0.5) < 0.02
    with pytest.raises(DataError, match="missing.png"):
        read_image(str(tmp_path / "missing.png"))
    (tmp_path / "bad.png").write_bytes(b"not an image at all")
    with pytest.raises(DataError, match="bad.png"):
        read_image(str(tmp_path / "bad.png"))


def test_resize_area_average():
    a = np.arange(16, dtype=np.float32).reshape(4, 4)
    np.testing.assert_allclose(resize_image(a, 0.5), [[2.5, 4.5], [10.5, 12.5]])
    rgb = np.random.default_rng(1).random((6, 9, 3)).astype(np.float32)
    r = resize_image(rgb, 1 / 3)
    assert r.shape == (2, 3, 3)
    np.testing.assert_allclose(r[0, 0], rgb[:3, :3].reshape(-1, 3).mean(0), atol=1e-6)
    odd = resize_image(rgb, 0.5)  # non-integer block: PIL BOX
    assert odd.shape == (3, 4, 3)  # round(4.5) == 4
    assert abs(float(odd.mean()) - float(rgb.mean())) < 0.05
    np.testing.assert_array_equal(resize_image(rgb, 1), rgb)


def test_read_with_reduce_matches_resize(tmp_path):
    rng = np.random.default_rng(2)
    img = rng.random((12, 16, 4)).astype(np.float32)
    save_image(str(tmp_path / "r.png"), img)
    full = read_image(str(tmp_path / "r.png"))
    composite_full = full[..., :3] * full[..., 3:] + (1 - full[..., 3:])
    for n in (2, 4):
        fast = read_image(str(tmp_path / "r.png"), reduce=n)
        assert fast.shape == (12 // n, 16 // n, 4)
        slow = resize_image(full, 1 / n, premultiplied_alpha=True)
        np.testing.assert_allclose(fast[..., 3], slow[..., 3], atol=0.51 / 255)
        # compositing the reduced image == reducing the composited image
        comp = fast[..., :3] * fast[..., 3:] + (1 - fast[..., 3:])
        np.testing.assert_allclose(comp, resize_image(composite_full, 1 / n), atol=2 / 255)  # PIL rounds in 8 bit
        comp_slow = slow[..., :3] * slow[..., 3:] + (1 - slow[..., 3:])
        np.testing.assert_allclose(comp_slow, resize_image(composite_full, 1 / n), atol=1e-5)
    odd = read_image(str(tmp_path / "r.png"), reduce=5)  # not divisible: float fallback
    np.testing.assert_allclose(odd, resize_image(full, 1 / 5, premultiplied_alpha=True), atol=1e-6)
    rgb = read_image(str(tmp_path / "r.png"))[..., :3]
    save_image(str(tmp_path / "rgb.png"), rgb)
    np.testing.assert_allclose(read_image(str(tmp_path / "rgb.png"), reduce=2), resize_image(rgb, 0.5), atol=0.51 / 255)


def test_srgb_to_linear_is_the_srgb_transfer_function():
    x = np.array([-0.5, 0.0, 0.04045, 0.5, 1.0])
    y = srgb_to_linear(x)
    assert y.dtype == np.float32
    np.testing.assert_allclose(y, [0.0, 0.0, 0.04045 / 12.92, 0.21404114, 1.0], rtol=1e-5, atol=1e-7)
    # the two pieces meet: continuous at the threshold, increasing throughout
    assert abs(float(srgb_to_linear(0.04046)) - 0.04045 / 12.92) < 1e-5
    assert np.all(np.diff(srgb_to_linear(np.linspace(0, 1, 256))) > 0)
