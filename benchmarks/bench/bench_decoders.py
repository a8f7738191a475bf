"""Render cost of the per-vertex decoder binding: a trained field as it is (one decoder), with a second
decoder present but unused, with half of its vertices bound to a second decoder, and (optionally) the
same field rendered by the code from before decoder binding existed.

    python benchmarks/bench/bench_decoders.py --field runs/lego/field.neumesh --data ../shared/data/nerf_synthetic/lego
    python benchmarks/bench/bench_decoders.py --field F --data D --old-tree /tmp/old   # + the pre-binding code

``--old-tree`` is a checkout of the project before decoder binding (commit 15b1ad3, which reads field
files of format 1 only): the field is written as format 1 and timed there in a subprocess, on the
same views, so "a field whose vertices all use decoder 0 costs what it costs today" is measured, not
assumed.  The variants are timed in ``--rounds`` interleaved rounds (one subprocess per variant and
round), so a burst of other work on the machine hits every variant alike; a view's figure is its best
over rounds and ``--repeats``, and each figure is the median of those over ``--views`` val views.
Writes benchmarks/results/log/decoders_<name>.json.  The timer runs in a process of the timed checkout
(its own loop: that process imports the other checkout's modules, not this tree's helper).
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import subprocess
import sys

import numpy as np
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
from benchmarks._results import add_options, write_results  # noqa: E402

_TIMER = r"""
import json, sys, time, numpy as np, torch
sys.path.insert(0, sys.argv[1])
import neumesh_core as nm
f = nm.load_field(sys.argv[2]); f.eval()
cams = nm.load_scene(sys.argv[3]).split("val").cameras
views, repeats = json.loads(sys.argv[4]), int(sys.argv[5])
out = []
with torch.no_grad():
    nm.render_camera(f, cams.K[views[0]], cams.c2w[views[0]], cams.width, cams.height)
    for i in views:
        best = 1e9
        for _ in range(repeats):
            t = time.perf_counter()
            nm.render_camera(f, cams.K[i], cams.c2w[i], cams.width, cams.height)
            best = min(best, time.perf_counter() - t)
        out.append(best)
print("TIMES", json.dumps(out))
"""


def write_v1(field, path: str) -> None:
    """``field`` (one decoder, no texture frames) in the format-1 layout the old code reads."""
    import neumesh_core as nm
    from safetensors.torch import load_file, save_file

    from neumesh_core.field.io import _V1_RENAMES, read_header

    if field.num_decoders != 1 or field.tex_frame is not None:
        raise SystemExit("only a one-decoder field without texture frames has a format-1 form")
    tmp = path + ".v2"
    nm.save_field(field, tmp)
    meta = read_header(tmp)
    t = load_file(tmp)
    os.unlink(tmp)
    out = {}
    for k, v in t.items():
        kind, _, rest = k.partition("/")
        if rest == "decoder_id" or rest.startswith("sem_decoder") or rest.startswith("tex_frame"):
            continue
        if kind in ("param", "buffer"):
            for old, new in _V1_RENAMES:
                if rest == new.rstrip(".") or (new.endswith(".") and rest.startswith(new)):
                    rest = old + rest[len(new):] if new.endswith(".") else old
                    break
            k = f"{kind}/{rest}"
        out[k] = v
    out.setdefault("param/sem_codes", torch.zeros(field.num_vertices, 0))   # the old field's empty slot
    meta = {k: v for k, v in meta.items() if k not in ("num_decoders", "semantics")}
    meta["version"] = 1
    save_file(out, path, metadata={"neumesh": json.dumps(meta)})


def time_in(tree: str, field_path: str, data: str, views, repeats: int, python=sys.executable):
    r = subprocess.run([python, "-c", _TIMER, tree, field_path, data, json.dumps(views), str(repeats)],
                       capture_output=True, text=True, check=True)
    return json.loads(r.stdout.split("TIMES", 1)[1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(ap, "field", "data", "name", "results_dir",
                field=dict(required=True, help="trained field (one decoder)"),
                data=dict(required=True, help="dataset whose val cameras are rendered"))
    ap.add_argument("--views", type=int, default=5, help="val views (evenly spread; default 5)")
    ap.add_argument("--repeats", type=int, default=2, help="renders per view, the best counts (default 2)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds over the variants (default 3)")
    ap.add_argument("--old-tree", help="checkout of the pre-binding code (commit 15b1ad3) to time too")
    args = ap.parse_args(argv)
    root = ROOT
    import neumesh_core as nm

    field = nm.load_field(args.field)
    n_val = len(nm.load_scene(args.data).split("val").cameras)
    views = [int(i) for i in np.linspace(0, n_val - 1, args.views).round()]
    name = args.name or os.path.basename(os.path.dirname(os.path.abspath(args.field)))
    tmp = os.path.join(os.path.dirname(os.path.abspath(args.field)), f".bench_decoders_{os.getpid()}")
    os.makedirs(tmp, exist_ok=True)
    variants = {"one_decoder": copy.deepcopy(field)}
    two = copy.deepcopy(field)
    other = copy.deepcopy(field.rad_decoder)
    with torch.no_grad():
        for p in other.parameters():
            p.add_(0.01)
    two.add_decoder(other)
    variants["two_decoders_unused"] = two
    half = copy.deepcopy(two)
    with torch.no_grad():
        v = half.rest_vertices
        half.decoder_id[v[:, 0] > v[:, 0].median()] = 1
    variants["two_decoders_half_each"] = half
    runs = []      # (key, tree, file)
    try:
        for key, f in variants.items():
            path = os.path.join(tmp, f"{key}.neumesh")
            nm.save_field(f, path)
            runs.append((key, root, path))
        if args.old_tree:
            path = os.path.join(tmp, "v1.neumesh")
            write_v1(field, path)
            runs.append(("before_binding", os.path.abspath(args.old_tree), path))
            runs.append(("one_decoder_again", root, path))      # the same format-1 file, this code
        per_round = {key: [] for key, _, _ in runs}
        for r in range(args.rounds):
            for key, tree, path in runs:
                per_round[key].append(time_in(tree, path, args.data, views, args.repeats))
                print(f"round {r + 1} {key}: median {np.median(per_round[key][-1]):.3f} s", flush=True)
        times = {key: [float(x) for x in np.min(np.array(v), axis=0)] for key, v in per_round.items()}
    finally:
        for fn in os.listdir(tmp):
            os.unlink(os.path.join(tmp, fn))
        os.rmdir(tmp)
    med = {k: float(np.median(v)) for k, v in times.items()}
    base = med["one_decoder"]
    result = {"field": args.field, "vertices": field.num_vertices, "interpolation": field.config.interpolation,
              "views": views, "rounds": args.rounds, "repeats": args.repeats,
              "seconds_per_view": times, "seconds_per_round_and_view": per_round, "median_s": med,
              "ratio_to_one_decoder": {k: v / base for k, v in med.items()}}
    if "before_binding" in med:
        result["ratio_this_code_to_before_binding"] = med["one_decoder_again"] / med["before_binding"]
    print("ratios to one decoder: " + ", ".join(f"{k} {v:.2f}" for k, v in result["ratio_to_one_decoder"].items()))
    write_results(result, f"decoders_{name}.json", args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
