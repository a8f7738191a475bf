import torch

from neumesh_core.render.volume import composite, composite_reference


def _random_packed(n_rays=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, 12, (n_rays,), generator=g)
    ray = torch.repeat_interleave(torch.arange(n_rays), counts)
    ts, te = [], []
    for c in counts.tolist():
        t = torch.sort(torch.rand(c, generator=g) * 4).values
        ts.append(t)
        te.append(t + 0.05)
    ts, te = torch.cat(ts), torch.cat(te)
    sigma = torch.rand(len(ray), generator=g) * 30
    rgb = torch.rand(len(ray), 3, generator=g)
    return ray, ts, te, sigma, rgb, n_rays


def test_composite_matches_reference():
    ray, ts, te, sigma, rgb, n = _random_packed()
    out = composite(ray, ts, te, sigma, {"rgb": rgb}, n)
    ref = composite_reference(ray, ts, te, sigma, {"rgb": rgb}, n)
    for k in ("opacity", "depth", "rgb"):
        assert torch.allclose(out[k], ref[k], atol=1e-5), k
    assert (out["opacity"] <= 1 + 1e-6).all()


def test_composite_gradients_flow_to_sigma_and_colour():
    ray, ts, te, sigma, rgb, n = _random_packed(seed=1)
    sigma = sigma.clone().requires_grad_(True)
    rgb = rgb.clone().requires_grad_(True)
    out = composite(ray, ts, te, sigma, {"rgb": rgb}, n)
    out["rgb"].sum().backward()
    assert sigma.grad.abs().sum() > 0 and rgb.grad.abs().sum() > 0
    # numeric check on one sigma
    i = 3
    eps = 1e-3
    s2 = sigma.detach().clone()
    s2[i] += eps
    up = composite(ray, ts, te, s2, {"rgb": rgb.detach()}, n)["rgb"].sum()
    s2[i] -= 2 * eps
    dn = composite(ray, ts, te, s2, {"rgb": rgb.detach()}, n)["rgb"].sum()
    assert abs(float((up - dn) / (2 * eps)) - float(sigma.grad[i])) < 1e-2


def test_empty_samples():
    e = torch.zeros(0)
    out = composite(torch.zeros(0, dtype=torch.long), e, e, e, {"rgb": torch.zeros(0, 3)}, 5)
    assert out["opacity"].shape == (5,) and torch.all(out["opacity"] == 0)
