"""EditRecord: undo/redo are exact row writes of what an edit changed."""
import copy

import numpy as np
import pytest
import torch

from neumesh_core.edit import EditRecord, as_vertex_ids

from ..conftest import textured_field


def test_vertex_ids_are_validated_and_normalised():
    assert as_vertex_ids([5, 2, 2, 9], 10).tolist() == [2, 5, 9]
    assert as_vertex_ids(np.array([1.0, 3.0]), 10).tolist() == [1, 3]
    mask = np.zeros(10, bool)
    mask[[0, 7]] = True
    assert as_vertex_ids(mask, 10).tolist() == [0, 7]
    with pytest.raises(ValueError, match="empty"):
        as_vertex_ids([], 10)
    with pytest.raises(ValueError, match=r"\[0, 10\)"):
        as_vertex_ids([3, 10], 10)
    with pytest.raises(ValueError, match="whole vertex indices"):
        as_vertex_ids([0.5], 10)
    with pytest.raises(ValueError, match="one entry per vertex"):
        as_vertex_ids(np.zeros(4, bool), 10)


def test_undo_and_redo_restore_rows_and_decoders_exactly(blob_mesh):
    f = textured_field(blob_mesh)
    before = {n: getattr(f, n).detach().clone() for n in ("tex_codes", "mod_colours", "decoder_id")}
    region = np.arange(10, 60)
    rec = EditRecord.begin("test", f, region, ("tex_codes", "mod_colours", "decoder_id"))
    other = copy.deepcopy(f.rad_decoder)
    with torch.no_grad():
        other[0].bias.add_(1.0)
        d = f.add_decoder(other)
        f.tex_codes[region] = 1.5
        f.mod_colours[region] = -0.25
        f.decoder_id[region] = d
    rec.finish(f, residual=0.5)
    after = {n: getattr(f, n).detach().clone() for n in before}
    assert rec.num_changed == 50 and rec.info["residual"] == 0.5 and rec.decoders_after == 2
    rec.undo(f)
    assert f.num_decoders == 1
    for n, t in before.items():   # exact: the old rows are copies written back
        assert torch.equal(getattr(f, n), t), n
    rec.redo(f)
    assert f.num_decoders == 2 and f.rad_decoders[1] is rec.added_decoders[0]   # the very module it added
    for n, t in after.items():
        assert torch.equal(getattr(f, n), t), n
    with pytest.raises(RuntimeError, match="cannot redo"):
        rec.redo(f)


def test_undo_out_of_order_is_refused(blob_mesh):
    f = textured_field(blob_mesh)
    first = EditRecord.begin("a", f, [1, 2], ("decoder_id",))
    other = copy.deepcopy(f.rad_decoder)
    with torch.no_grad():
        other[0].bias.add_(1.0)
        f.decoder_id[[1, 2]] = f.add_decoder(other)
    first.finish(f)
    second = EditRecord.begin("b", f, [3], ("decoder_id",))
    third_dec = copy.deepcopy(other)
    with torch.no_grad():
        third_dec[0].bias.add_(1.0)
        f.decoder_id[3] = f.add_decoder(third_dec)
    second.finish(f)
    with pytest.raises(RuntimeError, match="undo later edits first"):
        first.undo(f)
    second.undo(f)
    first.undo(f)
    assert f.num_decoders == 1 and int(f.decoder_id.abs().sum()) == 0


def test_count_changed_counts_rows_whose_values_moved_beyond_rounding(blob_mesh):
    f = textured_field(blob_mesh)
    region = np.arange(10, 20)
    rec = EditRecord.begin("test", f, region, ("mod_colours", "decoder_id"))
    assert rec.count_changed() == len(region)   # nothing to compare yet: every row written counts
    with torch.no_grad():
        f.mod_colours[10:12] += 0.25             # moved
        f.mod_colours[12:14] *= 1.0 + 1e-7       # a rounding difference: not a change
        f.decoder_id[14] = 1                     # an integer table: any difference is a change
    rec.finish(f)
    assert rec.count_changed() == 3
    assert rec.count_changed(rtol=0.0, atol=0.0) >= 3
