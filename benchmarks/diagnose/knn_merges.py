"""How much work the fused renderer's neighbour search does, counted without a GPU: the rounds and
K-merges of ``kernels/knn.knn_keys`` for the points a real frame evaluates, with and without
``knn_early_out``.

    python benchmarks/diagnose/knn_merges.py                       # the built-in blob (163,842 vertices), 800²
    python benchmarks/diagnose/knn_merges.py --field lego.neumesh  # a trained field

The points: each pixel's ray at the depth the torch renderer gives it (pixels it finds opaque), in the
kernel's blocks of ``--block`` consecutive rays of the list render_camera hands it (the pixels whose
rays meet an occupied cell), ordered by rows or by 8 x (block / 8) tiles (``renderer.tile_order``).  The
count replays the kernel's scan on the same tables (TritonHashGrid): per block, rounds = the largest
vertex count of the cells the block's points read (the c-th vertex of each cell per round), and per
round K merges (the default) or min(K, the largest number of a row's candidates nearer than its worst
key) with ``knn_early_out`` (cells read 32 at a time, nearest first: 27 cells one radius wide are one
tile, 125 half a radius wide four, each with its own rounds, a tile's cells beyond a row's K-th nearest
so far left out; "2_all": every cell, as the kernel did before).  Only the first surface point of each
ray is counted. A merge is two row reductions of 64-bit keys and two selects over the (rays, 32) tile,
the heaviest part of a round.  Writes benchmarks/results/log/knn_merges_<name>.json.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from benchmarks._results import add_options, use_threads, write_results  # noqa: E402

from neumesh_core.kernels.knn import TritonHashGrid, cell_order  # noqa: E402


def count_merges(points: np.ndarray, live: np.ndarray, grid, k: int, block: int, chunk: int = 1024,
                 ncp: int = 32, nearest_first: bool = False) -> dict:
    """Replay knn_keys's scan for points (M,3) (``live``: which are looked up) in blocks of ``block``;
    blocks without a live point are left out (the kernel skips them: no sample to look up)."""
    m = len(points)
    pad = (-m) % block
    pts = np.concatenate([points, np.zeros((pad, 3))]).reshape(-1, block, 3)
    liv = np.concatenate([live, np.zeros(pad, bool)]).reshape(-1, block)
    keep = liv.any(1)
    pts, liv = pts[keep], liv[keep]
    parts = [_count_blocks(pts[i:i + chunk], liv[i:i + chunk], grid, k, ncp, nearest_first)
             for i in range(0, len(pts), chunk)]
    n_max = np.concatenate([p[0] for p in parts])
    full = np.concatenate([p[1] for p in parts])
    eo = np.concatenate([p[2] for p in parts])
    found = np.concatenate([p[3] for p in parts])
    return {"blocks": int(len(pts)), "points": int(liv.sum()),
            "rounds_per_block_mean": float(n_max.mean()), "rounds_per_block_max": int(n_max.max(initial=0)),
            "merges_per_block_default": float(full.mean()), "merges_per_block_early_out": float(eo.mean()),
            "merge_ratio": float(eo.sum() / max(full.sum(), 1)),
            "neighbours_within_radius_mean": float(found.mean())}


def _count_blocks(pts: np.ndarray, liv: np.ndarray, grid, k: int, ncp: int, nearest_first: bool):
    """nearest_first: the cells in order of their offset's length, and a tile's cells farther from a
    point than its K-th nearest vertex found so far left out (they cannot hold a nearer one)."""
    c = grid.c
    s = 2 * c + 1
    start = grid.cell_start.cpu().numpy().astype(np.int64)
    count = grid.cell_count.cpu().numpy().astype(np.int64)
    vs = grid.v_sorted.cpu().numpy()[:, :3].astype(np.float64)
    lo = np.array(grid.lo)
    dims = np.array(grid.dims)
    r = grid.radius
    nb, block = liv.shape
    q = np.floor((pts - lo) / grid.cell).astype(np.int64)
    off = np.stack(np.meshgrid(*[np.arange(-c, c + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)   # (S^3,3)
    if nearest_first:   # the kernel's order
        off = off[cell_order(c).numpy()]
    cells = q[:, :, None, :] + off[None, None]                                            # (nb,B,S^3,3)
    inside = np.all((cells >= 0) & (cells < dims), -1)
    box_lo = lo + cells * grid.cell
    gap = np.maximum(box_lo - pts[:, :, None], 0) + np.maximum(pts[:, :, None] - (box_lo + grid.cell), 0)
    gap2 = (gap ** 2).sum(-1)
    near = liv[:, :, None] & inside & (gap2 <= r * r)
    key = (cells[..., 0] * dims[1] + cells[..., 1]) * dims[2] + cells[..., 2]
    key = np.where(near, key, 0)
    cst = np.where(near, start[key], 0)
    cnt = np.where(near, count[key], 0)
    worst = np.full((nb, block, k), np.inf)                            # each row's K best distances
    rounds = np.zeros(nb)
    merges_full = np.zeros(nb)
    merges_eo = np.zeros(nb)
    for c0 in range(0, s ** 3, ncp):                                   # the kernel's tiles of NCP cells
        cst_t, cnt_t = cst[:, :, c0:c0 + ncp], cnt[:, :, c0:c0 + ncp]
        if nearest_first:   # cells beyond each row's K-th nearest so far cannot help
            far_k = np.where(np.isfinite(worst[..., -1]), worst[..., -1], r)
            cnt_t = np.where(gap2[:, :, c0:c0 + ncp] <= (far_k ** 2)[:, :, None], cnt_t, 0)
        n_max = cnt_t.reshape(nb, -1).max(1)                           # this tile's rounds per block
        rounds += n_max
        for rnd in range(int(n_max.max(initial=0))):
            go = rnd < n_max                                           # blocks still scanning
            m_ok = (rnd < cnt_t) & go[:, None, None]
            j = np.where(m_ok, cst_t + rnd, 0)
            d = np.linalg.norm(pts[:, :, None] - vs[j], axis=-1)
            d = np.where(m_ok & (d <= r), d, np.inf)                   # (nb, B, cells of the tile)
            n_near = (d < worst.max(-1, keepdims=True)).sum(-1)        # per row
            merges_full += np.where(go, k, 0)
            merges_eo += np.where(go, np.minimum(n_near.max(1), k), 0)
            worst = np.sort(np.concatenate([worst, d], -1), -1)[..., :k]
    return rounds, merges_full, merges_eo, np.isfinite(worst).sum(-1)[liv]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "field", "threads", "name", "results_dir",
                field=dict(help="a .neumesh file (default: the procedural blob)"),
                threads=dict(default=0, help="torch threads (default 0: one per core)"))
    ap.add_argument("--subdiv", type=int, default=7)
    ap.add_argument("--size", type=int, default=800)
    ap.add_argument("--block", type=int, default=32, help="rays per program (the GPU default)")
    ap.add_argument("--cells", type=int, nargs="+", default=[1, 2], help="cells per radius")
    args = ap.parse_args(argv)
    import neumesh_core as nm
    from neumesh_core.render.renderer import tile_order

    from benchmarks.bench.bench_render_gpu import orbit_cameras, procedural_field, scaled
    from neumesh_core.data.cameras import pixel_rays

    use_threads(args.threads)
    if args.field:
        field = nm.load_field(args.field)
        name = args.name or os.path.splitext(os.path.basename(args.field))[0]
    else:
        field = procedural_field(args.subdiv, "cpu")
        name = args.name or f"blob{args.subdiv}"
    field.eval()
    K, c2w = orbit_cameras(field.rest_vertices.detach().cpu().numpy(), 1)[0]
    t = time.perf_counter()
    with torch.no_grad():
        out = nm.render_camera(field, scaled(K, args.size / 400), c2w, args.size, args.size,
                               settings=nm.RenderSettings(backend="torch"))
    render_s = time.perf_counter() - t
    Ks = scaled(K, args.size / 400)
    origins, dirs = pixel_rays(Ks, c2w, args.size, args.size)
    depth = out.depth.reshape(-1)
    live = (out.opacity.reshape(-1) > 0.5) & np.isfinite(depth)
    pts = origins.numpy().reshape(-1, 3) + dirs.numpy().reshape(-1, 3) * np.where(live, depth, 0)[:, None]
    # the rays render_camera hands the kernel: pixels whose rays meet an occupied cell, in rows or tiles
    r_near, r_far = field.grid.camera_ranges(Ks, c2w, args.size, args.size, nm.RenderSettings().empty_tile)
    marched = (r_near <= r_far).nonzero().squeeze(1)
    result = {"field": args.field or f"procedural blob, subdiv {args.subdiv}",
              "vertices": int(field.rest_vertices.shape[0]),
              "radius": float(field.radius), "k": int(field.config.k), "size": args.size, "block": args.block,
              "torch_render_s": render_s, "opaque_pixels": int(live.sum()), "marched_pixels": len(marched),
              "cells": {}, "orders": {}}
    orders = {"rows": marched, "tiles": tile_order(marched, args.size, (8, args.block // 8))}
    for order, seq in orders.items():
        seq = seq.numpy()
        # the kernel reads the cells nearest first and leaves out those beyond the K-th nearest so far;
        # "<C>_all" counts the kernel before that (every cell within the radius, row-major)
        for c, pruned in [(c, p) for c in args.cells for p in ((True, False) if c > 1 else (True,))]:
            grid = TritonHashGrid(field.scaffold.vertices_.detach(), field.radius, c)
            t = time.perf_counter()
            row = count_merges(pts[seq].astype(np.float64), np.asarray(live)[seq], grid, int(field.config.k),
                               args.block, nearest_first=pruned)
            row["count_s"] = time.perf_counter() - t
            row["lanes_hitting"] = row["points"] / max(1, row["blocks"] * args.block)
            result["orders"].setdefault(order, {})[str(c) if pruned else f"{c}_all"] = row
            if order == "rows" and pruned:
                result["cells"][str(c)] = row
            print(f"{order}, cells per radius {c}{'' if pruned else ', every cell'}: {row['blocks']} blocks "
                  f"with a hit ({row['lanes_hitting']:.2f} "
                  f"of their lanes), rounds per block {row['rounds_per_block_mean']:.1f} (max "
                  f"{row['rounds_per_block_max']}), merges per block {row['merges_per_block_default']:.1f} -> "
                  f"{row['merges_per_block_early_out']:.1f} with early out ({row['merge_ratio']:.2f}), "
                  f"{row['neighbours_within_radius_mean']:.2f} of K found", flush=True)
    write_results(result, f"knn_merges_{name}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
