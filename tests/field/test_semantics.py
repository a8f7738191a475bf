"""The semantic branch of the field: absent by default (nothing changes), codes interpolated then
decoded once, composited with the colour's weights, colour untouched, carried by field files."""
import os

import numpy as np
import pytest
import torch

import neumesh_core as nm
from neumesh_core.data.cameras import pixel_rays
from neumesh_core.data.synthetic import look_at_opencv
from neumesh_core.render.renderer import render_rays

from ..conftest import textured_field

DATA = os.path.join(os.path.dirname(__file__), "data")
W = H = 24


def _camera():
    K = nm.intrinsics_from_fov(0.9, W, H)
    return K, look_at_opencv(np.array([3.2, 1.0, 1.2]))


def _with_semantics(field, dim=6, feats=5):
    field.enable_semantics(dim, feats, hidden=16)
    with torch.no_grad():
        field.sem_codes.normal_(0, 1.0)
    return field


def test_a_field_without_semantics_has_no_branch(blob_mesh):
    f = nm.create_field(blob_mesh)
    assert not f.has_semantics and f.sem_decoder is None and f.sem_codes.shape == (f.num_vertices, 0)
    assert not any(n.startswith("sem_decoder") for n, _ in f.named_parameters())
    o, d = pixel_rays(*_camera(), W, H)
    out = render_rays(f, o, d)
    assert "sem" not in out
    with pytest.raises(nm.NoSemanticsError, match="neumesh semantics"):
        render_rays(f, o, d, semantics=True)
    with pytest.raises(ValueError, match="both sem_dim and sem_features"):
        nm.FieldConfig(sem_dim=8)


@pytest.mark.parametrize("interpolation", ["post", "early"])
def test_semantics_leave_colour_bit_identical(blob_mesh, interpolation):
    f = textured_field(blob_mesh, interpolation)
    K, c2w = _camera()
    before = nm.render_camera(f, K, c2w, W, H)
    _with_semantics(f)
    plain = nm.render_camera(f, K, c2w, W, H)
    both = nm.render_camera(f, K, c2w, W, H, semantics=True)
    # bit-equal: the colour path is the same code on the same inputs in this process; semantics are
    # decoded beside it and composited into a separate output
    for a in (plain, both):
        for k in ("rgb", "opacity", "depth", "mod_colour"):
            assert np.array_equal(getattr(a, k), getattr(before, k)), k
    assert plain.sem is None and both.sem.shape == (H, W, 5) and np.isfinite(both.sem).all()
    assert np.abs(both.sem).max() > 0


def test_codes_are_interpolated_then_decoded_once(blob_mesh):
    f = _with_semantics(textured_field(blob_mesh))
    x = torch.randn(300, 3) * 0.6
    nb = f.neighbourhood(x)
    got = f.decode_semantics(nb)
    ref = torch.stack([f.sem_decoder((f.sem_codes[nb.idx[i]] * nb.w[i, :, None]).sum(0)) for i in range(len(x))])
    assert torch.allclose(got, ref, atol=1e-6)
    # vertex_semantics decodes each vertex's own code
    v = torch.tensor([0, 5, 17])
    assert torch.allclose(f.vertex_semantics(v), f.sem_decoder(f.sem_codes[v]), atol=1e-6)


def test_semantic_features_use_the_colour_weights(blob_mesh):
    """Rendered features = sum of compositing weights x decoded sample features (reference compositing)."""
    from neumesh_core.render.volume import composite_reference
    from neumesh_core.sampling.marcher import march_rays
    from neumesh_core.render.renderer import RenderSettings, default_step

    f = _with_semantics(textured_field(blob_mesh))
    o, d = pixel_rays(*_camera(), 8, 8)
    out = render_rays(f, o, d, semantics=True)
    s = march_rays(o, d, f.grid, f.sigma_fn, default_step(f, RenderSettings()))
    with torch.no_grad():
        sem = f.decode_semantics(s.aux)
    ref = composite_reference(s.ray_indices, s.t_starts, s.t_ends, s.sigmas, {"sem": sem}, len(o))
    assert torch.allclose(out["sem"], ref["sem"], atol=1e-5)
    assert torch.allclose(out["opacity"], ref["opacity"], atol=1e-5)


def test_semantics_round_trip_through_field_files(blob_mesh, tmp_path):
    f = _with_semantics(textured_field(blob_mesh))
    f.semantics_info = {"extractor": {"name": "test"}, "steps": 3}
    p = str(tmp_path / "sem.neumesh")
    nm.save_field(f, p)
    g = nm.load_field(p)
    assert g.has_semantics and g.config.sem_dim == 6 and g.config.sem_features == 5
    assert torch.equal(g.sem_codes, f.sem_codes) and g.semantics_info == f.semantics_info
    for (n1, a), (n2, b) in zip(f.sem_decoder.state_dict().items(), g.sem_decoder.state_dict().items()):
        assert n1 == n2 and torch.equal(a, b)
    K, c2w = _camera()
    a = nm.render_camera(f, K, c2w, W, H, semantics=True)
    b = nm.render_camera(g, K, c2w, W, H, semantics=True)
    assert np.allclose(a.sem, b.sem, atol=1e-6) and np.allclose(a.rgb, b.rgb, atol=1e-6)
    # a field saved without semantics loads without them (and its header has no semantics entry)
    q = str(tmp_path / "plain.neumesh")
    nm.save_field(textured_field(blob_mesh), q)
    assert not nm.load_field(q).has_semantics
    from neumesh_core.field.io import read_header

    assert "semantics" not in read_header(q)


@pytest.mark.parametrize("name", ["field_v1_post.neumesh", "field_v1_early.neumesh"])
def test_format_1_files_load_without_semantics(name):
    f = nm.load_field(os.path.join(DATA, name))
    assert not f.has_semantics and f.sem_codes.shape[1] == 0


def test_enable_semantics_validates(blob_mesh):
    f = nm.create_field(blob_mesh)
    with pytest.raises(ValueError):
        f.enable_semantics(0, 4)
    f.enable_semantics(4, 3)
    assert f.config.sem_dim == 4 and f.sem_codes.shape == (f.num_vertices, 4)
