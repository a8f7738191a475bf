"""Deformation fidelity: a briefly trained field of the small built-in scene, bent, against ground truth
(neumesh_core/data/mesh_truth.py; the full measurement is benchmarks/bench/bench_deform.py)."""
import math

import numpy as np
import torch

import neumesh_core as nm
from neumesh_core.data.deformations import bend
from neumesh_core.data.mesh_truth import render_mesh_truth
from neumesh_core.data.synthetic import CAMERA_ANGLE_X, look_at_opencv
from neumesh_core.metrics import psnr
from ..conftest import one_thread

VIEWS = [(-60.0, 20.0), (120.0, 35.0), (30.0, -10.0)]


def _psnr_against_truth(field, vertices, rest, size=64):
    K = nm.intrinsics_from_fov(CAMERA_ANGLE_X, size, size)
    field.set_vertices(vertices.astype(np.float32))
    out = []
    for az, el in VIEWS:
        a, e = math.radians(az), math.radians(el)
        c2w = look_at_opencv(4.0 * np.array([math.cos(a) * math.cos(e), math.sin(a) * math.cos(e), math.sin(e)]))
        pred = nm.render_camera(field, K, c2w.astype(np.float32), size, size).rgb
        gt, _ = render_mesh_truth(K, c2w, size, size, vertices, field.faces.numpy(), rest_vertices=rest)
        out.append(psnr(np.clip(pred, 0, 1), gt))
    return float(np.mean(out))


def test_moderate_bend_of_a_trained_field_stays_close_to_its_truth(small_scene_dir):
    # 150 steps x 1024 rays, early interpolation; 64 px, 3 views against the mesh truth. A neighbour
    # index left in the rest pose fails. Not caught at this budget: dropping the rest-frame
    # rotation of the view direction (the field has hardly learned highlights in 150 steps).
    # One torch thread: the small batches are faster so, and far faster on a busy 2-core machine.
    with one_thread():
        torch.manual_seed(0)
        scene = nm.load_scene(small_scene_dir)
        field = nm.create_field(nm.load_mesh(scene.mesh_path), nm.FieldConfig(interpolation="early"))
        nm.train(field, scene, nm.TrainConfig(steps=150, rays_per_batch=1024, log_every=50))
        rest = field.rest_vertices.numpy().astype(np.float64)
        undeformed = _psnr_against_truth(field, rest, rest)
        bent = _psnr_against_truth(field, bend(rest, 45.0), rest)
        field.set_vertices(rest.astype(np.float32))
    print(f"undeformed {undeformed:.2f} dB, bent 45 deg {bent:.2f} dB")
    assert undeformed > 22.5
    assert bent > undeformed - 0.5
