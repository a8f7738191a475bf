"""RowSparseAdam against torch's Adam (the plain reference), and the field's sparse code lookups."""
import pytest
import torch

from neumesh_core.train.optim import RowSparseAdam


def _pair(n=50, d=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    init = torch.randn(n, d, generator=g)
    a = torch.nn.Parameter(init.clone())
    b = torch.nn.Parameter(init.clone())
    return a, b


@pytest.mark.parametrize("lazy,every_row", [(False, False), (False, True), (True, True)])
def test_matches_adam(lazy, every_row):
    """Exact Adam; the lazy variant only when every row is looked up at every step."""
    a, b = _pair()
    ref = torch.optim.Adam([a], lr=1e-2, betas=(0.9, 0.99), eps=1e-15)
    opt = RowSparseAdam([b], lazy=lazy, lr=1e-2, betas=(0.9, 0.99), eps=1e-15)
    g = torch.Generator().manual_seed(1)
    for _ in range(20):
        # duplicates must be summed; rows missed in a step must still move by their momentum
        head = torch.randperm(50, generator=g) if every_row else torch.randint(0, 50, (20,), generator=g)
        idx = torch.cat([head, torch.randint(0, 50, (30,), generator=g)])
        target = torch.randn(len(idx), 5, generator=g)
        for p, o, sparse in ((a, ref, False), (b, opt, True)):
            o.zero_grad(set_to_none=True)
            rows = torch.nn.functional.embedding(idx, p, sparse=sparse)
            ((rows - target) ** 2).sum().backward()
            assert p.grad.is_sparse == sparse
            o.step()
    # RowSparseAdam is Adam computed by another kernel (fused, row-sparse input), so the two agree to
    # float32 rounding, not bit for bit: a relative tolerance of ~100 ulps over 20 steps
    assert torch.allclose(a, b, rtol=1e-5, atol=1e-6)
    assert torch.allclose(ref.state[a]["exp_avg_sq"], opt.state[b]["exp_avg_sq"], rtol=1e-5, atol=1e-9)


def test_lazy_rows_not_looked_up_keep_values_and_moments():
    _, p = _pair()
    other = torch.nn.Parameter(torch.ones(3))
    opt = RowSparseAdam([{"params": [p]}, {"params": [other]}], lazy=True, lr=1e-2)
    before = p.detach().clone()
    for step in range(3):
        opt.zero_grad(set_to_none=True)
        idx = torch.tensor([1, 4, 4]) if step == 0 else torch.tensor([1])
        loss = torch.nn.functional.embedding(idx, p, sparse=True).sum() + (other ** 2).sum()
        loss.backward()
        opt.step()
    moved = (p.detach() != before).any(1)
    assert moved.nonzero().flatten().tolist() == [1, 4]
    # row 4 was looked up only at the first step: its moments stayed where that step left them
    assert float(opt.state[p]["exp_avg"][4, 0]) == pytest.approx(0.2, rel=1e-6)
    assert opt.state[p]["exp_avg"][0].abs().sum() == 0
    assert int(opt.state[p]["step"]) == 3
    assert (other.detach() < 1).all()  # the dense group took Adam's own path


def test_field_lookups_are_sparse_only_while_training(blob_mesh):
    import neumesh_core as nm

    f = nm.create_field(blob_mesh, nm.FieldConfig(interpolation="early"))
    x = torch.from_numpy(blob_mesh.vertices[:64]).float()
    d = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    grads = {}
    for sparse in (False, True):
        f.zero_grad(set_to_none=True)
        f.sparse_grads = sparse
        sigma, rgb, _ = f.query(x, d)
        (sigma.sum() + rgb.sum() + f.tv_loss(256, generator=torch.Generator().manual_seed(0))).backward()
        assert f.tex_codes.grad.is_sparse == sparse
        grads[sparse] = f.tex_codes.grad.to_dense()
    f.sparse_grads = False
    assert torch.allclose(grads[False], grads[True], atol=1e-6)


def test_parameter_average_is_the_mean_of_its_snapshots():
    from neumesh_core.train.optim import ParameterAverage

    g = torch.Generator().manual_seed(3)
    p = torch.nn.Parameter(torch.randn(20, 4, generator=g))
    frozen = torch.nn.Parameter(torch.randn(3), requires_grad=False)
    avg = ParameterAverage([p, frozen])
    snaps = []
    for _ in range(7):
        with torch.no_grad():
            p.add_(torch.randn(20, 4, generator=g))
        snaps.append(p.detach().clone())
        avg.update()
    before = frozen.detach().clone()
    avg.apply()
    assert avg.count == 7
    assert torch.allclose(p, torch.stack(snaps).mean(0), atol=1e-6)
    assert torch.equal(frozen, before)  # only trained parameters are averaged
