"""What the fused renderer's kernel costs a GPU before it runs: each launch variant compiled offline for
a CUDA target (no GPU needed: Triton's compiler and the cuobjdump it ships), with the registers and the
stack (spilled registers, local memory) per thread and the programs that fit on one multiprocessor.

    python benchmarks/kernel_resources.py                 # the lego field's sizes, sm_90 (H100 / H200)
    python benchmarks/kernel_resources.py --arch 89       # an RTX 40xx

The decoder sizes are those of ``FieldConfig()`` (the lego field's).  A variant is (schedule, early or
post, at rest or deformed, rays per program, warps, neighbour-grid cells per radius).  Spills are local
memory traffic inside the hottest loop; registers x threads bound the programs an SM keeps resident
(65,536 registers), i.e. how much gather latency the others can hide.  Timing needs a GPU
(``bench_render_gpu.py --sweep``); this says which variants are worth its time.  Writes
benchmarks/results/kernel_resources_sm<arch>.json.
"""
from __future__ import annotations

import argparse
import inspect
import os
import re
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _results import write_results  # noqa: E402

# the kernel's pointer arguments that are not float32, and its integer scalars
_PTR_TYPES = {"occ": "*u8", "cell_start": "*i32", "cell_count": "*i32", "ids_sorted": "*i32",
              "ray_counter": "*i32"}
_INTS = {"n_rays", "res_x", "res_y", "res_z", "h_dx", "h_dy", "h_dz"}
_POINTERS = {"orig", "dirs", "gorig", "gdirs", "tnear", "tfar", "tstart", "occ", "cell_start", "cell_count",
             "v_sorted", "ids_sorted", "vtab", "geo", "tex", "modc", "rest_n", "rot", "gw1", "gb1", "gw2",
             "gb2", "gw3", "gb3", "rw1", "rb1", "rw2", "rb2", "rw3", "rb3", "out", "ray_counter"}

DEFAULT_VARIANTS = ("static,early,rest,32,4,1;refill,early,rest,32,4,1;static,early,rest,64,8,2;"
                    "static,early,rest,16,2,1;refill,early,rest,16,2,1;static,post,rest,32,4,1;"
                    "refill,post,rest,32,4,1;static,early,deformed,32,4,1;refill,post,deformed,32,4,1;"
                    "static,early,rest,32,4,1,tf32;static,early,rest,32,4,1,tf32x3;"
                    "static,early,rest,32,4,1,ieee,128;refill,early,rest,32,4,1,ieee,128")


def constants(cfg, *, refill, early, deformed, block, cells, precision="ieee") -> dict:
    """The kernel's constexpr arguments for a field of config ``cfg`` (as FieldTables derives them)."""
    from neumesh_core.field.knn_triton import TritonHashGrid, next_pow2

    pe = 1 + 2 * cfg.pos_freqs
    return dict(BLOCK=block, KP=next_pow2(cfg.k), K=cfg.k, WINDOW=64, MAX_EVAL=8, EARLY=early,
                DEFORMED=deformed, GEO_D=cfg.geo_dim, TEX_D=cfg.tex_dim, PE_F=cfg.pos_freqs,
                SH_DEG=cfg.sh_degree, GI=next_pow2(cfg.geo_dim + pe + 1, 16),
                RI=next_pow2(cfg.tex_dim + pe + 1 + cfg.sh_degree ** 2 + 3, 16), H=next_pow2(cfg.hidden, 16),
                PREC=precision, C=cells, NCP=TritonHashGrid.ncp, SCAN=8, REFILL=refill)


def compile_variant(kernel, consts: dict, warps: int, arch: int, maxnreg=None):
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    sig = {}
    for p in inspect.signature(kernel.fn).parameters:
        if p in consts:
            sig[p] = "constexpr"
        elif p in _POINTERS:
            sig[p] = _PTR_TYPES.get(p, "*fp32")
        else:
            sig[p] = "i32" if p in _INTS else "fp32"
    src = ASTSource(fn=kernel, signature=sig, constexprs=consts)
    opts = {"num_warps": warps}
    if maxnreg:
        opts["maxnreg"] = int(maxnreg)
    return triton.compile(src, target=GPUTarget("cuda", arch, 32), options=opts)


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
                    help="';'-separated schedule,early|post,rest|deformed,block,warps,cells[,precision[,maxnreg]]")
    ap.add_argument("--name", default=None)
    ap.add_argument("--results-dir", default=None)
    args = ap.parse_args(argv)
    try:
        import triton  # noqa: F401
    except ImportError:
        print("kernel_resources: triton does not import (pip install -e '.[gpu]')", file=sys.stderr)
        return 2
    import neumesh_core as nm
    from neumesh_core.render import fused_triton as ft

    cfg = nm.FieldConfig()
    rows = []
    for spec in args.variants.split(";"):
        parts = [x.strip() for x in spec.split(",")]
        sched, mode, pose, block, warps, cells = parts[:6]
        prec = parts[6] if len(parts) > 6 else "ieee"
        maxnreg = int(parts[7]) if len(parts) > 7 else None
        key = {"schedule": sched, "interpolation": mode, "deformed": pose == "deformed", "block": int(block),
               "num_warps": int(warps), "cells_per_radius": int(cells), "precision": prec,
               "maxnreg": maxnreg}
        t = time.perf_counter()
        try:
            kern = compile_variant(ft._render_kernel, constants(
                cfg, refill=sched == "refill", early=mode == "early", deformed=pose == "deformed",
                block=int(block), cells=int(cells), precision=prec), int(warps), args.arch, maxnreg)
            use = resource_usage(kern.asm["cubin"])
        except Exception as e:   # a variant the compiler rejects: record it, go on
            rows.append({**key, "error": repr(e)[:300]})
            print(f"{key}: failed {e!r}"[:300], flush=True)
            continue
        threads = 32 * int(warps)
        use["programs_per_sm_by_registers"] = 65536 // (max(use["reg"], 1) * threads)
        use["compile_s"] = round(time.perf_counter() - t, 1)
        rows.append({**key, **use})
        print(f"{sched:6s} {mode:5s} {pose:8s} {block:>3s} rays x {warps} warps, cells {cells}, {prec}, maxnreg {maxnreg}: "
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
