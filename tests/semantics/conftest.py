"""Session fixtures for the semantic tests: the small multi-part scene, a field trained on it briefly
and a copy with semantics distilled by the weight-free extractor (about 40 s together).

The fixtures run torch on one thread: on a 2-core machine that other jobs keep busy, two OpenMP threads spin
against each other and take several times longer; on an idle machine one thread costs little here (small
batches)."""
import copy

import numpy as np
import pytest
from ..conftest import one_thread


@pytest.fixture(scope="session")
def multipart_dir(tmp_path_factory):
    from neumesh_core.data.multipart import SMALL_KWARGS, make_multipart_scene

    with one_thread():
        return make_multipart_scene(str(tmp_path_factory.mktemp("multipart")), **SMALL_KWARGS)


@pytest.fixture(scope="session")
def multipart_field(multipart_dir):
    """A field trained 200 steps on the multi-part scene (no semantics)."""
    import neumesh_core as nm

    scene = nm.load_scene(multipart_dir)
    field = nm.create_field(nm.load_mesh(f"{multipart_dir}/mesh.ply"), nm.FieldConfig(interpolation="early"))
    with one_thread():
        nm.train(field, scene, nm.TrainConfig(steps=200, rays_per_batch=1024, log_every=50))
    return field


@pytest.fixture(scope="session")
def semantic_field(multipart_dir, multipart_field):
    """(field with semantics, DistillResult): a copy of ``multipart_field`` distilled 300 steps."""
    import neumesh_core as nm
    from neumesh_core.semantics import DistillConfig, distill_semantics

    field = copy.deepcopy(multipart_field)
    with one_thread():
        res = distill_semantics(field, nm.load_scene(multipart_dir),
                                config=DistillConfig(steps=300, rays_per_view=1024, rays_per_batch=4096))
    return field, res


def part_clicks(scene_dir):
    """For each part: (training view, pixel (x, y)) of the pixel deepest inside that part's image region,
    over the training views (ground truth from the scene's ray tracer)."""
    from scipy.ndimage import distance_transform_edt

    import neumesh_core as nm
    from neumesh_core.data import multipart as mp

    cams = nm.load_scene(scene_dir).split("train").cameras
    best = {}
    for i in range(len(cams)):
        lab = mp.label_image(cams.K[i], cams.c2w[i], cams.width, cams.height)
        for p in range(len(mp.PART_NAMES)):
            dt = distance_transform_edt(lab == p)
            if p not in best or dt.max() > best[p][0]:
                y, x = np.unravel_index(dt.argmax(), dt.shape)
                best[p] = (dt.max(), i, (x + 0.5, y + 0.5))
    return {p: (i, xy) for p, (_, i, xy) in best.items()}
