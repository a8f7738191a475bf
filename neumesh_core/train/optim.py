"""Adam that also takes row-sparse gradients (per-vertex code tables looked up with sparse grads), and a
running mean of parameters (weight averaging)."""
from __future__ import annotations

import torch


class RowSparseAdam(torch.optim.Adam):
    """``torch.optim.Adam`` whose parameters may receive sparse COO gradients (``nn.functional.embedding
    (..., sparse=True)``), which cost the rows looked up rather than a fill and an add of the whole
    table per lookup (at 1.8M vertices the dense gradients made a training step twice as slow).

    ``lazy=False`` (default): the result is exactly Adam's.  The sparse gradient is written into a kept
    dense buffer (only the rows touched in the previous step are cleared) and Adam's own fused step
    runs; rows not looked up still move by their momentum, as with dense gradients.
    ``lazy=True``: only the rows looked up are updated, moments included (as ``torch.optim.SparseAdam``),
    with bias correction by the parameter's step count.  Cheaper for huge tables; the default is exact
    Adam.

    The state has Adam's keys and shapes (``step``, ``exp_avg``, ``exp_avg_sq``), so checkpoints written
    with either optimizer resume with the other.
    """

    def __init__(self, params, lazy: bool = False, **kwargs):
        super().__init__(params, **kwargs)
        self.lazy = bool(lazy)
        self._grad_buffers: dict = {}  # param -> (dense buffer, rows written last step)

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        held = []
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for p in group["params"]:
                g = p.grad
                if g is None or not g.is_sparse:
                    continue
                held.append((p, g))
                idx, val = _summed_rows(g, p)
                if self.lazy:
                    p.grad = None
                    self._lazy_update(p, idx, val, group["lr"], beta1, beta2, group["eps"],
                                      group["weight_decay"])
                else:
                    p.grad = self._densify(p, idx, val)
        try:
            super().step()
        finally:
            for p, g in held:
                p.grad = g
        return loss

    def _densify(self, p, idx, val):
        buf, last = self._grad_buffers.get(p, (None, None))
        if buf is None or buf.shape != p.shape:
            buf = torch.zeros_like(p)
        elif last is not None:
            buf.index_fill_(0, last, 0.0)
        buf.index_copy_(0, idx, val)
        self._grad_buffers[p] = (buf, idx)
        return buf

    def _lazy_update(self, p, idx, val, lr, beta1, beta2, eps, weight_decay) -> None:
        if weight_decay:
            raise ValueError("RowSparseAdam(lazy=True): weight_decay is not supported")
        st = self.state[p]
        if len(st) == 0:
            st["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
            st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        st["step"] += 1
        if idx.numel() == 0:
            return
        m = st["exp_avg"].index_select(0, idx).mul_(beta1).add_(val, alpha=1 - beta1)
        v = st["exp_avg_sq"].index_select(0, idx).mul_(beta2).addcmul_(val, val, value=1 - beta2)
        st["exp_avg"].index_copy_(0, idx, m)
        st["exp_avg_sq"].index_copy_(0, idx, v)
        step = float(st["step"])
        bc1 = 1 - beta1 ** step
        bc2 = 1 - beta2 ** step
        denom = (v / bc2).sqrt_().add_(eps)
        p.index_copy_(0, idx, p.index_select(0, idx).addcdiv_(m, denom, value=-lr / bc1))


def _summed_rows(g: torch.Tensor, p: torch.Tensor):
    """(unique row indices, summed rows) of a row-sparse COO gradient.  Faster than Tensor.coalesce,
    and index_add_ into the full table is slow on CPU."""
    raw = g._indices()[0]
    vals = g._values().reshape(raw.numel(), -1)
    idx, inv = torch.unique(raw, return_inverse=True)
    val = torch.zeros(len(idx), vals.shape[1], dtype=vals.dtype, device=vals.device)
    if raw.numel():
        val.scatter_add_(0, inv[:, None].expand_as(vals), vals)
    return idx, val.view((len(idx),) + tuple(p.shape[1:]))


class ParameterAverage:
    """Running mean of parameters (stochastic weight averaging).

    Late in training the parameters wander around a minimum, and their mean sits nearer its centre, so
    the average renders held-out views better than the last weights (DTU scan24: docs/benchmarks.md,
    "Every full run").  (Weights of two separate runs do not average:
    they sit in different minima.)"""

    def __init__(self, params):
        self.params = [p for p in params if p.requires_grad]
        self.means = None
        self.count = 0

    @torch.no_grad()
    def update(self) -> None:
        if self.means is None:
            self.means = [p.detach().clone() for p in self.params]
        else:
            for m, p in zip(self.means, self.params):
                m.lerp_(p, 1.0 / (self.count + 1))
        self.count += 1

    @torch.no_grad()
    def apply(self) -> None:
        """Write the means into the parameters."""
        if self.means is not None:
            for m, p in zip(self.means, self.params):
                p.copy_(m)
