"""The decoders that read a field's per-vertex tables: the geometry decoder (sigma) and the radiance
decoders (colour) with their per-vertex binding ``decoder_id``, post- and early interpolation, texture
frames. :class:`RadianceDecoding` is the part of :class:`~neumesh_core.field.field.NeuMeshField` that
decodes (see the module docstring of :mod:`.field` for the rules).
"""
from __future__ import annotations

import copy
import hashlib
from typing import Optional

import torch
from torch import nn
import torch.nn.functional as F

from .encoding import frequency_encoding, sh_encoding, trunc_exp
from .scaffold import Neighbourhood, take_rows


def _mlp(d_in: int, hidden: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(d_in, hidden), nn.ReLU(inplace=True),
        nn.Linear(hidden, hidden), nn.ReLU(inplace=True),
        nn.Linear(hidden, d_out),
    )


# rows per decoder call when no gradient is needed: the hidden activations of ~16k rows stay in the
# CPU's cache, where one call on 600k rows streams them through memory (2-3x slower on this machine;
# benchmarks/bench/bench_render.py)
_INFERENCE_ROWS = 16384


def run_decoder(module: nn.Module, x) -> torch.Tensor:
    """``module(x)``, in row blocks of ``_INFERENCE_ROWS`` when autograd is off (rows are independent,
    so the result is the same up to the float rounding of the matrix products).

    ``x``: the input, or a list of column blocks (tensors with the same rows) that make the input side
    by side.  On the CPU without autograd the blocks are copied into one small reused buffer per row
    block, so the whole concatenated input never exists (``torch.cat`` along columns is ~3x slower than
    slice copies on the CPU, and the decoder then reads its input from the cache, not from memory).
    With autograd or on a GPU the blocks are concatenated (the reference)."""
    parts = list(x) if isinstance(x, (list, tuple)) else None
    first = parts[0] if parts is not None else x
    n = first.shape[0]
    if torch.is_grad_enabled() or first.device.type != "cpu":
        return module(torch.cat(parts, -1) if parts is not None else x)
    if parts is None:
        if n <= _INFERENCE_ROWS:
            return module(x)
        return torch.cat([module(x[s:s + _INFERENCE_ROWS]) for s in range(0, n, _INFERENCE_ROWS)])
    widths = [p.shape[1] for p in parts]
    if n == 0:
        return module(first.new_empty(0, sum(widths)))
    rows = min(n, _INFERENCE_ROWS)
    buf = first.new_empty(rows, sum(widths))
    outs = []
    for s in range(0, n, rows):
        e = min(n, s + rows)
        o = 0
        for p, w in zip(parts, widths):
            buf[:e - s, o:o + w].copy_(p[s:e])
            o += w
        outs.append(module(buf[:e - s]))
    return outs[0] if len(outs) == 1 else torch.cat(outs)


def decoder_key(module: nn.Module) -> str:
    """Content hash of a decoder's weights: equal keys mean bit-identical decoders (copies of one)."""
    h = hashlib.sha1()
    for name, t in module.state_dict().items():
        t = t.detach().cpu().contiguous()
        h.update(name.encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(t.numpy().tobytes())
    return h.hexdigest()


class RadianceDecoding:
    """Mixin of :class:`NeuMeshField`: decoder binding and decoding of samples (sigma, colour,
    modification colour) from the K neighbours' codes."""

    # ------------------------------------------------------------------ decoder binding
    @property
    def rad_decoder(self) -> nn.Module:
        """The field's own (first) radiance decoder."""
        return self.rad_decoders[0]

    @property
    def num_decoders(self) -> int:
        return len(self.rad_decoders)

    def decoder_keys(self) -> list:
        """Content hash of each radiance decoder (see :func:`decoder_key`)."""
        return [decoder_key(d) for d in self.rad_decoders]

    def add_decoder(self, decoder: nn.Module) -> int:
        """Index of ``decoder`` in this field, appending a frozen copy of it when no bit-identical
        decoder is here yet (so binding codes from one source several times adds its decoder once)."""
        key = decoder_key(decoder)
        for i, d in enumerate(self.rad_decoders):
            if decoder_key(d) == key:
                return i
        if len(self.rad_decoders) >= torch.iinfo(self.decoder_id.dtype).max:
            raise ValueError("too many radiance decoders in one field")
        dec = copy.deepcopy(decoder).to(self.geo_codes.device)
        for prm in dec.parameters():
            prm.requires_grad_(False)
        self.rad_decoders.append(dec)
        return len(self.rad_decoders) - 1

    def drop_unused_decoders(self, keep: int = 1) -> int:
        """Remove trailing radiance decoders (index >= ``keep``) that no vertex is bound to; returns how
        many were removed.  Used to undo an edit that added decoders."""
        removed = 0
        used = int(self.decoder_id.max()) if self.num_vertices else 0
        while len(self.rad_decoders) > max(1, keep) and len(self.rad_decoders) - 1 > used:
            del self.rad_decoders[len(self.rad_decoders) - 1]
            removed += 1
        return removed

    def ensure_tex_frame(self) -> torch.Tensor:
        """The (N,3,3) texture frames, created as identities when the field has none yet."""
        if self.tex_frame is None:
            eye = torch.eye(3, device=self.geo_codes.device)
            self.tex_frame = eye.expand(self.num_vertices, 3, 3).clone()
        return self.tex_frame

    def compact_tex_frame(self) -> bool:
        """Drop the texture frames when every one is exactly the identity (the field then decodes as a
        trained field does, at no extra cost).  Returns True when the field has none afterwards."""
        if self.tex_frame is not None:
            eye = torch.eye(3, device=self.tex_frame.device)
            if bool((self.tex_frame == eye).all()):
                self.tex_frame = None
        return self.tex_frame is None

    def _code_frame(self, vid: torch.Tensor, d: torch.Tensor):
        """View directions ``d`` (...,3) (world, current pose) and rest normals of vertices ``vid`` (...,),
        both in the frame of each vertex's texture code (rest frame, then :attr:`tex_frame`)."""
        d = self.scaffold.rest_dirs(vid, d)
        n = take_rows(self.rest_normals, vid)
        if self.tex_frame is not None:
            Q = take_rows(self.tex_frame, vid)
            d = (Q * d[..., None, :]).sum(-1)
            n = (Q * n[..., None, :]).sum(-1)
        return d, n

    def _decode_rgb_rows(self, rad_in: list, vid: torch.Tensor) -> torch.Tensor:
        """Radiance decoder output (pre-sigmoid) for rows whose texture codes belong to vertices ``vid``
        (post-interpolation: each row with its own vertex's decoder).  ``rad_in``: the input's column
        blocks (:func:`run_decoder`)."""
        if len(self.rad_decoders) == 1:
            return run_decoder(self.rad_decoders[0], rad_in)
        dec = take_rows(self.decoder_id, vid).long()
        if len(dec) == 0:
            return rad_in[0].new_zeros(0, 3)
        lo, hi = int(dec.min()), int(dec.max())
        if lo == hi:   # every row on one decoder (most chunks of an edited field): no grouping
            return run_decoder(self.rad_decoders[lo], rad_in)
        out = None
        for d in torch.unique(dec).tolist():
            rows = (dec == d).nonzero().squeeze(1)
            y = run_decoder(self.rad_decoders[d], [p.index_select(0, rows) for p in rad_in])
            if out is None:
                out = y.new_zeros(len(dec), y.shape[1])
            out = out.index_copy(0, rows, y)
        return out if out is not None else rad_in[0].new_zeros(0, 3)

    def _p_encoding(self, p: torch.Tensor) -> torch.Tensor:
        return frequency_encoding(p / self.config.radius, self.config.pos_freqs)

    def decode(self, nb: Neighbourhood, dirs: Optional[torch.Tensor] = None, with_rgb: bool = True,
               with_sigma: bool = True):
        """Decode samples: returns (sigma (M,) or None, rgb (M,3) or None, mod (M,3) or None).

        ``dirs`` (M,3) are unit ray directions (towards the scene), needed for rgb.
        """
        if self.config.interpolation == "early":
            return self._decode_early(nb, dirs, with_rgb, with_sigma)
        m, k = nb.idx.shape
        n_valid = int(nb.valid.sum())
        if n_valid >= 0.85 * m * k:
            # dense: decode every slot (invalid ones carry w=0), reduce with a reshape-sum
            vid, wk, pk = nb.idx.reshape(-1), nb.w.reshape(-1), nb.p.reshape(-1)
            sample = None
        else:
            flat = nb.valid.reshape(-1).nonzero().squeeze(1)
            vid, wk, pk = nb.idx.reshape(-1)[flat], nb.w.reshape(-1)[flat], nb.p.reshape(-1)[flat]
            sample = torch.div(flat, k, rounding_mode="floor")

        def reduce(values):  # sum_k w_k * values_k per sample
            wv = wk[:, None] * values
            if sample is None:
                return wv.view(m, k, -1).sum(1)
            return torch.zeros(m, wv.shape[1], device=wv.device, dtype=wv.dtype).index_add(0, sample, wv)

        pe = self._p_encoding(pk)
        sigma = None
        if with_sigma:
            geo_in = [self.codes(("geo",), vid)[0], pe, wk[:, None]]
            sigma = reduce(trunc_exp(run_decoder(self.geo_decoder, geo_in))).squeeze(-1)
        if not with_rgb:
            return sigma, None, None
        if self.to_rest is None and self.tex_frame is None and not torch.is_grad_enabled():
            # every neighbour of a sample sees the same direction: encode it once per sample (the SH
            # of each row, below, is the reference; the same values)
            sh_s = sh_encoding(dirs, self.config.sh_degree)
            sh = sh_s[:, None, :].expand(m, k, -1).reshape(m * k, -1) if sample is None else take_rows(sh_s, sample)
            n = take_rows(self.rest_normals, vid)
        else:
            d = dirs[:, None, :].expand(m, k, 3).reshape(-1, 3) if sample is None else dirs[sample]
            d, n = self._code_frame(vid, d)
            sh = sh_encoding(d, self.config.sh_degree)
        rad_in = [self.codes(("tex",), vid)[0], pe, wk[:, None], sh, n]
        mod_k = self.rows(self.mod_colours, vid)
        c_k = torch.sigmoid(self._decode_rgb_rows(rad_in, vid)) + mod_k
        return sigma, reduce(c_k), reduce(mod_k)

    def _decode_early(self, nb: Neighbourhood, dirs, with_rgb: bool, with_sigma: bool):
        w = nb.w[..., None]
        wb = nb.w[:, None, :]     # (M,1,K): w-weighted sums over the neighbours as batched products

        def wsum(rows):           # (M,K,C) -> (M,C)
            return torch.bmm(wb, rows).squeeze(1)

        # without autograd and coarse code levels, sum_k w_k table[idx_k] is one embedding bag: no (M,K,C)
        # gather (several times faster on the CPU; the reference is the gather-and-sum)
        bag = not torch.is_grad_enabled() and self._code_prior is None

        def wsum_rows(table):     # sum_k w_k table[idx_k] -> (M,C)
            if bag:
                return F.embedding_bag(nb.idx, table, per_sample_weights=nb.w, mode="sum")
            return wsum(self.rows(table, nb.idx))

        def code_sum(name):       # sum_k w_k codes_k (with the coarse levels, when attached)
            return wsum_rows(self.code_table(name)) if bag else wsum(codes[name])

        p = (nb.p * nb.w).sum(1)
        wi = (nb.w * nb.w).sum(1)
        pe = self._p_encoding(p)
        names = (("geo",) if with_sigma else ()) + (("tex",) if with_rgb else ())
        codes = {} if bag else dict(zip(names, self.codes(names, nb.idx)))
        sigma = None
        if with_sigma:
            geo = code_sum("geo")
            sigma = trunc_exp(run_decoder(self.geo_decoder, [geo, pe, wi[:, None]]).squeeze(-1))
            sigma = torch.where(nb.valid.any(1), sigma, torch.zeros_like(sigma))
        if not with_rgb:
            return sigma, None, None
        if self.tex_frame is None:
            n = wsum_rows(self.rest_normals)
            if self.to_rest is None:
                d = dirs
            else:   # sum_k w_k R_k d = (sum_k w_k R_k) d: one weighted sum of the (N,9) rotations
                r = wsum_rows(self.to_rest.reshape(-1, 9)).view(-1, 3, 3)
                d = torch.bmm(r, dirs[:, :, None]).squeeze(-1)
                d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        else:   # each neighbour's normal and view direction in its code frame, then w-weighted means
            dk, nk = self._code_frame(nb.idx, dirs[:, None, :].expand(-1, nb.idx.shape[1], 3))
            n = (nk * w).sum(1)
            d = (dk * w).sum(1)
            d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        mod = wsum_rows(self.mod_colours)
        shared = [pe, wi[:, None], sh_encoding(d, self.config.sh_degree), n]   # column blocks
        single = 0 if len(self.rad_decoders) == 1 else self._single_decoder(nb)
        if single is not None:   # one decoder for every neighbour: decode the interpolated code once
            tex = code_sum("tex")
            rgb = torch.sigmoid(run_decoder(self.rad_decoders[single], [tex] + shared)) + mod
        else:
            tex_k = take_rows(self.tex_codes, nb.idx) if bag else codes["tex"]
            rgb = self._early_rgb_by_decoder(nb, tex_k, shared) + mod
        return sigma, rgb, mod

    def _single_decoder(self, nb: Neighbourhood) -> Optional[int]:
        """The decoder every valid neighbour of every sample is bound to, or None when they differ."""
        dec = take_rows(self.decoder_id, nb.idx)
        if not bool(nb.valid.any()):
            return 0
        lo = int(torch.where(nb.valid, dec, dec.new_full((), torch.iinfo(dec.dtype).max)).min())
        hi = int(torch.where(nb.valid, dec, dec.new_full((), -1)).max())
        return lo if lo == hi else None

    def _early_rgb_by_decoder(self, nb: Neighbourhood, tex_k: torch.Tensor, shared: list):
        """Early interpolation over several decoders: sum_d W_d sigmoid(dec_d(codes of group d, h))."""
        dec = take_rows(self.decoder_id, nb.idx).long()
        rgb = shared[0].new_zeros(shared[0].shape[0], 3)
        for d in torch.unique(dec[nb.valid]).tolist():
            wd = torch.where((dec == d) & nb.valid, nb.w, torch.zeros_like(nb.w))   # (M,K)
            W = wd.sum(1)
            rows = (W > 0).nonzero().squeeze(1)
            wn = wd[rows] / W[rows, None]
            tex = (tex_k[rows] * wn[..., None]).sum(1)
            c = torch.sigmoid(run_decoder(self.rad_decoders[d], [tex] + [p.index_select(0, rows) for p in shared]))
            rgb = rgb.index_add(0, rows, W[rows, None] * c)
        return rgb

    def query(self, x: torch.Tensor, dirs: Optional[torch.Tensor] = None, with_rgb: bool = True):
        """Convenience: neighbourhood + decode for world points x (M,3)."""
        return self.decode(self.neighbourhood(x), dirs, with_rgb)

    def sigma_fn(self, x: torch.Tensor):
        """Density callback for the marcher: returns (sigma, neighbourhood)."""
        nb = self.neighbourhood(x)
        sigma, _, _ = self.decode(nb, None, with_rgb=False)
        return sigma, nb
