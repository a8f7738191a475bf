"""Distillation with the weight-free extractor on the multi-part scene, then one click per part."""
import os

import numpy as np
import pytest
import torch

import neumesh_core as nm
from neumesh_core.data.multipart import PART_NAMES
from neumesh_core.semantics import DistillConfig, distill_semantics, select_region

from .conftest import one_thread, part_clicks


def test_one_click_selects_each_part(multipart_dir, semantic_field):
    field, res = semantic_field
    assert res.steps_done == 300 and not res.cancelled and res.final_loss < 0.2
    labels = np.load(os.path.join(multipart_dir, "part_labels.npy"))
    cams = nm.load_scene(multipart_dir).split("train").cameras
    ious = {}
    with one_thread():
        clicks = part_clicks(multipart_dir)
        sels = {part: select_region(field, cams.subset(view), pixel) for part, (view, pixel) in clicks.items()}
    for part, sel in sels.items():
        gt = np.nonzero(labels == part)[0]
        ious[PART_NAMES[part]] = len(np.intersect1d(sel.vertices, gt)) / len(np.union1d(sel.vertices, gt))
    print("IoU per part:", {k: round(v, 3) for k, v in ious.items()})
    assert all(v >= 0.85 for v in ious.values()), ious


def test_distillation_changes_only_the_semantic_branch(multipart_field, semantic_field):
    field, _ = semantic_field
    before = {k: v for k, v in multipart_field.state_dict().items()}
    after = field.state_dict()
    for k, v in before.items():
        if k == "sem_codes":
            continue
        # bit-equal: distillation never writes these tensors (copied, not recomputed)
        assert torch.equal(after[k], v), k
    assert field.has_semantics and not multipart_field.has_semantics
    assert field.sem_codes.shape == (field.num_vertices, 8) and not field.sem_codes.requires_grad
    info = field.semantics_info
    assert info["extractor"]["name"] == "colour-texture" and info["steps"] == 300


def test_cancel_before_training_leaves_the_field_as_it_was(multipart_dir, multipart_field):
    import copy

    field = copy.deepcopy(multipart_field)
    stages = []

    def cb(p):
        stages.append(p.stage)
        return p.stage != "features"

    res = distill_semantics(field, nm.load_scene(multipart_dir), config=DistillConfig(steps=5), progress=cb)
    assert res.cancelled and res.steps_done == 0 and stages == ["features"]
    assert not field.has_semantics


def test_cancel_while_training_keeps_what_was_learned(multipart_dir, multipart_field):
    import copy

    field = copy.deepcopy(multipart_field)
    cfg = DistillConfig(steps=50, rays_per_view=128, rays_per_batch=256, log_every=2, max_views=4)
    res = distill_semantics(field, nm.load_scene(multipart_dir), config=cfg,   # callback=: the older name
                            callback=lambda p: not (p.stage == "train" and p.step >= 4))
    assert res.cancelled and res.steps_done == 4 and field.has_semantics
    assert field.semantics_info["cancelled"] is True


def test_distill_refuses_a_deformed_field(multipart_dir, multipart_field):
    import copy

    field = copy.deepcopy(multipart_field)
    field.set_vertices(field.vertices * 1.1)
    with pytest.raises(ValueError, match="deformed"):
        distill_semantics(field, nm.load_scene(multipart_dir), config=DistillConfig(steps=1))


def test_cli_writes_an_edited_file_with_semantics(multipart_dir, multipart_field, tmp_path, capsys):
    from neumesh_core.cli import main

    src = str(tmp_path / "mp.neumesh")
    nm.save_field(multipart_field, src)
    before = open(src, "rb").read()
    rc = main(["semantics", "--field", src, "--data", multipart_dir, "--steps", "3", "--rays-per-view", "64",
               "--max-views", "3", "--pca", "4", "--sem-dim", "6"])
    assert rc == 0
    out = str(tmp_path / "mp.edit-001.neumesh")
    assert "wrote " + out in capsys.readouterr().out
    assert open(src, "rb").read() == before            # the trained file is never rewritten
    f = nm.load_field(out)
    assert f.has_semantics and f.config.sem_dim == 6 and f.config.sem_features == 4
    assert f.semantics_info["steps"] == 3
    assert nm.edit.edit_info(out)["op"] == "semantics" and nm.edit.parent_of(out) == src
    # bad options are reported as option errors, not tracebacks
    assert main(["semantics", "--field", src, "--data", multipart_dir, "--sem-dim", "0"]) == 2
    assert main(["semantics", "--field", src, "--data", multipart_dir, "--extractor", "nope"]) == 2
