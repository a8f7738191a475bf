"""Shared fixtures for core tests: tiny meshes and the small built-in scene (made once per session)."""
import contextlib
import os

import numpy as np
import pytest
import torch

torch.set_num_threads(max(1, os.cpu_count() or 1))

# the Triton kernels' tests (tests/kernels/) run in Triton's interpreter where torch sees
# no GPU; the variable must be set before triton is first imported by any test module
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")


@contextlib.contextmanager
def one_thread():
    """torch on one thread inside the block: small training batches run faster so, and far faster on a
    busy 2-core machine, where two threads per process spin against each other."""
    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(saved)


@pytest.fixture(scope="session")
def small_scene_dir(tmp_path_factory):
    from neumesh_core.data.synthetic import make_default_scene

    d = tmp_path_factory.mktemp("scene64")
    make_default_scene(str(d), resolution=64, n_train=30, n_val=4, n_test=4)
    return str(d)


@pytest.fixture(scope="session")
def blob_mesh():
    from neumesh_core.data.synthetic import default_mesh

    return default_mesh(subdiv=4)


def textured_field(mesh, interpolation="post", seed=0, **config):
    """An untrained field made deterministic and visibly textured: random codes, a colour per vertex
    (x>0 red, else blue) in the modification colour, dense shell."""
    from neumesh_core.field.field import FieldConfig, NeuMeshField

    torch.manual_seed(seed)
    f = NeuMeshField(mesh, FieldConfig(interpolation=interpolation, **config))
    with torch.no_grad():
        f.geo_codes.normal_(0, 0.5)
        f.tex_codes.normal_(0, 0.5)
        f.geo_decoder[-1].bias.fill_(float(np.log(8.0 / f.radius)))
        x = f.rest_vertices[:, 0]
        f.mod_colours.copy_(torch.where(x[:, None] > 0, torch.tensor([0.8, -0.3, -0.3]),
                                       torch.tensor([-0.3, -0.3, 0.8])))
    f.eval()
    return f
