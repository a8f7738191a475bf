"""The multi-part built-in scene: parts, labels, mesh orientation, dataset files."""
import json
import os

import numpy as np
import torch

import neumesh_core as nm
from neumesh_core.data import multipart as mp


def test_mesh_labels_and_orientation():
    mesh, labels = mp.multipart_mesh(grid=40)
    assert len(labels) == mesh.num_vertices and set(np.unique(labels)) == {0, 1, 2, 3}
    d = mp.distance(torch.as_tensor(mesh.vertices, dtype=torch.float64)).abs().max()
    assert float(d) < 0.035   # on the surface to within half a marching-cubes cell (0.066)
    from neumesh_core.mesh import vertex_normals

    n = vertex_normals(torch.as_tensor(mesh.vertices), torch.as_tensor(mesh.faces)).numpy()
    analytic = mp.normals(torch.as_tensor(mesh.vertices, dtype=torch.float64)).numpy()
    assert ((n * analytic).sum(1) > 0.5).mean() > 0.97   # faces wound outwards


def test_trace_hits_the_surface_and_labels_follow_albedo():
    K = nm.intrinsics_from_fov(mp.CAMERA_ANGLE_X, 32, 32)
    from neumesh_core.data.synthetic import look_at_opencv

    c2w = look_at_opencv(mp.CENTRE + np.array([mp.CAMERA_RADIUS, 0, 0.5]), mp.CENTRE)
    lab = mp.label_image(K, c2w, 32, 32)
    assert (lab == -1).any() and {0, 1, 2}.issubset(set(np.unique(lab)))
    rgb, alpha = mp.render(K, c2w, 32, 32, spp=1)
    assert ((alpha > 0.5) == (lab >= 0)).mean() > 0.95   # jittered samples vs centre rays: edges differ
    # red body, blue/white head: mean colour per label
    assert rgb[lab == 0][:, 0].mean() > rgb[lab == 0][:, 2].mean() + 0.2
    assert rgb[lab == 1][:, 2].mean() > rgb[lab == 1][:, 0].mean() + 0.1


def test_dataset_files(tmp_path):
    d = mp.make_multipart_scene(str(tmp_path / "mp"), resolution=16, n_train=3, n_val=1, n_test=0, grid=24)
    scene = nm.load_scene(d)
    assert len(scene.split("train")) == 3 and scene.split("train").masks is not None
    labels = np.load(os.path.join(d, "part_labels.npy"))
    assert len(labels) == nm.load_mesh(os.path.join(d, "mesh.ply")).num_vertices
    assert json.load(open(os.path.join(d, "scene.json")))["parts"] == list(mp.PART_NAMES)


def test_same_colour_variant_paints_every_part_alike(tmp_path):
    K = nm.intrinsics_from_fov(mp.CAMERA_ANGLE_X, 48, 48)
    from neumesh_core.data.synthetic import look_at_opencv

    c2w = look_at_opencv(mp.CENTRE + np.array([mp.CAMERA_RADIUS, 0.4, 0.8]), mp.CENTRE)
    lab = mp.label_image(K, c2w, 48, 48)
    pts = torch.rand(2000, 3, dtype=torch.float64) * 2 - 1
    parts = torch.arange(2000) % 4
    alb = mp.albedo(pts, parts, same_colour=True)
    ref = mp.albedo(pts, torch.full_like(parts, mp.SHARED_TEXTURE_PART))
    assert torch.equal(alb, ref)   # one texture, whatever the part
    assert not torch.equal(mp.albedo(pts, parts), ref)
    rgb, _ = mp.render(K, c2w, 48, 48, spp=1, same_colour=True)
    seen = [p for p in range(4) if (lab == p).sum() > 20]
    assert len(seen) >= 3
    # mean hue per part: yellow everywhere (red and green high, blue low), unlike the coloured scene
    for p in seen:
        r, g, b = rgb[lab == p].mean(0)
        assert r > b + 0.2 and g > b + 0.1, (p, r, g, b)
    d = mp.make_multipart_scene(str(tmp_path / "same"), resolution=16, n_train=2, n_val=1, n_test=0, grid=24,
                                same_colour=True)
    desc = json.load(open(os.path.join(d, "scene.json")))
    assert desc["params"]["same_colour"] is True and desc["parts"] == list(mp.PART_NAMES)
    assert len(np.load(os.path.join(d, "part_labels.npy"))) == nm.load_mesh(os.path.join(d, "mesh.ply")).num_vertices
