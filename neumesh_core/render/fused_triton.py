"""The fused GPU renderer: one Triton kernel marches rays through the occupancy grid, finds each
sample's K nearest scaffold vertices (:func:`neumesh_core.field.knn_triton.knn_keys`), evaluates the
geometry and radiance decoders and composites, with no host synchronisation inside a frame.

Reference: :func:`neumesh_core.render.renderer.render_rays` (the torch marcher
:func:`~neumesh_core.sampling.marcher.march_rays`, the field's ``decode`` and
:func:`~neumesh_core.render.volume.composite`), which stays the default on the CPU and the path for
everything this kernel does not cover.  ``RenderSettings.backend`` chooses: "auto" (this kernel on CUDA
when triton imports and the field is supported, torch otherwise), "torch" or "triton".

One program handles a block of rays.  Each ray walks the steps of its interval (multiples of the step
from the ray's origin, in windows of ``window`` steps that restart after ``max_eval`` evaluated steps,
as the torch marcher does), skipping unoccupied cells; whenever every live ray of the block stands on
an occupied step (or has finished), the block evaluates those samples together: the neighbour search,
the indicators (w_k, p_k), the encodings and the decoders as small matrix products (``tl.dot`` on
(block, width) tiles, fp32; "ieee" precision by default), early or post interpolation, at rest or
deformed (per-vertex rotations to the rest frame).  A sample's compositing weight is computed from the
densities of the samples kept before it, exactly as the reference composites the kept samples; its
colour is decoded only when it is kept (weight above ``weight_threshold`` while the transmittance is
above ``early_stop_eps``), and a ray stops when its transmittance falls below ``early_stop_eps``.

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

from ..field.knn_triton import (TritonHashGrid, decode_keys, knn_keys, next_pow2, require_triton, triton,
                                triton_available, triton_runs_on, tl)

BACKENDS = ("auto", "torch", "triton")


def supported(field) -> Optional[str]:
    """None when the fused kernel renders ``field`` exactly as the torch path does, else the reason
    it does not (the torch path then renders it)."""
    if len(field.rad_decoders) != 1:
        return "the field has several radiance decoders (decoder binding after a texture edit)"
    if field.tex_frame is not None:
        return "the field has texture frames (a swap or fill from a differently oriented surface)"
    if field.code_prior is not None:
        return "coarse code levels are attached (training)"
    if field.config.sh_degree > 4 or field.config.sh_degree < 1:
        return f"sh_degree {field.config.sh_degree} (the kernel encodes degrees 1-4)"
    if field.config.k > 32:
        return f"k={field.config.k} (the kernel keeps up to 32 neighbours)"
    if not math.isfinite(field.radius) or field.radius <= 0:
        return "the field's radius is not finite"
    return None


def use_triton(settings, fields, device, *, train: bool = False, jitter=None, vertex_ids: bool = False,
               semantics: bool = False) -> bool:
    """Whether :func:`render_rays` renders this call with the fused kernel alone (``settings.backend``).
    Training, jitter, vertex ids, semantics and several fields composited together take render_rays'
    torch path (autograd, the extra outputs, the joint sort), whose marching the kernel still does where
    it covers the fields (:func:`use_fused_march`)."""
    backend = _backend(settings)
    if backend == "torch":
        return False
    whole = not (train or jitter is not None or vertex_ids or semantics) and len(fields) == 1
    if backend == "auto":
        return whole and supported(fields[0]) is None and torch.device(device).type == "cuda" and triton_available()
    # "triton" asked for explicitly: every field must be covered
    for f in fields:
        _require_supported(f, device)
    return whole


def use_fused_march(settings, field, device) -> bool:
    """Whether render_rays' torch path marches ``field`` with the kernel (:func:`march_rays_fused`, the
    torch decoders then decode its samples): "auto" on CUDA when triton imports and the kernel covers the
    field, "triton" always (an error when it cannot), "torch" never."""
    backend = _backend(settings)
    if backend == "torch":
        return False
    if backend == "auto":
        return supported(field) is None and torch.device(device).type == "cuda" and triton_available()
    _require_supported(field, device)
    return True


def _backend(settings) -> str:
    backend = getattr(settings, "backend", "auto")
    if backend not in BACKENDS:
        raise ValueError(f"RenderSettings.backend must be one of {', '.join(BACKENDS)}, not {backend!r}")
    return backend


def _require_supported(field, device) -> None:
    require_triton(device)
    reason = supported(field)
    if reason is not None:
        from ..errors import NeuMeshError

        raise NeuMeshError(f"the Triton renderer cannot render this: {reason}; use "
                           "RenderSettings(backend='auto') to fall back to the torch renderer")


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
        self.mod = field.mod_colors.detach().contiguous()
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


# ---------------------------------------------------------------------------------------------- kernel
if triton is not None:
    _PI = tl.constexpr(3.141592653589793)

    @triton.jit
    def _rows(table, idx, ok, D: tl.constexpr, W: tl.constexpr, OFF: tl.constexpr):
        """table[idx, :D] placed at columns OFF..OFF+D of a (B, W) tile (zero elsewhere and where not ok)."""
        col = tl.arange(0, W) - OFF
        m = ok[:, None] & ((col >= 0) & (col < D))[None, :]
        return tl.load(table + idx.to(tl.int64)[:, None] * D + col[None, :], mask=m, other=0.0)

    @triton.jit
    def _pe_cols(x, W: tl.constexpr, OFF: tl.constexpr, F: tl.constexpr):
        """The frequency encoding [x, sin(2^i pi x), cos(2^i pi x)] (i < F) of x (B,) at columns OFF.."""
        cc = tl.arange(0, W) - OFF
        fi = tl.where(cc <= F, cc - 1, cc - F - 1)
        fi = tl.minimum(tl.maximum(fi, 0), 30)
        f = (tl.full([W], 1, tl.int32) << fi).to(tl.float32) * _PI
        ang = x[:, None] * f[None, :]
        v = tl.where((cc == 0)[None, :], x[:, None], tl.where((cc <= F)[None, :], tl.sin(ang), tl.cos(ang)))
        return tl.where(((cc >= 0) & (cc < 2 * F + 1))[None, :], v, 0.0)

    @triton.jit
    def _sh_cols(x, y, z, W: tl.constexpr, OFF: tl.constexpr, DEG: tl.constexpr):
        """Real spherical harmonics (degree DEG <= 4) of unit directions (B,) x3 at columns OFF.."""
        cc = tl.arange(0, W) - OFF
        out = tl.where((cc == 0)[None, :], (tl.full(x.shape, 0.28209479177387814, tl.float32))[:, None], 0.0)
        if DEG > 1:
            out += tl.where((cc == 1)[None, :], (-0.48860251190291987 * y)[:, None], 0.0)
            out += tl.where((cc == 2)[None, :], (0.48860251190291987 * z)[:, None], 0.0)
            out += tl.where((cc == 3)[None, :], (-0.48860251190291987 * x)[:, None], 0.0)
        if DEG > 2:
            xx = x * x
            yy = y * y
            zz = z * z
            xy = x * y
            yz = y * z
            xz = x * z
            out += tl.where((cc == 4)[None, :], (1.0925484305920792 * xy)[:, None], 0.0)
            out += tl.where((cc == 5)[None, :], (-1.0925484305920792 * yz)[:, None], 0.0)
            out += tl.where((cc == 6)[None, :], (0.94617469575755997 * zz - 0.31539156525251999)[:, None], 0.0)
            out += tl.where((cc == 7)[None, :], (-1.0925484305920792 * xz)[:, None], 0.0)
            out += tl.where((cc == 8)[None, :], (0.54627421529603959 * (xx - yy))[:, None], 0.0)
            if DEG > 3:
                out += tl.where((cc == 9)[None, :], (0.59004358992664352 * y * (-3.0 * xx + yy))[:, None], 0.0)
                out += tl.where((cc == 10)[None, :], (2.8906114426405538 * xy * z)[:, None], 0.0)
                out += tl.where((cc == 11)[None, :], (0.45704579946446572 * y * (1.0 - 5.0 * zz))[:, None], 0.0)
                out += tl.where((cc == 12)[None, :], (0.3731763325901154 * z * (5.0 * zz - 3.0))[:, None], 0.0)
                out += tl.where((cc == 13)[None, :], (0.45704579946446572 * x * (1.0 - 5.0 * zz))[:, None], 0.0)
                out += tl.where((cc == 14)[None, :], (1.4453057213202769 * z * (xx - yy))[:, None], 0.0)
                out += tl.where((cc == 15)[None, :], (0.59004358992664352 * x * (-xx + 3.0 * yy))[:, None], 0.0)
        return out

    @triton.jit
    def _dot(x, a, PREC: tl.constexpr):
        """x @ a, fp32 out: fp32 operands at tl.dot's input precision PREC, or ("fp16") operands rounded to
        half precision (10-bit mantissa as tf32's, the tensor cores' most common path)."""
        if PREC == "fp16":
            return tl.dot(x.to(tl.float16), a.to(tl.float16), out_dtype=tl.float32)
        else:
            return tl.dot(x, a, input_precision=PREC)

    @triton.jit
    def _mlp3(x, w1, b1, w2, b2, w3, b3, IN: tl.constexpr, H: tl.constexpr, OUT: tl.constexpr,
              PREC: tl.constexpr):
        """Linear-ReLU-Linear-ReLU-Linear of a (B, IN) tile -> (B, OUT) (padded weights)."""
        ri = tl.arange(0, IN)
        rh = tl.arange(0, H)
        ro = tl.arange(0, OUT)
        a = tl.load(w1 + ri[:, None] * H + rh[None, :])
        h = _dot(x, a, PREC) + tl.load(b1 + rh)[None, :]
        h = tl.maximum(h, 0.0)
        a = tl.load(w2 + rh[:, None] * H + rh[None, :])
        h = tl.maximum(_dot(h, a, PREC) + tl.load(b2 + rh)[None, :], 0.0)
        a = tl.load(w3 + rh[:, None] * OUT + ro[None, :])
        return _dot(h, a, PREC) + tl.load(b3 + ro)[None, :]

    @triton.jit
    def _store_out(out, rows, mask, acc_r, acc_g, acc_b, acc_o, acc_d, acc_mr, acc_mg, acc_mb, n_kept):
        """A ray's outputs: premultiplied rgb, opacity, weighted depth, modification colour, samples kept."""
        base = out + rows.to(tl.int64) * 10
        tl.store(base, acc_r, mask=mask)
        tl.store(base + 1, acc_g, mask=mask)
        tl.store(base + 2, acc_b, mask=mask)
        tl.store(base + 3, acc_o, mask=mask)
        tl.store(base + 4, acc_d, mask=mask)
        tl.store(base + 5, acc_mr, mask=mask)
        tl.store(base + 6, acc_mg, mask=mask)
        tl.store(base + 7, acc_mb, mask=mask)
        tl.store(base + 8, n_kept.to(tl.float32), mask=mask)

    @triton.jit
    def _take3(ptr, rows, mask, x, y, z):
        """Row ``rows`` of an (n, 3) float array where ``mask``; the lanes' old x, y, z elsewhere."""
        x = tl.where(mask, tl.load(ptr + rows * 3, mask=mask, other=0.0), x)
        y = tl.where(mask, tl.load(ptr + rows * 3 + 1, mask=mask, other=0.0), y)
        z = tl.where(mask, tl.load(ptr + rows * 3 + 2, mask=mask, other=0.0), z)
        return x, y, z

    @triton.jit
    def _render_kernel(
            orig, dirs, gorig, gdirs, tnear, tfar, tstart, n_rays,
            occ, res_x, res_y, res_z,
            h_lo_x, h_lo_y, h_lo_z, h_cell, h_dx, h_dy, h_dz, cell_start, cell_count, v_sorted, ids_sorted,
            cell_order, radius,
            vtab, geo, tex, modc, rest_n, rot,
            gw1, gb1, gw2, gb2, gw3, gb3, rw1, rb1, rw2, rb2, rw3, rb3,
            out, step, log_eps, weight_thr, ray_counter, jit, s_t, s_sig, s_keys, s_max,
            BLOCK: tl.constexpr, KP: tl.constexpr, K: tl.constexpr, WINDOW: tl.constexpr,
            MAX_EVAL: tl.constexpr, EARLY: tl.constexpr, DEFORMED: tl.constexpr,
            GEO_D: tl.constexpr, TEX_D: tl.constexpr, PE_F: tl.constexpr, SH_DEG: tl.constexpr,
            GI: tl.constexpr, RI: tl.constexpr, H: tl.constexpr, PREC: tl.constexpr,
            C: tl.constexpr, NCP: tl.constexpr, SCAN: tl.constexpr, REFILL: tl.constexpr,
            KNN_EO: tl.constexpr, MARCH: tl.constexpr, JITTER: tl.constexpr):
        # MARCH: no colour; each kept sample's t, density and neighbour keys go to slot n_kept of its ray
        # in s_t / s_sig / s_keys (s_max slots a ray; n_kept counts them all). JITTER: each ray's steps
        # are offset by (jit[ray] - 0.5) steps, as the torch marcher's ``jitter`` does.
        # static schedule: this program's lanes hold rays pid*BLOCK.. to the end; refill: the lanes start
        # empty and a lane whose ray has finished stores it and takes the next ray of ray_counter
        if REFILL:
            rows = tl.zeros([BLOCK], tl.int32)
            inb = rows < 0
            more = tl.program_id(0) * 0 + 1
        else:
            rows = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
            inb = rows < n_rays
            more = tl.program_id(0) * 0
        zero = tl.zeros([BLOCK], tl.float32)
        ox, oy, oz = _take3(orig, rows, inb, zero, zero, zero)
        dx, dy, dz = _take3(dirs, rows, inb, zero, zero, zero)
        gox, goy, goz = _take3(gorig, rows, inb, zero, zero, zero)
        gdx, gdy, gdz = _take3(gdirs, rows, inb, zero, zero, zero)
        tn = tl.load(tnear + rows, mask=inb, other=0.0)
        tf = tl.load(tfar + rows, mask=inb, other=-1.0)
        t0 = tl.load(tstart + rows, mask=inb, other=0.0)
        if JITTER:
            jv = tl.load(jit + rows, mask=inb, other=0.5)
        else:
            jv = zero + 0.5
        PE: tl.constexpr = 1 + 2 * PE_F
        SH: tl.constexpr = SH_DEG * SH_DEG
        half = 0.5 * step
        slot = tl.arange(0, KP)
        sc = tl.arange(0, SCAN)

        active = inb & (tf > tn)
        j = tl.zeros([BLOCK], tl.int32)
        nev = tl.zeros([BLOCK], tl.int32)
        walked = tl.zeros([BLOCK], tl.int32)
        log_t = tl.zeros([BLOCK], tl.float32)       # transmittance seen by the marcher (every sample)
        log_tc = tl.zeros([BLOCK], tl.float32)      # transmittance of the kept samples (compositing)
        acc_r = tl.zeros([BLOCK], tl.float32)
        acc_g = tl.zeros([BLOCK], tl.float32)
        acc_b = tl.zeros([BLOCK], tl.float32)
        acc_o = tl.zeros([BLOCK], tl.float32)
        acc_d = tl.zeros([BLOCK], tl.float32)
        acc_mr = tl.zeros([BLOCK], tl.float32)
        acc_mg = tl.zeros([BLOCK], tl.float32)
        acc_mb = tl.zeros([BLOCK], tl.float32)
        n_kept = tl.zeros([BLOCK], tl.int32)

        while tl.max(active.to(tl.int32), 0) + more > 0:
            if REFILL:
                # ---- lanes whose ray finished store it; free lanes take the next rays (one atomic a block)
                done = inb & ~active
                _store_out(out, rows, done, acc_r, acc_g, acc_b, acc_o, acc_d, acc_mr, acc_mg, acc_mb, n_kept)
                inb = active
                free = (~inb).to(tl.int32)
                n_free = tl.sum(free, 0)
                if (more > 0) & (n_free > 0):
                    base = tl.atomic_add(ray_counter, n_free)
                    new_id = base + tl.cumsum(free, 0) - 1
                    take = (free > 0) & (new_id < n_rays)
                    more = (base + n_free < n_rays).to(tl.int32)
                    rows = tl.where(take, new_id, rows)
                    ox, oy, oz = _take3(orig, rows, take, ox, oy, oz)
                    dx, dy, dz = _take3(dirs, rows, take, dx, dy, dz)
                    gox, goy, goz = _take3(gorig, rows, take, gox, goy, goz)
                    gdx, gdy, gdz = _take3(gdirs, rows, take, gdx, gdy, gdz)
                    tn = tl.where(take, tl.load(tnear + rows, mask=take, other=0.0), tn)
                    tf = tl.where(take, tl.load(tfar + rows, mask=take, other=-1.0), tf)
                    t0 = tl.where(take, tl.load(tstart + rows, mask=take, other=0.0), t0)
                    if JITTER:
                        jv = tl.where(take, tl.load(jit + rows, mask=take, other=0.5), jv)
                    j = tl.where(take, 0, j)
                    nev = tl.where(take, 0, nev)
                    walked = tl.where(take, 0, walked)
                    log_t = tl.where(take, 0.0, log_t)
                    log_tc = tl.where(take, 0.0, log_tc)
                    acc_r = tl.where(take, 0.0, acc_r)
                    acc_g = tl.where(take, 0.0, acc_g)
                    acc_b = tl.where(take, 0.0, acc_b)
                    acc_o = tl.where(take, 0.0, acc_o)
                    acc_d = tl.where(take, 0.0, acc_d)
                    acc_mr = tl.where(take, 0.0, acc_mr)
                    acc_mg = tl.where(take, 0.0, acc_mg)
                    acc_mb = tl.where(take, 0.0, acc_mb)
                    n_kept = tl.where(take, 0, n_kept)
                    inb = inb | take
                    active = active | (take & (tf > tn))
            # ---- every live ray walks to its next occupied step inside its interval (or finishes)
            searching = active
            found = active & (tl.zeros([BLOCK], tl.int32) > 0)
            while tl.max(searching.to(tl.int32), 0) > 0:
                # SCAN steps at once (within the window): the first occupied one in the ray's interval
                jj = j[:, None] + sc[None, :]
                inwin = jj < WINDOW
                t2 = t0[:, None] + (jj.to(tl.float32) + 0.5) * step
                if JITTER:
                    t2 = t2 + ((jv - 0.5) * step)[:, None]
                in_range = (t2 < tf[:, None]) & (t2 >= tn[:, None]) & inwin
                ix = tl.minimum(tl.maximum(tl.floor(gox[:, None] + gdx[:, None] * t2).to(tl.int32), 0), res_x - 1)
                iy = tl.minimum(tl.maximum(tl.floor(goy[:, None] + gdy[:, None] * t2).to(tl.int32), 0), res_y - 1)
                iz = tl.minimum(tl.maximum(tl.floor(goz[:, None] + gdz[:, None] * t2).to(tl.int32), 0), res_z - 1)
                o = tl.load(occ + (ix * res_y + iy) * res_z + iz, mask=searching[:, None] & in_range, other=0)
                first = tl.min(tl.where(in_range & (o != 0), sc[None, :], SCAN), 1)
                past = tl.min(tl.where(inwin & (t2 >= tf[:, None]), sc[None, :], SCAN), 1)
                hit = searching & (first < SCAN) & (first < past)
                # past the interval's end (or, a guard against a ray that cannot advance in float32 far
                # from the origin, after 2^22 steps)
                ended = searching & ~hit & ((past < SCAN) | (walked >= 4194304))
                walked += tl.where(searching, SCAN, 0)
                active = active & ~ended
                # hits stand on their step; the others move past the steps they scanned
                scanned = tl.minimum(WINDOW - j, SCAN)
                j = tl.where(hit, j + first, tl.where(searching & ~ended, j + scanned, j))
                wrap = searching & ~hit & ~ended & (j >= WINDOW)
                t0 = tl.where(wrap, t0 + WINDOW * step, t0)
                j = tl.where(wrap, 0, j)
                nev = tl.where(wrap, 0, nev)
                # the (MAX_EVAL+1)-th occupied step of a window starts the next window
                cap = hit & (nev >= MAX_EVAL)
                t0 = tl.where(cap, t0 + j.to(tl.float32) * step, t0)
                j = tl.where(cap, 0, j)
                nev = tl.where(cap, 0, nev)
                found = found | hit
                searching = searching & ~hit & ~ended

            if tl.max(found.to(tl.int32), 0) > 0:
                # ---- the samples: neighbours, indicators, density
                t = t0 + (j.to(tl.float32) + 0.5) * step
                if JITTER:
                    t = t + (jv - 0.5) * step
                px = ox + dx * t
                py = oy + dy * t
                pz = oz + dz * t
                keys = knn_keys(px, py, pz, found, h_lo_x, h_lo_y, h_lo_z, h_cell, h_dx, h_dy, h_dz,
                                cell_start, cell_count, v_sorted, ids_sorted, cell_order, radius, BLOCK, KP, K,
                                C, NCP, KNN_EO)
                dist = (keys >> 32).to(tl.int32).to(tl.float32, bitcast=True)
                valid = (slot[None, :] < K) & (dist < 3.0e38) & found[:, None]
                idx = tl.where(valid, (keys & 0xFFFFFFFF).to(tl.int32), 0)
                inv = tl.where(valid, 1.0 / tl.maximum(dist, 1e-8), 0.0)
                w = inv / tl.maximum(tl.sum(inv, 1), 1e-12)[:, None]
                vrow = idx.to(tl.int64) * 6
                vm = valid
                pk = (tl.load(vtab + vrow, mask=vm, other=0.0) - px[:, None]) * tl.load(vtab + vrow + 3, mask=vm, other=0.0) + \
                    (tl.load(vtab + vrow + 1, mask=vm, other=0.0) - py[:, None]) * tl.load(vtab + vrow + 4, mask=vm, other=0.0) + \
                    (tl.load(vtab + vrow + 2, mask=vm, other=0.0) - pz[:, None]) * tl.load(vtab + vrow + 5, mask=vm, other=0.0)
                any_valid = tl.max(valid.to(tl.int32), 1) > 0
                if EARLY:
                    gin = tl.zeros([BLOCK, GI], tl.float32)
                    for k in range(K):
                        gin += tl.sum(tl.where(slot[None, :] == k, w, tl.zeros_like(w)), 1)[:, None] * _rows(geo, tl.sum(tl.where(slot[None, :] == k, idx, tl.zeros_like(idx)), 1), found, GEO_D, GI, 0)
                    p = tl.sum(pk * w, 1)
                    wi = tl.sum(w * w, 1)
                    pe_x = p / radius
                    gin += _pe_cols(pe_x, GI, GEO_D, PE_F) + tl.where((tl.arange(0, GI) == GEO_D + PE)[None, :], (wi)[:, None], 0.0)
                    y = _mlp3(gin, gw1, gb1, gw2, gb2, gw3, gb3, GI, H, 16, PREC)
                    sigma = tl.exp(tl.minimum(tl.sum(tl.where((tl.arange(0, 16) == 0)[None, :], y, 0.0), 1), 15.0))
                    sigma = tl.where(any_valid, sigma, 0.0)
                else:
                    sigma = tl.zeros([BLOCK], tl.float32)
                    for k in range(K):
                        wk = tl.sum(tl.where(slot[None, :] == k, w, tl.zeros_like(w)), 1)
                        gin = _rows(geo, tl.sum(tl.where(slot[None, :] == k, idx, tl.zeros_like(idx)), 1), found, GEO_D, GI, 0)
                        gin += _pe_cols(tl.sum(tl.where(slot[None, :] == k, pk, tl.zeros_like(pk)), 1) / radius, GI, GEO_D, PE_F) + tl.where((tl.arange(0, GI) == GEO_D + PE)[None, :], (wk)[:, None], 0.0)
                        y = _mlp3(gin, gw1, gb1, gw2, gb2, gw3, gb3, GI, H, 16, PREC)
                        sigma += wk * tl.exp(tl.minimum(tl.sum(tl.where((tl.arange(0, 16) == 0)[None, :], y, 0.0), 1), 15.0))
                sigma = tl.where(found, sigma, 0.0)
                # ---- marching transmittance: which samples are kept, when a ray stops
                tau = sigma * step
                log_ts = log_t
                weight = tl.exp(log_ts) * (1.0 - tl.exp(-tau))
                keep = found & (weight > weight_thr) & (log_ts > log_eps)
                log_t = tl.where(found, log_t - tau, log_t)
                nev = tl.where(found, nev + 1, nev)
                j = tl.where(found, j + 1, j)
                wrap = found & (j >= WINDOW)
                t0 = tl.where(wrap, t0 + WINDOW * step, t0)
                j = tl.where(wrap, 0, j)
                nev = tl.where(wrap, 0, nev)
                active = active & (log_t > log_eps)
                if MARCH:
                    # ---- the kept samples themselves (the torch decoders take them from here)
                    spos = rows.to(tl.int64) * s_max + n_kept
                    sm = keep & (n_kept < s_max)
                    tl.store(s_t + spos, t, mask=sm)
                    tl.store(s_sig + spos, sigma, mask=sm)
                    tl.store(s_keys + spos[:, None] * KP + slot[None, :], keys, mask=sm[:, None])
                    n_kept += keep.to(tl.int32)
                else:
                    if tl.max(keep.to(tl.int32), 0) > 0:
                        # ---- colour of the kept samples
                        ts = t - half
                        te = t + half
                        tau_c = sigma * (te - ts)
                        wc = tl.where(keep, tl.exp(log_tc) * (1.0 - tl.exp(-tau_c)), 0.0)
                        log_tc = tl.where(keep, log_tc - tau_c, log_tc)
                        if EARLY:
                            tin = tl.zeros([BLOCK, RI], tl.float32)
                            nx = tl.zeros([BLOCK], tl.float32)
                            ny = tl.zeros([BLOCK], tl.float32)
                            nz = tl.zeros([BLOCK], tl.float32)
                            mr = tl.zeros([BLOCK], tl.float32)
                            mg = tl.zeros([BLOCK], tl.float32)
                            mb = tl.zeros([BLOCK], tl.float32)
                            r0 = tl.zeros([BLOCK], tl.float32)
                            r1 = tl.zeros([BLOCK], tl.float32)
                            r2 = tl.zeros([BLOCK], tl.float32)
                            r3 = tl.zeros([BLOCK], tl.float32)
                            r4 = tl.zeros([BLOCK], tl.float32)
                            r5 = tl.zeros([BLOCK], tl.float32)
                            r6 = tl.zeros([BLOCK], tl.float32)
                            r7 = tl.zeros([BLOCK], tl.float32)
                            r8 = tl.zeros([BLOCK], tl.float32)
                            for k in range(K):
                                wk = tl.sum(tl.where(slot[None, :] == k, w, tl.zeros_like(w)), 1)
                                ik = tl.sum(tl.where(slot[None, :] == k, idx, tl.zeros_like(idx)), 1).to(tl.int64)
                                tin += wk[:, None] * _rows(tex, ik, keep, TEX_D, RI, 0)
                                nx += wk * tl.load(rest_n + ik * 3, mask=keep, other=0.0)
                                ny += wk * tl.load(rest_n + ik * 3 + 1, mask=keep, other=0.0)
                                nz += wk * tl.load(rest_n + ik * 3 + 2, mask=keep, other=0.0)
                                mr += wk * tl.load(modc + ik * 3, mask=keep, other=0.0)
                                mg += wk * tl.load(modc + ik * 3 + 1, mask=keep, other=0.0)
                                mb += wk * tl.load(modc + ik * 3 + 2, mask=keep, other=0.0)
                                if DEFORMED:
                                    r0 += wk * tl.load(rot + ik * 9, mask=keep, other=0.0)
                                    r1 += wk * tl.load(rot + ik * 9 + 1, mask=keep, other=0.0)
                                    r2 += wk * tl.load(rot + ik * 9 + 2, mask=keep, other=0.0)
                                    r3 += wk * tl.load(rot + ik * 9 + 3, mask=keep, other=0.0)
                                    r4 += wk * tl.load(rot + ik * 9 + 4, mask=keep, other=0.0)
                                    r5 += wk * tl.load(rot + ik * 9 + 5, mask=keep, other=0.0)
                                    r6 += wk * tl.load(rot + ik * 9 + 6, mask=keep, other=0.0)
                                    r7 += wk * tl.load(rot + ik * 9 + 7, mask=keep, other=0.0)
                                    r8 += wk * tl.load(rot + ik * 9 + 8, mask=keep, other=0.0)
                            if DEFORMED:
                                ex = r0 * dx + r1 * dy + r2 * dz
                                ey = r3 * dx + r4 * dy + r5 * dz
                                ez = r6 * dx + r7 * dy + r8 * dz
                                en = tl.maximum(tl.sqrt(ex * ex + ey * ey + ez * ez), 1e-8)
                                ex = ex / en
                                ey = ey / en
                                ez = ez / en
                            else:
                                ex = dx
                                ey = dy
                                ez = dz
                            nn = tl.maximum(tl.sqrt(nx * nx + ny * ny + nz * nz), 1e-8)
                            nx = nx / nn
                            ny = ny / nn
                            nz = nz / nn
                            p = tl.sum(pk * w, 1)
                            wi = tl.sum(w * w, 1)
                            tin += _pe_cols(p / radius, RI, TEX_D, PE_F) + tl.where((tl.arange(0, RI) == TEX_D + PE)[None, :], (wi)[:, None], 0.0)
                            tin += _sh_cols(ex, ey, ez, RI, TEX_D + PE + 1, SH_DEG)
                            NO: tl.constexpr = TEX_D + PE + 1 + SH
                            tin += tl.where((tl.arange(0, RI) == NO)[None, :], (nx)[:, None], 0.0) + tl.where((tl.arange(0, RI) == NO + 1)[None, :], (ny)[:, None], 0.0) + tl.where((tl.arange(0, RI) == NO + 2)[None, :], (nz)[:, None], 0.0)
                            y = _mlp3(tin, rw1, rb1, rw2, rb2, rw3, rb3, RI, H, 16, PREC)
                            cr = (1.0 / (1.0 + tl.exp(-tl.sum(tl.where((tl.arange(0, 16) == 0)[None, :], y, 0.0), 1)))) + mr
                            cg = (1.0 / (1.0 + tl.exp(-tl.sum(tl.where((tl.arange(0, 16) == 1)[None, :], y, 0.0), 1)))) + mg
                            cb = (1.0 / (1.0 + tl.exp(-tl.sum(tl.where((tl.arange(0, 16) == 2)[None, :], y, 0.0), 1)))) + mb
                        else:
                            cr = tl.zeros([BLOCK], tl.float32)
                            cg = tl.zeros([BLOCK], tl.float32)
                            cb = tl.zeros([BLOCK], tl.float32)
                            mr = tl.zeros([BLOCK], tl.float32)
                            mg = tl.zeros([BLOCK], tl.float32)
                            mb = tl.zeros([BLOCK], tl.float32)
                            NO2: tl.constexpr = TEX_D + PE + 1 + SH
                            for k in range(K):
                                wk = tl.sum(tl.where(slot[None, :] == k, w, tl.zeros_like(w)), 1)
                                ik = tl.sum(tl.where(slot[None, :] == k, idx, tl.zeros_like(idx)), 1).to(tl.int64)
                                if DEFORMED:
                                    ex = tl.load(rot + ik * 9, mask=keep, other=0.0) * dx + \
                                        tl.load(rot + ik * 9 + 1, mask=keep, other=0.0) * dy + \
                                        tl.load(rot + ik * 9 + 2, mask=keep, other=0.0) * dz
                                    ey = tl.load(rot + ik * 9 + 3, mask=keep, other=0.0) * dx + \
                                        tl.load(rot + ik * 9 + 4, mask=keep, other=0.0) * dy + \
                                        tl.load(rot + ik * 9 + 5, mask=keep, other=0.0) * dz
                                    ez = tl.load(rot + ik * 9 + 6, mask=keep, other=0.0) * dx + \
                                        tl.load(rot + ik * 9 + 7, mask=keep, other=0.0) * dy + \
                                        tl.load(rot + ik * 9 + 8, mask=keep, other=0.0) * dz
                                else:
                                    ex = dx
                                    ey = dy
                                    ez = dz
                                tin = _rows(tex, ik, keep, TEX_D, RI, 0)
                                tin += _pe_cols(tl.sum(tl.where(slot[None, :] == k, pk, tl.zeros_like(pk)), 1) / radius, RI, TEX_D, PE_F) + tl.where((tl.arange(0, RI) == TEX_D + PE)[None, :], (wk)[:, None], 0.0)
                                tin += _sh_cols(ex, ey, ez, RI, TEX_D + PE + 1, SH_DEG)
                                tin += tl.where((tl.arange(0, RI) == NO2)[None, :], (tl.load(rest_n + ik * 3, mask=keep, other=0.0))[:, None], 0.0)
                                tin += tl.where((tl.arange(0, RI) == NO2 + 1)[None, :], (tl.load(rest_n + ik * 3 + 1, mask=keep, other=0.0))[:, None], 0.0)
                                tin += tl.where((tl.arange(0, RI) == NO2 + 2)[None, :], (tl.load(rest_n + ik * 3 + 2, mask=keep, other=0.0))[:, None], 0.0)
                                y = _mlp3(tin, rw1, rb1, rw2, rb2, rw3, rb3, RI, H, 16, PREC)
                                m0 = tl.load(modc + ik * 3, mask=keep, other=0.0)
                                m1 = tl.load(modc + ik * 3 + 1, mask=keep, other=0.0)
                                m2 = tl.load(modc + ik * 3 + 2, mask=keep, other=0.0)
                                cr += wk * ((1.0 / (1.0 + tl.exp(-tl.sum(tl.where((tl.arange(0, 16) == 0)[None, :], y, 0.0), 1)))) + m0)
                                cg += wk * ((1.0 / (1.0 + tl.exp(-tl.sum(tl.where((tl.arange(0, 16) == 1)[None, :], y, 0.0), 1)))) + m1)
                                cb += wk * ((1.0 / (1.0 + tl.exp(-tl.sum(tl.where((tl.arange(0, 16) == 2)[None, :], y, 0.0), 1)))) + m2)
                                mr += wk * m0
                                mg += wk * m1
                                mb += wk * m2
                        acc_r += wc * cr
                        acc_g += wc * cg
                        acc_b += wc * cb
                        acc_mr += wc * mr
                        acc_mg += wc * mg
                        acc_mb += wc * mb
                        acc_o += wc
                        acc_d += wc * (0.5 * (ts + te))
                        n_kept += keep.to(tl.int32)

        # static: every ray of the block; refill: the rays finished since the last refill
        _store_out(out, rows, inb, acc_r, acc_g, acc_b, acc_o, acc_d, acc_mr, acc_mg, acc_mb, n_kept)


def default_block(device) -> int:
    """Rays per program: 32 on a GPU (with 4 warps: on an H200 the fastest of the options timed by
    ``benchmarks/bench_render_gpu.py --sweep``, 37.7 ms for lego 800² against 44.7 ms for 64 rays x 8
    warps, although the sm_90 build of 64 x 8 spills less: a smaller block waits less for its slowest
    ray); in the interpreter (CPU) one big block, since there each operation costs about the same for any
    block size."""
    return 32 if torch.device(device).type == "cuda" else 1024


# launch options, chosen by benchmarks/bench_render_gpu.py (``--sweep``); render_rays_fused's defaults
# (block / cells_per_radius None: by device, see default_block / default_cells; num_warps: per program)
KERNEL_OPTIONS = {"block": None, "precision": "ieee", "num_warps": 4, "cells_per_radius": None, "scan": 8,
                  "schedule": "static", "programs_per_sm": 8, "maxnreg": None, "knn_early_out": False,
                  "ray_order": "tiles"}


def default_cells(device) -> int:
    """Neighbour-grid cells per radius: 1 on a GPU and in the interpreter (27 cells a radius wide; on an
    H200 37.7 ms for lego 800² against 41.8 ms with 125 half-radius cells, which measured fewer vertices
    but walked more cells -- before knn_keys read them nearest first and pruned them, which cuts their
    rounds about threefold (benchmarks/knn_merges.py); the GPU sweep times both again)."""
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
    each variant compiles with the installed Triton, and by ``benchmarks/kernel_resources.py`` to read
    its registers and spills."""
    import inspect

    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    if triton is None or type(_render_kernel).__name__ == "InterpretedFunction":
        raise RuntimeError("compile_for needs triton imported without TRITON_INTERPRET=1 (the interpreter "
                           "runs kernels, it does not build them): run it in a process without that variable")
    opts = _checked({**KERNEL_OPTIONS, **options})
    consts = kernel_constants(cfg, early=interpolation == "early", deformed=deformed,
                              block=opts["block"] or default_block("cuda"),
                              cells=opts["cells_per_radius"] or default_cells("cuda"),
                              precision=opts["precision"], scan=opts["scan"], refill=opts["schedule"] == "refill",
                              knn_early_out=opts["knn_early_out"], march=march, jitter=jitter)
    sig = {}
    for p in inspect.signature(_render_kernel.fn).parameters:
        if p in consts:
            sig[p] = "constexpr"
        elif p in _POINTERS:
            sig[p] = _PTR_TYPES.get(p, "*fp32")
        else:
            sig[p] = "i32" if p in _INTS else "fp32"
    build = {"num_warps": int(opts["num_warps"])}
    if opts["maxnreg"]:
        build["maxnreg"] = int(opts["maxnreg"])
    return triton.compile(ASTSource(fn=_render_kernel, signature=sig, constexprs=consts),
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
    registers per thread (``benchmarks/kernel_resources.py`` shows what each cap spills); knn_early_out:
    the neighbour search skips the merges no candidate needs (``knn_triton.knn_keys``; the same image).
    ``ray_order`` ("tiles" or "rows") is read by ``render_camera``: the order of the pixels it hands
    the kernel (``renderer.tile_order``: 8 x 4 screen patches per 32 rays)."""
    opts = _checked({**KERNEL_OPTIONS, **options})
    out = torch.zeros(origins.shape[0], 10, device=origins.device)
    _launch(field, origins, dirs, settings.window, settings.early_stop_eps, settings.weight_threshold, step,
            near, far, opts, out)
    opacity = out[:, 3]
    depth = torch.where(opacity > 1e-6, out[:, 4] / opacity.clamp_min(1e-6), torch.full_like(opacity, float("inf")))
    return {"rgb": out[:, :3], "opacity": opacity, "depth": depth, "mod_rgb": out[:, 5:8],
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
    if march is None:   # pointers the plain render never reads
        s_t, s_sig, s_keys, s_max = out, out, counter, 0
    else:
        s_t, s_sig, s_keys, s_max = march
    jit = out if jitter is None else jitter.to(dev, torch.float32).contiguous()
    # a register cap per thread (ptx .maxnreg): more programs resident per multiprocessor, more spills
    extra = {} if not opts["maxnreg"] else {"maxnreg": int(opts["maxnreg"])}
    launch = _render_kernel[(n_prog,)]
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
