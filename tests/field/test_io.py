import os

import numpy as np
import pytest
import torch

import neumesh_core as nm
from neumesh_core.data.cameras import intrinsics_from_fov

from ..conftest import textured_field


def _render(f):
    K = intrinsics_from_fov(0.8, 32, 32)
    c2w = np.eye(4, dtype=np.float32)
    c2w[2, 3] = -3.5
    return nm.render_camera(f, K, c2w, 32, 32)


def test_round_trip_renders_identical_pixels(blob_mesh, tmp_path):
    f = textured_field(blob_mesh)
    f.grid.refresh(lambda x: f.query(x, with_rgb=False)[0], f.radius * 0.25)
    path = str(tmp_path / "a.neumesh")
    nm.save_field(f, path)
    g = nm.load_field(path)
    a, b = _render(f), _render(g)
    # exact on purpose: the loaded tensors are bit copies and both renders take the same path in one
    # process on one machine, so the floats are guaranteed identical
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.opacity, b.opacity)
    assert torch.equal(f.grid.occ, g.grid.occ)
    assert g.config == f.config
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".tmp")]


def test_tensors_saved_under_earlier_names_load_under_the_current_ones(blob_mesh, tmp_path):
    """A file whose modification colours (and their Adam moments) are stored as ``mod_colors``, whose
    tangent neighbours are ``scaffold.tangent_ref`` and whose field config says ``knn="kdtree"`` loads as
    the field it was: the same rows, the same tangent frames, the same neighbour search."""
    import json

    from safetensors import safe_open
    from safetensors.torch import save_file

    f = textured_field(blob_mesh)
    with torch.no_grad():
        f.mod_colours.copy_(torch.rand_like(f.mod_colours) - 0.5)
    opt = torch.optim.Adam(f.parameters(), lr=1e-3)
    f.mod_colours.sum().backward()
    opt.step()
    path, old = str(tmp_path / "new.neumesh"), str(tmp_path / "old.neumesh")
    nm.save_field(f, path, optimizer=opt)
    with safe_open(path, framework="pt") as fh:
        meta = json.loads(fh.metadata()["neumesh"])
        tensors = {k.replace("mod_colours", "mod_colors").replace("tangent_neighbour", "tangent_ref"): fh.get_tensor(k)
                   for k in fh.keys()}
    meta["field_config"]["knn"] = "kdtree"
    assert {"param/mod_colors", "optim/mod_colors/exp_avg", "buffer/scaffold.tangent_ref"} <= set(tensors)
    save_file(tensors, old, metadata={"neumesh": json.dumps(meta)})
    g = nm.load_field(old)
    assert torch.equal(g.mod_colours, f.mod_colours) and g.config.knn == "auto"
    assert torch.equal(g.scaffold.tangent_neighbour, f.scaffold.tangent_neighbour)
    assert torch.equal(g._checkpoint_optim["mod_colours/exp_avg"], opt.state[f.mod_colours]["exp_avg"])


def test_saving_a_deformed_field_keeps_rest_pose(blob_mesh, tmp_path):
    f = textured_field(blob_mesh)
    rest = _render(f)
    f.set_vertices(f.vertices * 1.3)
    path = str(tmp_path / "d.neumesh")
    nm.save_field(f, path)
    g = nm.load_field(path)
    assert np.allclose(g.vertices, f.rest_vertices.numpy())
    assert np.array_equal(_render(g).rgb, rest.rgb)  # bit copies, same path, same process: exact


@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty"])
def test_corrupt_checkpoint_gives_clear_error(blob_mesh, tmp_path, damage):
    f = textured_field(blob_mesh)
    path = str(tmp_path / "c.neumesh")
    nm.save_field(f, path)
    data = open(path, "rb").read()
    with open(path, "wb") as fh:
        if damage == "truncate":
            fh.write(data[: len(data) // 2])
        elif damage == "garbage":
            fh.write(b"\x00\x01garbage" * 100)
    with pytest.raises(nm.CheckpointError, match="not a readable NeuMesh field"):
        nm.load_field(path)


def test_missing_and_foreign_files(tmp_path):
    with pytest.raises(nm.CheckpointError, match="not found"):
        nm.load_field(str(tmp_path / "nope.neumesh"))
    from safetensors.torch import save_file

    p = str(tmp_path / "other.safetensors")
    save_file({"x": torch.zeros(3)}, p)
    with pytest.raises(nm.CheckpointError, match="not a NeuMesh field"):
        nm.load_field(p)


def test_nan_parameters_are_never_saved(blob_mesh, tmp_path):
    f = textured_field(blob_mesh)
    path = str(tmp_path / "n.neumesh")
    nm.save_field(f, path)
    before = open(path, "rb").read()
    with torch.no_grad():
        f.tex_codes[3, 0] = float("nan")
    with pytest.raises(nm.CheckpointError, match="NaN"):
        nm.save_field(f, path)
    assert open(path, "rb").read() == before  # the good file is untouched


def test_step_scale_travels_with_the_field(blob_mesh, tmp_path):
    """Rendering marches with the step the field was trained with (FieldConfig.step_scale); fields saved
    before the step was stored were trained with 0.25 and load with it."""
    import json

    from safetensors.torch import load_file, save_file

    from neumesh_core.render.renderer import RenderSettings, default_step
    from neumesh_core.field.io import read_checkpoint

    f = textured_field(blob_mesh)
    assert default_step(f, RenderSettings()) == pytest.approx(f.radius * f.config.step_scale)
    assert default_step(f, RenderSettings(step_scale=0.1)) == pytest.approx(f.radius * 0.1)
    path = str(tmp_path / "s.neumesh")
    nm.save_field(f, path)
    assert nm.load_field(path).config.step_scale == f.config.step_scale
    # an older file: field_config without step_scale
    meta, _ = read_checkpoint(path)
    del meta["field_config"]["step_scale"]
    tensors = load_file(path)
    old = str(tmp_path / "old.neumesh")
    save_file(tensors, old, metadata={"neumesh": json.dumps(meta)})
    assert nm.load_field(old).config.step_scale == 0.25


DATA = os.path.join(os.path.dirname(__file__), "data")


@pytest.mark.parametrize("interp", ["post", "early"])
def test_version1_files_load_as_single_decoder_fields_and_render_as_before(interp, tmp_path):
    """``data/field_v1_*.neumesh`` were written by the format-1 code (one ``rad_decoder``, scaffold
    buffers at the top level; commit dd8565b), with the render it gave then (``*_render.npy``, RGB +
    opacity of the camera below).  They load as one-decoder fields with every vertex on decoder 0 and
    render the same image: within 1e-5 of the stored pixels (they were rendered on another machine,
    whose float rounding may differ), and bit-identical to the same field saved as format 2 and
    loaded again (same path, same process)."""
    from neumesh_core.field.io import read_header

    path = os.path.join(DATA, f"field_v1_{interp}.neumesh")
    assert read_header(path)["version"] == 1
    f = nm.load_field(path)
    assert f.num_decoders == 1 and int(f.decoder_id.abs().sum()) == 0
    assert f.config.interpolation == interp and f._checkpoint_meta["train_state"]["step"] == 7
    K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]], np.float32)
    c2w = np.eye(4, dtype=np.float32)
    c2w[:3, 3] = [0, 0, -3.5]
    out = nm.render_camera(f, K, c2w, 32, 24)
    got = np.concatenate([out.rgb, out.opacity[..., None]], -1)
    ref = np.load(os.path.join(DATA, f"field_v1_{interp}_render.npy"))
    assert ref.std() > 0.1 and np.abs(got - ref).max() < 1e-5
    v2 = str(tmp_path / "v2.neumesh")
    nm.save_field(f, v2)
    assert read_header(v2)["version"] == 2 and read_header(v2)["train_state"]["step"] == 7
    again = nm.render_camera(nm.load_field(v2), K, c2w, 32, 24)
    assert np.array_equal(again.rgb, out.rgb) and np.array_equal(again.opacity, out.opacity)


@pytest.mark.parametrize("interp", ["post", "early"])
def test_several_decoders_and_their_binding_round_trip(blob_mesh, tmp_path, interp):
    import copy

    f = textured_field(blob_mesh, interp)
    other = copy.deepcopy(f.rad_decoder)
    with torch.no_grad():
        for p in other.parameters():
            p.add_(0.3)
    f.add_decoder(other)
    with torch.no_grad():
        f.decoder_id.copy_((f.rest_vertices[:, 0] > 0.2).to(f.decoder_id.dtype))
    path = str(tmp_path / "two.neumesh")
    nm.save_field(f, path)
    g = nm.load_field(path)
    assert g.num_decoders == 2 and torch.equal(g.decoder_id, f.decoder_id)
    assert g.decoder_keys() == f.decoder_keys()
    a, b = _render(f), _render(g)
    assert np.array_equal(a.rgb, b.rgb)  # bit copies, same path, same process: exact
    # the second decoder matters: binding everything to decoder 0 changes the picture
    with torch.no_grad():
        g.decoder_id.zero_()
    assert np.abs(_render(g).rgb - a.rgb).max() > 0.05


def test_corrupt_decoder_binding_is_refused(blob_mesh, tmp_path):
    import json

    from safetensors.torch import load_file, save_file

    from neumesh_core.field.io import read_header

    f = textured_field(blob_mesh)
    path = str(tmp_path / "a.neumesh")
    nm.save_field(f, path)
    t = load_file(path)
    t["buffer/decoder_id"][3] = 5   # points at a decoder the file does not have
    bad = str(tmp_path / "bad.neumesh")
    save_file(t, bad, metadata={"neumesh": json.dumps(read_header(path))})
    with pytest.raises(nm.CheckpointError, match="decoder ids"):
        nm.load_field(bad)


def test_saved_files_are_readable_like_ordinary_files(blob_mesh, tmp_path):
    f = textured_field(blob_mesh)
    path = str(tmp_path / "p.neumesh")
    old = os.umask(0o022)
    try:
        nm.save_field(f, path)
    finally:
        os.umask(old)
    assert os.stat(path).st_mode & 0o777 == 0o644


@pytest.mark.parametrize("interp", ["post", "early"])
def test_texture_frames_round_trip_and_bad_ones_are_refused(blob_mesh, tmp_path, interp):
    import json

    from safetensors.torch import load_file, save_file

    from neumesh_core.field.io import read_header

    f = textured_field(blob_mesh, interp)
    a, b = np.radians(40.0), np.radians(-25.0)
    R = torch.tensor([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]], dtype=torch.float32)
    R = R @ torch.tensor([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]], dtype=torch.float32)
    with torch.no_grad():
        f.ensure_tex_frame()[f.rest_vertices[:, 0] > 0] = R
    plain = nm.load_field(_save(textured_field(blob_mesh, interp), tmp_path / "plain.neumesh"))
    assert plain.tex_frame is None        # a trained field has no frames, in memory or on disk
    path = _save(f, tmp_path / "frames.neumesh")
    g = nm.load_field(path)
    assert torch.equal(g.tex_frame, f.tex_frame)
    assert np.array_equal(_render(g).rgb, _render(f).rgb)   # bit copies, same path, same process
    assert np.abs(_render(g).rgb - _render(plain).rgb).max() > 0.005   # the frames change the picture
    t = load_file(path)
    t["buffer/tex_frame"] = t["buffer/tex_frame"][:10]
    bad = str(tmp_path / "bad.neumesh")
    save_file(t, bad, metadata={"neumesh": json.dumps(read_header(path))})
    with pytest.raises(nm.CheckpointError, match="tex_frame"):
        nm.load_field(bad)


def _save(field, path):
    nm.save_field(field, str(path))
    return str(path)
