"""render_camera and render_rays (neumesh_core/render/renderer.py): supersampling, mod-colour weights."""
import numpy as np
import pytest
import torch

import neumesh_core as nm
from neumesh_core.data.cameras import intrinsics_from_fov

from ..conftest import textured_field


def _cam(w=20, h=16):
    K = intrinsics_from_fov(0.8, w, h)
    c2w = np.eye(4, dtype=np.float32)
    c2w[2, 3] = -3.5
    return K, c2w


def test_supersample_is_the_box_average_of_a_finer_render(blob_mesh):
    f = textured_field(blob_mesh)
    f.grid.refresh(lambda x: f.query(x, with_rgb=False)[0], f.radius * 0.25)
    K, c2w = _cam()
    one = nm.render_camera(f, K, c2w, 20, 16)
    # exact on purpose: supersample=1 is the default, the very same code path in the same process
    assert np.array_equal(one.rgb, nm.render_camera(f, K, c2w, 20, 16, settings=nm.RenderSettings(supersample=1)).rgb)
    ss = nm.render_camera(f, K, c2w, 20, 16, settings=nm.RenderSettings(supersample=2))
    K2 = K.copy()
    K2[:2] *= 2
    fine = nm.render_camera(f, K2, c2w, 40, 32)
    box = lambda a: a.reshape(16, 2, 20, 2, *a.shape[2:]).mean((1, 3))  # noqa: E731
    np.testing.assert_allclose(ss.rgb, box(fine.rgb), atol=1e-5)
    np.testing.assert_allclose(ss.opacity, box(fine.opacity), atol=1e-5)
    np.testing.assert_allclose(ss.mod_colour, box(fine.mod_colour), atol=1e-5)
    # the silhouette edge is anti-aliased: supersampling gives partial coverage that one ray cannot
    assert ss.n_samples > one.n_samples
    edge = (ss.opacity > 0.05) & (ss.opacity < 0.95)
    assert edge.sum() > edge.size * 0.02 and np.abs(ss.rgb - one.rgb)[edge].max() > 0.05
    # depth: opacity-weighted mean of the sub-rays; inf only where no sub-ray hits
    hit = fine.opacity > 1e-6
    assert np.all(np.isfinite(ss.depth) == (box(hit.astype(np.float32)) > 0))


@pytest.mark.parametrize("bad", [0, -1, 1.5])
def test_supersample_must_be_a_positive_whole_number(bad):
    with pytest.raises(ValueError, match="supersample"):
        nm.RenderSettings(supersample=bad)


def test_training_render_lists_the_vertices_it_looked_up(blob_mesh):
    """``vertex_ids`` are the scaffold vertices behind the samples: every code row that gets a
    gradient from the rendered colour is in it, and it is far from the whole scaffold.  Off by
    default (it costs a sort per training step)."""
    import torch

    f = textured_field(blob_mesh)
    f.grid.refresh(lambda x: f.query(x, with_rgb=False)[0], f.radius * 0.25)
    g = torch.Generator().manual_seed(0)
    o = torch.tensor([[0.0, 0.0, -3.5]]).expand(64, 3)
    d = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0]) + 0.08 * torch.randn(64, 3, generator=g), dim=-1)
    out = nm.render_rays(f, o, d, train=True, vertex_ids=True)
    (ids,) = out["vertex_ids"]
    assert len(ids) > 0 and torch.equal(ids, torch.unique(ids)) and len(ids) < f.num_vertices // 2
    out["rgb"].sum().backward()
    grad_rows = set(f.tex_codes.grad.abs().sum(1).nonzero().squeeze(1).tolist())
    assert grad_rows and grad_rows <= set(ids.tolist())
    assert "vertex_ids" not in nm.render_rays(f, o, d)
    assert "vertex_ids" not in nm.render_rays(f, o, d, train=True)


@pytest.mark.parametrize("interp", ["post", "early"])
def test_mod_colour_weights_predict_the_render_of_changed_mod_colours(blob_mesh, interp):
    """rgb(mod + delta) - rgb(mod) == W @ delta for any delta: the modification colour enters the
    render linearly (what painting solves with); one field and two fields composited jointly."""
    import copy

    from neumesh_core.render.renderer import mod_colour_weights, render_rays

    f = textured_field(blob_mesh, interp)
    g = copy.deepcopy(f)
    with torch.no_grad():
        g.scaffold.set_vertices(g.rest_vertices + torch.tensor([0.6, 0.0, 0.0]))   # a second, shifted copy
    K, c2w = _cam()
    o, d = nm.pixel_rays(K, c2w, 20, 16)
    for fields in ([f], [f, g]):
        Ws = mod_colour_weights(fields, o, d)
        before = render_rays(fields, o, d)["rgb"].numpy()
        gen = torch.Generator().manual_seed(1)
        deltas = [0.3 * torch.randn(x.num_vertices, 3, generator=gen) for x in fields]
        with torch.no_grad():
            for x, dl in zip(fields, deltas):
                x.mod_colours.add_(dl)
        after = render_rays(fields, o, d)["rgb"].numpy()
        with torch.no_grad():
            for x, dl in zip(fields, deltas):
                x.mod_colours.sub_(dl)
        pred = sum(W @ dl.numpy() for W, dl in zip(Ws, deltas))
        assert np.abs(after - before).max() > 0.05
        assert np.allclose(after - before, pred, atol=1e-5)


@pytest.mark.parametrize("interp", ["post", "early"])
def test_skipping_empty_pixels_and_distances_renders_the_same_image(blob_mesh, interp):
    """RenderSettings.skip_empty (per-pixel ray ranges from the occupancy grid, empty pixels not
    marched) against marching every pixel through the whole box: the same samples, so the same image
    up to float summation order; also supersampled, with a holdout in front, and for two fields."""
    f = textured_field(blob_mesh, interpolation=interp)
    f.grid.refresh(lambda x: f.query(x, with_rgb=False)[0], f.radius * 0.25)
    g = textured_field(blob_mesh, interpolation=interp, seed=1)
    g.set_vertices(g.rest_vertices + torch.tensor([0.9, 0.2, 0.0]))
    K, c2w = _cam(40, 32)
    c2w[2, 3] = -6.0    # the object in the middle, empty tiles around it
    near, far_r = f.grid.camera_ranges(K, c2w, 40, 32, 2)
    assert 0.3 < float((near <= far_r).float().mean()) < 0.9
    far = np.full((32, 40), np.inf, np.float32)
    far[:, :20] = 5.9   # a holdout cutting the left of the field
    cases = [dict(fields=f), dict(fields=f, settings=dict(supersample=2)), dict(fields=f, far=far),
             dict(fields=[f, g], background=None)]
    for case in cases:
        kw = {k: v for k, v in case.items() if k not in ("fields", "settings")}
        outs = [nm.render_camera(case["fields"], K, c2w, 40, 32, **kw, settings=nm.RenderSettings(
                    skip_empty=skip, empty_tile=2, **case.get("settings", {}))) for skip in (False, True)]
        a, b = outs
        assert a.opacity.max() > 0.5 and (a.opacity < 1e-6).mean() > 0.1, case   # object and empty pixels
        np.testing.assert_allclose(b.rgb, a.rgb, atol=1e-5)
        np.testing.assert_allclose(b.opacity, a.opacity, atol=1e-5)
        np.testing.assert_allclose(b.mod_colour, a.mod_colour, atol=1e-5)
        assert np.array_equal(np.isinf(a.depth), np.isinf(b.depth))
        fin = np.isfinite(a.depth)
        np.testing.assert_allclose(b.depth[fin], a.depth[fin], rtol=1e-4)
        assert abs(a.n_samples - b.n_samples) <= 2


def test_skip_empty_reports_progress_and_cancels(blob_mesh):
    f = textured_field(blob_mesh)
    K, c2w = _cam()
    seen = []
    nm.render_camera(f, K, c2w, 20, 16, progress=lambda x: seen.append(x),
                     settings=nm.RenderSettings(chunk_rays=37))
    assert len(seen) > 2 and seen == sorted(seen) and seen[-1] == pytest.approx(1.0)
    with pytest.raises(nm.Cancelled):
        nm.render_camera(f, K, c2w, 20, 16, progress=lambda x: False, settings=nm.RenderSettings(chunk_rays=37))


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA GPU (run on a GPU machine)"))])
def test_to_host_returns_each_plane_contiguous_and_exact(device):
    from neumesh_core.render.renderer import to_host

    g = torch.Generator().manual_seed(0)
    planes = [torch.rand(6, 3, generator=g), torch.rand(6, generator=g),
              torch.full((6,), float("inf")), torch.rand(6, 5, generator=g)]
    out = to_host([p.to(device) for p in planes])
    assert [o.shape for o in out] == [tuple(p.shape) for p in planes]
    for o, p in zip(out, planes):
        assert o.flags["C_CONTIGUOUS"] and o.dtype == np.float32
        assert np.array_equal(o, p.numpy())   # a copy, no arithmetic: exact


def test_tile_order_groups_pixels_into_screen_patches():
    from neumesh_core.render.renderer import tile_order

    w, h = 20, 9
    every = torch.arange(w * h)
    seq = tile_order(every, w)
    assert torch.equal(torch.sort(seq).values, every)             # a permutation
    first = seq[:32]                                              # the first block: the 8 x 4 top-left patch
    assert set((first % w).tolist()) == set(range(8)) and set((first // w).tolist()) == set(range(4))
    assert seq[32].item() == 8                                    # then the next patch along the row
    some = every[(every % 3) != 0]                                # a compacted list keeps its pixels
    assert torch.equal(torch.sort(tile_order(some, w)).values, some)
