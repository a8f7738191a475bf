"""`neumesh edit swap|fill` end to end on field files: a new file beside the input, never over it."""
import copy
import hashlib
import json
import os

import numpy as np
import torch

import neumesh_core as nm
from neumesh_core.cli import main

from ..conftest import textured_field
from ..edit.helpers import render
from ..edit.test_fill import _grid, _spherical_corner_uvs
from ..edit.test_inputs import write_obj
from ..edit.test_swap import _other_texture, _region


def _digest(path):
    return hashlib.sha1(open(path, "rb").read()).hexdigest()


def test_swap_writes_a_new_file_that_renders_like_the_api(blob_mesh, tmp_path, capsys):
    f = textured_field(blob_mesh)
    src = _other_texture(f)
    tpath, spath = str(tmp_path / "t.neumesh"), str(tmp_path / "s.neumesh")
    nm.save_field(f, tpath)
    nm.save_field(src, spath)
    region = _region(f)
    np.savetxt(tmp_path / "region.txt", region, fmt="%d")
    before = _digest(tpath)
    assert main(["edit", "swap", "--field", tpath, "--region", str(tmp_path / "region.txt"),
                 "--source", spath]) == 0
    report = json.loads(capsys.readouterr().out)
    out = str(tmp_path / "t.edit-001.neumesh")
    assert report["out"] == out and report["vertices_changed"] == len(region) and report["residual"] < 1e-6
    assert _digest(tpath) == before                     # the input is never touched
    g = nm.load_field(out)
    assert g.num_decoders == 2 and nm.edit.edit_info(out)["op"] == "swap_texture"
    api = nm.load_field(tpath)
    nm.swap_texture(api, region, nm.load_field(spath), region)
    assert np.abs(render(g).rgb - render(api).rgb).max() < 1e-6
    # a second edit of the edited file goes beside it, and knows its parent and root
    assert main(["edit", "swap", "--field", out, "--region", str(tmp_path / "region.txt"), "--rigid"]) == 0
    second = str(tmp_path / "t.edit-002.neumesh")
    assert nm.edit.parent_of(second) == out and nm.edit.root_of(second) == tpath


def test_fill_from_an_obj_uv_map(blob_mesh, tmp_path, capsys):
    f = textured_field(blob_mesh)
    path = str(tmp_path / "f.neumesh")
    nm.save_field(f, path)
    uvs = _spherical_corner_uvs(f)
    write_obj(tmp_path / "f.obj", f.rest_vertices.numpy(), f.faces.numpy(), uvs.uv.reshape(-1, 3, 2))
    np.savetxt(tmp_path / "a.txt", np.nonzero(f.rest_vertices[:, 0].numpy() > 0.3)[0], fmt="%d")
    np.savetxt(tmp_path / "b.txt", np.nonzero(f.rest_vertices[:, 0].numpy() < -0.3)[0], fmt="%d")
    assert main(["edit", "fill", "--field", path, "--region", str(tmp_path / "a.txt"), "--uv",
                 str(tmp_path / "f.obj"), "--template-region", str(tmp_path / "b.txt"), "--scale", "2",
                 "--out", str(tmp_path / "filled.neumesh")]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["scale"] == 2.0 and os.path.isfile(tmp_path / "filled.neumesh")
    api = copy.deepcopy(f)
    nm.fill_texture(api, np.loadtxt(tmp_path / "a.txt", dtype=int), uvs, api,
                    np.loadtxt(tmp_path / "b.txt", dtype=int), uvs, scale=2.0)
    g = nm.load_field(str(tmp_path / "filled.neumesh"))
    assert torch.allclose(g.tex_codes, api.tex_codes, atol=1e-6)


def test_bad_input_is_an_error_without_a_new_file(blob_mesh, tmp_path, capsys):
    f = textured_field(blob_mesh)
    path = str(tmp_path / "f.neumesh")
    nm.save_field(f, path)
    (tmp_path / "r.txt").write_text("1 2 3\n")
    mesh, _ = _grid(4)
    write_obj(tmp_path / "small.obj", mesh.vertices, mesh.faces, np.zeros((len(mesh.faces), 3, 2)))
    cases = [
        (["edit", "swap", "--field", path, "--region", str(tmp_path / "missing.txt")], "not found"),
        (["edit", "swap", "--field", path, "--region", str(tmp_path / "r.txt")], "at least 4 vertices"),
        (["edit", "fill", "--field", path, "--region", str(tmp_path / "r.txt"), "--uv",
          str(tmp_path / "small.obj"), "--template-region", str(tmp_path / "r.txt")], "25 vertices"),
        (["edit", "swap", "--field", path, "--region", str(tmp_path / "r.txt"), "--out", path],
         "refusing to overwrite"),
    ]
    for argv, msg in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "error:" in err and msg in err, (argv, err)
    assert sorted(os.listdir(tmp_path)) == ["f.neumesh", "r.txt", "small.obj"]
    big = np.arange(0, 400)
    np.savetxt(tmp_path / "big.txt", big, fmt="%d")
    assert main(["edit", "swap", "--field", path, "--region", str(tmp_path / "big.txt"), "--out", path]) == 2
    assert "refusing to overwrite the field it was edited from" in capsys.readouterr().err


def test_every_edit_option_is_explained():
    from neumesh_core.cli import build_parser

    edit = build_parser()._subparsers._group_actions[0].choices["edit"]
    subs = edit._subparsers._group_actions[0].choices
    assert {"swap", "fill"} <= set(subs)
    for name, p in subs.items():
        for action in p._actions:
            if action.option_strings and action.dest != "help":
                assert action.help, f"edit {name} {action.option_strings} has no help"


def test_paint_workflow_render_paint_apply(blob_mesh, tmp_path, capsys):
    """--save-render writes the view; the painted copy and the render give the paint; the edited file
    shows it in that view."""
    from neumesh_core.imageio import read_image, save_image

    from ..edit.helpers import camera

    f = textured_field(blob_mesh)
    path = str(tmp_path / "f.neumesh")
    nm.save_field(f, path)
    K, c2w = camera(0.0, size=48)
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({"K": K.tolist(), "c2w": c2w.tolist(), "width": 48, "height": 48}))
    view = str(tmp_path / "view.png")
    assert main(["edit", "paint", "--field", path, "--camera", str(cam), "--save-render", view]) == 0
    capsys.readouterr()
    img = read_image(view)
    painted = img.copy()
    painted[20:26, 16:32, :3] = [0.0, 0.8, 0.0]
    save_image(str(tmp_path / "painted.png"), painted)
    assert main(["edit", "paint", "--field", path, "--camera", str(cam), "--painted", str(tmp_path / "painted.png"),
                 "--original", view]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["op"] == "paint_texture" and report["painted_pixels"] == 96
    g = nm.load_field(report["out"])
    out = nm.render_camera(g, K, c2w, 48, 48)
    # mean, not max: this coarse blob (2,562 vertices) cannot hold a sharp 6 px stroke edge exactly
    assert np.abs(np.clip(out.rgb[20:26, 16:32], 0, 1) - [0.0, 0.8, 0.0]).mean() < 0.06
    assert main(["edit", "paint", "--field", path, "--camera", str(cam)]) == 2
    assert "give the paint" in capsys.readouterr().err
