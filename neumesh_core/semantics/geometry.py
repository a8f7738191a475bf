"""Geometric features of a scaffold for part selection: parts meet at concave creases (the minima rule),
sit apart in a crease-aware spectral embedding, and differ in thickness.

Computed once per scaffold from its rest pose (:func:`geometric_features`, cached in memory by content
key and, with ``cache_dir``, in an ``.npz`` file; no pickle):

* **Smoothed vertex normals** (area-weighted, ``normal_smoothing`` rounds of one-ring averaging) and the
  **signed bend of any vertex pair** (:func:`signed_bend`): the angle between the two normals, negative
  where the surface folds inwards between them (concave: ``(n_j - n_i) . (p_j - p_i) < 0``). Region
  growing cuts every graph edge whose bend is below ``-crease_angle``.
* **Crease-aware heat embedding** (:func:`crease_embedding`): the scaffold is decimated by vertex
  clustering to at most ``max_vertices`` vertices; the band of vertices along concave creases
  (:func:`vertex_concavity` above the crease angle) is taken out, so the parts it bounds fall apart;
  the rest's Laplacian is built with robust-laplacian (intrinsic Delaunay, so non-manifold clusters
  are fine), every off-diagonal weight also scaled by ``exp(-(concave bend / (crease_angle / 2))^2)``.
  The lowest
  ``eigenvectors`` modes (scipy ``eigsh``, shift-invert) give each vertex the vector
  ``phi_i(v) exp(-lambda_i t)``, ``t = heat_time * area``; normalised to unit length, the dot product of two
  vertices is the normalised heat kernel ``K_t(u,v) / sqrt(K_t(u,u) K_t(v,v))``: about 1 inside a part
  (heat has evened out there) and about 0 across a concave crease. Vertices taken out copy a
  neighbour's vector (:func:`attach`); every full-resolution vertex takes its cluster's vector.
* **Shape diameter** (optional, ``sdf_rays`` > 0; libigl's embree ``shape_diameter_function``): the
  thickness of the part under each vertex, as ``log(sdf / median)``; selection then scales the
  geometric similarity by the agreement of thickness.  Off by default: on the built-in parts the
  heat embedding already separates them, and near a junction the shape diameter varies as much inside
  a part as between parts.

The plain reference of the decimation is the identity (``max_vertices`` >= the vertex count); the tests
run both paths and ask each to separate the built-in parts.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass, field as dc_field
from typing import Callable, Optional

import numpy as np

from ..errors import NeuMeshError

CACHE_VERSION = 1


@dataclass(frozen=True)
class GeometryConfig:
    """Parameters of the geometric features (defaults suit marching-cubes and MVS scaffolds)."""

    max_vertices: int = 12000     # decimation target of the spectral / shape-diameter mesh
    eigenvectors: int = 24        # Laplacian modes of the heat embedding
    heat_time: float = 0.1        # diffusion time, as a fraction of the scaffold's surface area
    crease_angle: float = 20.0    # degrees: a concave bend beyond this between two vertices is a crease
    normal_smoothing: int = 0     # one-ring averaging rounds of the vertex normals
    sdf_rays: int = 0             # shape-diameter rays per decimated vertex (0: no shape diameter)
    thickness_tolerance: float = 0.5   # with the shape diameter: a log-thickness difference d scales
    #                                    the geometric similarity by exp(-d^2 / (2 tol^2))
    min_component: float = 0.002  # components smaller than this fraction of the vertices get no embedding

    def __post_init__(self) -> None:
        if self.max_vertices < 100 or self.eigenvectors < 2:
            raise ValueError("max_vertices must be >= 100 and eigenvectors >= 2")
        if not 0.0 < self.crease_angle < 180.0:
            raise ValueError(f"crease_angle is in degrees, in (0, 180), not {self.crease_angle}")
        if self.heat_time <= 0 or self.normal_smoothing < 0 or self.sdf_rays < 0:
            raise ValueError("heat_time must be > 0, normal_smoothing and sdf_rays >= 0")


@dataclass
class GeometricFeatures:
    """Per-vertex geometric features of one scaffold (rest pose).

    ``normals`` (N,3) smoothed unit normals; ``concavity`` (N,) :func:`vertex_concavity` (radians);
    ``embedding`` (C,k) unit heat-embedding vectors of the
    decimated vertices (zero rows: vertices of tiny components) and ``cluster`` (N,) the decimated vertex
    of each vertex; ``log_sdf`` (C,) log shape diameter over its median (None when skipped);
    ``key`` the content key; ``timings`` seconds per stage."""

    normals: np.ndarray
    concavity: np.ndarray
    embedding: np.ndarray
    cluster: np.ndarray
    log_sdf: Optional[np.ndarray]
    key: str
    config: GeometryConfig
    timings: dict = dc_field(default_factory=dict)

    @property
    def num_vertices(self) -> int:
        return len(self.cluster)

    def vertex_embedding(self) -> np.ndarray:
        """(N,k) unit heat-embedding vector of every vertex."""
        return self.embedding[self.cluster]


class GeometryUnavailable(NeuMeshError):
    """The geometric features cannot be computed: a library they need is missing, or the scaffold has
    no faces (selection then goes on with the semantic features alone)."""


def scaffold_key(vertices: np.ndarray, faces: np.ndarray, config: GeometryConfig) -> str:
    """Content key of a scaffold (rest positions as float32, faces as int64) and the feature config."""
    h = hashlib.sha1()
    v = np.ascontiguousarray(vertices, np.float32)
    f = np.ascontiguousarray(faces, np.int64)
    h.update(f"{CACHE_VERSION}:{v.shape}:{f.shape}:".encode())
    h.update(v.tobytes())
    h.update(f.tobytes())
    h.update(json.dumps(asdict(config), sort_keys=True).encode())
    return h.hexdigest()


# ------------------------------------------------------------------------------------------ building blocks
def adjacency(faces: np.ndarray, n: int, edges: Optional[np.ndarray] = None):
    """Symmetric (n,n) CSR 0/1 adjacency of the mesh edges (``edges``: their unique_edges, if known)."""
    import scipy.sparse as sp

    from ..mesh import unique_edges

    e = edges if edges is not None else (unique_edges(faces) if len(faces) else np.zeros((0, 2), np.int64))
    r = np.concatenate([e[:, 0], e[:, 1]])
    c = np.concatenate([e[:, 1], e[:, 0]])
    return sp.csr_matrix((np.ones(len(r), np.float32), (r, c)), shape=(n, n))


def smoothed_normals(vertices: np.ndarray, faces: np.ndarray, rounds: int, adj=None) -> np.ndarray:
    """Area-weighted vertex normals averaged ``rounds`` times with the one ring (unit length)."""
    import scipy.sparse as sp

    from ..mesh import vertex_normals

    n = np.asarray(vertex_normals(np.asarray(vertices, np.float32), np.asarray(faces, np.int64)), np.float64)
    if rounds:
        a = adjacency(faces, len(vertices)) if adj is None else adj
        a = (a + sp.identity(len(vertices), format="csr", dtype=np.float32)).tocsr()
        for _ in range(rounds):
            n = a @ n
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return n.astype(np.float32)


def signed_bend(positions: np.ndarray, normals: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Signed angle (radians) between the normals of vertex pairs (i, j): negative where the surface
    folds inwards between them (concave), positive where it bulges (convex)."""
    ni, nj = normals[i].astype(np.float64), normals[j].astype(np.float64)
    d = positions[j].astype(np.float64) - positions[i].astype(np.float64)
    ang = np.arccos(np.clip((ni * nj).sum(1), -1.0, 1.0))
    return np.where(((nj - ni) * d).sum(1) < 0, -ang, ang)


def vertex_concavity(positions: np.ndarray, normals: np.ndarray, faces: np.ndarray,
                     edges: Optional[np.ndarray] = None) -> np.ndarray:
    """(N,) how sharply the surface folds inwards at each vertex: the largest concave bend (radians,
    >= 0) over its mesh edges.  Vertices above the crease angle form a band along every concave crease
    that is closed where single edges would leave gaps (a crease crosses edges at all angles)."""
    from ..mesh import unique_edges

    e = unique_edges(faces) if edges is None else edges
    b = np.maximum(-signed_bend(positions, normals, e[:, 0], e[:, 1]), 0.0)
    idx = np.concatenate([e[:, 0], e[:, 1]])
    val = np.concatenate([b, b])
    order = np.argsort(idx, kind="stable")
    idx, val = idx[order], val[order]
    c = np.zeros(len(positions), np.float64)
    if len(idx):
        start = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
        c[idx[start]] = np.maximum.reduceat(val, start)
    return c.astype(np.float32)


def cluster_vertices(vertices: np.ndarray, faces: np.ndarray, max_vertices: int):
    """Vertex clustering on a grid fine enough to keep at most ``max_vertices`` clusters.

    Returns (cluster (N,) int64 id of each vertex, cluster positions (C,3), faces (G,3) of the clustered
    mesh without degenerate or repeated triangles).  With ``max_vertices >= N`` it is the identity."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    n = len(v)
    if n <= max_vertices:
        return np.arange(n, dtype=np.int64), v.copy(), f.copy()
    lo = v.min(0)
    ext = float((v.max(0) - lo).max())
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    h = max(np.sqrt(area / max_vertices), 1e-9 * max(ext, 1e-9))
    for _ in range(60):
        cell = np.floor((v - lo) / h).astype(np.int64)
        dims = cell.max(0) + 1
        key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
        uniq, cluster = np.unique(key, return_inverse=True)
        if len(uniq) <= max_vertices:
            break
        h *= 1.15
    c = len(uniq)
    counts = np.bincount(cluster, minlength=c).astype(np.float64)
    pos = np.stack([np.bincount(cluster, weights=v[:, k], minlength=c) for k in range(3)], 1) / counts[:, None]
    g = cluster[f]
    ok = (g[:, 0] != g[:, 1]) & (g[:, 1] != g[:, 2]) & (g[:, 0] != g[:, 2])
    g = g[ok]
    if len(g):
        s = np.sort(g, 1)
        _, first = np.unique((s[:, 0] * c + s[:, 1]) * c + s[:, 2], return_index=True)
        g = g[np.sort(first)]
    return cluster.astype(np.int64), pos, g


def crease_laplacian(positions: np.ndarray, faces: np.ndarray, normals: np.ndarray, crease_angle_deg: float):
    """(L, M): robust-laplacian's cotangent Laplacian (intrinsic Delaunay) and lumped mass of the mesh,
    with each off-diagonal weight (i, j) scaled by exp(-(b / (crease / 2))^2), b the concave bend
    between i and j (0 where convex)."""
    import scipy.sparse as sp

    try:
        import robust_laplacian
    except ImportError as exc:   # pragma: no cover - depends on the environment
        raise GeometryUnavailable("geometric features need robust-laplacian: pip install robust-laplacian") from exc
    L, M = robust_laplacian.mesh_laplacian(np.asarray(positions, np.float64), np.asarray(faces, np.int64))
    L = sp.coo_matrix(L)
    off = L.row != L.col
    r, c, w = L.row[off], L.col[off], -L.data[off]   # cotangent weights (>= 0 on an intrinsic Delaunay mesh)
    w = np.maximum(w, 0.0)
    bend = signed_bend(positions, normals, r, c)
    sigma = np.deg2rad(crease_angle_deg) / 2.0
    w = w * np.exp(-(np.maximum(-bend, 0.0) / sigma) ** 2)
    n = len(positions)
    W = sp.coo_matrix((w, (r, c)), shape=(n, n)).tocsr()
    W = 0.5 * (W + W.T)
    Lw = sp.diags(np.asarray(W.sum(1)).ravel()) - W
    return Lw.tocsc(), sp.csc_matrix(M)


def heat_embedding(L, M, k: int, t: float) -> np.ndarray:
    """(n,k') unit rows phi_i exp(-lambda_i t) / norm of the k lowest modes of L phi = lambda M phi
    (k' = min(k, n - 2); a mesh of several components has one zero mode per component, so k must
    exceed their number)."""
    import scipy.sparse.linalg as sla

    n = L.shape[0]
    k = int(min(k, n - 2))
    if k < 1:
        return np.ones((n, 1), np.float32)
    mass = np.asarray(M.diagonal()).ravel()
    shift = -1e-8 * float(np.abs(L.diagonal()).mean() / max(mass.mean(), 1e-30))
    try:
        lam, phi = sla.eigsh(L, k=k, M=M, sigma=shift, which="LM", tol=1e-6,
                             v0=np.ones(n) / np.sqrt(n))
    except (RuntimeError, sla.ArpackNoConvergence):   # pragma: no cover - ill-conditioned meshes
        lam, phi = sla.eigsh(L + sp_identity(n, 1e-9), k=k, M=M, sigma=shift, which="LM", tol=1e-4)
    lam = np.maximum(lam, 0.0)
    e = phi * np.exp(-lam * t)[None]
    e /= np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-30)
    return e.astype(np.float32)


def sp_identity(n: int, s: float):
    import scipy.sparse as sp

    return sp.identity(n, format="csc") * s


def shape_diameter(positions: np.ndarray, faces: np.ndarray, normals: np.ndarray, rays: int) -> np.ndarray:
    """Shape diameter per vertex (libigl + embree: mean length of ``rays`` rays cast inwards in a
    cone around -normal, outliers dropped)."""
    try:
        from igl.embree import shape_diameter_function
    except ImportError as exc:   # pragma: no cover - depends on the environment
        raise GeometryUnavailable("the shape diameter needs libigl: pip install libigl") from exc
    p = np.asarray(positions, np.float64)
    nrm = np.asarray(normals, np.float64)
    s = shape_diameter_function(p, np.asarray(faces, np.int64), p - 1e-5 * nrm, nrm, int(rays))
    return np.asarray(s, np.float64)


def attach(ok: np.ndarray, adj, normals: np.ndarray) -> np.ndarray:
    """(N,) for every vertex a vertex with ``ok`` set that it takes its values from: itself where ``ok``,
    else, ring by ring outwards, the ``ok`` (or already attached) neighbour whose normal agrees best with
    its own (-1 where none is reachable)."""
    n = len(ok)
    src = np.where(ok, np.arange(n), -1).astype(np.int64)
    a = adj.tocoo()
    r, c = a.row.astype(np.int64), a.col.astype(np.int64)
    score = (normals[r].astype(np.float64) * normals[c]).sum(1)
    while True:
        sel = (src[r] < 0) & (src[c] >= 0)
        if not sel.any():
            return src
        rr, cc, ss = r[sel], c[sel], score[sel]
        order = np.lexsort((-ss, rr))          # per row, the best-agreeing neighbour first
        rr, cc = rr[order], cc[order]
        first = np.ones(len(rr), bool)
        first[1:] = rr[1:] != rr[:-1]
        src[rr[first]] = src[cc[first]]


def crease_embedding(positions: np.ndarray, faces: np.ndarray, normals: np.ndarray, cfg: GeometryConfig):
    """(C,k) unit heat-embedding rows of a (decimated) mesh, and sizes for the log.

    Vertices on concave creases (:func:`vertex_concavity` above the crease angle) are taken out first, so
    the parts the creases bound fall apart into separate components; the heat kernel of the
    crease-weighted Laplacian (:func:`crease_laplacian`) over the remaining mesh is then exactly 0
    between components.  Components below ``min_component`` of the vertices (and all but the
    ``eigenvectors // 2`` largest) are taken out as well, and every vertex taken out copies the row of
    the neighbour it is attached to (:func:`attach`)."""
    from scipy.sparse.csgraph import connected_components

    C = len(positions)
    adj = adjacency(faces, C)
    barrier = vertex_concavity(positions, normals, faces) > np.deg2rad(cfg.crease_angle)
    keepf = ~barrier[faces].any(1)
    has_face = np.zeros(C, bool)
    has_face[faces[keepf].ravel()] = True
    ncomp, comp = connected_components(adjacency(faces[keepf], C), directed=False)
    sizes = np.bincount(comp[has_face], minlength=ncomp)
    big = np.nonzero(sizes >= max(8, cfg.min_component * C))[0]
    big = big[np.argsort(-sizes[big])][: max(1, cfg.eigenvectors // 2)]
    inside = has_face & np.isin(comp, big)
    if not inside.any():   # no part survives the creases (a crumpled scaffold): use the whole mesh
        inside = np.ones(C, bool)
        keepf = np.ones(len(faces), bool)
    idx = np.nonzero(inside)[0]
    remap = np.full(C, -1, np.int64)
    remap[idx] = np.arange(len(idx))
    sub = remap[faces[keepf]]
    sub = sub[(sub >= 0).all(1)]
    tri = positions[idx][sub]
    area = float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())
    L, M = crease_laplacian(positions[idx], sub, normals[idx], cfg.crease_angle)
    e = heat_embedding(L, M, cfg.eigenvectors, cfg.heat_time * area)
    emb = np.zeros((C, cfg.eigenvectors), np.float32)
    emb[idx, : e.shape[1]] = e
    src = attach(inside, adj, normals)
    emb = np.where((src >= 0)[:, None], emb[np.maximum(src, 0)], 0.0).astype(np.float32)
    return emb, {"crease_clusters": int(barrier.sum()), "parts": int(len(big)), "embedded": int(len(idx))}


# ------------------------------------------------------------------------------------------ the features
def compute_geometric_features(vertices: np.ndarray, faces: np.ndarray, config: Optional[GeometryConfig] = None,
                               log: Optional[Callable[[str], None]] = None) -> GeometricFeatures:
    """Geometric features of a scaffold (rest positions (N,3), faces (F,3)); see the module doc.  ``log``
    gets the name of each stage as it starts."""

    cfg = config or GeometryConfig()
    v = np.asarray(vertices, np.float32)
    f = np.asarray(faces, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"vertices must be a non-empty (N,3) array, got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise GeometryUnavailable("geometric features need a triangle mesh: the scaffold has no faces")
    timings = {}
    say = log or (lambda s: None)
    t0 = time.perf_counter()
    key = scaffold_key(v, f, cfg)
    say("normals")
    from ..mesh import unique_edges

    edges = unique_edges(f)
    adj = adjacency(f, len(v), edges) if cfg.normal_smoothing else None
    normals = smoothed_normals(v, f, cfg.normal_smoothing, adj)
    concavity = vertex_concavity(v, normals, f, edges)
    timings["normals_s"] = time.perf_counter() - t0

    t = time.perf_counter()
    say("decimate")
    cluster, cpos, cfaces = cluster_vertices(v, f, cfg.max_vertices)
    C = len(cpos)
    cn = np.stack([np.bincount(cluster, weights=normals[:, k], minlength=C) for k in range(3)], 1)
    cn /= np.maximum(np.linalg.norm(cn, axis=1, keepdims=True), 1e-12)
    timings["decimate_s"] = time.perf_counter() - t
    timings["clusters"] = int(C)

    t = time.perf_counter()
    say("spectral")
    emb, info = crease_embedding(cpos, cfaces, cn, cfg)
    timings["spectral_s"] = time.perf_counter() - t
    timings.update(info)

    log_sdf = None
    if cfg.sdf_rays:
        t = time.perf_counter()
        say("shape diameter")
        s = shape_diameter(cpos, cfaces, cn, cfg.sdf_rays)
        ok = np.isfinite(s) & (s > 0)
        med = float(np.median(s[ok])) if ok.any() else 1.0
        log_sdf = np.where(ok, np.log(np.maximum(s, 1e-12) / med), 0.0).astype(np.float32)
        timings["sdf_s"] = time.perf_counter() - t
    timings["total_s"] = time.perf_counter() - t0
    return GeometricFeatures(normals, concavity, emb, cluster, log_sdf, key, cfg, timings)


# ------------------------------------------------------------------------------------------ cache
_MEMO: "OrderedDict[str, GeometricFeatures]" = OrderedDict()
_MEMO_SIZE = 2


def cache_file(cache_dir: str, key: str) -> str:
    return os.path.join(os.fspath(cache_dir), f"neumesh-geometry-{key[:20]}.npz")


def save_geometric_features(feats: GeometricFeatures, path: str) -> str:
    """Write ``feats`` to ``path`` (.npz, atomic: a temporary file renamed over it; no pickle)."""
    path = os.fspath(path)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    arrays = {"normals": feats.normals, "concavity": feats.concavity, "embedding": feats.embedding,
              "cluster": feats.cluster.astype(np.int32),
              "meta": np.frombuffer(json.dumps({"key": feats.key, "config": asdict(feats.config),
                                                "timings": feats.timings, "version": CACHE_VERSION}).encode(),
                                    np.uint8)}
    if feats.log_sdf is not None:
        arrays["log_sdf"] = feats.log_sdf
    tmp = f"{path}.tmp-{os.getpid()}"
    try:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return path


def load_geometric_features(path: str, key: Optional[str] = None) -> Optional[GeometricFeatures]:
    """Features stored at ``path``; None when the file is missing, unreadable or for another key."""
    try:
        with np.load(os.fspath(path), allow_pickle=False) as z:
            meta = json.loads(bytes(z["meta"]).decode())
            if meta.get("version") != CACHE_VERSION or (key is not None and meta["key"] != key):
                return None
            return GeometricFeatures(z["normals"], z["concavity"], z["embedding"], z["cluster"].astype(np.int64),
                                     z["log_sdf"] if "log_sdf" in z.files else None, meta["key"],
                                     GeometryConfig(**meta["config"]), meta.get("timings", {}))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def geometric_features(field, config: Optional[GeometryConfig] = None, cache_dir: Optional[str] = None,
                       log: Optional[Callable[[str], None]] = None) -> GeometricFeatures:
    """Geometric features of ``field``'s scaffold in its rest pose, computed once: kept in memory by
    content key (the last two scaffolds) and, with ``cache_dir``, read from / written to
    ``<cache_dir>/neumesh-geometry-<key>.npz``."""
    cfg = config or GeometryConfig()
    v = field.rest_vertices.detach().cpu().numpy().astype(np.float32)
    f = field.faces.detach().cpu().numpy().astype(np.int64)
    key = scaffold_key(v, f, cfg)
    hit = _MEMO.get(key)
    if hit is not None:
        _MEMO.move_to_end(key)
        return hit
    feats = load_geometric_features(cache_file(cache_dir, key), key) if cache_dir else None
    if feats is None:
        feats = compute_geometric_features(v, f, cfg, log)
        if cache_dir:
            try:
                save_geometric_features(feats, cache_file(cache_dir, key))
            except OSError:   # a read-only folder: keep it in memory only
                pass
    _MEMO[key] = feats
    while len(_MEMO) > _MEMO_SIZE:
        _MEMO.popitem(last=False)
    return feats
