"""Lens models of real cameras and their removal (undistortion) with OpenCV, cached on disk.

A :class:`Lens` is one camera as a capture tool stored it: size, focal lengths, principal point and
distortion coefficients, named with COLMAP's camera models (PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV,
FULL_OPENCV, OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE). Pixel convention: as everywhere in
this project (and in COLMAP / instant-ngp), pixel i spans [i, i+1) and its centre is i + 0.5.

Distortion is removed once: :func:`undistort_image` remaps an image to a pinhole camera of the same
size whose field of view keeps only valid pixels (OpenCV ``getOptimalNewCameraMatrix`` with alpha 0;
``estimateNewCameraMatrixForUndistortRectify`` with balance 0 for fisheye lenses).
:func:`undistorted_file` does that for an image file and keeps the result (a .npy, or a PNG for
other programs, and the new K in a JSON) in a cache folder keyed by the file, its size/mtime, the lens
and the downscale, so the next run reads it back. The cache is ``$NEUMESH_CACHE`` or
``$XDG_CACHE_HOME/neumesh`` or ``~/.cache/neumesh`` (``undistorted/`` inside), never the dataset folder
unless asked.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import DataError

# COLMAP model -> parameter names (after fx/fy/cx/cy or f/cx/cy)
_COLMAP_PARAMS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
    "SIMPLE_RADIAL_FISHEYE": ("f", "cx", "cy", "k1"),
    "RADIAL_FISHEYE": ("f", "cx", "cy", "k1", "k2"),
}
SUPPORTED_MODELS = tuple(_COLMAP_PARAMS)
_FISHEYE = ("OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE")
_CACHE_VERSION = 1


@dataclass
class Lens:
    """One physical camera: ``model`` (a COLMAP model name), image size in pixels, pinhole part and
    distortion coefficients by name (k1..k6, p1, p2; absent = 0). ``fisheye`` models use OpenCV's
    equidistant model (k1..k4); the others OpenCV's radial-tangential (rational for k4..k6)."""

    model: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.model not in _COLMAP_PARAMS:
            raise DataError(
                f"camera model {self.model} is not supported (supported: {', '.join(SUPPORTED_MODELS)}); "
                "undistort the images first (COLMAP: `colmap image_undistorter`) and load the PINHOLE result"
            )
        self.width, self.height = int(self.width), int(self.height)
        self.dist = {k: float(v) for k, v in self.dist.items() if float(v) != 0.0}
        if self.width <= 0 or self.height <= 0 or not (self.fx > 0 and self.fy > 0):
            raise DataError(f"camera {self.model} {self.width}x{self.height} f=({self.fx}, {self.fy}) is invalid; "
                            "the focal lengths and the image size must be positive")

    @classmethod
    def from_colmap(cls, model: str, width: int, height: int, params) -> "Lens":
        """From a COLMAP camera (model name, size, params in COLMAP's order)."""
        names = _COLMAP_PARAMS.get(model)
        if names is None:
            cls(model, width, height, 1, 1, 0, 0)  # raises the unsupported-model error
        params = [float(p) for p in params]
        if len(params) != len(names):
            raise DataError(f"COLMAP camera {model} needs {len(names)} parameters ({', '.join(names)}), "
                            f"got {len(params)}")
        v = dict(zip(names, params))
        fx = v.pop("fx", v.get("f"))
        fy = v.pop("fy", v.pop("f", fx))
        cx, cy = v.pop("cx"), v.pop("cy")
        return cls(model, width, height, fx, fy, cx, cy, v)

    @property
    def is_pinhole(self) -> bool:
        return not self.dist

    @property
    def is_fisheye(self) -> bool:
        return self.model in _FISHEYE

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)

    def opencv_coeffs(self) -> np.ndarray:
        """Distortion vector in OpenCV's order: (k1,k2,k3,k4) for fisheye, else (k1,k2,p1,p2,k3[,k4,k5,k6])."""
        d = self.dist
        if self.is_fisheye:
            return np.array([d.get(k, 0.0) for k in ("k1", "k2", "k3", "k4")], dtype=np.float64)
        names = ["k1", "k2", "p1", "p2", "k3"]
        if any(k in d for k in ("k4", "k5", "k6")):
            names += ["k4", "k5", "k6"]
        return np.array([d.get(k, 0.0) for k in names], dtype=np.float64)

    def scaled(self, sx: float, sy: float) -> "Lens":
        """The lens for images resized by (sx, sy) (distortion is in normalised coordinates: unchanged)."""
        return Lens(self.model, round(self.width * sx), round(self.height * sy), self.fx * sx, self.fy * sy,
                    self.cx * sx, self.cy * sy, dict(self.dist))

    def to_dict(self) -> dict:
        return asdict(self)


def _cv2():
    try:
        import cv2
    except ImportError as exc:  # pragma: no cover - a declared dependency
        raise DataError("removing lens distortion needs OpenCV: pip install opencv-python-headless") from exc
    return cv2


def pinhole_for(lens: Lens) -> np.ndarray:
    """The pinhole K (3x3, float64, this project's pixel convention) that :func:`undistort_image` maps to:
    same image size, only valid pixels (no black borders). ``lens.K`` when the lens has no distortion."""
    if lens.is_pinhole:
        return lens.K
    cv2 = _cv2()
    K = lens.K.copy()
    K[:2, 2] -= 0.5  # OpenCV puts pixel centres at integers
    D = lens.opencv_coeffs()
    size = (lens.width, lens.height)
    if lens.is_fisheye:
        newK = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(K, D.reshape(4, 1), size, np.eye(3),
                                                                      balance=0.0)
    else:
        newK, _ = cv2.getOptimalNewCameraMatrix(K, D, size, 0.0, size)
    newK = np.asarray(newK, dtype=np.float64)
    newK[:2, 2] += 0.5
    if not (np.isfinite(newK).all() and newK[0, 0] > 0 and newK[1, 1] > 0):
        raise DataError(f"the {lens.model} distortion {lens.dist} cannot be removed (no valid pinhole view); "
                        "check the distortion coefficients")
    return newK


def undistort_image(image: np.ndarray, lens: Lens, K_new: np.ndarray | None = None,
                    interpolation: str = "linear") -> tuple[np.ndarray, np.ndarray]:
    """Remap ``image`` (H,W[,C], uint8 or float32, matching ``lens``' size) to the pinhole camera
    ``K_new`` (default :func:`pinhole_for`). Returns (image, K_new). A pinhole lens returns the image as is."""
    if image.shape[0] != lens.height or image.shape[1] != lens.width:
        raise DataError(f"image is {image.shape[1]}x{image.shape[0]} but its camera says {lens.width}x{lens.height}; "
                        "the camera file does not describe these images")
    if lens.is_pinhole and K_new is None:
        return image, lens.K
    cv2 = _cv2()
    K_new = pinhole_for(lens) if K_new is None else np.asarray(K_new, np.float64)
    K, Kn = lens.K.copy(), K_new.copy()
    K[:2, 2] -= 0.5
    Kn[:2, 2] -= 0.5
    size = (lens.width, lens.height)
    D = lens.opencv_coeffs()
    if lens.is_fisheye:
        m1, m2 = cv2.fisheye.initUndistortRectifyMap(K, D.reshape(4, 1), np.eye(3), Kn, size, cv2.CV_32FC1)
    else:
        m1, m2 = cv2.initUndistortRectifyMap(K, D, np.eye(3), Kn, size, cv2.CV_32FC1)
    flag = {"linear": cv2.INTER_LINEAR, "nearest": cv2.INTER_NEAREST, "cubic": cv2.INTER_CUBIC}[interpolation]
    out = cv2.remap(np.ascontiguousarray(image), m1, m2, flag, borderMode=cv2.BORDER_REPLICATE)
    if image.ndim == 3 and out.ndim == 2:
        out = out[..., None]
    return out, K_new


def cache_folder(name: str) -> str:
    """The folder ``name`` of NeuMesh's cache: under ``$NEUMESH_CACHE``, else ``$XDG_CACHE_HOME/neumesh``
    or ``~/.cache/neumesh`` (never a dataset folder)."""
    base = os.environ.get("NEUMESH_CACHE")
    if not base:
        xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        base = os.path.join(xdg, "neumesh")
    return os.path.join(base, name)


def default_cache_dir() -> str:
    return cache_folder("undistorted")


def _cache_key(path: str, lens: Lens, reduce: float, kind: str) -> str:
    st = os.stat(path)
    blob = json.dumps([_CACHE_VERSION, os.path.abspath(path), st.st_size, st.st_mtime_ns, lens.to_dict(),
                       float(reduce), kind], sort_keys=True)
    return hashlib.sha1(blob.encode()).hexdigest()


def read_uint8(path: str, reduce: float = 1, grey: bool = False) -> np.ndarray:
    """An image file as uint8 (H,W,3) RGB (or (H,W) grey), area-reduced by ``reduce`` (PIL's box
    reduce for integer factors, a box resize to round(size / reduce) otherwise)."""
    from PIL import Image

    if not os.path.isfile(path):
        raise DataError(f"image not found: {path}; check the dataset folder and file names")
    try:
        with Image.open(path) as im:
            im.load()
            im = im.convert("L" if grey else "RGB")
            if float(reduce).is_integer() and reduce > 1:
                im = im.reduce(int(reduce))
            elif reduce != 1:
                w, h = im.size
                im = im.resize((max(1, round(w / reduce)), max(1, round(h / reduce))), Image.BOX)
            return np.asarray(im, dtype=np.uint8)
    except Exception as exc:
        raise DataError(f"could not read image {path}: {exc}; the file is corrupt or not an image") from exc


def _write_png_atomic(path: str, arr: np.ndarray) -> None:
    from PIL import Image

    folder = os.path.dirname(path)
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp_", suffix=".png", dir=folder)
    try:
        with os.fdopen(fd, "wb") as fh:
            Image.fromarray(arr).save(fh, format="PNG", compress_level=1)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def undistorted_file(path: str, lens: Lens, reduce: float = 1, cache_dir: str | None = None,
                     grey: bool = False, fmt: str = "npy") -> tuple:
    """Read ``path`` (taken with ``lens``, its full-size camera), reduce by ``reduce``, remove the
    distortion, keep the result in the cache. Returns (uint8 image, pinhole K of the returned image,
    whether it came from the cache, the cached file or ``path`` itself). Pinhole lenses are read
    directly (nothing cached). ``fmt``: 'npy' (what the loader keeps: read back without decoding) or
    'png' (an image file for other programs, e.g. Blender backgrounds)."""
    if fmt not in ("npy", "png"):
        raise ValueError(f"fmt must be 'npy' or 'png', got {fmt!r}")
    if lens.is_pinhole:
        img = read_uint8(path, reduce, grey)
        h, w = img.shape[:2]
        return img, lens.scaled(w / lens.width, h / lens.height).K, False, path
    cache_dir = cache_dir or default_cache_dir()
    key = _cache_key(path, lens, reduce, ("grey" if grey else "rgb") + fmt)
    stem = os.path.join(cache_dir, key[:2], key)
    data, meta = stem + "." + fmt, stem + ".json"
    if os.path.isfile(data) and os.path.isfile(meta):
        try:
            with open(meta, "r", encoding="utf-8") as fh:
                K = np.asarray(json.load(fh)["K"], dtype=np.float64)
            img = np.load(data, allow_pickle=False) if fmt == "npy" else read_uint8(data, 1, grey)
            if img.dtype == np.uint8 and img.ndim == (2 if grey else 3):
                return img, K, True, data
        except (OSError, ValueError, KeyError, DataError):
            pass  # a broken cache entry is rebuilt
    img = read_uint8(path, reduce, grey)
    h, w = img.shape[:2]
    small = lens.scaled(w / lens.width, h / lens.height)
    out, K = undistort_image(img, small)
    try:
        os.makedirs(os.path.dirname(stem), exist_ok=True)
        if fmt == "png":
            _write_png_atomic(data, out)
        else:
            fd, tmp = tempfile.mkstemp(prefix=".tmp_", suffix=".npy", dir=os.path.dirname(stem))
            with os.fdopen(fd, "wb") as fh:
                np.save(fh, np.ascontiguousarray(out), allow_pickle=False)
            os.replace(tmp, data)
        fd, tmp = tempfile.mkstemp(prefix=".tmp_", suffix=".json", dir=os.path.dirname(stem))
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump({"K": K.tolist(), "source": os.path.abspath(path), "lens": lens.to_dict(), "reduce": reduce}, fh)
        os.replace(tmp, meta)
    except OSError:
        data = path  # a read-only cache only costs the next run the remap again
    return out, K, False, data
