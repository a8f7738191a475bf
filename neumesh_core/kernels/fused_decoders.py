"""The decoders of the fused renderer's kernel as ``@triton.jit`` parts (inlined into
:mod:`neumesh_core.kernels.fused_kernel`): the frequency and spherical-harmonic encodings, the 3-layer
MLPs as small matrix products on (block, width) tiles (``tl.dot``; "ieee" fp32 by default, zero-padded
weights from ``fused.FieldTables``), and the density and colour of a block of samples from their K
neighbours, early or post interpolation (reference: the field's ``decode``, field/decoders.py).
"""
from __future__ import annotations

from .knn import triton, tl

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
    def _column(y, i: tl.constexpr):
        """Column ``i`` of a (B, 16) decoder output tile, (B,)."""
        return tl.sum(tl.where((tl.arange(0, 16) == i)[None, :], y, 0.0), 1)

    @triton.jit
    def _slot(x, slot, k):
        """Slot ``k`` of a (B, KP) tile of per-neighbour values, (B,)."""
        return tl.sum(tl.where(slot[None, :] == k, x, tl.zeros_like(x)), 1)

    @triton.jit
    def density(idx, w, pk, any_valid, found, geo, gw1, gb1, gw2, gb2, gw3, gb3, radius,
                BLOCK: tl.constexpr, KP: tl.constexpr, K: tl.constexpr, GEO_D: tl.constexpr, GI: tl.constexpr,
                H: tl.constexpr, PE_F: tl.constexpr, PREC: tl.constexpr, EARLY: tl.constexpr):
        """Density of the samples ``found`` (B,) from their neighbours (idx, w, indicator p_k: (B, KP)):
        early interpolation decodes the weighted codes and indicators once, post interpolation decodes
        each neighbour and blends the densities."""
        slot = tl.arange(0, KP)
        PE: tl.constexpr = 1 + 2 * PE_F
        if EARLY:
            gin = tl.zeros([BLOCK, GI], tl.float32)
            for k in range(K):
                gin += _slot(w, slot, k)[:, None] * _rows(geo, _slot(idx, slot, k), found, GEO_D, GI, 0)
            p = tl.sum(pk * w, 1)
            wi = tl.sum(w * w, 1)
            pe_x = p / radius
            gin += _pe_cols(pe_x, GI, GEO_D, PE_F) + \
                tl.where((tl.arange(0, GI) == GEO_D + PE)[None, :], (wi)[:, None], 0.0)
            y = _mlp3(gin, gw1, gb1, gw2, gb2, gw3, gb3, GI, H, 16, PREC)
            sigma = tl.exp(tl.minimum(_column(y, 0), 15.0))
            sigma = tl.where(any_valid, sigma, 0.0)
        else:
            sigma = tl.zeros([BLOCK], tl.float32)
            for k in range(K):
                wk = _slot(w, slot, k)
                gin = _rows(geo, _slot(idx, slot, k), found, GEO_D, GI, 0)
                gin += _pe_cols(_slot(pk, slot, k) / radius, GI, GEO_D, PE_F) + \
                    tl.where((tl.arange(0, GI) == GEO_D + PE)[None, :], (wk)[:, None], 0.0)
                y = _mlp3(gin, gw1, gb1, gw2, gb2, gw3, gb3, GI, H, 16, PREC)
                sigma += wk * tl.exp(tl.minimum(_column(y, 0), 15.0))
        return tl.where(found, sigma, 0.0)

    @triton.jit
    def colour_early(idx, w, pk, keep, dx, dy, dz, tex, modc, rest_n, rot, rw1, rb1, rw2, rb2, rw3, rb3, radius,
                     BLOCK: tl.constexpr, KP: tl.constexpr, K: tl.constexpr, TEX_D: tl.constexpr, RI: tl.constexpr,
                     H: tl.constexpr, PE_F: tl.constexpr, SH_DEG: tl.constexpr, PREC: tl.constexpr,
                     DEFORMED: tl.constexpr):
        """Colour (rgb with the modification colour added) and modification colour of the ``keep``
        samples, early interpolation: the neighbours' texture codes, normals, modification colours (and,
        deformed, rotations to the rest frame) blended first, then one radiance decoding."""
        slot = tl.arange(0, KP)
        PE: tl.constexpr = 1 + 2 * PE_F
        SH: tl.constexpr = SH_DEG * SH_DEG
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
            wk = _slot(w, slot, k)
            ik = _slot(idx, slot, k).to(tl.int64)
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
        tin += _pe_cols(p / radius, RI, TEX_D, PE_F) + \
            tl.where((tl.arange(0, RI) == TEX_D + PE)[None, :], (wi)[:, None], 0.0)
        tin += _sh_cols(ex, ey, ez, RI, TEX_D + PE + 1, SH_DEG)
        NO: tl.constexpr = TEX_D + PE + 1 + SH
        tin += tl.where((tl.arange(0, RI) == NO)[None, :], (nx)[:, None], 0.0) + \
            tl.where((tl.arange(0, RI) == NO + 1)[None, :], (ny)[:, None], 0.0) + \
            tl.where((tl.arange(0, RI) == NO + 2)[None, :], (nz)[:, None], 0.0)
        y = _mlp3(tin, rw1, rb1, rw2, rb2, rw3, rb3, RI, H, 16, PREC)
        cr = (1.0 / (1.0 + tl.exp(-_column(y, 0)))) + mr
        cg = (1.0 / (1.0 + tl.exp(-_column(y, 1)))) + mg
        cb = (1.0 / (1.0 + tl.exp(-_column(y, 2)))) + mb
        return cr, cg, cb, mr, mg, mb

    @triton.jit
    def colour_post(idx, w, pk, keep, dx, dy, dz, tex, modc, rest_n, rot, rw1, rb1, rw2, rb2, rw3, rb3, radius,
                    BLOCK: tl.constexpr, KP: tl.constexpr, K: tl.constexpr, TEX_D: tl.constexpr, RI: tl.constexpr,
                    H: tl.constexpr, PE_F: tl.constexpr, SH_DEG: tl.constexpr, PREC: tl.constexpr,
                    DEFORMED: tl.constexpr):
        """As :func:`colour_early`, post interpolation: each neighbour decoded with its own code, normal
        and (deformed) view direction in its rest frame, the colours blended."""
        slot = tl.arange(0, KP)
        PE: tl.constexpr = 1 + 2 * PE_F
        SH: tl.constexpr = SH_DEG * SH_DEG
        cr = tl.zeros([BLOCK], tl.float32)
        cg = tl.zeros([BLOCK], tl.float32)
        cb = tl.zeros([BLOCK], tl.float32)
        mr = tl.zeros([BLOCK], tl.float32)
        mg = tl.zeros([BLOCK], tl.float32)
        mb = tl.zeros([BLOCK], tl.float32)
        NO2: tl.constexpr = TEX_D + PE + 1 + SH
        for k in range(K):
            wk = _slot(w, slot, k)
            ik = _slot(idx, slot, k).to(tl.int64)
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
            tin += _pe_cols(_slot(pk, slot, k) / radius, RI, TEX_D, PE_F) + \
                tl.where((tl.arange(0, RI) == TEX_D + PE)[None, :], (wk)[:, None], 0.0)
            tin += _sh_cols(ex, ey, ez, RI, TEX_D + PE + 1, SH_DEG)
            tin += tl.where((tl.arange(0, RI) == NO2)[None, :],
                            (tl.load(rest_n + ik * 3, mask=keep, other=0.0))[:, None], 0.0)
            tin += tl.where((tl.arange(0, RI) == NO2 + 1)[None, :],
                            (tl.load(rest_n + ik * 3 + 1, mask=keep, other=0.0))[:, None], 0.0)
            tin += tl.where((tl.arange(0, RI) == NO2 + 2)[None, :],
                            (tl.load(rest_n + ik * 3 + 2, mask=keep, other=0.0))[:, None], 0.0)
            y = _mlp3(tin, rw1, rb1, rw2, rb2, rw3, rb3, RI, H, 16, PREC)
            m0 = tl.load(modc + ik * 3, mask=keep, other=0.0)
            m1 = tl.load(modc + ik * 3 + 1, mask=keep, other=0.0)
            m2 = tl.load(modc + ik * 3 + 2, mask=keep, other=0.0)
            cr += wk * ((1.0 / (1.0 + tl.exp(-_column(y, 0)))) + m0)
            cg += wk * ((1.0 / (1.0 + tl.exp(-_column(y, 1)))) + m1)
            cb += wk * ((1.0 / (1.0 + tl.exp(-_column(y, 2)))) + m2)
            mr += wk * m0
            mg += wk * m1
            mb += wk * m2
        return cr, cg, cb, mr, mg, mb
else:  # pragma: no cover - without triton nothing launches the kernel
    density = colour_early = colour_post = None
