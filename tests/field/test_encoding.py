"""The decoders' input encodings: the no-autograd form (written column by column into one output)
against the autograd form (torch.cat / torch.stack), which is the reference."""
import pytest
import torch

from neumesh_core.field.encoding import frequency_encoding, sh_encoding


@pytest.mark.parametrize("shape", [(50,), (7, 4), (0,)])
def test_frequency_encoding_forms_agree(shape):
    x = torch.randn(*shape, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        fast = frequency_encoding(x, 4)
    ref = frequency_encoding(x.clone().requires_grad_(), 4).detach()
    assert fast.shape == (*shape, 9) and torch.equal(fast, ref)
    assert torch.equal(fast[..., 0], x) and torch.allclose(fast[..., 1], torch.sin(torch.pi * x))
    assert frequency_encoding(x, 0).shape == (*shape, 1)


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
def test_sh_encoding_forms_agree(degree):
    d = torch.nn.functional.normalize(torch.randn(6, 5, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
    with torch.no_grad():
        fast = sh_encoding(d, degree)
    ref = sh_encoding(d.clone().requires_grad_(), degree).detach()
    assert fast.shape == (6, 5, degree ** 2) and torch.equal(fast, ref)
    # orthonormal real SH: the squares of one band sum to (2l+1)/(4 pi) on the unit sphere
    band = fast[..., (degree - 1) ** 2:degree ** 2].pow(2).sum(-1)
    assert torch.allclose(band, torch.full_like(band, (2 * degree - 1) / (4 * torch.pi)), atol=1e-5)
