"""`neumesh fit` on a capture without masks: the built-in blob in a textured room written
as an instant-ngp transforms.json capture, end to end at a tiny budget."""
import json
import math
import os

import numpy as np

from tests.conftest import one_thread


def _write_room_capture(folder, n=16, res=32):
    from neumesh_core.data.synthetic.room import make_room_scene
    from neumesh_core.imageio import save_image

    scene, _ = make_room_scene(resolution=res, n_train=n, n_val=0)
    imgs = scene.split("train")
    os.makedirs(os.path.join(folder, "images"), exist_ok=True)
    frames = []
    for i in range(len(imgs)):
        p = f"images/{i:03d}.png"
        save_image(os.path.join(folder, p), imgs.images[i])
        c2w = imgs.cameras.c2w[i].astype(np.float64).copy()
        c2w[:3, 1:3] *= -1   # OpenCV -> OpenGL (transforms.json)
        frames.append({"file_path": p, "transform_matrix": c2w.tolist()})
    K = imgs.cameras.K[0]
    with open(os.path.join(folder, "transforms.json"), "w") as fh:
        json.dump({"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
                   "w": res, "h": res, "frames": frames}, fh)


def test_fit_without_masks_box_background(tmp_path, capsys):
    import neumesh_core as nm
    from neumesh_core.cli import main
    from neumesh_core.field.background import background_of

    data = tmp_path / "room"
    _write_room_capture(str(data))
    out = tmp_path / "out"
    with one_thread():
        rc = main(["fit", "--data", str(data), "--out", str(out), "--steps", "40", "--rays", "1024",
                   "--method", "density", "--iters", "40,40", "--density-resolutions", "24,32",
                   "--box", "0,0,0,1.4,1.4,1.4", "--threads", "1", "--vertices", "5000"])
    assert rc == 0
    summary = json.loads((out / "fit.json").read_text())
    assert summary["object_box"]["half_extents"] == [1.4, 1.4, 1.4]
    assert "eval" in summary and math.isfinite(summary["eval"]["psnr"])
    f = nm.load_field(str(out / "field.neumesh"))
    assert np.allclose(f.object_box.half_extents, 1.4)
    assert background_of(f) is not None
    # the scaffold lies inside the box (up to the density grid's margin of a few cells)
    v = np.abs(f.rest_vertices.numpy())
    assert v.max() <= 1.4 * 1.2, v.max()
    # `neumesh eval`: full frame on the held-out photos, background on and off
    figures = {}
    for mode in ("on", "off"):
        capsys.readouterr()
        with one_thread():
            assert main(["eval", "--field", str(out / "field.neumesh"), "--data", str(data),
                         "--background-model", mode, "--json", str(tmp_path / f"ev_{mode}.json")]) == 0
        text = capsys.readouterr().out
        assert f"full-frame figures (2 held-out photos of 'val'); background model {mode}" in text
        figures[mode] = json.loads((tmp_path / f"ev_{mode}.json").read_text())["mean"]["psnr"]
    assert figures["on"] != figures["off"]
