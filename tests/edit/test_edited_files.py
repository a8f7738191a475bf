"""Edited files are saved beside their parent, never over it, and know their parent and root."""
import os

import numpy as np
import pytest
import torch

import neumesh_core as nm
from neumesh_core.edit import EditRecord, edit_info, next_edit_path, parent_of, root_of, save_edited

from ..conftest import textured_field


def _edit(f, value):
    rec = EditRecord.begin("paint", f, np.arange(5), ("mod_colours",))
    with torch.no_grad():
        f.mod_colours[:5] = value
    return rec.finish(f, note="x")


def test_edit_chain_names_parent_and_root(blob_mesh, tmp_path):
    f = textured_field(blob_mesh)
    trained = str(tmp_path / "lego.neumesh")
    nm.save_field(f, trained, train_state={"step": 3})
    assert next_edit_path(trained) == str(tmp_path / "lego.edit-001.neumesh")
    assert edit_info(trained) is None and root_of(trained) == trained and parent_of(trained) is None

    g = nm.load_field(trained)
    e1 = save_edited(g, trained, _edit(g, 0.5))
    assert e1 == str(tmp_path / "lego.edit-001.neumesh")
    h = nm.load_field(e1)
    e2 = save_edited(h, e1, _edit(h, -0.5))
    assert e2 == str(tmp_path / "lego.edit-002.neumesh")
    assert next_edit_path(e2) == str(tmp_path / "lego.edit-003.neumesh")
    assert parent_of(e2) == e1 and parent_of(e1) == trained
    assert root_of(e2) == trained and root_of(e1) == trained
    info = edit_info(e2)
    assert info["op"] == "paint" and [h["op"] for h in info["history"]] == ["paint", "paint"]
    assert info["history"][0]["vertices"] == 5 and info["history"][1]["info"]["note"] == "x"
    assert nm.load_field(e2)._checkpoint_meta["train_state"]["step"] == 3   # carried from the parent
    # the pixels of each file are what was saved
    assert torch.allclose(nm.load_field(e1).mod_colours[:5], torch.full((5, 3), 0.5))
    assert torch.allclose(nm.load_field(e2).mod_colours[:5], torch.full((5, 3), -0.5))


def test_an_edit_never_overwrites_its_parent_or_the_trained_file(blob_mesh, tmp_path):
    f = textured_field(blob_mesh)
    trained = str(tmp_path / "a.neumesh")
    nm.save_field(f, trained)
    before = open(trained, "rb").read()
    e1 = save_edited(f, trained, _edit(f, 0.2))
    for target in (trained, e1):
        with pytest.raises(nm.NeuMeshError, match="refusing to overwrite"):
            save_edited(f, e1, _edit(f, 0.3), out_path=target)
    assert open(trained, "rb").read() == before  # byte-identical: untouched
    out = save_edited(f, e1, _edit(f, 0.3), out_path=str(tmp_path / "sub" / "mine.neumesh"))
    assert parent_of(out) == e1 and root_of(out) == trained   # relative links resolve from another folder
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".tmp")]
