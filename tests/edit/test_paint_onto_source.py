"""Paint on a remapped field carried onto the field it was remapped from: each source vertex takes the
mean of its painted copies, new vertices are left out, nothing else changes, undo is exact."""
import numpy as np
import torch

from neumesh_core.edit import EditRecord, paint_onto_source

from ..conftest import textured_field


def _painted(shown, rows, colours):
    rec = EditRecord.begin("paint_texture", shown, rows, ("mod_colours",))
    with torch.no_grad():
        shown.mod_colours[torch.as_tensor(rows)] = torch.as_tensor(colours, dtype=shown.mod_colours.dtype)
    return rec.finish(shown, painted_pixels=7)


def test_each_source_vertex_takes_the_mean_of_its_painted_copies(blob_mesh):
    source, shown = textured_field(blob_mesh), textured_field(blob_mesh, seed=1)
    before = source.mod_colours.detach().clone()
    ids = np.arange(shown.num_vertices, dtype=np.int64)
    ids[[3, 4, 5]] = [20, 20, -1]            # two copies of source vertex 20, one new vertex
    rows = np.array([3, 4, 5, 9])
    colours = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.5, 0.5], [0.2, -0.4, 0.9]], np.float32)
    rec = paint_onto_source(_painted(shown, rows, colours), shown, source, ids)

    assert rec.vertices.tolist() == [9, 20] and rec.op == "paint_texture"
    assert rec.info["painted_pixels"] == 7
    after = source.mod_colours.detach()
    assert torch.allclose(after[20], torch.tensor([0.5, 0.5, 0.0]), atol=1e-6)
    assert torch.allclose(after[9], torch.tensor([0.2, -0.4, 0.9]), atol=1e-6)
    others = np.setdiff1d(np.arange(source.num_vertices), [9, 20])
    assert torch.equal(after[others], before[others])
    rec.undo(source)
    assert torch.equal(source.mod_colours.detach(), before)


def test_paint_on_new_vertices_only_changes_nothing(blob_mesh):
    source, shown = textured_field(blob_mesh), textured_field(blob_mesh, seed=1)
    before = source.mod_colours.detach().clone()
    ids = np.full(shown.num_vertices, -1, np.int64)
    rec = _painted(shown, np.array([1, 2]), np.ones((2, 3), np.float32))
    assert paint_onto_source(rec, shown, source, ids) is None
    assert torch.equal(source.mod_colours.detach(), before)
