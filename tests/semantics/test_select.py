"""Selection from one click: errors for background clicks and fields without semantics, the region
growing fixed point, thresholds and the 3D-point variant."""
import numpy as np
import pytest

import neumesh_core as nm
from neumesh_core.semantics import SelectConfig, SelectionContext, select_at_point, select_region

from .conftest import one_thread, part_clicks


def _cam(scene_dir, view):
    return nm.load_scene(scene_dir).split("train").cameras.subset(view)


def test_click_on_background_is_a_clear_error(multipart_dir, semantic_field):
    field, _ = semantic_field
    cam = _cam(multipart_dir, 0)
    with pytest.raises(nm.SelectionError, match="background"):
        select_region(field, cam, (1.5, 1.5))
    with pytest.raises(nm.SelectionError, match="outside the 64x64 image"):
        select_region(field, cam, (64, 10))


def test_selection_on_a_field_without_semantics_says_to_distill(multipart_dir, multipart_field):
    with pytest.raises(nm.NoSemanticsError, match="neumesh semantics"):
        select_region(multipart_field, _cam(multipart_dir, 0), (32, 32))
    with pytest.raises(nm.NoSemanticsError):
        select_at_point(multipart_field, (0, 0, 0.75))


def test_point_variant_and_thresholds(multipart_dir, semantic_field):
    field, _ = semantic_field
    labels = np.load(f"{multipart_dir}/part_labels.npy")
    head_top = field.vertices[labels == 1][field.vertices[labels == 1][:, 2].argmax()]
    ctx = SelectionContext(field)
    with one_thread():
        loose = select_at_point(field, head_top, SelectConfig(threshold=0.6), context=ctx)
        strict = select_at_point(field, head_top, SelectConfig(threshold=0.9), context=ctx)
    assert set(strict.vertices) <= set(loose.vertices)
    assert (labels[loose.vertices] == 1).mean() > 0.9
    with pytest.raises(nm.SelectionError, match="nearest scaffold vertex"):
        select_at_point(field, (5.0, 5.0, 5.0), context=ctx)
    with pytest.raises(nm.SelectionError, match="lower the similarity"):
        select_at_point(field, head_top, SelectConfig(threshold=1.0), context=ctx)
    with pytest.raises(ValueError, match="cosine similarity"):
        SelectConfig(threshold=1.5)


def test_without_a_2d_segmenter_the_click_still_selects_its_part(multipart_dir, semantic_field):
    field, _ = semantic_field
    labels = np.load(f"{multipart_dir}/part_labels.npy")
    view, pixel = part_clicks(multipart_dir)[3]
    with one_thread():
        sel = select_region(field, _cam(multipart_dir, view), pixel, SelectConfig(segmenter=None))
    assert "segment_pixels" not in sel.info and (labels[sel.vertices] == 3).mean() > 0.9


def _grow_step_by_step(graph, ok, seeds):
    """Reference: add neighbours that pass until nothing is added."""
    region = set(int(s) for s in seeds if ok[s])
    frontier = list(region)
    while frontier:
        nxt = []
        for v in frontier:
            for u in graph.indices[graph.indptr[v]:graph.indptr[v + 1]]:
                if ok[u] and u not in region:
                    region.add(int(u))
                    nxt.append(int(u))
        frontier = nxt
    return np.array(sorted(region), np.int64)


def test_region_growing_equals_the_step_by_step_fixed_point(semantic_field):
    field, _ = semantic_field
    ctx = SelectionContext(field)
    rng = np.random.default_rng(0)
    for t in (0.5, 0.8):
        mean = ctx.features[rng.integers(field.num_vertices)]
        seeds = rng.integers(0, field.num_vertices, 20)
        got = ctx.grow(mean, seeds, t)
        ok = ctx.features @ (mean / np.linalg.norm(mean)) >= t
        assert np.array_equal(got, _grow_step_by_step(ctx.graph, ok, seeds))
    # the graph holds every mesh edge, symmetric
    faces = field.faces.numpy()
    g = ctx.graph
    assert g[faces[0, 0], faces[0, 1]] and g[faces[0, 1], faces[0, 0]]
    assert ctx.matches(field)
