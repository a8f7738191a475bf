"""Code transfer shared by swap and fill: IDW weights, one decoder per target vertex, rotations."""
import copy

import numpy as np
import torch

from neumesh_core.edit.transfer import TransferPlan, apply_transfer, idw_neighbours, minimal_rotations

from ..conftest import textured_field


def test_idw_weights_sum_to_one_and_copy_coinciding_points():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3))
    q = np.concatenate([pts[:5], rng.normal(size=(20, 3))])
    idx, w = idw_neighbours(q, pts, k=4)
    assert idx.shape == (25, 4) and np.allclose(w.sum(1), 1.0)
    assert (idx[:5, 0] == np.arange(5)).all() and np.array_equal(w[:5], np.tile([1.0, 0, 0, 0], (5, 1)))
    d = np.linalg.norm(pts[idx[5:]] - q[5:, None], axis=-1)
    ref = (1 / d) / (1 / d).sum(1, keepdims=True)
    assert np.allclose(w[5:], ref)
    brute = np.argsort(np.linalg.norm(q[5:, None] - pts[None], axis=-1), axis=1)[:, :4]
    assert np.array_equal(idx[5:], brute)


def test_minimal_rotations_take_a_to_b_and_are_rotations():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(100, 3))
    b = rng.normal(size=(100, 3))
    b[0] = -a[0]           # opposite
    b[1] = a[1] * 3        # the same direction
    R = minimal_rotations(a, b)
    an = a / np.linalg.norm(a, axis=1, keepdims=True)
    bn = b / np.linalg.norm(b, axis=1, keepdims=True)
    assert np.allclose(np.einsum("nij,nj->ni", R, an), bn, atol=1e-9)
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(R), 1.0) and np.allclose(R[1], np.eye(3))


def test_a_target_vertex_is_bound_to_the_decoder_holding_most_of_its_weight(blob_mesh):
    """Codes of different decoders are never averaged: the weights of the minority decoder's vertices
    are dropped and the rest renormalised."""
    src = textured_field(blob_mesh)
    other = copy.deepcopy(src.rad_decoder)
    with torch.no_grad():
        for p in other.parameters():
            p.add_(0.5)
    with torch.no_grad():
        src.decoder_id[[10, 11]] = src.add_decoder(other)
    tgt = textured_field(blob_mesh, seed=1)
    plan = TransferPlan(np.array([0, 1]), np.array([[10, 11, 12, 13], [10, 12, 13, 14]]),
                        np.array([[0.4, 0.3, 0.2, 0.1], [0.4, 0.3, 0.2, 0.1]]))
    apply_transfer("t", tgt, plan, src)
    assert tgt.num_decoders == 2 and tgt.decoder_id[:2].tolist() == [1, 0]
    # row 0: decoder 1 holds 0.7 of the weight -> vertices 10, 11 renormalised to 4/7, 3/7
    assert torch.allclose(tgt.tex_codes[0], (4 * src.tex_codes[10] + 3 * src.tex_codes[11]) / 7, atol=1e-6)
    # row 1: decoder 0 holds 0.6 -> vertices 12, 13, 14 with 0.3, 0.2, 0.1 renormalised
    assert torch.allclose(tgt.tex_codes[1], (3 * src.tex_codes[12] + 2 * src.tex_codes[13] + src.tex_codes[14]) / 6,
                          atol=1e-6)
    assert torch.allclose(tgt.mod_colours[1],
                          (3 * src.mod_colours[12] + 2 * src.mod_colours[13] + src.mod_colours[14]) / 6, atol=1e-6)


def test_transfer_plans_average_several_queries_per_vertex():
    plan = TransferPlan.from_queries(np.array([3, 8]), np.array([0, 1, 0]),
                                     np.array([[1, 2], [5, 6], [7, 9]]), np.array([[1.0, 0], [0.5, 0.5], [0.25, 0.75]]))
    assert plan.src.shape == (2, 4) and np.allclose(plan.w.sum(1), 1.0)
    row0 = dict(zip(plan.src[0].tolist(), plan.w[0].tolist()))
    assert np.isclose(row0[1], 0.5) and np.isclose(row0[7], 0.125) and np.isclose(row0[9], 0.375)
