"""The fused GPU renderer: one Triton kernel marches rays through the occupancy grid, finds each
sample's K nearest scaffold vertices (:func:`neumesh_core.kernels.knn.knn_keys`), evaluates the
geometry and radiance decoders and composites, with no host synchronisation inside a frame.

Reference: :func:`neumesh_core.render.renderer.render_rays` (the torch marcher
:func:`~neumesh_core.sampling.marcher.march_rays`, the field's ``decode`` and
:func:`~neumesh_core.render.volume.composite`), which stays the default on the CPU and the path for
everything this kernel does not cover.  ``RenderSettings.backend`` chooses: "auto" (this kernel on CUDA
when triton imports and the field is supported, torch otherwise), "torch" or "triton";
:func:`neumesh_core.kernels.path.render_path` decides.

The kernel itself (and how it marches, searches and decodes): :mod:`neumesh_core.kernels.fused_kernel`.

Covered: one field, one radiance decoder, no texture frames, no semantics (:func:`supported` says why
a field is not).  What the whole kernel does not render (training with autograd, jitter, vertex ids,
semantics, several fields composited together) takes render_rays' torch path, which still marches each
covered field with the kernel: its MARCH variant decodes no colour and hands the kept samples (t,
density, neighbour keys; one slot per kept sample of a ray) to :func:`march_rays_fused`, whose reference
is the torch marcher, and the torch decoders decode them with autograd (training on a GPU).
"""
from __future__ import annotations

import math
from contextlib import nullcontext as _nullcontext
from typing import Optional

import torch

from .fused_kernel import render_kernel
from .knn import TritonHashGrid, decode_keys, next_pow2, require_triton, triton
# the choice of path lives in path.py; its callers on the launch side read it here too
from .path import BACKENDS, supported, use_fused_march, use_triton  # noqa: F401


# ---------------------------------------------------------------------------------------------- tables
def _padded_mlp(seq: torch.nn.Sequential, in_p: int, h_p: int, out_p: int, device):
    """(W1 (in_p,h_p), b1, W2 (h_p,h_p), b2, W3 (h_p,out_p), b3): the 3-layer MLP's weights transposed
    and zero-padded (padding rows/columns stay zero through ReLU)."""
    l1, l2, l3 = seq[0], seq[2], seq[4]
    out = []
    for lin, (a, b) in ((l1, (in_p, h_p)), (l2, (h_p, h_p)), (l3, (h_p, out_p))):
        w = torch.zeros(a, b, device=device)
        w[:lin.in_features, :lin.out_features] = lin.weight.detach().t().float()
        bias = torch.zeros(b, device=device)
        bias[:lin.out_features] = lin.bias.detach().float()
        out += [w.contiguous(), bias]
    return out


def _version_key(*tensors) -> tuple:
    return tuple((t.data_ptr(), t._version, tuple(t.shape)) if t is not None else None for t in tensors)


def decoder_widths(cfg) -> tuple:
    """(geometry input, radiance input, hidden) widths of the kernel's decoder tiles: the decoders'
    widths rounded up to powers of two of at least 16 (tl.dot's smallest), zero-padded."""
    pe = 1 + 2 * int(cfg.pos_freqs)
    return (next_pow2(int(cfg.geo_dim) + pe + 1, 16),
            next_pow2(int(cfg.tex_dim) + pe + 1 + int(cfg.sh_degree) ** 2 + 3, 16),
            next_pow2(int(cfg.hidden), 16))


class FieldTables:
    """What the kernel reads of a field, rebuilt only when the tensors behind it change: the hash grid
    of the current vertices, the (position, normal) table, the code tables and the padded decoders."""

    def __init__(self, field, cells_per_radius: int = 2):
        cfg = field.config
        sc = field.scaffold
        dev = sc.vertices_.device
        self.gi, self.ri, self.h = decoder_widths(cfg)
        grid_key = _version_key(sc.vertices_) + (cells_per_radius, float(cfg.radius))
        cache = sc.__dict__.get("_triton_hash_cache")
        if cache is None or cache[0] != grid_key:
            cache = (grid_key, TritonHashGrid(sc.vertices_, cfg.radius, cells_per_radius))
            sc.__dict__["_triton_hash_cache"] = cache
        self.hash = cache[1]
        self.vtab = sc._vertex_table().contiguous()
        self.geo = field.geo_codes.detach().contiguous()
        self.tex = field.tex_codes.detach().contiguous()
        self.mod = field.mod_colours.detach().contiguous()
        self.rest_n = field.rest_normals.contiguous()
        self.rot = None if sc.to_rest is None else sc.to_rest.reshape(-1, 9).contiguous()
        params = list(field.geo_decoder.parameters()) + list(field.rad_decoders[0].parameters())
        w_key = _version_key(*params)
        wcache = field.__dict__.get("_triton_mlp_cache")
        if wcache is None or wcache[0] != w_key:
            wcache = (w_key, _padded_mlp(field.geo_decoder, self.gi, self.h, 16, dev) +
                      _padded_mlp(field.rad_decoders[0], self.ri, self.h, 16, dev))
            field.__dict__["_triton_mlp_cache"] = wcache
        self.mlp = wcache[1]


def default_block(device) -> int:
    """Rays per program: 32 on a GPU (with 4 warps: the fastest of the options timed by
    ``benchmarks/bench/bench_render_gpu.py --sweep``, docs/benchmarks.md "Fused Triton renderer"; a smaller
    block waits less for its slowest ray); in the interpreter (CPU) one big block, since there each operation
    costs about the same for any block size."""
    return 32 if torch.device(device).type == "cuda" else 1024


# launch options, chosen by benchmarks/bench/bench_render_gpu.py (``--sweep``); render_rays_fused's defaults
# (block / cells_per_radius None: by device, see default_block / default_cells; num_warps: per program)
KERNEL_OPTIONS = {"block": None, "precision": "ieee", "num_warps": 4, "cells_per_radius": None, "scan": 8,
                  "schedule": "static", "programs_per_sm": 8, "maxnreg": None, "knn_early_out": False,
                  "ray_order": "tiles"}


def default_cells(device) -> int:
    """Neighbour-grid cells per radius: 1 on a GPU and in the interpreter (27 cells a radius wide; 125
    half-radius cells hold fewer vertices but take more cells to walk: the GPU sweep times both,
    benchmarks/diagnose/knn_merges.py counts their work; docs/benchmarks.md)."""
    return 1


SCHEDULES = ("static", "refill")
RAY_ORDERS = ("tiles", "rows")
PRECISIONS = ("ieee", "tf32", "tf32x3", "fp16")


def kernel_constants(cfg, *, early: bool, deformed: bool, block: int, cells: int, precision: str = "ieee",
                     scan: int = 8, refill: bool = False, window: int = 64,
                     knn_early_out: bool = False, march: bool = False, jitter: bool = False) -> dict:
    """The kernel's compile-time (constexpr) arguments for a field of config ``cfg``: each set of them is
    one compiled variant."""
    gi, ri, h = decoder_widths(cfg)
    return dict(BLOCK=int(block), KP=next_pow2(int(cfg.k)), K=int(cfg.k), WINDOW=int(window), MAX_EVAL=8,
                EARLY=bool(early), DEFORMED=bool(deformed), GEO_D=int(cfg.geo_dim), TEX_D=int(cfg.tex_dim),
                PE_F=int(cfg.pos_freqs), SH_DEG=int(cfg.sh_degree), GI=gi, RI=ri, H=h, PREC=precision,
                C=int(cells), NCP=TritonHashGrid.ncp, SCAN=int(scan), REFILL=bool(refill),
                KNN_EO=bool(knn_early_out), MARCH=bool(march), JITTER=bool(jitter))


# the kernel's pointer arguments that are not float32, its other pointers, and its integer scalars (the
# rest are float32 scalars): the signature of an ahead-of-time build
_PTR_TYPES = {"occ": "*u8", "cell_start": "*i32", "cell_count": "*i32", "ids_sorted": "*i32",
              "cell_order": "*i32", "ray_counter": "*i32", "s_keys": "*i64"}
_POINTERS = {"orig", "dirs", "gorig", "gdirs", "tnear", "tfar", "tstart", "occ", "cell_start", "cell_count",
             "v_sorted", "ids_sorted", "cell_order", "vtab", "geo", "tex", "modc", "rest_n", "rot", "gw1", "gb1",
             "gw2", "gb2", "gw3", "gb3", "rw1", "rb1", "rw2", "rb2", "rw3", "rb3", "out", "ray_counter", "jit",
             "s_t", "s_sig", "s_keys"}
_INTS = {"n_rays", "res_x", "res_y", "res_z", "h_dx", "h_dy", "h_dz", "s_max"}


def compile_for(cfg, arch: int = 90, *, interpolation: str = "early", deformed: bool = False,
                march: bool = False, jitter: bool = False, **options):
    """Build the kernel ahead of time for a CUDA target (compute capability x10; 90: H100/H200) without a
    GPU: Triton's compiler and the ptxas it ships.  ``options`` as :func:`render_rays_fused`'s (block and
    cells_per_radius default to a GPU's).  Returns Triton's compiled kernel (``.asm["cubin"]``, ...).
    ``march`` / ``jitter``: the variant :func:`march_rays_fused` runs (training).  Used to check that
    each variant compiles with the installed Triton, and by ``benchmarks/diagnose/kernel_resources.py`` to read
    its registers and spills."""
    import inspect

    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    if triton is None or type(render_kernel).__name__ == "InterpretedFunction":
        raise RuntimeError("compile_for needs triton imported without TRITON_INTERPRET=1 (the interpreter "
                           "runs kernels, it does not build them): run it in a process without that variable")
    opts = _checked({**KERNEL_OPTIONS, **options})
    consts = kernel_constants(cfg, early=interpolation == "early", deformed=deformed,
                              block=opts["block"] or default_block("cuda"),
                              cells=opts["cells_per_radius"] or default_cells("cuda"),
                              precision=opts["precision"], scan=opts["scan"], refill=opts["schedule"] == "refill",
                              knn_early_out=opts["knn_early_out"], march=march, jitter=jitter)
    sig = {}
    for p in inspect.signature(render_kernel.fn).parameters:
        if p in consts:
            sig[p] = "constexpr"
        elif p in _POINTERS:
            sig[p] = _PTR_TYPES.get(p, "*fp32")
        else:
            sig[p] = "i32" if p in _INTS else "fp32"
    build = {"num_warps": int(opts["num_warps"])}
    if opts["maxnreg"]:
        build["maxnreg"] = int(opts["maxnreg"])
    return triton.compile(ASTSource(fn=render_kernel, signature=sig, constexprs=consts),
                          target=GPUTarget("cuda", int(arch), 32), options=build)


def _checked(opts: dict) -> dict:
    if opts["schedule"] not in SCHEDULES:
        raise ValueError(f"schedule must be one of {', '.join(SCHEDULES)}, not {opts['schedule']!r}")
    if opts["precision"] not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, not {opts['precision']!r}")
    if opts["ray_order"] not in RAY_ORDERS:
        raise ValueError(f"ray_order must be one of {', '.join(RAY_ORDERS)}, not {opts['ray_order']!r}")
    return opts


def refill_programs(device, n_blocks: int, programs_per_sm: int) -> int:
    """Programs launched by the refill schedule: enough to fill the GPU (``programs_per_sm`` on each of
    its multiprocessors), never more than the static schedule's blocks; 2 in the interpreter (its
    programs run one after another, so 2 exercise the shared ray counter)."""
    dev = torch.device(device)
    if dev.type == "cuda":
        sms = torch.cuda.get_device_properties(dev).multi_processor_count
        return max(1, min(n_blocks, sms * int(programs_per_sm)))
    return max(1, min(n_blocks, 2))


@torch.no_grad()
def render_rays_fused(field, origins: torch.Tensor, dirs: torch.Tensor, settings, step: float, near=0.0,
                      far=float("inf"), **options) -> dict:
    """Render rays (R,3) through ``field`` with the fused kernel: the outputs of
    :func:`~neumesh_core.render.renderer.render_rays` (rgb premultiplied, no background) with
    ``n_samples`` the number of samples composited.  ``step``: the marching step
    (:func:`~neumesh_core.render.renderer.default_step`).  ``near``/``far``: a distance or (R,) per ray.
    ``options``: launch options overriding :data:`KERNEL_OPTIONS` (block: rays per program; precision:
    tl.dot's input precision, "ieee" (fp32) or "tf32x3"/"tf32", or "fp16" (operands rounded to half
    precision, fp32 sums); num_warps; cells_per_radius: 1 or 2, the
    neighbour grid's cells per radius; scan: occupancy steps looked at per marching iteration; schedule:
    "static" (a program's lanes keep their rays until the last one finishes) or "refill" (a persistent
    program's lane takes the next ray as soon as its own finishes, so no lane idles beside a long ray;
    programs_per_sm: how many such programs each multiprocessor runs); maxnreg: None or a cap on the
    registers per thread (``benchmarks/diagnose/kernel_resources.py`` shows what each cap spills); knn_early_out:
    the neighbour search skips the merges no candidate needs (``kernels.knn.knn_keys``; the same image).
    ``ray_order`` ("tiles" or "rows") is read by ``render_camera``: the order of the pixels it hands
    the kernel (``renderer.tile_order``: 8 x 4 screen patches per 32 rays)."""
    opts = _checked({**KERNEL_OPTIONS, **options})
    out = torch.zeros(origins.shape[0], 10, device=origins.device)
    _launch(field, origins, dirs, settings.window, settings.early_stop_eps, settings.weight_threshold, step,
            near, far, opts, out)
    opacity = out[:, 3]
    depth = torch.where(opacity > 1e-6, out[:, 4] / opacity.clamp_min(1e-6), torch.full_like(opacity, float("inf")))
    return {"rgb": out[:, :3], "opacity": opacity, "depth": depth, "mod_colour": out[:, 5:8],
            "n_samples": out[:, 8]}


# kept samples a ray has room for in the first launch of march_rays_fused (a chunk whose rays keep more
# is marched again with room for its longest ray), and the sample buffers' bytes per launch
MARCH_SLOTS = 64
MARCH_BUFFER_BYTES = 256 << 20


@torch.no_grad()
def march_rays_fused(field, origins: torch.Tensor, dirs: torch.Tensor, step: float, near=0.0,
                     far=float("inf"), window: int = 64, early_stop_eps: float = 1e-4,
                     weight_threshold: float = 1e-4, jitter: Optional[torch.Tensor] = None, **options):
    """The samples :func:`~neumesh_core.sampling.marcher.march_rays` keeps for ``field.sigma_fn`` (its
    reference), found by the fused kernel without decoding colours (its MARCH variant): the same steps
    (``jitter`` included), densities and neighbours, one launch per chunk of rays and one host
    synchronisation (the number of samples) instead of the torch marcher's launches and synchronisations
    every window.  Returns :class:`~neumesh_core.sampling.marcher.RaySamples` sorted by (ray, t) whose
    ``aux`` is the samples' :class:`~neumesh_core.field.scaffold.Neighbourhood`, ready for the field's
    ``decode`` with autograd (training) or without.  ``options``: launch options as
    :func:`render_rays_fused`'s."""
    from ..sampling.marcher import RaySamples

    opts = _checked({**KERNEL_OPTIONS, **options})
    dev = origins.device
    n = origins.shape[0]
    kp = next_pow2(int(field.config.k))
    slots = MARCH_SLOTS
    chunk = max(1, MARCH_BUFFER_BYTES // (slots * (8 + 8 * kp)))
    rays, ts, sigmas, keys = [], [], [], []
    for s0 in range(0, n, chunk):
        part = slice(s0, min(n, s0 + chunk))
        o, d = origins[part], dirs[part]
        nr, fr = (x[part] if torch.is_tensor(x) else x for x in (near, far))
        jt = None if jitter is None else jitter[part]
        m = o.shape[0]
        while True:
            s_t = torch.empty(m * slots, device=dev)
            s_sig = torch.empty(m * slots, device=dev)
            s_keys = torch.empty(m * slots, kp, dtype=torch.int64, device=dev)
            out = torch.zeros(m, 10, device=dev)
            _launch(field, o, d, window, early_stop_eps, weight_threshold, step, nr, fr, opts, out,
                    march=(s_t, s_sig, s_keys, slots), jitter=jt)
            count = out[:, 8].to(torch.int64)
            most = int(count.max())   # the one synchronisation
            if most <= slots:
                break
            slots = next_pow2(most)
        flat = (torch.arange(slots, device=dev)[None, :] < count[:, None]).reshape(-1).nonzero().squeeze(1)
        rays.append(torch.div(flat, slots, rounding_mode="floor") + s0)
        ts.append(s_t[flat])
        sigmas.append(s_sig[flat])
        keys.append(s_keys[flat])
    half = 0.5 * step
    if not rays or sum(len(r) for r in rays) == 0:
        z = torch.zeros(0, device=dev)
        return RaySamples(torch.zeros(0, dtype=torch.long, device=dev), z, z.clone(), z.clone(), None, n)
    ray, t, sig = torch.cat(rays), torch.cat(ts), torch.cat(sigmas)
    idx, dist = decode_keys(torch.cat(keys), int(field.config.k))
    x = origins.index_select(0, ray) + dirs.index_select(0, ray) * t[:, None]
    nb = field.scaffold.neighbourhood_from(x, idx, dist)
    return RaySamples(ray, t - half, t + half, sig, nb, n)


def _launch(field, origins, dirs, window, early_stop_eps, weight_threshold, step, near, far, opts, out,
            march=None, jitter=None) -> None:
    """One launch of the kernel for rays (R,3): per-ray outputs into ``out`` (R,10); with ``march`` =
    (s_t, s_sig, s_keys, s_max) the kept samples instead of colours (MARCH), ``jitter`` (R,) or None."""
    require_triton(origins.device)
    reason = supported(field)
    if reason is not None:
        from ..errors import NeuMeshError

        raise NeuMeshError(f"the Triton renderer cannot render this field: {reason}")
    dev = origins.device
    n = origins.shape[0]
    if not n:
        return
    grid = field.grid
    origins = origins.float().contiguous()
    dirs = dirs.float().contiguous()
    t_near, t_far = grid.ray_aabb(origins, dirs)
    t_near = torch.maximum(t_near, near) if torch.is_tensor(near) else t_near.clamp_min(near)
    t_far = torch.minimum(t_far, far) if torch.is_tensor(far) else t_far.clamp_max(far)
    t_start = torch.floor(t_near / step) * step
    g_o, g_d = grid.cell_coordinates(origins, dirs)
    tb = FieldTables(field, int(opts["cells_per_radius"] or default_cells(dev)))
    occ = grid.occ.contiguous().view(torch.uint8)
    res = list(grid.occ.shape)   # host metadata: no device sync
    blk = int(opts["block"] or default_block(dev))
    rot = tb.rot if tb.rot is not None else tb.rest_n
    refill = opts["schedule"] == "refill"
    n_prog = triton.cdiv(n, blk)
    if refill:
        n_prog = refill_programs(dev, n_prog, opts["programs_per_sm"])
    counter = torch.zeros(1, dtype=torch.int32, device=dev)
    if march is None:   # pointers the plain render never reads (of the types compile_for builds with)
        s_t, s_sig, s_keys, s_max = out, out, torch.zeros(1, dtype=torch.int64, device=dev), 0
    else:
        s_t, s_sig, s_keys, s_max = march
    jit = out if jitter is None else jitter.to(dev, torch.float32).contiguous()
    # a register cap per thread (ptx .maxnreg): more programs resident per multiprocessor, more spills
    extra = {} if not opts["maxnreg"] else {"maxnreg": int(opts["maxnreg"])}
    launch = render_kernel[(n_prog,)]
    with torch.cuda.device(dev) if dev.type == "cuda" else _nullcontext():
        launch(
            origins, dirs, g_o.contiguous(), g_d.contiguous(), t_near.contiguous(), t_far.contiguous(),
            t_start.contiguous(), n,
            occ, res[0], res[1], res[2],
            *tb.hash.args()[:12], float(field.radius),
            tb.vtab, tb.geo, tb.tex, tb.mod, tb.rest_n, rot,
            *tb.mlp,
            out, float(step), float(math.log(early_stop_eps)), float(weight_threshold), counter,
            jit, s_t, s_sig, s_keys, int(s_max),
            **kernel_constants(field.config, early=field.config.interpolation == "early",
                               deformed=tb.rot is not None and march is None, block=blk, cells=tb.hash.c,
                               precision=opts["precision"], scan=int(opts["scan"]), refill=refill,
                               window=int(window), knn_early_out=bool(opts["knn_early_out"]),
                               march=march is not None, jitter=jitter is not None),
            num_warps=int(opts["num_warps"]), **extra)
