"""The scaffold builder's configuration and report: :class:`ScaffoldConfig` (method, target vertex
count, stage options), :class:`ScaffoldReport` (vertices, timings, silhouette IoU, Chamfer; saved as
JSON), :class:`ScaffoldError`."""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Optional

import numpy as np

if TYPE_CHECKING:
    from .fusion import FusionConfig
    from .mvs import MVSConfig

from ..errors import DataError


class ScaffoldError(DataError):
    """The scaffold cannot be built from this input (the message says what to change)."""


METHODS = ("auto", "hull", "hull+mvs", "hull+density", "density", "fusion")


@dataclass
class ScaffoldConfig:
    """Settings of :func:`build_scaffold`.

    method: "auto" (with masks: "hull+mvs"; without masks: "fusion"), "hull" (visual
        hull only; fastest; no concavities; needs masks), "hull+mvs" (hull, then plane-sweep stereo
        depth maps fused on the hull grid carve what no silhouette shows: concavities, and the depth
        of one-sided captures such as DTU; textureless parts keep the hull; needs masks; docs/benchmarks.md
        gives its effect on lego and DTU),
        "hull+density" (hull, then a density grid fitted by volume rendering; slower; needs masks),
        "density" (photometric density only; needs a bbox; no masks needed; an iso-level of the grid),
        "fusion" (photos without masks, what "auto" picks for them: the density grid fitted with a
        background model behind it, its per-view depths fused into one surface; needs an object box;
        ``fusion.py``).
    target_vertices: vertex count the mesh is resampled to (within ~12%); 0 keeps the grid's count.
    max_mesh_grid: cap on that resampled grid (~this^3 nodes in all); beyond it the mesh is midpoint-
        subdivided instead.  640 reaches ~2M vertices on scan24 (3.2 GB peak at 567^3; 420 stopped
        near 1M).
    hull_resolution: cells on the longest side of the visual-hull grid (sub-voxel surface).
    mask_tolerance: views allowed to disagree that a point is inside the mask (default 0; raise it
        for hand-made masks that cut off parts of the object in some views).  On DTU's masks a
        tolerance of 1 view lowered the hull's silhouette IoU from 0.995 to 0.954: points in frame
        in few views keep volume that one mask removes.
    hull_dilate_px: grow the hull by this many pixels (protects thin parts from discretisation);
        -1 = auto: 0.5 px at 400 px images, scaled with the image size (0.1 px minimum).
    min_view_fraction: the cameras must share a volume that this fraction of the views has in frame
        (the check against poses from different captures).
    reconstruct_view_fraction: a point is reconstructed when it is in frame in at least this
        fraction of the views (>= 2 views; at most min_view_fraction).  Low, because close-up
        captures (DTU) cut the object at the frame in most views: at 0.6, 4.9% of scan24's mask
        pixels had no scaffold behind them (the field renders black there), at 0.1 0.1%.
    density_resolutions / density_iters: coarse-to-fine stages of the density grid.
    density_iso_alpha: a node is solid when one voxel of its density is at least this opaque.
    """

    method: str = "auto"
    target_vertices: int = 200_000
    hull_resolution: int = 256
    mask_tolerance: int = 0
    mask_threshold: float = 0.5
    hull_dilate_px: float = -1.0
    min_view_fraction: float = 0.6
    reconstruct_view_fraction: float = 0.1
    density_resolutions: tuple = (64, 128)
    density_iters: tuple = (300, 300)
    density_batch_rays: int = 4096
    density_lr: float = 0.1
    density_iso_alpha: float = 0.1
    density_max_image_side: int = 400
    mvs: Optional["MVSConfig"] = None  # plane-sweep settings for "hull+mvs" (None: MVSConfig())
    mvs_max_image_side: int = 400
    min_component_fraction: float = 0.002
    max_mesh_grid: int = 640    # the grid resampled to reach target_vertices has about this^3 nodes at most
    max_faces: int = 5_000_000
    iou_views: int = 0          # 0: all training views
    compute_iou: bool = True
    chamfer_samples: int = 100_000  # against Scene.mesh_path when present; 0 disables
    fusion: Optional["FusionConfig"] = None  # "fusion" settings (None: FusionConfig())
    seed: int = 0


@dataclass
class ScaffoldReport:
    method: str = ""
    num_vertices: int = 0
    num_faces: int = 0
    num_views: int = 0
    image_size: tuple = (0, 0)
    bbox: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)  # seconds per stage + "total"
    silhouette_iou: Optional[dict] = None          # mean/min/pooled (per_view dropped from summary)
    chamfer: Optional[dict] = None                 # against the scene's reference mesh, if any
    hull: dict = field(default_factory=dict)
    density: dict = field(default_factory=dict)
    mvs: dict = field(default_factory=dict)
    meshing: dict = field(default_factory=dict)
    fusion: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    config: dict = field(default_factory=dict)
    #: "fusion": the background model fitted with the density grid (world space; not saved), for the
    #: field's training to start from
    background: Optional[object] = field(default=None, repr=False, compare=False)

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "background"}
        return json.loads(json.dumps(d, default=_json_default))

    def save(self, path: str) -> None:
        os.makedirs(os.path.dirname(os.path.abspath(path)) or ".", exist_ok=True)
        tmp = path + ".tmp"
        with open(tmp, "w") as fh:
            json.dump(self.to_dict(), fh, indent=2)
        os.replace(tmp, path)

    def summary(self) -> str:
        lines = [f"scaffold ({self.method}): {self.num_vertices} vertices, {self.num_faces} faces "
                 f"from {self.num_views} views {self.image_size[0]}x{self.image_size[1]}"]
        lines.append("time: " + ", ".join(f"{k} {v:.1f}s" for k, v in self.timings.items()))
        if self.silhouette_iou:
            s = self.silhouette_iou
            lines.append(f"silhouette IoU vs train masks: mean {s['mean']:.4f}, min {s['min']:.4f}, "
                         f"pooled {s['pooled']:.4f}")
        if self.chamfer:
            c = self.chamfer
            lines.append(f"Chamfer to reference mesh: {c['chamfer']:.5f} (acc {c['accuracy']:.5f}, "
                         f"comp {c['completeness']:.5f}; {c.get('relative', float('nan')):.4%} of bbox diagonal)")
        for n in self.notes:
            lines.append(f"note: {n}")
        return "\n".join(lines)


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    return str(o)
