"""Per-vertex radiance-decoder binding: each neighbour is decoded by its own vertex's decoder
(post-interpolation); early interpolation decodes each decoder's group of neighbours once and blends
the groups by their total weight.  Both are compared with plain per-sample references."""
import copy

import pytest
import torch

from neumesh_core.field.encoding import frequency_encoding, sh_encoding

from ..conftest import textured_field


def _two_decoder_field(mesh, interpolation, seed=3):
    f = textured_field(mesh, interpolation)
    other = copy.deepcopy(f.rad_decoder)
    with torch.no_grad():
        for p in other.parameters():
            p.normal_(0, 0.5, generator=torch.Generator().manual_seed(seed))
    assert f.add_decoder(other) == 1
    with torch.no_grad():   # bind the vertices with y > 0 to the second decoder
        f.decoder_id.copy_((f.rest_vertices[:, 1] > 0).to(f.decoder_id.dtype))
    return f


def _samples(f, n=300, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = f.rest_vertices[torch.randint(0, f.num_vertices, (n,), generator=g)]
    x = x + 0.3 * f.radius * torch.randn(n, 3, generator=g)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    return x, d


def test_post_interpolation_decodes_each_neighbour_with_its_vertex_decoder(blob_mesh):
    f = _two_decoder_field(blob_mesh, "post")
    x, d = _samples(f)
    nb = f.neighbourhood(x)
    _, rgb, _ = f.decode(nb, d)
    ids = f.decoder_id.long()
    mixed = 0
    for m in range(len(x)):
        ref = torch.zeros(3)
        dec_seen = set()
        for k in range(f.config.k):
            if not nb.valid[m, k]:
                continue
            i = nb.idx[m, k]
            dec_seen.add(int(ids[i]))
            pe = frequency_encoding(nb.p[m, k:k + 1] / f.radius, f.config.pos_freqs)[0]
            inp = torch.cat([f.tex_codes[i], pe, nb.w[m, k:k + 1], sh_encoding(d[m], f.config.sh_degree),
                             f.rest_normals[i]])
            ref = ref + nb.w[m, k] * (torch.sigmoid(f.rad_decoders[int(ids[i])](inp)) + f.mod_colours[i])
        mixed += len(dec_seen) > 1
        assert torch.allclose(rgb[m], ref, atol=1e-5), m
    assert mixed > 10  # the test covers samples whose neighbours use both decoders


def test_early_interpolation_never_mixes_codes_of_different_decoders(blob_mesh):
    f = _two_decoder_field(blob_mesh, "early")
    x, d = _samples(f)
    nb = f.neighbourhood(x)
    _, rgb, mod = f.decode(nb, d)
    ids = f.decoder_id.long()
    mixed = 0
    for m in range(len(x)):
        if not nb.valid[m].any():
            continue
        w = nb.w[m]
        p = (nb.p[m] * w).sum()
        shared = torch.cat([frequency_encoding(p[None] / f.radius, f.config.pos_freqs)[0], (w * w).sum()[None],
                            sh_encoding(d[m], f.config.sh_degree)])
        n = torch.nn.functional.normalize((f.rest_normals[nb.idx[m]] * w[:, None]).sum(0), dim=0)
        ref = (f.mod_colours[nb.idx[m]] * w[:, None]).sum(0)
        groups = {int(ids[nb.idx[m, k]]) for k in range(f.config.k) if nb.valid[m, k]}
        mixed += len(groups) > 1
        for dec in groups:
            sel = torch.tensor([bool(nb.valid[m, k]) and int(ids[nb.idx[m, k]]) == dec for k in range(f.config.k)])
            W = w[sel].sum()
            tex = (f.tex_codes[nb.idx[m][sel]] * (w[sel] / W)[:, None]).sum(0)
            ref = ref + W * torch.sigmoid(f.rad_decoders[dec](torch.cat([tex, shared, n])))
        assert torch.allclose(rgb[m], ref, atol=1e-5), m
    assert mixed > 10


@pytest.mark.parametrize("interp", ["post", "early"])
def test_vertices_bound_to_a_copy_render_like_the_original(blob_mesh, interp):
    """Binding vertices to a bit-identical copy of decoder 0 changes nothing (up to rounding) where the
    decoding is per vertex: every sample with post-interpolation, and with early interpolation the
    samples whose neighbours share one decoder.  (Early interpolation decodes a mixed sample once per
    group, which is not the decoding of the blended code; ``add_decoder`` never adds a copy of a
    decoder the field has, so this mix only happens between different decoders.)"""
    f = textured_field(blob_mesh, interp)
    x, d = _samples(f)
    _, rgb0, _ = f.query(x, d)
    f.rad_decoders.append(copy.deepcopy(f.rad_decoder))   # a copy (add_decoder would reuse decoder 0)
    with torch.no_grad():
        f.decoder_id.copy_((f.rest_vertices[:, 2] > 0).to(f.decoder_id.dtype))
    _, rgb1, _ = f.query(x, d)
    if interp == "post":
        assert torch.allclose(rgb0, rgb1, atol=2e-6)
    else:
        nb = f.neighbourhood(x)
        ids = f.decoder_id.long()[nb.idx]
        pure = ((ids == ids[:, :1]) | ~nb.valid).all(1)
        assert pure.sum() > 100 and (~pure).sum() > 10
        assert torch.allclose(rgb0[pure], rgb1[pure], atol=2e-6)


@pytest.mark.parametrize("interp", ["post", "early"])
def test_a_region_bound_wholly_to_another_decoder_renders_with_it(blob_mesh, interp):
    """All vertices on decoder 1 render as a single-decoder field whose decoder is decoder 1."""
    f = _two_decoder_field(blob_mesh, interp)
    with torch.no_grad():
        f.decoder_id.fill_(1)
    x, d = _samples(f)
    _, rgb, _ = f.query(x, d)
    g = copy.deepcopy(f)
    g.rad_decoders = torch.nn.ModuleList([f.rad_decoders[1]])
    with torch.no_grad():
        g.decoder_id.zero_()
    _, ref, _ = g.query(x, d)
    assert torch.allclose(rgb, ref, atol=2e-6)


def test_add_decoder_adds_each_distinct_decoder_once(blob_mesh):
    f = textured_field(blob_mesh)
    assert f.add_decoder(f.rad_decoder) == 0
    assert f.add_decoder(copy.deepcopy(f.rad_decoder)) == 0   # bit-identical weights: the same decoder
    other = copy.deepcopy(f.rad_decoder)
    with torch.no_grad():
        other[0].bias.add_(0.1)
    assert f.add_decoder(other) == 1 and f.add_decoder(copy.deepcopy(other)) == 1 and f.num_decoders == 2
    assert not any(p.requires_grad for p in f.rad_decoders[1].parameters())  # bound decoders are frozen
    assert f.drop_unused_decoders() == 1 and f.num_decoders == 1          # no vertex used it


@pytest.mark.parametrize("interp", ["post", "early"])
def test_codes_bound_to_several_decoders_still_train(blob_mesh, interp):
    f = _two_decoder_field(blob_mesh, interp)
    x, d = _samples(f, 64)
    _, rgb, _ = f.query(x, d)
    rgb.sum().backward()
    g = f.tex_codes.grad.abs().sum(1)
    on1 = f.decoder_id.bool()
    assert g[on1].sum() > 0 and g[~on1].sum() > 0
