"""A field carried onto another mesh through vertex ids (what topology edits in a modeller need):
identity, subsets, duplicates, new vertices, and ids that must be rejected."""

import numpy as np
import pytest
import torch

import neumesh_core as nm
from neumesh_core.field.remap import (field_key, is_identity, remap_field, resolve_ids, split_by_key,
                                      sub_triangles)

from ..conftest import textured_field
from ..edit.helpers import only_touching


def _cam(size=40, az=0.0):
    from neumesh_core.data.synthetic import look_at_opencv

    a = np.radians(az)
    K = np.array([[0.9 * size, 0, size / 2], [0, 0.9 * size, size / 2], [0, 0, 1]], np.float32)
    return K, look_at_opencv(3.5 * np.array([np.sin(a), -np.cos(a), 0.3])).astype(np.float32)


def _render(f, size=40, az=0.0):
    K, c2w = _cam(size, az)
    return nm.render_camera(f, K, c2w, size, size)


def _midpoint_subdivide(vertices, faces):
    """Each triangle into four; new vertices at edge midpoints (as a modeller interpolates a point
    attribute such as the rest position)."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    mid = len(vertices) + inv.reshape(3, -1).T          # (F,3): midpoints of edges 01, 12, 20
    v = np.concatenate([vertices, 0.5 * (vertices[uniq[:, 0]] + vertices[uniq[:, 1]])])
    a, b, c = faces.T
    m01, m12, m20 = mid.T
    f = np.concatenate([np.stack([a, m01, m20], 1), np.stack([m01, b, m12], 1), np.stack([m20, m12, c], 1),
                        np.stack([m01, m12, m20], 1)])
    return v, f


@pytest.mark.parametrize("interp", ["post", "early"])
def test_the_identity_map_renders_the_field(blob_mesh, interp):
    f = textured_field(blob_mesh, interp)
    rest = f.rest_vertices.numpy()
    ids = np.arange(f.num_vertices)
    assert is_identity(f, ids) and not is_identity(f, ids[::-1])
    g = remap_field(f, ids, rest, f.faces.numpy())
    assert g.geo_decoder is f.geo_decoder and g.rad_decoders[0] is f.rad_decoders[0]   # shared
    assert np.abs(_render(g).rgb - _render(f).rgb).max() < 1e-5
    assert field_key(g) == field_key(f)


def test_a_subset_renders_only_its_part(blob_mesh):
    """Keep the vertices with y > 0: the pixels that see only kept vertices in the full field render
    as before, and nothing appears where only deleted vertices were."""
    f = textured_field(blob_mesh)
    rest = f.rest_vertices.numpy()
    keep = np.nonzero(rest[:, 1] > 0)[0]
    pos = np.full(f.num_vertices, -1)
    pos[keep] = np.arange(len(keep))
    faces = f.faces.numpy()
    kf = faces[(pos[faces] >= 0).all(1)]
    g = remap_field(f, keep, rest[keep], pos[kf])
    assert g.num_vertices == len(keep)
    full, part = _render(f, az=90.0), _render(g, az=90.0)
    assert part.opacity.sum() < 0.8 * full.opacity.sum()      # the deleted half is gone
    pure = only_touching(f, keep, cam=_cam(40, 90.0), size=40)
    assert pure.sum() > 100
    assert np.abs(part.rgb[pure] - full.rgb[pure]).max() < 2e-3


def test_a_moved_duplicate_renders_like_the_original_moved(blob_mesh):
    f = textured_field(blob_mesh)
    rest = f.rest_vertices.numpy()
    ids = np.arange(f.num_vertices)
    dup = remap_field(f, ids, rest, f.faces.numpy())
    shift = np.array([0.0, 0.0, 0.4], np.float32)
    dup.set_vertices(rest + shift)
    K, c2w = _cam()
    moved_cam = c2w.copy()
    moved_cam[:3, 3] -= shift                                  # the camera moved the other way
    a = nm.render_camera(dup, K, c2w, 40, 40).rgb
    b = nm.render_camera(f, K, moved_cam, 40, 40).rgb
    assert np.abs(a - b).max() < 1e-4


def test_new_vertices_are_interpolated_from_the_nearest_field_vertices(blob_mesh):
    """Midpoint subdivision: the original vertices keep their rows, each new one takes the inverse-
    distance mean of its 4 nearest field vertices (in the rest pose); the image stays close to the
    original (a trained field is smoother than this random-coded blob)."""
    from neumesh_core.edit.transfer import idw_neighbours
    from neumesh_core.metrics import psnr

    f = textured_field(blob_mesh)
    rest = f.rest_vertices.numpy().astype(np.float64)
    v, faces = _midpoint_subdivide(rest, f.faces.numpy())
    n = f.num_vertices
    ids = np.concatenate([np.arange(n), np.full(len(v) - n, -1)])
    g = remap_field(f, ids, v, faces)
    assert g.num_vertices == len(v) and torch.equal(g.tex_codes[:n], f.tex_codes.detach())
    idx, w = idw_neighbours(v[n:], rest, 4)
    want = (f.tex_codes.detach().numpy()[idx] * w[..., None]).sum(1)
    assert np.allclose(g.tex_codes[n:].detach().numpy(), want, atol=1e-5)
    p = psnr(np.clip(_render(g).rgb, 0, 1), np.clip(_render(f).rgb, 0, 1))
    print(f"midpoint subdivision: {p:.1f} dB against the original render")
    assert p > 25


def test_ids_whose_rest_position_disagrees_are_new_vertices(blob_mesh):
    f = textured_field(blob_mesh)
    rest = f.rest_vertices.numpy().copy()
    ids = np.arange(f.num_vertices)
    ids[5] = 10 ** 6            # out of range
    rest[7] += 0.01             # an interpolated (moved) rest position
    got = resolve_ids(f, ids, rest)
    assert got[5] == -1 and got[7] == -1 and (got[8:] == np.arange(8, f.num_vertices)).all()
    other = textured_field(blob_mesh, seed=3)
    assert field_key(other) != field_key(f)


def test_a_joined_mesh_splits_by_field_key_and_unknown_keys_count_as_its_own():
    keys = np.array([7, 3, 7, 99, 3, 5])           # 99: no field of that key; 5: the mesh's own field
    groups = split_by_key(keys, known={5: None, 3: None, 7: None}, own=5)
    assert [k for k, _ in groups] == [3, 5, 7]
    assert [sel.tolist() for _, sel in groups] == [[1, 4], [3, 5], [0, 2]]
    assert [k for k, _ in split_by_key(np.array([99, 98]), known={5: None}, own=5)] == [5]


def test_sub_triangles_keeps_the_triangles_inside_the_selection_renumbered():
    tri = np.array([[0, 1, 2], [2, 3, 4], [1, 3, 4], [4, 5, 1]])
    out = sub_triangles(tri, np.array([1, 3, 4, 5]), 6)
    assert out.tolist() == [[0, 1, 2], [2, 3, 0]]
    assert sub_triangles(tri, np.array([0, 5]), 6).shape == (0, 3)
