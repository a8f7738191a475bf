"""Background model of real captures: frame and box, compositing, training without masks, no seam at the box,
save/load.  The scene is the built-in blob in a textured room, rendered without masks."""
import numpy as np
import pytest
import torch

from neumesh_core.data.frame import ObjectBox, focus_point, object_box, parse_box, scene_frame
from neumesh_core.field.background import (BackgroundModel, attach_background, background_for, background_of,
                                           bilinear_reference, contract, fit_background_for, plane_features)
from neumesh_core.render.renderer import RenderSettings, render_camera, render_rays
from tests.conftest import one_thread, textured_field


@pytest.fixture(scope="module")
def room():
    from neumesh_core.data.synthetic.room import make_room_scene

    with one_thread():
        return make_room_scene(resolution=40, n_train=20, n_val=2)


def _with_background(mesh, scene, plain=False, **kw):
    from neumesh_core.field.field import FieldConfig, create_field

    f = create_field(mesh, FieldConfig()) if plain else textured_field(mesh)
    cams = scene.split("train").cameras
    box = object_box(cams.c2w)
    f.object_box = box
    attach_background(f, background_for(cams.c2w, box, resolution=kw.pop("resolution", 24), **kw))
    return f


def test_frame_and_box_from_cameras(room):
    scene, _ = room
    c2w = scene.split("train").cameras.c2w
    assert np.allclose(focus_point(c2w), 0, atol=1e-3)          # every camera looks at the origin
    fr = scene_frame(c2w)
    assert fr.radius == pytest.approx(4.0, rel=1e-3)
    box = object_box(c2w)
    assert np.allclose(box.centre, 0, atol=1e-3) and np.allclose(box.half_extents, 1.2, rtol=1e-3)
    # with sparse points: the points near the focus point, robust to a far outlier cloud
    rng = np.random.default_rng(0)
    obj = rng.uniform(-0.5, 0.5, (400, 3)) + [0.2, 0, 0]
    wall = rng.uniform(-1, 1, (400, 3)) * [0.1, 5, 5] + [9, 0, 0]
    b = object_box(c2w, np.concatenate([obj, wall]))
    assert b.contains(obj).mean() > 0.95 and not b.contains(wall).any()
    assert np.allclose(b.centre, [0.2, 0, 0], atol=0.05)
    assert parse_box("1,2,3,0.5,0.5,1").aabb().tolist() == [[0.5, 1.5, 2], [1.5, 2.5, 4]]
    with pytest.raises(ValueError, match="six numbers"):
        parse_box("1,2,3")
    with pytest.raises(ValueError, match="> 0"):
        ObjectBox([0, 0, 0], [1, 0, 1])


def test_contract_bounds():
    y = torch.randn(1000, 3) * 50
    z = contract(y)
    assert float(z.norm(dim=-1).max()) < 2.0
    inner = y.norm(dim=-1) <= 1
    assert torch.allclose(z[inner], y[inner])


def test_plane_features_match_the_reference():
    """K-Planes' grid_sample reads equal explicit bilinear corner gathers, multiplied over the three
    planes of each scale (xy, xz, yz)."""
    g = torch.Generator().manual_seed(0)
    planes = [torch.rand(1, 3, n, n, generator=g) for n in (5, 5, 5, 9, 9, 9)]
    z = torch.rand(200, 3, generator=g) * 2 - 1
    z[:4] = torch.tensor([[-1.0, -1, -1], [1, 1, 1], [1, -1, 0.3], [0, 0, 0]])   # the corners and middle
    got = plane_features(z, planes)
    want = []
    for k in (0, 3):
        f = 1
        for (a, b), pl in zip(((0, 1), (0, 2), (1, 2)), planes[k:k + 3]):
            f = f * bilinear_reference(z[:, (a, b)], pl[0])
        want.append(f)
    assert got.shape == (200, 6)
    assert torch.allclose(got, torch.cat(want, -1), atol=1e-5)
    # and the reference itself hits the texels at the corners
    assert torch.allclose(bilinear_reference(torch.tensor([[-1.0, -1.0], [1.0, -1.0]]), planes[0][0]),
                          planes[0][0][:, 0, [0, -1]].t())


def test_fit_background_frames_the_box(room):
    scene, _ = room
    c2w = scene.split("train").cameras.c2w
    box = object_box(c2w)
    m = fit_background_for(c2w, box)
    assert m.planes and m.radius == pytest.approx(2 * box.half_extents.max())
    # an older header (no planes) is the dense grid it was
    old = {k: v for k, v in m.config().items() if k not in ("planes", "plane_features")}
    assert BackgroundModel.from_config(old).planes == () and hasattr(BackgroundModel.from_config(old), "grid")
    with pytest.raises(ValueError, match="plane"):
        BackgroundModel([0, 0, 0], 1.0, planes=(1,))


@pytest.mark.parametrize("planes", [(), (8, 16)])
def test_compositing_alpha_is_the_fields_opacity(blob_mesh, room, planes):
    """Background off: the object alone, alpha = the mesh field's opacity; on: the frame is
    rgb_field + (1 - opacity) * rgb_background, covering every pixel."""
    scene, _ = room
    f = _with_background(blob_mesh, scene, planes=planes)
    cam = scene.split("val").cameras
    K, c2w, W, H = cam.K[0], cam.c2w[0], cam.width, cam.height
    with one_thread():
        on = render_camera(f, K, c2w, W, H, background=(0, 0, 0))
        off = render_camera(f, K, c2w, W, H, background=(0, 0, 0), settings=RenderSettings(background_model=False))
        bgm = background_of(f)
        attach_background(f, None)
        plain = render_camera(f, K, c2w, W, H, background=(0, 0, 0))
        # the background alone, per pixel, as the renderer composites it
        from neumesh_core.data.cameras import pixel_rays

        o, d = pixel_rays(K, c2w, W, H)
        with torch.no_grad():
            bg_rgb, bg_op = bgm(o, d)
    assert off.background_opacity is None and plain.background_opacity is None
    np.testing.assert_allclose(off.opacity, plain.opacity, atol=1e-6)
    np.testing.assert_allclose(off.rgb, plain.rgb, atol=1e-6)
    np.testing.assert_allclose(on.opacity, off.opacity, atol=1e-6)     # the object's alpha is unchanged
    assert 0.05 < off.opacity.mean() < 0.95
    a = off.opacity[..., None]
    want = off.rgb + (1 - a) * bg_rgb.numpy().reshape(H, W, 3)
    np.testing.assert_allclose(on.rgb, want, atol=1e-5)
    np.testing.assert_allclose(on.alpha, 1.0, atol=1e-5)                 # the background is opaque
    assert np.allclose(bg_op.numpy(), 1.0, atol=1e-6)
    assert on.rgba()[..., 3].min() > 0.999 and np.allclose(off.rgba()[..., 3], np.clip(off.opacity, 0, 1))


def test_render_rays_reference_per_ray(blob_mesh, room):
    """render_rays with a background model equals the field's own render plus the background per ray."""
    scene, _ = room
    f = _with_background(blob_mesh, scene)
    bgm = background_of(f)
    g = torch.Generator().manual_seed(0)
    o = torch.tensor([[4.0, 0.3, 0.2]]).expand(64, 3).clone()
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=g) * 0.3 + torch.tensor([-1.0, 0, 0]), dim=-1)
    with one_thread(), torch.no_grad():
        a = render_rays(f, o, d, background=(0.2, 0.4, 0.6), background_model=bgm)
        b = render_rays(f, o, d, background=None)
        c, op = bgm(o, d)
        # the background model's own sum, sample by sample (a loop reference of its compositing)
        t0 = bgm.ray_start(o, d)
        assert (t0 > 0).all()
    wall = torch.tensor([0.2, 0.4, 0.6])
    exp = b["rgb"] + (1 - b["opacity"])[:, None] * c + ((1 - b["opacity"]) * (1 - op))[:, None] * wall
    assert torch.allclose(a["rgb"], exp, atol=1e-6)
    assert torch.allclose(a["opacity"], b["opacity"])
    # rays through the box start the background where they leave it
    box = f.object_box
    hit = torch.tensor([[4.0, 0, 0]]), torch.tensor([[-1.0, 0, 0]])
    assert float(bgm.ray_start(*hit)) == pytest.approx(4.0 + box.half_extents[0], rel=1e-5)


def test_far_cuts_the_background(blob_mesh, room):
    scene, _ = room
    bgm = background_of(_with_background(blob_mesh, scene))
    o = torch.tensor([[4.0, 0, 0]]).repeat(8, 1)
    d = torch.nn.functional.normalize(torch.tensor([[-1.0, 0.8, 0.1]]).repeat(8, 1), dim=-1)
    with torch.no_grad():
        _, op = bgm(o, d, far=torch.full((8,), 1e-3))
    assert torch.allclose(op, torch.zeros(8))


@pytest.mark.parametrize("planes", [(), (8, 16)])
def test_save_load_round_trip(tmp_path, blob_mesh, room, planes):
    import neumesh_core as nm

    scene, _ = room
    f = _with_background(blob_mesh, scene, planes=planes)
    with torch.no_grad():
        for p in background_of(f).parameters():
            p.normal_(0, 0.5)
    p = tmp_path / "f.neumesh"
    nm.save_field(f, str(p))
    g = nm.load_field(str(p))
    assert np.allclose(g.object_box.centre, f.object_box.centre)
    bg_f, bg_g = background_of(f), background_of(g)
    assert bg_g is not None and bg_g.config() == bg_f.config()
    for (n1, a), (n2, b) in zip(bg_f.state_dict().items(), bg_g.state_dict().items()):
        assert n1 == n2 and torch.allclose(a, b)
    cam = scene.split("val").cameras
    with one_thread():
        r1 = render_camera(f, cam.K[0], cam.c2w[0], cam.width, cam.height)
        r2 = render_camera(g, cam.K[0], cam.c2w[0], cam.width, cam.height)
    np.testing.assert_allclose(r1.rgb, r2.rgb, atol=1e-5)
    # a field without background saves and loads without one (and without a box)
    attach_background(f, None)
    del f.object_box
    nm.save_field(f, str(p))
    h = nm.load_field(str(p))
    assert background_of(h) is None and getattr(h, "object_box", None) is None
    header = nm.field.io.read_header(str(p)) if hasattr(nm, "field") else None
    assert header is None or "background" not in header


def test_old_files_load_without_background():
    import os

    from neumesh_core.field.io import load_field

    here = os.path.join(os.path.dirname(__file__), "data", "field_v1_post.neumesh")
    f = load_field(here)
    assert background_of(f) is None and getattr(f, "object_box", None) is None


def test_deformation_leaves_the_background(blob_mesh, room):
    scene, _ = room
    f = _with_background(blob_mesh, scene)
    bgm = background_of(f)
    before = {k: v.clone() for k, v in bgm.state_dict().items()}
    f.set_vertices(f.rest_vertices.numpy() * 1.1 + 0.05)
    assert background_of(f) is bgm
    assert all(torch.equal(before[k], v) for k, v in bgm.state_dict().items())


@pytest.mark.parametrize("planes", [(), (32, 64)])
def test_training_without_masks_keeps_the_object_in_the_box(blob_mesh, room, planes):
    """Trained on full frames (no masks), the field renders its object inside the box (its alpha
    matches the true silhouette) and the background model the room (better full-frame PSNR than off),
    with the dense grid and with the K-Planes background."""
    from neumesh_core import metrics
    from neumesh_core.train.trainer import TrainConfig, train

    scene, alphas = room
    assert not scene.has_masks
    f = _with_background(blob_mesh, scene, plain=True, resolution=32, planes=planes)
    with one_thread():
        res = train(f, scene, TrainConfig(steps=300, rays_per_batch=1024, log_every=100, seed=0))
    assert res.steps_done == 300
    val = scene.split("val")
    cam = val.cameras
    ious, gains = [], []
    with one_thread():
        for i in range(len(val)):
            on = render_camera(f, cam.K[i], cam.c2w[i], cam.width, cam.height, background=(0, 0, 0))
            off = render_camera(f, cam.K[i], cam.c2w[i], cam.width, cam.height, background=(0, 0, 0),
                                settings=RenderSettings(background_model=False))
            a, t = off.opacity > 0.5, alphas["val"][i] > 0.5
            ious.append((a & t).sum() / max(1, (a | t).sum()))
            gains.append(metrics.psnr(np.clip(on.rgb, 0, 1), val.images[i]) -
                         metrics.psnr(np.clip(off.rgb, 0, 1), val.images[i]))
    assert min(ious) > 0.85, ious
    assert min(gains) > 3.0, gains


def test_appearance_codes_take_the_exposure_changes(blob_mesh, room):
    """Half the training photos darker (an exposure change): the per-image appearance codes learn a
    lower colour scale for them than for the others, and the codes are centred (mean zero)."""
    import dataclasses

    from neumesh_core.train.trainer import TrainConfig, train

    scene, _ = room
    tr = scene.split("train")
    dark = np.arange(len(tr)) % 2 == 0
    images = tr.images.copy()
    images[dark] *= 0.6
    data = dataclasses.replace(tr, images=images)
    f = _with_background(blob_mesh, scene, plain=True, resolution=16, planes=(16, 32))
    with one_thread():
        res = train(f, data, TrainConfig(steps=150, rays_per_batch=1024, log_every=50, seed=0,
                                         appearance_codes=True, lr_appearance=1e-2))
    codes = res.appearance
    assert codes.shape == (len(tr), 6)
    assert np.allclose(codes.mean(0), 0, atol=1e-5)
    scale = codes[:, :3].mean(1)
    assert scale[dark].mean() < scale[~dark].mean() - 0.1, (scale[dark].mean(), scale[~dark].mean())
    plain = train(_with_background(blob_mesh, scene, plain=True, resolution=16), data,
                  TrainConfig(steps=2, rays_per_batch=64, log_every=1))
    assert plain.appearance is None


def test_plane_tv_is_the_mean_squared_neighbour_difference():
    bg = BackgroundModel([0, 0, 0], 1.0, planes=(4, 8), plane_features=2)
    with torch.no_grad():
        for p in bg.plane_params:
            p.fill_(0.3)
    assert float(bg.tv_loss()) == 0.0                       # constant planes: nothing to smooth
    with torch.no_grad():
        bg.plane_params[1][0, 0, 2, 2] += 1.0               # an inner texel of a 4x4 plane: 4 neighbours
    # 2 of the 3x4 vertical and 2 of the 4x3 horizontal pairs differ by 1 (x 2 channels: 24 pairs each)
    assert float(bg.tv_loss()) == pytest.approx(2 / (2 * 3 * 4) + 2 / (2 * 4 * 3))
    bg.tv_loss().backward()
    assert float(bg.plane_params[1].grad[0, 0, 2, 2]) > 0     # the gradient pulls the texel back
    assert float(BackgroundModel([0, 0, 0], 1.0, resolution=4).tv_loss()) == 0.0   # dense grid: none


def _seam_row(version, seed=0):
    """The background alone along a row of rays that crosses the object box's outline: colours (N,3) and
    the index of the first ray that misses the box."""
    from neumesh_core.data.frame import ObjectBox

    box = ObjectBox([0.0, 0.0, 0.0], [0.5, 0.5, 0.5])
    torch.manual_seed(seed)   # the colour MLP's initial weights
    bg = BackgroundModel(box.centre, 1.0, box, planes=(16, 32), samples=32, version=version)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in bg.plane_params:   # a dense room of varied colour all around the box
            p.copy_(torch.rand(p.shape, generator=gen) + 0.5)
        for layer in (bg.density_mlp[-1], bg.mlp[-1], bg.mlp[0]):
            layer.weight.mul_(3.0)
    o = torch.tensor([[0.0, -3.0, 0.0]]).repeat(2001, 1)
    x = torch.linspace(-0.3, 0.3, 2001)   # the box's outline seen from o lies at x = +-0.5 * 3 / 2.5 = 0.2
    d = torch.nn.functional.normalize(torch.stack([x, torch.ones_like(x), torch.zeros_like(x)], 1), dim=-1)
    with torch.no_grad():
        rgb, op = bg(o, d)
    t_in, t_out = bg._box_range(o, d)
    misses = ~((t_in <= t_out) & (t_out > 0))
    return rgb, op, int(torch.nonzero(misses & (x > 0))[0])


def test_the_box_outline_leaves_no_seam_in_the_background():
    rgb, op, edge = _seam_row(version=2)
    assert torch.allclose(op, torch.ones_like(op))   # opaque: a photo has no holes
    steps = (rgb[1:] - rgb[:-1]).abs().max(1).values
    beside = torch.cat([steps[edge - 40:edge - 2], steps[edge + 1:edge + 40]]).max()
    assert float(steps[edge - 1]) <= 3.0 * float(beside)   # the step across the outline is like those beside it
    old, _, edge_v1 = _seam_row(version=1)   # the first version starts each ray at the box exit: a seam
    steps_v1 = (old[1:] - old[:-1]).abs().max(1).values
    beside_v1 = torch.cat([steps_v1[edge_v1 - 40:edge_v1 - 2], steps_v1[edge_v1 + 1:edge_v1 + 40]]).max()
    assert float(steps_v1[edge_v1 - 1]) > 5.0 * float(beside_v1)


def test_the_object_box_holds_nothing_of_the_room():
    from neumesh_core.data.frame import ObjectBox

    box = ObjectBox([0.0, 0.0, 0.0], [0.5, 0.5, 0.5])
    bg = BackgroundModel(box.centre, 1.0, box, planes=(8,), samples=32, version=2)
    with torch.no_grad():
        for p in bg.plane_params:
            p.fill_(2.0)
        bg.density_mlp[-1].bias.fill_(5.0)   # dense everywhere
    o = torch.zeros(6, 3)   # rays from the box's centre, cut where they leave the box
    d = torch.tensor([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0.6, 0.6, 0.53]])
    d = torch.nn.functional.normalize(d, dim=-1)
    _, t_out = bg._box_range(o, d)
    with torch.no_grad():
        _, inside = bg(o, d, far=t_out - 1e-4)
        _, beyond = bg(o, d, far=t_out + 0.3)
    assert torch.allclose(inside, torch.zeros(6))
    assert bool((beyond > 0.05).all())   # and the room right behind the box's faces is there


def test_support_samples_sit_on_the_support_behind_the_box():
    """A box resting on a support (its face at -half_extents[2] just in front of a wall or table):
    ``support_samples`` extra interval edges per ray lie in the slab from that face to a tenth of the
    half-size behind it, where the ray meets it; rays that never meet it get empty intervals; the
    colour of a thin wall there comes through (the even steps alone straddle it); the setting is saved
    in the config and files without it read as 0."""
    box = ObjectBox([0.0, 0.0, 0.0], [0.5, 0.5, 0.5], on_support=True)
    bg = BackgroundModel(box.centre, 1.0, box, planes=(8,), samples=8, version=2, support_samples=4)
    o = torch.tensor([[0.1, 0.0, 3.0], [0.0, 0.2, 3.0], [0.0, 0.0, 3.0]])
    d = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, -1.0], [0.1, 0.0, -1.0], [0.0, 0.0, 1.0]]), dim=-1)
    te = bg._support_edges(o, d, None)
    z = o[:, 2:3] + d[:, 2:3] * te
    assert bool(((z[:2] <= -0.5 + 1e-6) & (z[:2] >= -0.55 - 1e-6)).all())   # in the slab behind the face
    assert torch.allclose(te[2], torch.full((4,), 0.01))                   # looks away: empty intervals
    # a thin wall in the slab: density only there (a plane at z = -0.53); dense samples find it
    wall = -0.53

    def query(x, dd):
        on = (x[:, 2] - wall).abs() < 0.01
        sigma = torch.where(on, torch.full_like(x[:, 0], 1e4), torch.zeros_like(x[:, 0]))
        red, blue = torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, 1.0])
        return sigma, torch.where(on[:, None], red, blue)

    bg.query = query
    plain = BackgroundModel(box.centre, 1.0, box, planes=(8,), samples=8, version=2)
    plain.query = query
    with torch.no_grad():
        rgb, op = bg(o[:2], d[:2])
        rgb_plain, _ = plain(o[:2], d[:2])
    assert bool((rgb[:, 0] > 0.99).all()) and torch.allclose(op, torch.ones(2))
    assert bool((rgb_plain[:, 0] < 0.5).all())   # 8 even steps over the whole ray straddle the wall
    cfg = bg.config()
    assert cfg["support_samples"] == 4 and BackgroundModel.from_config(cfg).support_samples == 4
    del cfg["support_samples"]
    assert BackgroundModel.from_config(cfg).support_samples == 0
