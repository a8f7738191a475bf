"""What the Triton kernels' tests share: the device they run on (a GPU; else Triton's interpreter on the
CPU, TRITON_INTERPRET=1, set here before triton is imported: slow, so the scenes are tiny) and a small
scene.  Importing it skips the importing test module, with the reason, where triton does not import
(install the optional extra: ``.[gpu]``) or cannot run here."""
import os
import sys

import numpy as np
import pytest
import torch

if not torch.cuda.is_available() and "triton" not in sys.modules:
    os.environ.setdefault("TRITON_INTERPRET", "1")

triton = pytest.importorskip("triton", reason="triton is not installed (pip install -e '.[gpu]')")

from neumesh_core.kernels import knn  # noqa: E402

from ..conftest import textured_field  # noqa: E402

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
if not knn.triton_runs_on(DEVICE):
    pytest.skip("triton was imported before TRITON_INTERPRET=1 could be set and there is no GPU; run "
                "this module on its own or with TRITON_INTERPRET=1", allow_module_level=True)


def scene(interpolation, deformed):
    from neumesh_core.data.synthetic import default_mesh

    field = textured_field(default_mesh(subdiv=2), interpolation, grid_resolution=32).to(DEVICE)
    if deformed:
        v = field.rest_vertices * torch.tensor([1.15, 1.0, 0.9], device=DEVICE)
        v = v + 0.2 * torch.sin(2.0 * v[:, 1:2])           # a bend: per-vertex rotations differ
        field.set_vertices(v)
        assert field.to_rest is not None
    K = np.array([[11.0, 0.0, 6.0], [0.5, 11.0, 6.0], [0.0, 0.0, 1.0]], np.float32)   # with skew
    c2w = np.eye(4)
    c2w[:3, :3] = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]) @ \
        np.array([[1.0, 0.0, 0.0], [0.0, 0.98, -0.2], [0.0, 0.2, 0.98]])
    c2w[:3, 3] = -6.0 * c2w[:3, 2]
    return field, K, c2w
