"""The automatic swap alignment between fields, its fit check and the preview.

A swap whose aligned source does not cover the target is refused (EditError saying what to do) and
writes nothing; the multi-part scene's body lands on a region of the blob; a moved, rotated and scaled
copy of a field is found without pairs; the record counts the rows whose values changed.
"""
import copy
import os

import numpy as np
import pytest
import torch

import neumesh_core as nm
from neumesh_core.cli import main
from neumesh_core.data.multipart import multipart_mesh
from neumesh_core.edit import SwapConfig, swap_alignment, swap_texture
from neumesh_core.edit.align import Similarity
from neumesh_core.edit.fit_check import FitThresholds, fit_figures
from neumesh_core.errors import EditError

from ..conftest import textured_field
from .helpers import masked_psnr, render
from .test_swap import _other_texture, _region, _rotation

TABLES = ("tex_codes", "mod_colours", "decoder_id", "geo_codes")
# an alignment that places the multi-part body ~14 units from the 2-unit blob: a failed fit
OFF_TARGET = Similarity(0.67, np.eye(3), np.array([-9.95, -8.79, -5.73]))


@pytest.fixture(scope="module")
def multipart():
    """A field on the built-in multi-part scene's mesh (another field, another texture) and its
    per-vertex part labels (0 body, 1 head, 2 arm, 3 base)."""
    mesh, labels = multipart_mesh(grid=40)
    torch.manual_seed(1)
    f = nm.NeuMeshField(mesh, nm.FieldConfig())
    with torch.no_grad():
        f.tex_codes.normal_(0, 0.5)
        f.mod_colours.copy_(torch.tensor([0.5, -0.4, -0.4]).expand_as(f.mod_colours))
    f.eval()
    return f, labels


def _snapshot(f):
    return {n: getattr(f, n).detach().clone() for n in TABLES}


def _unchanged(f, before, decoders=1):
    for n, t in before.items():
        assert torch.equal(getattr(f, n), t), n
    assert f.num_decoders == decoders and f.tex_frame is None


def _cap(f, direction, n):
    """The ``n`` vertices of ``f`` farthest along ``direction`` (a cap of the blob)."""
    v = f.rest_vertices.numpy().astype(np.float64)
    return np.sort(np.argsort(-(v @ np.asarray(direction, np.float64)))[:n])


def test_fit_figures_of_a_perfect_and_a_lost_fit():
    rng = np.random.default_rng(0)
    t = rng.normal(size=(500, 3))
    same = fit_figures(t, t, 0.1)
    assert same.overlap == 1.0 and same.target_residual == 0.0 and same.centroid_offset < 1e-9
    assert same.problems(FitThresholds()) == []
    far = fit_figures(t + 14.0, t, 0.1)
    assert far.overlap == 0.0 and far.target_residual > 100
    assert len(far.problems(FitThresholds())) == 2
    # a coarser source is measured in its own (larger) edge length
    assert fit_figures(t[::4], t, 0.01, source_edge=1.0).overlap > 0.99
    assert fit_figures(t[::4], t, 0.01).overlap == pytest.approx(0.25)   # only the shared points
    with pytest.raises(ValueError, match="min_overlap"):
        FitThresholds(min_overlap=1.5)


def test_a_cross_field_swap_whose_alignment_fails_is_refused_and_changes_nothing(blob_mesh, multipart):
    """The multi-part scene's flat base onto the whole blob, rigid only: no similarity lays a slab over
    a closed blob."""
    f = textured_field(blob_mesh)
    src, labels = multipart
    before = _snapshot(f)
    base = np.nonzero(labels == 3)[0]
    everything = np.arange(f.num_vertices)
    cfg = SwapConfig(nonrigid=False)
    al = swap_alignment(f, everything, src, base, config=cfg)
    assert not al.ok and al.figures.overlap < FitThresholds().min_overlap
    with pytest.raises(EditError, match="Pick 3 or more vertex pairs") as exc:
        swap_texture(f, everything, src, base, config=cfg)
    assert "nothing was changed" in str(exc.value) and "non-rigid fit was off" in str(exc.value)
    _unchanged(f, before)
    # forced: applied, and the record carries the failed figures
    rec = swap_texture(f, everything, src, base, config=SwapConfig(nonrigid=False, check_fit=False))
    assert rec.info["fit_ok"] is False and rec.info["overlap"] == pytest.approx(al.figures.overlap)


def test_an_alignment_off_the_target_is_refused_and_no_file_is_written(blob_mesh, multipart, tmp_path,
                                                                        monkeypatch, capsys):
    """An alignment that places the body ~14 units from the 2-unit blob is caught by the fit check:
    `neumesh edit swap` fails with the message and writes no file."""
    f = textured_field(blob_mesh)
    src, labels = multipart
    tpath, spath = str(tmp_path / "blob.neumesh"), str(tmp_path / "parts.neumesh")
    nm.save_field(f, tpath)
    nm.save_field(src, spath)
    np.savetxt(tmp_path / "cap.txt", _cap(f, (0, 0, 1), 220), fmt="%d")
    np.savetxt(tmp_path / "body.txt", np.nonzero(labels == 0)[0], fmt="%d")
    monkeypatch.setattr("neumesh_core.edit.swap.initial_alignment", lambda *a, **k: OFF_TARGET)
    files = sorted(os.listdir(tmp_path))
    assert main(["edit", "swap", "--field", tpath, "--region", str(tmp_path / "cap.txt"), "--source", spath,
                 "--source-region", str(tmp_path / "body.txt")]) == 2
    err = capsys.readouterr().err
    assert "texture swap refused" in err and "0% of the target" in err and "vertex pairs" in err
    assert sorted(os.listdir(tmp_path)) == files          # no edited file
    g = nm.load_field(tpath)
    assert torch.equal(g.tex_codes, f.tex_codes)
    # --no-check applies it anyway (the artist's call), and the saved history keeps the failed fit
    assert main(["edit", "swap", "--field", tpath, "--region", str(tmp_path / "cap.txt"), "--source", spath,
                 "--source-region", str(tmp_path / "body.txt"), "--no-check", "--rigid"]) == 0
    out = str(tmp_path / "blob.edit-001.neumesh")
    assert nm.edit.edit_info(out)["history"][-1]["info"]["fit_ok"] is False


@pytest.mark.parametrize("direction", [(0, 0, 1), (0.6, -0.8, 0.0)])
def test_the_multipart_body_onto_a_region_of_the_blob_aligns(multipart, direction):
    """The body of the multi-part scene (another field) swapped onto an 888-vertex region of the
    10,242-vertex blob: the aligned body's centroid lies within one mean edge of the region's, the fit
    passes and the swap writes the region."""
    from neumesh_core.data.synthetic import default_mesh

    blob = textured_field(default_mesh(subdiv=5))
    src, labels = multipart
    region = _cap(blob, direction, 888)
    body = np.nonzero(labels == 0)[0]
    al = swap_alignment(blob, region, src, body)
    target = blob.rest_vertices.numpy().astype(np.float64)[region]
    edge = al.mean_edge
    assert np.linalg.norm(al.rigid_points.mean(0) - target.mean(0)) < 1e-6 * edge
    assert np.linalg.norm(al.points.mean(0) - target.mean(0)) < edge
    assert np.linalg.norm(al.transform.t) < 2.0 and al.ok, al.figures
    print(f"body -> blob {direction}: {al.figures}")
    before = blob.tex_codes.detach().clone()
    rec = swap_texture(blob, region, src, body)
    assert rec.info["overlap"] == pytest.approx(al.figures.overlap) and rec.num_changed == len(region)
    outside = np.setdiff1d(np.arange(blob.num_vertices), region)
    assert torch.equal(blob.tex_codes[outside], before[outside])


def _similar_copy(f, s, R, t):
    """``f`` moved to x -> s R x + t in its rest pose: the same codes and decoders on a new scaffold,
    texture frames R^T so that its decoders see what they saw before the move."""
    mesh = nm.Mesh((s * f.rest_vertices.numpy().astype(np.float64) @ R.T + t).astype(np.float32), f.faces.numpy())
    g = nm.NeuMeshField(mesh, f.config, num_decoders=f.num_decoders)
    g.load_state_dict({k: v for k, v in f.state_dict().items() if not k.startswith("scaffold.")}, strict=False)
    g.tex_frame = torch.as_tensor(R.T, dtype=torch.float32).expand(g.num_vertices, 3, 3).clone()
    g.eval()
    return g


@pytest.mark.parametrize("interp", ["post", "early"])
def test_a_moved_rotated_scaled_copy_is_found_without_pairs(blob_mesh, interp):
    """A copy of the field moved by a known similarity (scale 1.7, a rotation, a shift of 5 units);
    its region swapped back onto the original region with the automatic alignment recovers the
    similarity and renders like the untouched field (>= 40 dB)."""
    f = textured_field(blob_mesh, interp)
    img = render(f)
    s, R, t = 1.7, _rotation(110.0, -35.0), np.array([4.0, -2.5, 1.5])
    moved = _similar_copy(f, s, R, t)
    region = _region(f)
    rec = swap_texture(f, region, moved, region)
    M = rec.info["transform"]       # moved -> original: the inverse similarity
    assert rec.info["scale"] == pytest.approx(1 / s, rel=1e-6)
    assert np.allclose(M[:3, :3], R.T / s, atol=1e-5) and np.allclose(M[:3, 3], -R.T @ t / s, atol=1e-4)
    assert rec.info["pairs"] == 0 and rec.info["overlap"] == 1.0
    p = masked_psnr(render(f).rgb, img.rgb, np.ones(img.rgb.shape[:2], bool))
    print(f"{interp}: similar copy swapped back: {p:.1f} dB")
    assert p >= 40.0


def test_the_record_counts_rows_whose_values_changed(blob_mesh):
    """A region swapped onto itself writes its rows with the values they held: nothing changed.  A swap
    from another texture changes exactly the rows that differ afterwards."""
    f = textured_field(blob_mesh)
    region = _region(f)
    rec = swap_texture(f, region, f, region)
    assert len(rec.vertices) == len(region) and rec.num_changed == 0 and len(rec.changed) == 0
    before = _snapshot(f)
    src = _other_texture(f)
    with torch.no_grad():            # a few rows of the source already hold the target's values
        for n in ("tex_codes", "mod_colours"):
            getattr(src, n)[region[:5]] = getattr(f, n)[region[:5]]
    src.rad_decoders[0] = copy.deepcopy(f.rad_decoders[0])
    rec = swap_texture(f, region, src, region)
    differ = np.zeros(f.num_vertices, bool)
    for n in ("tex_codes", "mod_colours", "decoder_id"):
        differ |= (getattr(f, n) != before[n]).reshape(f.num_vertices, -1).any(1).numpy()
    assert np.array_equal(rec.changed, np.nonzero(differ)[0]) and rec.num_changed == len(region) - 5


def test_the_alignment_preview_writes_nothing_and_matches_the_swap(blob_mesh, multipart):
    f = textured_field(blob_mesh)
    src, labels = multipart
    before = _snapshot(f)
    region = _cap(f, (1, 0, 0), 300)
    body = np.nonzero(labels == 0)[0]
    al = swap_alignment(f, region, src, body)
    _unchanged(f, before)
    assert al.points.shape == al.rigid_points.shape == (len(body), 3) and al.message == ""
    assert len(al.faces) > 0 and al.faces.max() < len(body)       # the wireframe of the source region
    assert np.allclose(al.transform.apply(src.rest_vertices.numpy()[body]), al.rigid_points)
    g = copy.deepcopy(f)
    rec = swap_texture(f, region, src, body)
    info = al.info()
    for k in ("scale", "residual", "overlap", "target_residual", "centroid_offset"):
        assert rec.info[k] == pytest.approx(info[k], rel=1e-9, abs=1e-12), k
    # accepting the preview applies exactly what it showed, without aligning again
    accepted = swap_texture(g, region, src, body, alignment=al)
    assert torch.equal(g.tex_codes, f.tex_codes) and accepted.info["overlap"] == info["overlap"]
    with pytest.raises(EditError, match="other regions"):
        swap_texture(g, region[1:], src, body, alignment=al)


def test_automatic_alignment_of_a_differently_sampled_copy_with_near_equal_spreads():
    """The whole blob (spreads 0.342, 0.344, 0.399 along its principal axes: their order is not
    determined by the shape) at subdivision 4 onto a rotated, scaled, shifted copy at subdivision 5
    (other vertices): the rotation search and point-to-plane ICP about the fixed centroids find the
    pose."""
    from neumesh_core.data.synthetic import default_mesh
    from neumesh_core.edit.align import initial_alignment
    from neumesh_core.mesh import vertex_normals

    m4, m5 = default_mesh(subdiv=4), default_mesh(subdiv=5)
    v4, v5 = m4.vertices.astype(np.float64), m5.vertices.astype(np.float64)
    n4 = vertex_normals(m4.vertices, m4.faces).astype(np.float64)
    n5 = vertex_normals(m5.vertices, m5.faces).astype(np.float64)
    for deg_z, deg_x in ((70.0, 25.0), (-150.0, 80.0)):
        R = _rotation(deg_z, deg_x)
        T = Similarity(0.6, R, np.array([3.0, -1.0, 2.0]))
        A = initial_alignment(v4, T.apply(v5), dst_normals=n5 @ R.T, src_normals=n4)
        angle = np.degrees(np.arccos(np.clip((np.trace(A.R.T @ R) - 1) / 2, -1, 1)))
        assert angle < 0.1 and A.scale == pytest.approx(0.6, rel=1e-3), (deg_z, deg_x, angle)
