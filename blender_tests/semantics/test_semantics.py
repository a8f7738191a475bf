"""Semantics in Blender: Select by click (driven with a camera view and a pixel, and with the stored
viewport matrices the modal click records) writes the clicked part as a vertex group and the edit-mode
selection; Distill semantics runs the core in the background; semantic colours."""
from __future__ import annotations

import os
import sys
import shutil

import bpy
import numpy as np
import pytest

from helpers import add_camera, draw_panel

W, H = 64, 64


@pytest.fixture(scope="module")
def parts_data(tmp_path_factory):
    """(dataset dir, field without semantics, field with semantics, labels): the multi-part scene,
    48 px, trained and distilled briefly with the core."""
    import torch

    import neumesh_core as nm
    from neumesh_core.data import multipart as mp

    d = str(tmp_path_factory.mktemp("parts"))
    saved = torch.get_num_threads()
    torch.set_num_threads(1)   # see tests/semantics/conftest.py: busy 2-core machines
    try:
        mp.make_multipart_scene(d, resolution=48, n_train=16, n_val=1, n_test=0, grid=40)
        scene = nm.load_scene(d)
        field = nm.create_field(nm.load_mesh(os.path.join(d, "mesh.ply")), nm.FieldConfig(interpolation="early"))
        nm.train(field, scene, nm.TrainConfig(steps=150, rays_per_batch=1024, log_every=50))
        plain = os.path.join(d, "parts.neumesh")
        nm.save_field(field, plain)
        nm.semantics.distill_semantics(field, scene, config=nm.semantics.DistillConfig(
            steps=200, rays_per_view=1024, rays_per_batch=4096))
        sem = os.path.join(d, "parts_sem.neumesh")
        nm.save_field(field, sem)
    finally:
        torch.set_num_threads(saved)
    return d, plain, sem, np.load(os.path.join(d, "part_labels.npy"))


def _scene(path):
    assert bpy.ops.neumesh.load_field(filepath=path, new_object=True) == {"FINISHED"}
    obj = bpy.context.active_object
    cam = add_camera((3.4, -1.6, 1.6), look_at=(0.25, 0.0, 0.3), lens=40.0, name="cam")
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = W, H
    scene.render.resolution_percentage = 100
    return obj, cam


def _click_on(addon, cam, part):
    """The pixel deepest inside ``part``'s image region in the camera's view (ground-truth tracer)."""
    from scipy.ndimage import distance_transform_edt

    from neumesh_core.data import multipart as mp

    K, c2w, w, h = addon.scene.camera.camera_K_c2w(cam, bpy.context.scene)
    dt = distance_transform_edt(mp.label_image(K, c2w, w, h) == part)
    assert dt.max() > 2, "the part is not visible from the test camera"
    y, x = np.unravel_index(dt.argmax(), dt.shape)
    return (x + 0.5, y + 0.5)


def _group(obj, name):
    vg = obj.vertex_groups[name]
    return np.array(sorted(v.index for v in obj.data.vertices if any(g.group == vg.index for g in v.groups)))


def test_click_creates_the_parts_vertex_group(addon, parts_data):
    _, _, sem, labels = parts_data
    obj, cam = _scene(sem)
    head = _click_on(addon, cam, 1)
    assert bpy.ops.neumesh.select_by_click(camera="cam", pixel=head, group_name="head") == {"FINISHED"}
    got = _group(obj, "head")
    gt = np.nonzero(labels == 1)[0]
    precision = np.isin(got, gt).mean()
    recall = np.isin(gt, got).mean()
    assert precision > 0.9 and recall > 0.8, (precision, recall)
    assert obj.vertex_groups.active.name == "head"
    sel = np.zeros(len(obj.data.vertices), bool)
    obj.data.vertices.foreach_get("select", sel)
    assert np.array_equal(np.nonzero(sel)[0], got)          # the edit-mode selection is the group
    # the redo panel's slider: a stricter similarity re-runs the growth and keeps a subset
    assert bpy.ops.neumesh.select_by_click(camera="cam", pixel=head, group_name="head", threshold=0.97) == {"FINISHED"}
    strict = _group(obj, "head")
    assert len(strict) < len(got) and np.isin(strict, got).all()
    # Add mode: the base joins the same group
    base = _click_on(addon, cam, 3)
    assert bpy.ops.neumesh.select_by_click(camera="cam", pixel=base, group_name="head", mode="ADD") == {"FINISHED"}
    both = _group(obj, "head")
    assert np.isin(strict, both).all() and np.isin(np.nonzero(labels == 3)[0], both).mean() > 0.8
    # in edit mode the selection shows there too
    bpy.ops.object.mode_set(mode="EDIT")
    assert bpy.ops.neumesh.select_by_click(camera="cam", pixel=head) == {"FINISHED"}
    assert obj.mode == "EDIT"
    bpy.ops.object.mode_set(mode="OBJECT")
    assert np.array_equal(_group(obj, addon.semantics.select.DEFAULT_GROUP), got)


def test_the_viewport_click_path_uses_the_stored_view(addon, parts_data):
    """What the modal click stores (viewport view and window matrices, region size, region mouse
    coordinates) gives the same region as the camera path."""
    _, _, sem, labels = parts_data
    obj, cam = _scene(sem)
    head = _click_on(addon, cam, 1)
    dg = bpy.context.evaluated_depsgraph_get()
    P = cam.evaluated_get(dg).calc_matrix_camera(dg, x=W, y=H)
    V = cam.matrix_world.inverted()
    flat = lambda m: [v for row in m for v in row]  # noqa: E731
    assert bpy.ops.neumesh.select_by_click(view_matrix=flat(V), window_matrix=flat(P), view_size=(W, H),
                                           pixel=head, group_name="viewport") == {"FINISHED"}
    assert bpy.ops.neumesh.select_by_click(camera="cam", pixel=head, group_name="camera") == {"FINISHED"}
    assert np.array_equal(_group(obj, "viewport"), _group(obj, "camera"))


def test_context_prepared_before_the_click_gives_the_same_group(addon, parts_data):
    """Select by click starts building the selection context when it starts waiting for the click
    (prepare_selection, a background thread); the click then uses it and selects what a cold click
    selects."""
    _, _, sem, _ = parts_data
    obj, cam = _scene(sem)
    head = _click_on(addon, cam, 1)
    addon.semantics.select._CONTEXTS.clear()
    assert bpy.ops.neumesh.select_by_click(camera="cam", pixel=head, group_name="cold") == {"FINISHED"}
    addon.semantics.select._CONTEXTS.clear()
    job = addon.semantics.select.prepare_selection(obj, bpy.context)
    assert job is not None
    job.join()
    ctx = addon.semantics.select._CONTEXTS[obj.name_full]
    assert ctx._graph is not None and ctx._tree is not None   # built before the click
    assert addon.semantics.select.prepare_selection(obj, bpy.context) is None   # already current: nothing to do
    assert bpy.ops.neumesh.select_by_click(camera="cam", pixel=head, group_name="warm") == {"FINISHED"}
    assert addon.semantics.select._CONTEXTS[obj.name_full] is ctx                # reused, not rebuilt
    assert np.array_equal(_group(obj, "warm"), _group(obj, "cold"))
    # a field without semantics: nothing is started, the click reports the error
    plain_obj, _ = _scene(parts_data[1])
    assert addon.semantics.select.prepare_selection(plain_obj, bpy.context) is None


def test_click_errors(addon, parts_data):
    _, plain, sem, _ = parts_data
    obj, cam = _scene(sem)
    with pytest.raises(RuntimeError, match="background"):
        bpy.ops.neumesh.select_by_click(camera="cam", pixel=(0.5, 0.5))
    with pytest.raises(RuntimeError, match="no view"):
        bpy.ops.neumesh.select_by_click(pixel=(10, 10))
    assert "NeuMesh selection" not in obj.vertex_groups
    obj2, _ = _scene(plain)
    with pytest.raises(RuntimeError, match="no semantic codes") as exc:
        bpy.ops.neumesh.select_by_click(camera="cam", pixel=_click_on(addon, cam, 1))
    # the panel button that makes them, not a shell command
    assert "press Distill semantics (Edit field > Semantics)" in str(exc.value)
    assert "neumesh semantics --field" not in str(exc.value)


def test_distill_semantics_operator_writes_an_edit(addon, parts_data, tmp_path):
    import neumesh_core as nm

    d, plain, _, _ = parts_data
    src = str(tmp_path / "parts.neumesh")
    shutil.copy(plain, src)
    obj, _ = _scene(src)
    bpy.context.scene.neumesh.dataset_path = d
    bpy.context.scene.neumesh_semantics.steps = 3
    assert bpy.ops.neumesh.distill_semantics(wait=True, max_views=2, rays_per_view=64) == {"FINISHED"}
    out = addon.scene.props.field_abspath(obj)
    assert out == str(tmp_path / "parts.edit-001.neumesh")
    f = nm.load_field(out)
    assert f.has_semantics and f.semantics_info["steps"] == 3
    assert nm.edit.edit_info(out)["op"] == "semantics"
    assert bpy.ops.neumesh.undo_edit() == {"FINISHED"} and addon.scene.props.field_abspath(obj) == src
    bpy.context.scene.neumesh.dataset_path = str(tmp_path / "missing")
    with pytest.raises(RuntimeError, match="dataset folder"):
        bpy.ops.neumesh.distill_semantics(wait=True)
    # the former operator ids still run, for scripts and keymaps written against them
    with pytest.raises(RuntimeError, match="dataset folder"):
        bpy.ops.neumesh.distil_semantics(wait=True)
    assert bpy.ops.neumesh.distil_cancel() == {"CANCELLED"}


def test_semantic_colours(addon, parts_data):
    _, _, sem, labels = parts_data
    obj, _ = _scene(sem)
    assert bpy.ops.neumesh.semantic_colours() == {"FINISHED"}
    attr = obj.data.color_attributes[addon.semantics.semantic_colours.COLOUR_ATTRIBUTE]
    rgba = np.empty(len(obj.data.vertices) * 4, np.float32)
    attr.data.foreach_get("color", rgba)
    rgb = rgba.reshape(-1, 4)[:, :3]
    means = np.stack([rgb[labels == p].mean(0) for p in range(4)])
    # parts get different colours: every pair of part means differs clearly
    gaps = [np.abs(means[i] - means[j]).max() for i in range(4) for j in range(i + 1, 4)]
    assert min(gaps) > 0.1, means


def test_click_after_deleting_part_of_the_mesh_selects_mesh_vertices(addon, parts_data):
    """Topology edits: after deleting the base, the click maps the remapped field's vertices back to
    the mesh's own vertex indices (which shifted with the deletion)."""
    import bmesh

    _, _, sem, labels = parts_data
    obj, cam = _scene(sem)
    head = _click_on(addon, cam, 1)
    bm = bmesh.new()
    bm.from_mesh(obj.data)
    bm.verts.ensure_lookup_table()
    bmesh.ops.delete(bm, geom=[bm.verts[int(i)] for i in np.nonzero(labels == 3)[0]], context="VERTS")
    bm.to_mesh(obj.data)
    bm.free()
    kept = np.nonzero(labels != 3)[0]               # mesh vertex i is now field vertex kept[i]
    assert bpy.ops.neumesh.select_by_click(camera="cam", pixel=head, group_name="head") == {"FINISHED"}
    got = _group(obj, "head")
    gt = np.nonzero(labels[kept] == 1)[0]
    inter = len(np.intersect1d(got, gt))
    assert inter / len(got) > 0.9 and inter / len(gt) > 0.8


def test_shape_options_reach_the_core_and_cache_in_the_edits_folder(addon, parts_data, monkeypatch):
    """Select by click's redo panel has Shape weight and Stop at creases; they reach the core's
    SelectConfig, and the shape features are cached in the scene's Edits folder (geometry_cache), never
    in the folder the field was read from."""
    _, _, sem, _ = parts_data
    obj, cam = _scene(sem)
    head = _click_on(addon, cam, 1)
    nm = addon.runtime.core.get()
    rna = bpy.ops.neumesh.select_by_click.get_rna_type().properties
    assert "colour + shape" in rna["threshold"].description
    assert rna["geometry"].name == "Shape weight" and rna["creases"].name == "Stop at creases"
    seen = []
    real = nm.semantics.select_region

    def spy(field, view, pixel, cfg=None, context=None, **kw):
        seen.append((cfg.geometry, cfg.creases, context.geometry_cache))
        return real(field, view, pixel, cfg, context=context, **kw)

    monkeypatch.setattr(nm.semantics, "select_region", spy)
    addon.semantics.select._CONTEXTS.clear()
    sys.modules[nm.__name__ + ".semantics.geometry"]._MEMO.clear()   # computed here, not kept from another test
    assert bpy.ops.neumesh.select_by_click(camera="cam", pixel=head, group_name="shape", geometry=0.3,
                                           creases=False) == {"FINISHED"}
    folder = addon.scene.props.scene_edits_folder()
    assert folder != os.path.dirname(sem)
    assert seen == [(pytest.approx(0.3), False, folder)]
    assert any(f.startswith("neumesh-geometry-") and f.endswith(".npz") for f in os.listdir(folder))
    assert not any(f.startswith("neumesh-geometry-") for f in os.listdir(os.path.dirname(sem)))
    assert bpy.ops.neumesh.select_by_click(camera="cam", pixel=head, group_name="colour", geometry=0.0,
                                           creases=False) == {"FINISHED"}
    assert len(_group(obj, "colour")) > 0


def test_panel_says_selection_is_colour_only_without_robust_laplacian(addon, monkeypatch):
    """robust-laplacian is in the add-on's one dependency list (feature 'shape', what setup_blender.sh
    installs too); when it is missing the Semantics panel offers it and says selection uses colour only."""
    deps = addon.runtime.deps
    assert "robust-laplacian" in deps.full_requirements((3, 4, 0))
    assert deps.missing_for("shape") == []           # installed here
    panel = bpy.types.NEUMESH_PT_semantics
    labels, _ = draw_panel(panel, bpy.context)
    assert not any("colour only" in t for t in labels)
    real = deps.missing_for
    monkeypatch.setattr(deps, "missing_for", lambda f, s=None: ["robust-laplacian"] if f == "shape" else real(f, s))
    labels, ops = draw_panel(panel, bpy.context)
    text = " ".join(labels)
    assert "Shape-aware selection needs robust-laplacian" in text and "colour only" in text
    assert "neumesh.install_dependencies" in ops and "neumesh.select_by_click" in ops
    assert "robust-laplacian" in addon.semantics.select.shape_note({"geometry": "geometric features need "
                                                                           "robust-laplacian"})
    assert addon.semantics.select.shape_note({}) == ""
