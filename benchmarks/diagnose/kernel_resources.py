"""What the fused renderer's kernel costs a GPU before it runs: each launch variant compiled offline for
a CUDA target (no GPU needed: Triton's compiler and the cuobjdump it ships), with the registers and the
stack (spilled registers, local memory) per thread and the programs that fit on one multiprocessor.

    python benchmarks/diagnose/kernel_resources.py             # the lego field's sizes, sm_90 (H100 / H200)
    python benchmarks/diagnose/kernel_resources.py --arch 89   # an RTX 40xx

The decoder sizes are those of ``FieldConfig()`` (the lego field's).  A variant is (schedule, early or
post, at rest or deformed, rays per program, warps, neighbour-grid cells per radius).  Spills are local
memory traffic inside the hottest loop; registers x threads bound the programs an SM keeps resident
(65,536 registers), i.e. how much gather latency the others can hide.  Timing needs a GPU
(``bench_render_gpu.py --sweep``); this says which variants are worth its time.  Writes
benchmarks/results/log/kernel_resources_sm<arch>.json.
"""
from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from benchmarks._results import add_options, write_results  # noqa: E402

DEFAULT_VARIANTS = ("static,early,rest,32,4,1;refill,early,rest,32,4,1;static,early,rest,64,8,2;"
                    "static,early,rest,16,2,1;refill,early,rest,16,2,1;static,post,rest,32,4,1;"
                    "refill,post,rest,32,4,1;static,early,deformed,32,4,1;refill,post,deformed,32,4,1;"
                    "static,early,rest,32,4,1,tf32;static,early,rest,32,4,1,tf32x3;"
                    "static,early,rest,32,4,1,ieee,128;refill,early,rest,32,4,1,ieee,128;"
                    "static,early,rest,32,4,1,fp16;refill,early,rest,32,4,1,fp16;static,post,rest,32,4,1,fp16;"
                    "static,early,rest,32,4,1,ieee,-,eo;refill,early,rest,32,4,1,fp16,-,eo;"
                    "static,post,deformed,32,4,1,ieee,-,eo;static,early,rest,32,4,2;"
                    "static,early,rest,32,4,2,fp16,-,eo;static,early,rest,32,4,1,ieee,-,-,march;"
                    "static,post,rest,32,4,1,ieee,-,-,march")


def resource_usage(cubin: bytes) -> dict:
    """REG / STACK / SHARED / LOCAL of the cubin's kernel, from cuobjdump --dump-resource-usage."""
    import triton

    tool = os.path.join(os.path.dirname(triton.__file__), "backends", "nvidia", "bin", "cuobjdump")
    with tempfile.NamedTemporaryFile(suffix=".cubin", delete=False) as fh:
        fh.write(cubin)
    try:
        text = subprocess.run([tool, "--dump-resource-usage", fh.name], capture_output=True, text=True,
                              check=True).stdout
    finally:
        os.unlink(fh.name)
    line = next(ln for ln in text.splitlines() if "REG:" in ln)
    return {k.lower(): int(v) for k, v in re.findall(r"(REG|STACK|SHARED|LOCAL):(\d+)", line)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--arch", type=int, default=90, help="CUDA compute capability x10 (90: H100/H200)")
    ap.add_argument("--variants", default=DEFAULT_VARIANTS,
                    help="';'-separated schedule,early|post,rest|deformed,block,warps,cells[,precision[,maxnreg|-[,eo|-"
                         "[,march]]]] (eo: knn_early_out; march: the training's march, samples out and jitter)")
    add_options(ap, "name", "results_dir")
    args = ap.parse_args(argv)
    try:
        import triton  # noqa: F401
    except ImportError:
        print("kernel_resources: triton does not import (pip install -e '.[gpu]')", file=sys.stderr)
        return 2
    import neumesh_core as nm
    from neumesh_core.kernels import fused as ft

    cfg = nm.FieldConfig()
    rows = []
    for spec in args.variants.split(";"):
        parts = [x.strip() for x in spec.split(",")]
        sched, mode, pose, block, warps, cells = parts[:6]
        prec = parts[6] if len(parts) > 6 else "ieee"
        maxnreg = int(parts[7]) if len(parts) > 7 and parts[7] != "-" else None
        early_out = len(parts) > 8 and parts[8] == "eo"
        march = len(parts) > 9 and parts[9] == "march"
        key = {"schedule": sched, "interpolation": mode, "deformed": pose == "deformed", "block": int(block),
               "num_warps": int(warps), "cells_per_radius": int(cells), "precision": prec,
               "maxnreg": maxnreg, "knn_early_out": early_out, "march": march}
        t = time.perf_counter()
        try:
            kern = ft.compile_for(cfg, args.arch, interpolation=mode, deformed=pose == "deformed",
                                  schedule=sched, block=int(block), num_warps=int(warps),
                                  cells_per_radius=int(cells), precision=prec, maxnreg=maxnreg,
                                  knn_early_out=early_out, march=march, jitter=march)
            use = resource_usage(kern.asm["cubin"])
        except Exception as e:   # a variant the compiler rejects: record it, go on
            rows.append({**key, "error": repr(e)[:300]})
            print(f"{key}: failed {e!r}"[:300], flush=True)
            continue
        threads = 32 * int(warps)
        use["programs_per_sm_by_registers"] = 65536 // (max(use["reg"], 1) * threads)
        use["compile_s"] = round(time.perf_counter() - t, 1)
        rows.append({**key, **use})
        flags = (", knn early out" if early_out else "") + (", march" if march else "")
        print(f"{sched:6s} {mode:5s} {pose:8s} {block:>3s} rays x {warps} warps, cells {cells}, {prec}, "
              f"maxnreg {maxnreg}{flags}: "
              f"{use['reg']} registers, stack {use['stack']} B per thread, "
              f"{use['programs_per_sm_by_registers']} programs per SM", flush=True)
    import triton

    result = {"arch": f"sm_{args.arch}", "triton": triton.__version__, "field_config": {
        k: getattr(cfg, k) for k in ("geo_dim", "tex_dim", "hidden", "pos_freqs", "sh_degree", "k")},
        "variants": rows}
    write_results(result, f"{args.name or f'kernel_resources_sm{args.arch}'}.json", args.results_dir)
    return 0 if all("error" not in r for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
