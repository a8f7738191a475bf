"""Image reading / writing with PIL + numpy (no OpenCV, no imageio dependency).

Convention: images are float32 numpy arrays (H,W,C) with values in [0,1]; C is 1, 3 or 4.
"""
from __future__ import annotations

import os
import tempfile

import numpy as np

from .errors import DataError


def _pil():
    from PIL import Image

    return Image


def read_image(path: str, reduce: int = 1) -> np.ndarray:
    """Read a PNG/JPG (8 or 16 bit; grey, grey+alpha, RGB or RGBA) as float32 (H,W,C) in [0,1].

    Greyscale images come back as (H,W,1), grey+alpha as (H,W,2); alpha is kept. Palette images are
    expanded to RGB(A). ``reduce`` n > 1 area-downscales by n while reading, colour weighted by
    alpha (same as ``resize_image(img, 1/n, premultiplied_alpha=True)`` up to 8-bit rounding; PIL's
    box reduce on the stored data when the size is divisible by n, ~3x faster). Raises :class:`DataError`
    naming the file when it is missing or unreadable.
    """
    path = os.fspath(path)
    reduce = int(reduce)
    if reduce < 1:
        raise ValueError(f"read_image: reduce must be an integer >= 1, got {reduce}")
    if not os.path.isfile(path):
        raise DataError(f"image not found: {path}; check the dataset folder and file names")
    Image = _pil()
    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            if mode == "P":
                im = im.convert("RGBA" if "transparency" in im.info else "RGB")
            elif mode in ("CMYK", "YCbCr", "LAB", "HSV", "RGBX"):
                im = im.convert("RGB")
            elif mode == "1":
                im = im.convert("L")
            mode = im.mode
            w, h = im.size
            if reduce > 1 and mode in ("L", "LA", "RGB", "RGBA") and w % reduce == 0 and h % reduce == 0:
                im = im.reduce(reduce)
                reduce = 1
            if mode == "F":
                arr = np.clip(np.asarray(im, dtype=np.float32), 0.0, 1.0)[..., None]
            elif mode.startswith("I;16") or mode == "I":
                # 16-bit greyscale (PIL has no 16-bit RGB mode; such PNGs load as 8-bit RGB)
                raw = np.asarray(im).astype(np.float32)
                scale = 65535.0 if (mode.startswith("I;16") or raw.max() > 255) else 255.0
                arr = np.clip(raw / scale, 0.0, 1.0)[..., None]
            else:
                arr = np.asarray(im)
    except DataError:
        raise
    except Exception as exc:  # PIL raises UnidentifiedImageError, OSError, SyntaxError ...
        raise DataError(f"could not read image {path}: {exc}; the file is corrupt or not an image") from exc
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.dtype == np.uint8:
        arr = arr.astype(np.float32) * np.float32(1.0 / 255.0)
    elif arr.dtype == np.uint16:
        arr = arr.astype(np.float32) * np.float32(1.0 / 65535.0)
    elif arr.dtype != np.float32:
        arr = np.clip(arr.astype(np.float32), 0.0, 1.0)
    if reduce > 1:  # same weighting as PIL's reduce (premultiplied alpha)
        arr = resize_image(arr, 1.0 / reduce, premultiplied_alpha=True)
    return arr


def srgb_to_linear(x) -> np.ndarray:
    """sRGB-encoded values (display-referred, what a field renders and photos hold) decoded to linear
    light with the sRGB transfer function, as float32; negative values count as 0."""
    x = np.clip(np.asarray(x, np.float32), 0.0, None)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _to_uint8(array) -> np.ndarray:
    try:
        import torch

        if isinstance(array, torch.Tensor):
            array = array.detach().cpu().numpy()
    except ImportError:  # pragma: no cover
        pass
    arr = np.asarray(array)
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[-1] not in (2, 3, 4)):
        raise ValueError(f"save_image: expected (H,W), (H,W,3) or (H,W,4) array, got shape {arr.shape}")
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    if arr.dtype == bool:
        return arr.astype(np.uint8) * 255
    arr = np.nan_to_num(arr.astype(np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    return np.ascontiguousarray((np.clip(arr, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8))


def save_image(path: str, array) -> None:
    """Write an image (float [0,1] or uint8; (H,W), (H,W,3) or (H,W,4)) as PNG (or JPG by extension).

    The write is atomic (temporary file in the same folder, then ``os.replace``); parent folders are
    created. Values outside [0,1] are clipped.
    """
    path = os.fspath(path)
    data = _to_uint8(array)
    Image = _pil()
    im = Image.fromarray(data)  # mode inferred from the shape: L, LA, RGB or RGBA
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    ext = os.path.splitext(path)[1].lower()
    fmt = {".jpg": "JPEG", ".jpeg": "JPEG"}.get(ext, "PNG")
    if fmt == "JPEG" and im.mode in ("RGBA", "LA"):
        im = im.convert("RGB" if im.mode == "RGBA" else "L")
    fd, tmp = tempfile.mkstemp(prefix=".tmp_", suffix=ext or ".png", dir=folder)
    try:
        with os.fdopen(fd, "wb") as fh:
            im.save(fh, format=fmt, **({"quality": 95} if fmt == "JPEG" else {"compress_level": 1}))
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def resize_image(arr: np.ndarray, factor: float, premultiplied_alpha: bool = False) -> np.ndarray:
    """Resize a float image (H,W) or (H,W,C) by ``factor`` (0.5 halves it) with area averaging.

    Integer downscales (factor = 1/n) use an exact block mean; other factors use PIL's BOX filter per
    channel in float32. The output size is ``round(H*factor) x round(W*factor)``.
    ``premultiplied_alpha``: for (H,W,2|4) images the colour is averaged weighted by alpha (as PIL
    does for RGBA), so compositing the result equals downscaling the composited image.
    """
    arr = np.asarray(arr, dtype=np.float32)
    if premultiplied_alpha and arr.ndim == 3 and arr.shape[2] in (2, 4):
        a = arr[..., -1:]
        pre = np.concatenate([arr[..., :-1] * a, a], -1)
        out = resize_image(pre, factor)
        a2 = out[..., -1:]
        col = np.where(a2 > 1e-8, out[..., :-1] / np.maximum(a2, 1e-8), 0.0)
        return np.concatenate([np.clip(col, 0.0, 1.0), a2], -1).astype(np.float32)
    if factor == 1:
        return arr
    if factor <= 0:
        raise ValueError(f"resize_image: factor must be > 0, got {factor}")
    h, w = arr.shape[:2]
    nh, nw = max(1, int(round(h * factor))), max(1, int(round(w * factor)))
    inv = 1.0 / factor
    n = int(round(inv))
    if abs(inv - n) < 1e-9 and n >= 1 and h % n == 0 and w % n == 0:
        shp = (h // n, n, w // n, n) + arr.shape[2:]
        return arr.reshape(shp).mean(axis=(1, 3), dtype=np.float32)
    Image = _pil()
    squeeze = arr.ndim == 2
    a3 = arr[..., None] if squeeze else arr
    out = np.empty((nh, nw, a3.shape[2]), dtype=np.float32)
    for c in range(a3.shape[2]):
        im = Image.fromarray(np.ascontiguousarray(a3[..., c]))  # float32 -> mode "F"
        out[..., c] = np.asarray(im.resize((nw, nh), resample=Image.BOX), dtype=np.float32)
    return out[..., 0] if squeeze else out
