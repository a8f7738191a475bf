"""The built-in scene's camera rig and scene writer: cameras on a sphere around the blob, the scene
written (or cached) in NeRF-synthetic format."""
from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import time

import numpy as np

from ...mesh import save_mesh
from .shape import _LOBES, AMPLITUDE, _fibonacci_sphere, _torch_single_thread, default_mesh, shape_bounds  # noqa: F401
from .tracer import AMBIENT, DIFFUSE, LIGHT_DIR, SHININESS, SPECULAR, _render_unpremultiplied

SCENE_VERSION = 1

# Defaults of the scene and of the small variant used by tests.
CAMERA_RADIUS = 4.0
CAMERA_ANGLE_X = 0.9  # radians (~52 deg): the blob fills ~70% of the frame
SMALL_SCENE_KWARGS = dict(resolution=64, n_train=30, n_val=4, n_test=4, mesh_subdiv=4)



def look_at_opencv(position: np.ndarray, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """4x4 OpenCV camera-to-world (x right, y down, z forward) at ``position`` looking at ``target``."""
    pos = np.asarray(position, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - pos
    fwd /= np.linalg.norm(fwd)
    up = np.asarray(up, dtype=np.float64)
    if abs(float(fwd @ up)) > 0.999:
        up = np.array([0.0, 1.0, 0.0])
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, fwd, pos
    return c2w


def _rotation(axis, angle) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64)
    a /= np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def camera_positions(n_train: int, n_val: int, n_test: int, radius: float = CAMERA_RADIUS, seed: int = 0) -> dict:
    """Camera centres: train on a Fibonacci sphere; val/test on differently rotated Fibonacci spheres
    (both hemispheres, not coinciding with training views)."""
    rng = np.random.default_rng(seed)
    out = {"train": _fibonacci_sphere(n_train) * radius}
    for name, n in (("val", n_val), ("test", n_test)):
        rot = _rotation(rng.normal(size=3), rng.uniform(0.3, 2.8))
        out[name] = _fibonacci_sphere(n, offset=0.5, rotation=rot) * radius if n else np.zeros((0, 3))
    return out


def _render_split(pool, cams, K, res, folder, split, seed_base):
    from ...imageio import save_image

    def job(i):
        rgb, alpha = _render_unpremultiplied(K, cams[i], res, res, spp=4, seed=seed_base + i)
        rgba = np.concatenate([rgb, alpha[..., None]], -1)
        save_image(os.path.join(folder, split, f"r_{i}.png"), rgba)

    list(pool.map(job, range(len(cams))))


def _write_splits(out_dir, pos, K, resolution, camera_angle_x, seed, workers):
    from concurrent.futures import ThreadPoolExecutor

    split_seeds = {"train": seed * 100_003 + 0, "val": seed * 100_003 + 10_000, "test": seed * 100_003 + 20_000}
    with ThreadPoolExecutor(max_workers=workers) as pool:
        for split, centres in pos.items():
            cams = [look_at_opencv(c) for c in centres]
            # exact float64 OpenGL matrices (opencv_to_opengl rounds to float32)
            gl_flip = np.diag([1.0, -1.0, -1.0, 1.0])
            frames = [
                {"file_path": f"./{split}/r_{i}", "transform_matrix": (c @ gl_flip).tolist()}
                for i, c in enumerate(cams)
            ]
            os.makedirs(os.path.join(out_dir, split), exist_ok=True)
            _render_split(pool, cams, K, resolution, out_dir, split, split_seeds[split])
            meta = {"camera_angle_x": float(camera_angle_x), "frames": frames}
            tmp = os.path.join(out_dir, f".transforms_{split}.json.tmp")
            with open(tmp, "w", encoding="utf-8") as fh:
                json.dump(meta, fh, indent=1)
            os.replace(tmp, os.path.join(out_dir, f"transforms_{split}.json"))


def make_default_scene(out_dir: str, resolution: int = 128, n_train: int = 60, n_val: int = 8, n_test: int = 8,
                       seed: int = 0, mesh_subdiv: int = 5, camera_radius: float = CAMERA_RADIUS,
                       camera_angle_x: float = CAMERA_ANGLE_X, num_workers: int | None = None) -> str:
    """Write the default scene in NeRF-synthetic format and return ``out_dir``.

    Files: transforms_{train,val,test}.json (camera_angle_x, OpenGL transform_matrix), RGBA PNGs in
    train/ val/ test/, mesh.ply (the blob mesh, vertices exactly on the analytic surface) and
    scene.json (description; written last, so its presence marks a complete scene). Deterministic
    for given arguments. ``SMALL_SCENE_KWARGS`` gives a quick variant for tests.
    """
    if resolution < 8:
        raise ValueError(f"resolution must be >= 8, got {resolution}")
    if n_train < 1:
        raise ValueError("n_train must be >= 1")
    t_start = time.perf_counter()
    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    marker = os.path.join(out_dir, "scene.json")
    if os.path.exists(marker):
        os.remove(marker)
    pos = camera_positions(n_train, n_val, n_test, camera_radius, seed)
    f = 0.5 * resolution / math.tan(0.5 * camera_angle_x)
    K = np.array([[f, 0, resolution / 2], [0, f, resolution / 2], [0, 0, 1]], dtype=np.float64)
    workers = num_workers or max(1, min(8, os.cpu_count() or 1))
    # one torch thread per worker: images are rendered in parallel threads (ops release the GIL)
    with _torch_single_thread():
        _write_splits(out_dir, pos, K, resolution, camera_angle_x, seed, workers)
    mesh = default_mesh(mesh_subdiv)
    save_mesh(mesh, os.path.join(out_dir, "mesh.ply"))
    b = shape_bounds()
    desc = {
        "name": "neumesh default scene (bumpy blob)",
        "version": SCENE_VERSION,
        "description": (
            "Star-shaped non-convex blob r(u) = 1 + amplitude * sum_k c_k exp(kappa_k (u.d_k - 1)) with a "
            "solid texture (colour stripes x checker, two rows of stroke lettering around the equator, "
            "triplanar checker at the poles), shaded with ambient + Lambert + white Blinn-Phong "
            "(directional light), ray-traced analytically with 4 jittered samples per pixel. "
            "mesh.ply is an icosphere with its vertices on the analytic surface. Cameras use the "
            "NeRF-synthetic convention (OpenGL c2w), RGBA images (alpha = coverage)."
        ),
        "generator": "neumesh_core.data.synthetic.make_default_scene",
        "params": {
            "resolution": resolution, "n_train": n_train, "n_val": n_val, "n_test": n_test, "seed": seed,
            "mesh_subdiv": mesh_subdiv, "camera_radius": camera_radius, "camera_angle_x": camera_angle_x,
        },
        "shape": {
            "amplitude": AMPLITUDE, "lobes": _LOBES.tolist(), "r_min": round(b["r_min"], 4),
            "r_max": round(b["r_max"], 4),
        },
        "shading": {"light_dir": LIGHT_DIR.tolist(), "ambient": AMBIENT, "diffuse": DIFFUSE,
                    "specular": SPECULAR, "shininess": SHININESS, "samples_per_pixel": 4},
        "mesh": {"file": "mesh.ply", "vertices": int(mesh.num_vertices), "faces": int(len(mesh.faces))},
        "bbox": [[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]],
    }
    tmp = marker + ".tmp"
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(desc, fh, indent=1)
    os.replace(tmp, marker)
    _LAST_TIMING["seconds"] = time.perf_counter() - t_start
    return out_dir


_LAST_TIMING: dict = {}


def _cache_base(cache_root=None) -> str:
    if cache_root is not None:
        return os.fspath(cache_root)
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = xdg if xdg else os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "neumesh")


def _is_complete(path: str, params: dict) -> bool:
    try:
        with open(os.path.join(path, "scene.json"), "r", encoding="utf-8") as fh:
            desc = json.load(fh)
    except (OSError, ValueError):
        return False
    if desc.get("version") != SCENE_VERSION:
        return False
    stored = desc.get("params", {})
    return all(stored.get(k) == v for k, v in params.items()) and os.path.isfile(os.path.join(path, "mesh.ply"))


def default_scene_dir(cache_root: str | None = None, small: bool = False) -> str:
    """Path of the cached default scene, generating it on first use.

    Location: ``<cache_root>/default_scene_v1`` (``default_scene_v1_small`` for the quick test
    variant); ``cache_root`` defaults to ``$XDG_CACHE_HOME/neumesh`` or ``~/.cache/neumesh``. A scene
    is reused when its scene.json matches; otherwise it is generated in a temporary sibling folder
    and moved into place (safe against concurrent callers and interrupted runs).
    """
    base = _cache_base(cache_root)
    name = f"default_scene_v{SCENE_VERSION}" + ("_small" if small else "")
    path = os.path.join(base, name)
    kwargs = dict(SMALL_SCENE_KWARGS) if small else {}
    params = dict(resolution=128, n_train=60, n_val=8, n_test=8, seed=0, mesh_subdiv=5)
    params.update(kwargs)
    if _is_complete(path, params):
        return path
    os.makedirs(base, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=f".{name}.", dir=base)
    try:
        make_default_scene(tmp, **params)
        if os.path.isdir(path):
            if _is_complete(path, params):  # another process finished first
                return path
            stale = tempfile.mkdtemp(prefix=f".{name}.stale.", dir=base)
            os.replace(path, os.path.join(stale, "old"))
            shutil.rmtree(stale, ignore_errors=True)
        try:
            os.replace(tmp, path)
        except OSError:
            if not _is_complete(path, params):
                raise
    finally:
        if os.path.isdir(tmp):
            shutil.rmtree(tmp, ignore_errors=True)
    return path
