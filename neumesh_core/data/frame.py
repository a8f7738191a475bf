"""Scene frame and object box of a real capture.

A phone capture has the object somewhere in a room.  :func:`scene_frame` finds where the cameras look
(the least-squares point closest to every optical axis), how far they are (the scale) and which way
is up (the mean of the cameras' up vectors); the world coordinates are never changed (Blender's
cameras stay where they are): the frame only sizes the background model's contracted space.
:func:`find_object` finds the object in the sparse points: the plane it rests on (left to the room),
the cluster the cameras look at with its thin parts, and an oriented :class:`ObjectBox` around its
full extent; :func:`object_box` is its box.  ``parse_box`` reads ``--box cx,cy,cz,sx,sy,sz`` (centre
and half-extents).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np


@dataclass
class ObjectBox:
    """An oriented box: ``centre`` (3,), ``half_extents`` (3,) along the box axes, ``rotation`` (3,3)
    whose columns are the box axes in world space (identity: axis-aligned).  The mesh field holds
    what is inside; the background model holds the rest."""

    centre: np.ndarray
    half_extents: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    #: how it was found (said to the user; not saved): see :func:`object_box`
    source: str = field(default="", compare=False)
    #: the face at -half_extents[2] along the third axis lies just in front of the support the object
    #: rests on (a wall, a table: the room's, see :func:`find_object`)
    on_support: bool = False

    def __post_init__(self) -> None:
        self.centre = np.asarray(self.centre, np.float64).reshape(3)
        self.half_extents = np.asarray(self.half_extents, np.float64).reshape(3)
        self.rotation = np.asarray(self.rotation, np.float64).reshape(3, 3)
        if not (np.isfinite(self.centre).all() and np.isfinite(self.half_extents).all()
                and np.isfinite(self.rotation).all()):
            raise ValueError("ObjectBox: centre, half_extents and rotation must be finite numbers")
        if (self.half_extents <= 0).any():
            raise ValueError(f"ObjectBox: half_extents must be > 0, got {self.half_extents.tolist()}")
        if not np.allclose(self.rotation.T @ self.rotation, np.eye(3), atol=1e-4):
            raise ValueError("ObjectBox: rotation must be a rotation matrix (orthonormal columns); remove "
                             "shear/scale from the box object and put the size in half_extents")

    def corners(self) -> np.ndarray:
        s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
        return self.centre + (s * self.half_extents) @ self.rotation.T

    def aabb(self) -> np.ndarray:
        """(2,3) float32 world-space axis-aligned bounds of the box (min, max)."""
        c = self.corners()
        return np.stack([c.min(0), c.max(0)]).astype(np.float32)

    def contains(self, points: np.ndarray) -> np.ndarray:
        local = (np.asarray(points, np.float64) - self.centre) @ self.rotation
        return (np.abs(local) <= self.half_extents).all(-1)

    def to_dict(self) -> dict:
        d = {"centre": self.centre.tolist(), "half_extents": self.half_extents.tolist(),
             "rotation": self.rotation.tolist()}
        if self.on_support:
            d["on_support"] = True
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "ObjectBox":
        return cls(d["centre"], d["half_extents"], d.get("rotation", np.eye(3)), on_support=bool(d.get("on_support")))

    @classmethod
    def from_aabb(cls, bbox) -> "ObjectBox":
        b = np.asarray(bbox, np.float64).reshape(2, 3)
        return cls(0.5 * (b[0] + b[1]), np.maximum(0.5 * (b[1] - b[0]), 1e-6))


@dataclass
class SceneFrame:
    """Where the cameras look (``centre``), how far they are (``radius``: the largest camera distance
    from the centre) and which way is up (``up``, unit; the mean of the cameras' up vectors)."""

    centre: np.ndarray
    radius: float
    up: np.ndarray

    def to_dict(self) -> dict:
        return {"centre": np.asarray(self.centre).tolist(), "radius": float(self.radius),
                "up": np.asarray(self.up).tolist()}


def focus_point(c2w: np.ndarray) -> np.ndarray:
    """The point closest (least squares) to every camera's optical axis (OpenCV: +z forward)."""
    c2w = np.asarray(c2w, np.float64).reshape(-1, 4, 4)
    o = c2w[:, :3, 3]
    d = c2w[:, :3, 2] / np.linalg.norm(c2w[:, :3, 2], axis=1, keepdims=True)
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]   # projector orthogonal to each axis
    A = P.sum(0)
    b = np.einsum("nij,nj->i", P, o)
    if len(c2w) < 2 or np.linalg.cond(A) > 1e8:   # one camera or parallel axes: a point ahead of them
        return o.mean(0) + d.mean(0)
    return np.linalg.solve(A, b)


def scene_frame(c2w: np.ndarray, points: Optional[np.ndarray] = None) -> SceneFrame:
    """The capture's frame from its cameras (and sparse points, which widen the radius to the room)."""
    c2w = np.asarray(c2w, np.float64).reshape(-1, 4, 4)
    centre = focus_point(c2w)
    dist = np.linalg.norm(c2w[:, :3, 3] - centre, axis=1)
    radius = float(dist.max()) if len(dist) else 1.0
    if points is not None and len(points) >= 8:
        radius = max(radius, float(np.percentile(np.linalg.norm(points - centre, axis=1), 50)))
    up = -c2w[:, :3, 1].mean(0)   # OpenCV y points down
    n = np.linalg.norm(up)
    up = up / n if n > 1e-8 else np.array([0.0, 0.0, 1.0])
    return SceneFrame(centre, max(radius, 1e-6), up)


@dataclass
class SupportPlane:
    """The plane an object stands on or hangs from (a table, a wall): ``normal`` (3,) unit, pointing to
    the cameras' side; the plane is ``normal . x = offset``; ``sigma`` is the spread of its sparse
    points (robust standard deviation, world units). It belongs to the room: the object box ends
    ``clearance`` sigmas in front of it, so the background model holds it."""

    normal: np.ndarray
    offset: float
    sigma: float
    inliers: int = 0

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed distance of ``points`` (P,3) from the plane (positive on the cameras' side)."""
        return np.asarray(points, np.float64) @ self.normal - self.offset

    def to_dict(self) -> dict:
        return {"normal": np.asarray(self.normal).tolist(), "offset": float(self.offset),
                "sigma": float(self.sigma), "inliers": int(self.inliers)}


@dataclass
class ObjectFinding:
    """What :func:`find_object` found: the ``box``, the ``support`` plane (None: the object stands free
    in the sparse points), ``object_points`` (bool per input point: the object's own points, thin parts
    included) and ``candidates`` (bool: the points off the support near the cameras' focus, of which
    the object is the cluster the cameras look at), and ``notes`` for the log."""

    box: ObjectBox
    support: Optional[SupportPlane]
    object_points: np.ndarray
    candidates: np.ndarray
    notes: list = field(default_factory=list)


def support_plane(points: np.ndarray, cam_centres: np.ndarray, threshold: float, min_share: float = 0.2,
                  iterations: int = 1000, seed: int = 0) -> Optional[SupportPlane]:
    """The dominant plane of ``points`` (RANSAC with inlier distance ``threshold``, refined by least
    squares on its inliers), or None when it holds less than ``min_share`` of the points or has
    cameras on both sides (then it is not what the object rests on: the cameras stand on one side of a
    table top or a wall)."""
    P = np.asarray(points, np.float64)
    if len(P) < 16:
        return None
    rng = np.random.default_rng(seed)
    best_n, best_count = None, 0
    for _ in range(int(iterations)):
        a, b, c = P[rng.choice(len(P), 3, replace=False)]
        n = np.cross(b - a, c - a)
        nn = np.linalg.norm(n)
        if nn < 1e-12:
            continue
        n /= nn
        count = int((np.abs((P - a) @ n) < threshold).sum())
        if count > best_count:
            best_n, best_count, best_p = n, count, a
    if best_n is None:
        return None
    inl = np.abs((P - best_p) @ best_n) < threshold
    for _ in range(2):   # least squares on the inliers, then the inliers of that plane
        Q = P[inl]
        c = Q.mean(0)
        n = np.linalg.svd(Q - c, full_matrices=False)[2][-1]
        inl = np.abs((P - c) @ n) < threshold
    if inl.sum() < min_share * len(P):
        return None
    offset = float(c @ n)
    side = np.sign(np.asarray(cam_centres, np.float64) @ n - offset)
    if (side > 0).mean() < 0.9 and (side < 0).mean() < 0.9:
        return None
    if (side > 0).mean() < 0.5:
        n, offset = -n, -offset
    # the spread from a band four times the inlier distance wide: the inliers alone are cut at the
    # threshold and would understate it (the plane's points dominate the band, so its median holds)
    h = P @ n - offset
    band = h[np.abs(h) < 4.0 * threshold]
    centre = float(np.median(band))
    sigma = float(1.4826 * np.median(np.abs(band - centre)))
    return SupportPlane(n, offset + centre, max(sigma, 1e-9), int(inl.sum()))


def _clusters(points: np.ndarray, min_samples: int = 8):
    """DBSCAN labels of ``points`` (-1: noise) and its ``eps``: twice the median distance of a point to
    its ``min_samples``-th neighbour, so the clustering follows the points' own density."""
    from scipy.spatial import cKDTree
    from sklearn.cluster import DBSCAN

    k = min(min_samples, len(points) - 1)
    d, _ = cKDTree(points).query(points, k + 1)
    eps = 2.0 * float(np.median(d[:, k]))
    return DBSCAN(eps=max(eps, 1e-9), min_samples=min_samples).fit_predict(points), eps


def _grow_object(points: np.ndarray, labels: np.ndarray, seed_label: int, eps: float) -> np.ndarray:
    """The seed cluster and every cluster within a gap of ``max(3 eps, 0.1 x its size)`` of it (thin
    parts that the features split off: ear tips, a handle), repeated until nothing joins, then the
    noise points within 2 eps (lone points of thin tips). Returns a bool mask over ``points``."""
    from scipy.spatial import cKDTree

    inside = labels == seed_label
    others = set(int(x) for x in np.unique(labels) if x >= 0 and x != seed_label)
    while others:
        tree = cKDTree(points[inside])
        size = float(np.linalg.norm(np.ptp(points[inside], axis=0)))
        gap = max(3.0 * eps, 0.1 * size)
        joined = [lab for lab in others if tree.query(points[labels == lab], 1)[0].min() <= gap]
        if not joined:
            break
        for lab in joined:
            inside |= labels == lab
            others.discard(lab)
    noise = np.nonzero(labels < 0)[0]
    if len(noise):
        d, _ = cKDTree(points[inside]).query(points[noise], 1)
        inside[noise[d <= 2.0 * eps]] = True
    return inside


def _box_axes(points: np.ndarray, third: np.ndarray) -> np.ndarray:
    """Rotation whose third column is ``third`` and whose first two are the principal directions of
    ``points`` in the plane orthogonal to it (the tightest box about that axis)."""
    z = third / np.linalg.norm(third)
    q = points - points.mean(0)
    q = q - np.outer(q @ z, z)
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(ref, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    if len(q) >= 3:
        cov = np.cov(np.stack([q @ x, q @ y]))
        w, v = np.linalg.eigh(cov)
        a = v[:, -1]
        x, y = a[0] * x + a[1] * y, -a[1] * x + a[0] * y
    return np.stack([x, y, z], 1)


def find_object(c2w: np.ndarray, points: Optional[np.ndarray] = None, margin: float = 0.1,
                clearance: float = 3.0, min_points: int = 30) -> ObjectFinding:
    """Find the object the cameras look at, and its box, from the sparse points.

    1. The points within the median camera distance of the cameras' focus point (:func:`focus_point`).
    2. The support: the dominant plane of those points that has every camera on one side
       (:func:`support_plane`) and fewer points behind it than in front (else it is a face of the
       object itself), if there is one; the points more than ``clearance`` sigmas in front of
       it are the candidates (without a support, all of them).
    3. The candidates clustered by their own density (DBSCAN); the object is the cluster the cameras
       look at (large and near the focus point) grown by the clusters and lone points next to it, so
       thin parts split off by the features (ear tips, handles, spouts) belong to it: no percentile cut.
    4. The box: along the support's normal (else the cameras' up) and the object's principal
       directions about it, the object points' full extent plus ``margin`` of it on each side (at
       least two clustering radii, up to ``margin`` of the largest extent), its face towards the
       support ``clearance`` sigmas in front of it.

    Without enough points (fewer than ``min_points`` near the focus): a cube of half-size 0.3 x the
    median camera distance around the focus point, said in ``notes``."""
    c2w = np.asarray(c2w, np.float64).reshape(-1, 4, 4)
    centres = c2w[:, :3, 3]
    focus = focus_point(c2w)
    med = float(np.median(np.linalg.norm(centres - focus, axis=1))) if len(c2w) else 1.0
    P = np.zeros((0, 3)) if points is None else np.asarray(points, np.float64).reshape(-1, 3)
    P_ok = np.isfinite(P).all(1)
    near = P_ok & (np.linalg.norm(np.where(P_ok[:, None], P, 0.0) - focus, axis=1) <= med)
    none = np.zeros(len(P), bool)

    def fallback(why: str) -> ObjectFinding:
        box = ObjectBox(focus, np.full(3, 0.3 * med), source="the cameras' common look-at point")
        return ObjectFinding(box, None, none.copy(), none.copy(), [why])

    if near.sum() < min_points:
        return fallback(f"{int(near.sum())} sparse points near the cameras' focus (at least {min_points} "
                        "needed): the box is a cube around the point the cameras look at")
    idx = np.nonzero(near)[0]
    plane = support_plane(P[idx], centres, threshold=0.01 * med)
    notes = []
    if plane is not None:
        h = plane.height(P[idx])
        if (h < -clearance * plane.sigma).sum() > (h > clearance * plane.sigma).sum():
            plane = None   # most points lie behind it: a face of the object (a box, a book), not its support
    if plane is not None:
        cand_idx = idx[h > clearance * plane.sigma]
        notes.append(f"support plane (a wall or table: left to the background model) holds {plane.inliers} "
                     f"of {len(idx)} points near the focus, spread {plane.sigma:.3g}")
    else:
        cand_idx = idx
    if len(cand_idx) < min_points:
        return fallback(f"only {len(cand_idx)} sparse points off the support plane near the focus: the box "
                        "is a cube around the point the cameras look at")
    Q = P[cand_idx]
    labels, eps = _clusters(Q)
    found = np.unique(labels[labels >= 0])
    if len(found) == 0:
        return fallback("the sparse points near the focus form no cluster: the box is a cube around the "
                        "point the cameras look at")
    score = []
    for lab in found:
        q = Q[labels == lab]
        d = float(np.linalg.norm(q.mean(0) - focus))
        score.append(len(q) / (1.0 + (d / (0.25 * med)) ** 2))
    obj = _grow_object(Q, labels, int(found[int(np.argmax(score))]), eps)
    O = Q[obj]
    third = plane.normal if plane is not None else scene_frame(c2w).up
    R = _box_axes(O, third)
    local = (O - focus) @ R
    lo, hi = local.min(0), local.max(0)
    pad = np.maximum(margin * (hi - lo), min(2.0 * eps, margin * float(np.max(hi - lo))))
    lo, hi = lo - pad, hi + pad
    if plane is not None:   # the face towards the support just in front of it
        floor = clearance * plane.sigma - float(plane.height(focus[None])[0])
        lo[2] = max(lo[2], floor)
    box = ObjectBox(focus + R @ (0.5 * (lo + hi)), 0.5 * (hi - lo), R,
                    source="the sparse points of the object the cameras look at"
                           + (" (its support left out)" if plane is not None else ""),
                    on_support=plane is not None and lo[2] == floor)
    if box.contains(centres).any():
        notes.append(f"{int(box.contains(centres).sum())} camera(s) inside the object box: is this a room "
                     "rather than an object? Pass --box to choose one")
    object_points = none.copy()
    object_points[cand_idx[obj]] = True
    candidates = none.copy()
    candidates[cand_idx] = True
    notes.append(f"object: {int(obj.sum())} sparse points in {len(found)} cluster(s) found, "
                 f"box half-sizes {np.round(box.half_extents, 3).tolist()}")
    return ObjectFinding(box, plane, object_points, candidates, notes)


def object_box(c2w: np.ndarray, points: Optional[np.ndarray] = None) -> ObjectBox:
    """The box around the object the cameras look at (:func:`find_object`)."""
    return find_object(c2w, points).box


def parse_box(text: str) -> ObjectBox:
    """``"cx,cy,cz,sx,sy,sz"`` (centre, half-extents; world units) -> :class:`ObjectBox`."""
    try:
        v = [float(x) for x in str(text).replace(" ", "").split(",")]
    except ValueError:
        v = []
    if len(v) != 6:
        raise ValueError(f"--box wants six numbers cx,cy,cz,sx,sy,sz (centre and half-sizes), got {text!r}")
    return ObjectBox(v[:3], v[3:])
