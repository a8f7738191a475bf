"""One click -> a 3D region (NeuMesh++ semantic-guided selection).

:func:`select_region` (a camera and a pixel) and :func:`select_at_point` (a 3D point):

1. The click's ray is rendered: its expected depth gives the surface point, whose ``seed_vertices``
   nearest scaffold vertices seed the region.  A ray whose opacity is below ``min_opacity`` hit the
   background: :class:`~neumesh_core.errors.SelectionError`.
2. Optionally a 2D segmenter (:mod:`.segment`) gives the clicked 2D region first; up to
   ``segment_rays`` rays from it add their surface points' nearest vertices as seeds.
3. DBSCAN (scikit-learn, cosine distance) over the seeds' decoded semantic features; the cluster that
   holds the click's own seeds (else the largest) gives the region's mean feature.
4. Region growing over the mesh: starting from the seeds in that cluster, add neighbouring vertices
   (mesh edges, and vertices within ``spatial_radius`` so that parts that touch without sharing edges
   join; never across a concave crease) whose combined similarity is >= ``threshold``, until nothing
   is added.  The combined similarity is ``(1 - geometry) * semantic + geometry * geometric``: the
   cosine similarity of the vertex's semantic feature with the cluster's mean (or, where larger, a
   Gaussian of their distance in the extractor's units, ``semantic_tolerance``), and the similarity of
   its geometric heat-embedding vector (:mod:`.geometry`: about 1 inside a part, 0 across a concave
   crease) with the clicked vertex's.  ``geometry = 0, creases = False, semantic_tolerance = 0`` is the
   semantic-only selection of earlier versions.
   That fixed point is the union of the connected components, in the graph restricted to similar
   vertices, that hold a seed; it is computed that way (scipy's connected components), which gives the
   same set as growing step by step, at once.

A :class:`SelectionContext` caches the vertex features and the neighbour graph of one field pose, so
re-running the growth with another threshold (the add-on's redo slider) costs milliseconds; the
geometric features are computed once per scaffold (:func:`.geometry.geometric_features`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field as dc_field
from typing import Optional, Sequence

import numpy as np
import torch

from ..errors import SelectionError
from .geometry import GeometryConfig, GeometryUnavailable, geometric_features, signed_bend


@dataclass
class SelectConfig:
    """Selection parameters (defaults suit the built-in scenes and lego)."""

    threshold: float = 0.75        # cosine similarity to the region's mean feature for a vertex to join
    seed_vertices: int = 8         # nearest vertices of each seed surface point
    segmenter: Optional[object] = "features"   # 2D segmenter: "features" (weight-free), None, or an object
    segment_rays: int = 128        # rays drawn from the 2D region for extra seeds
    dbscan_eps: float = 0.1        # DBSCAN neighbourhood (cosine distance)
    dbscan_min_samples: int = 5
    spatial_radius: Optional[float] = None   # graph edges between vertices this close (None: the field's
    #                                          neighbour radius; 0: mesh edges only)
    spatial_k: int = 8             # at most this many spatial neighbours per vertex
    min_opacity: float = 0.5       # a click whose ray is less opaque hit the background
    seed: int = 0
    geometry: float = 0.5          # weight of the geometric similarity (0: semantic features only)
    semantic_tolerance: float = 1.0   # features closer than this (extractor units) are alike (0: cosine only)
    creases: bool = True           # never grow across a concave crease (bend beyond the crease angle)
    geometry_config: GeometryConfig = dc_field(default_factory=GeometryConfig)   # read from the
    #                                  SelectionContext's config (the features are computed once for it)

    def __post_init__(self) -> None:
        if not -1.0 <= self.threshold <= 1.0:
            raise ValueError(f"threshold is a cosine similarity in [-1, 1], not {self.threshold}")
        if self.seed_vertices < 1 or self.dbscan_min_samples < 1 or self.spatial_k < 0:
            raise ValueError("seed_vertices and dbscan_min_samples must be positive, spatial_k >= 0")
        if not 0.0 <= self.geometry <= 1.0:
            raise ValueError(f"geometry is a weight in [0, 1], not {self.geometry}")
        if self.semantic_tolerance < 0:
            raise ValueError(f"semantic_tolerance is a distance (>= 0), not {self.semantic_tolerance}")


@dataclass
class Selection:
    """A selected region: ``vertices`` (sorted int64), the region's ``mean_feature`` (unit), the
    ``seeds`` it grew from, the clicked ``surface_point`` and timings/sizes in ``info``."""

    vertices: np.ndarray
    mean_feature: np.ndarray
    seeds: np.ndarray
    surface_point: np.ndarray
    info: dict = dc_field(default_factory=dict)


class SelectionContext:
    """Vertex features (unit length), geometric features and the region-growing graph of ``field`` in
    its current pose.  ``geometry_cache``: a folder for the geometric features' cache file (they are
    kept in memory per scaffold in any case)."""

    def __init__(self, field, config: Optional[SelectConfig] = None, geometry_cache: Optional[str] = None):
        field._require_semantics()
        self.field = field
        self.config = config or SelectConfig()
        self.geometry_cache = geometry_cache
        self.vertices = np.asarray(field.vertices, np.float32)
        feats = field.vertex_semantics().float()
        self.features = torch.nn.functional.normalize(feats, dim=-1).cpu().numpy()
        # the distilled features were centred and divided by this scale: times it they are in the
        # extractor's own units again, where a distance means the same in every scene
        scale = (getattr(field, "semantics_info", None) or {}).get("targets", {}).get("target_scale")
        self.raw_features = feats.cpu().numpy() * float(scale) if scale else None
        self._graph = None
        self._cut_graph = None
        self._tree = None
        self._geometry = None
        self._geo_embedding = None
        self.geometry_error: Optional[str] = None

    def matches(self, field) -> bool:
        """Still valid for ``field`` (same object, same pose)?"""
        return field is self.field and np.array_equal(np.asarray(field.vertices, np.float32), self.vertices)

    def prepare(self) -> "SelectionContext":
        """Build the KD-tree and the region-growing graph now (they are otherwise built by the first
        click); the add-on calls this in a background thread while the artist moves to the click."""
        self.tree
        self.graph
        if self.config.geometry > 0 or self.config.creases:
            self.geometry
            if self.config.creases:
                self.cut_graph
        return self

    @property
    def geometry(self):
        """The scaffold's :class:`~.geometry.GeometricFeatures` (None when a library they need is missing:
        ``geometry_error`` says which; selection then uses the semantic features alone)."""
        if self._geometry is None and self.geometry_error is None:
            try:
                self._geometry = geometric_features(self.field, self.config.geometry_config, self.geometry_cache)
                self._geo_embedding = self._geometry.vertex_embedding()
            except GeometryUnavailable as exc:
                self.geometry_error = str(exc)
        return self._geometry

    @property
    def geo_embedding(self) -> Optional[np.ndarray]:
        """(N,k) unit heat-embedding vector per vertex (None without geometric features)."""
        return self._geo_embedding if self.geometry is not None else None

    @property
    def cut_graph(self):
        """:attr:`graph` without the edges across a concave crease (bend, in the rest pose, beyond the
        crease angle); :attr:`graph` itself when the geometric features are unavailable."""
        if self._cut_graph is None:
            geo = self.geometry
            if geo is None:
                return self.graph
            import scipy.sparse as sp

            a = sp.triu(self.graph, k=1).tocoo()
            rest = self.field.rest_vertices.detach().cpu().numpy()
            bend = signed_bend(rest, geo.normals, a.row, a.col)
            keep = bend >= -np.deg2rad(geo.config.crease_angle)
            n = len(self.vertices)
            c = sp.coo_matrix((np.ones(int(keep.sum()), np.int8), (a.row[keep], a.col[keep])), shape=(n, n)).tocsr()
            self._cut_graph = (c + c.T).tocsr()
        return self._cut_graph

    @property
    def tree(self):
        if self._tree is None:
            from ..field.knn import kd_tree

            self._tree = kd_tree(self.vertices)
        return self._tree

    def nearest_vertices(self, points: np.ndarray, k: int) -> np.ndarray:
        """(P,k) nearest vertex ids of points (P,3)."""
        k = min(k, len(self.vertices))
        _, idx = self.tree.query(np.ascontiguousarray(points, np.float32), k=k)
        return np.asarray(idx, np.int64).reshape(len(points), k)

    @property
    def graph(self):
        """Symmetric CSR adjacency: mesh edges plus spatial neighbours within the radius."""
        if self._graph is None:
            import scipy.sparse as sp

            from ..mesh import unique_edges

            n = len(self.vertices)
            faces = self.field.faces.cpu().numpy()
            e = unique_edges(faces) if len(faces) else np.zeros((0, 2), np.int64)
            rows, cols = [e[:, 0]], [e[:, 1]]
            radius = self.config.spatial_radius
            radius = float(self.field.radius) if radius is None else float(radius)
            if radius > 0 and self.config.spatial_k > 0:
                k = min(self.config.spatial_k + 1, n)
                dist, idx = self.tree.query(self.vertices, k=k, distance_upper_bound=radius)
                idx = np.asarray(idx, np.int64).reshape(n, k)
                ok = (idx < n) & np.isfinite(np.asarray(dist).reshape(n, k))
                src = np.repeat(np.arange(n), k)[ok.ravel()]
                dst = idx.ravel()[ok.ravel()]
                rows.append(src)
                cols.append(dst)
            r = np.concatenate(rows)
            c = np.concatenate(cols)
            a = sp.coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(n, n)).tocsr()
            self._graph = (a + a.T).tocsr()
        return self._graph

    def similarity(self, mean_feature: np.ndarray, geo_vertex: Optional[int] = None, geometry: float = 0.0,
                   raw_mean: Optional[np.ndarray] = None, tolerance: float = 0.0) -> np.ndarray:
        """(N,) combined similarity of every vertex: ``(1 - geometry)`` x semantic similarity +
        ``geometry`` x geometric similarity.

        The semantic similarity is the cosine similarity of the vertex's semantic feature with
        ``mean_feature``, or, where larger, ``exp(-d^2 / (2 tolerance^2))``, d the distance of the
        vertex's feature in the extractor's units from ``raw_mean`` (features that differ by less than
        the tolerance are alike whatever their direction: on an object of one colour the centred
        features are noise, and their directions mean nothing).  The geometric similarity with vertex
        ``geo_vertex`` (the dot product of their heat-embedding vectors, times
        ``exp(-(difference of log shape diameter)^2 / (2 thickness_tolerance^2))`` when the features hold
        the shape diameter).  The semantic term alone without ``geo_vertex`` or geometric features."""
        m = np.asarray(mean_feature, np.float32)
        m = m / max(float(np.linalg.norm(m)), 1e-12)
        sim = self.features @ m
        if tolerance > 0 and raw_mean is not None and self.raw_features is not None:
            d2 = ((self.raw_features - np.asarray(raw_mean, np.float32)) ** 2).sum(1)
            sim = np.maximum(sim, np.exp(-d2 / (2.0 * tolerance * tolerance)))
        emb = self.geo_embedding if geometry > 0 and geo_vertex is not None else None
        if emb is not None and float(np.linalg.norm(emb[geo_vertex])) > 1e-6:
            g = emb @ emb[geo_vertex]
            ls = self.geometry.log_sdf
            if ls is not None:
                ls = ls[self.geometry.cluster]
                tol = self.geometry.config.thickness_tolerance
                g = g * np.exp(-((ls - ls[geo_vertex]) ** 2) / (2.0 * tol * tol))
            sim = (1.0 - geometry) * sim + geometry * g
        return sim

    def grow(self, mean_feature: np.ndarray, seeds: np.ndarray, threshold: float,
             geo_vertex: Optional[int] = None, geometry: float = 0.0, creases: bool = False,
             raw_mean: Optional[np.ndarray] = None, tolerance: float = 0.0) -> np.ndarray:
        """Vertices reachable from ``seeds`` through vertices whose :meth:`similarity` is >= ``threshold``
        (seeds below it do not start a region); with ``creases``, never across a concave crease."""
        from scipy.sparse.csgraph import connected_components

        ok = self.similarity(mean_feature, geo_vertex, geometry, raw_mean, tolerance) >= threshold
        seeds = np.unique(np.asarray(seeds, np.int64))
        seeds = seeds[ok[seeds]]
        if len(seeds) == 0:
            return seeds
        keep = np.nonzero(ok)[0]
        graph = self.cut_graph if creases else self.graph
        sub = graph[keep][:, keep]
        _, comp = connected_components(sub, directed=False)
        pos = np.searchsorted(keep, seeds)
        chosen = np.zeros(comp.max() + 1, bool)
        chosen[comp[pos]] = True
        return keep[chosen[comp]]


def _camera(camera):
    """(K (3,3), c2w (4,4), width, height) from a (K, c2w, width, height) tuple or a one-camera
    :class:`~neumesh_core.data.cameras.Cameras`."""
    if hasattr(camera, "K") and hasattr(camera, "c2w"):
        if len(camera) != 1:
            raise ValueError(f"select_region needs one camera, got {len(camera)}; pass cameras.subset(i)")
        return camera.K[0], camera.c2w[0], int(camera.width), int(camera.height)
    K, c2w, w, h = camera
    return np.asarray(K, np.float32), np.asarray(c2w, np.float32), int(w), int(h)


def surface_points(field, K, c2w, pixels: np.ndarray, min_opacity: float):
    """Surface points (P,3), opacities (P,) and a hit mask of pixel centres (P,2) (x, y)."""
    from ..data.cameras import batch_pixel_rays
    from ..render.renderer import render_rays

    pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
    n = len(pixels)
    Kt = torch.as_tensor(np.asarray(K, np.float32)).expand(n, 3, 3)
    Ct = torch.as_tensor(np.asarray(c2w, np.float32)).expand(n, 4, 4)
    o, d = batch_pixel_rays(Kt, Ct, torch.as_tensor(np.floor(pixels[:, 0])), torch.as_tensor(np.floor(pixels[:, 1])))
    dev = field.rest_vertices.device
    with torch.no_grad():
        out = render_rays(field, o.to(dev), d.to(dev))
    op = out["opacity"].cpu().numpy()
    depth = out["depth"].cpu().numpy()
    hit = (op >= min_opacity) & np.isfinite(depth)
    pts = o.numpy() + np.where(hit, depth, 0.0)[:, None] * d.numpy()
    return pts, op, hit


def select_region(field, camera, pixel: Sequence[float], config: Optional[SelectConfig] = None,
                  context: Optional[SelectionContext] = None) -> Selection:
    """Vertices of the part under ``pixel`` = (x, y) (pixels, origin top-left, x right, y down) seen
    by ``camera`` (a (K, c2w OpenCV, width, height) tuple or a one-camera ``Cameras``).

    Raises :class:`~neumesh_core.errors.NoSemanticsError` for a field without semantics and
    :class:`~neumesh_core.errors.SelectionError` for a click outside the image or on the background.
    ``context``: a :class:`SelectionContext` to reuse (it is rebuilt when it no longer matches).
    """
    cfg = config or SelectConfig()
    field._require_semantics()
    t0 = time.perf_counter()
    K, c2w, w, h = _camera(camera)
    x, y = float(pixel[0]), float(pixel[1])
    if not (0 <= x < w and 0 <= y < h):
        raise SelectionError(f"pixel ({x:.0f}, {y:.0f}) lies outside the {w}x{h} image")
    pts, op, hit = surface_points(field, K, c2w, np.array([[x, y]]), cfg.min_opacity)
    if not hit[0]:
        raise SelectionError(f"the click at pixel ({x:.0f}, {y:.0f}) hits no surface (opacity {op[0]:.2f} < "
                             f"{cfg.min_opacity}): click on the object, not on the background")
    ctx = context if context is not None and context.matches(field) else SelectionContext(field, cfg)
    extra = np.zeros((0, 3), np.float32)
    info = {"click_opacity": float(op[0])}
    seg = _segmenter(cfg.segmenter)
    if seg is not None:
        t1 = time.perf_counter()
        mask = np.asarray(seg(field, (K, c2w, w, h), (x, y)), bool)
        ys, xs = np.nonzero(mask)
        info["segment_pixels"] = int(len(xs))
        if len(xs):
            rng = np.random.default_rng(cfg.seed)
            pick = rng.choice(len(xs), size=min(cfg.segment_rays, len(xs)), replace=False)
            p2, _, h2 = surface_points(field, K, c2w, np.stack([xs[pick], ys[pick]], -1) + 0.5, cfg.min_opacity)
            extra = p2[h2]
        info["segment_s"] = time.perf_counter() - t1
    sel = _select(ctx, pts[0], extra, cfg, info)
    sel.info["seconds"] = time.perf_counter() - t0
    return sel


def select_at_point(field, point: Sequence[float], config: Optional[SelectConfig] = None,
                    context: Optional[SelectionContext] = None, extra_points: Optional[np.ndarray] = None) -> Selection:
    """Vertices of the part at the 3D ``point`` (world space, on or near the surface); ``extra_points``
    (P,3) add seeds as a 2D segmenter's rays would."""
    cfg = config or SelectConfig()
    field._require_semantics()
    t0 = time.perf_counter()
    p = np.asarray(point, np.float32).reshape(3)
    if not np.isfinite(p).all():
        raise SelectionError("the point has NaN/inf coordinates")
    ctx = context if context is not None and context.matches(field) else SelectionContext(field, cfg)
    d = float(np.linalg.norm(ctx.vertices[ctx.nearest_vertices(p[None], 1)[0, 0]] - p))
    if d > 2 * float(field.radius):
        raise SelectionError(f"the point {p.round(3).tolist()} is {d:.3g} from the nearest scaffold vertex "
                             f"(more than twice the field's radius {field.radius:.3g}): pick a point on the surface")
    extra = np.zeros((0, 3), np.float32) if extra_points is None else np.asarray(extra_points, np.float32)
    sel = _select(ctx, p, extra, cfg, {})
    sel.info["seconds"] = time.perf_counter() - t0
    return sel


def _segmenter(seg):
    if seg is None:
        return None
    if isinstance(seg, str):
        from .segment import make_segmenter

        return make_segmenter(seg)
    return seg


def _select(ctx: SelectionContext, point: np.ndarray, extra: np.ndarray, cfg: SelectConfig, info: dict) -> Selection:
    from sklearn.cluster import DBSCAN

    click_seeds = ctx.nearest_vertices(point[None], cfg.seed_vertices)[0]
    extra_seeds = ctx.nearest_vertices(extra, 1)[:, 0] if len(extra) else np.zeros(0, np.int64)
    seeds = np.unique(np.concatenate([click_seeds, extra_seeds]))
    feats = ctx.features[seeds]
    labels = DBSCAN(eps=cfg.dbscan_eps, min_samples=min(cfg.dbscan_min_samples, len(seeds)),
                    metric="cosine").fit_predict(feats)
    click_labels = labels[np.searchsorted(seeds, np.unique(click_seeds))]
    click_labels = click_labels[click_labels >= 0]
    if len(click_labels):
        chosen = int(np.bincount(click_labels).argmax())
    elif (labels >= 0).any():
        chosen = int(np.bincount(labels[labels >= 0]).argmax())
    else:
        chosen = None   # every seed is noise: fall back to the click's own seeds
    members = seeds[labels == chosen] if chosen is not None else np.unique(click_seeds)
    mean = ctx.features[members].mean(0)
    mean = mean / max(float(np.linalg.norm(mean)), 1e-12)
    geo_vertex = None
    if cfg.geometry > 0 or cfg.creases:
        t = time.perf_counter()
        emb = ctx.geo_embedding   # computes the geometric features on first use (once per scaffold)
        info["geometry_s"] = time.perf_counter() - t
        if emb is not None:
            geo_vertex = int(click_seeds[0])   # the vertex nearest to the click
        elif ctx.geometry_error:
            info["geometry"] = ctx.geometry_error
    # seeds that the 2D step drew from another part of the same colour fall below the threshold of the
    # combined similarity and start nothing
    raw_mean = ctx.raw_features[members].mean(0) if ctx.raw_features is not None else None
    region = ctx.grow(mean, members, cfg.threshold, geo_vertex, cfg.geometry, cfg.creases, raw_mean,
                      cfg.semantic_tolerance)
    if len(region) == 0:
        raise SelectionError(f"no vertex near the click is within similarity {cfg.threshold:.2f} of the "
                             "region's mean feature; lower the similarity threshold")
    info.update({"seeds": int(len(seeds)), "cluster_seeds": int(len(members)),
                 "clusters": int(labels.max() + 1), "vertices": int(len(region))})
    return Selection(region, mean, members, np.asarray(point, np.float32), info)
