"""Swap texture and Fill texture as Blender operators: vertex groups / UV maps in, an edited field
beside the trained one out; F12 shows the core's render of the edited file; undo restores.

Tolerance: F12 EXR decoded to sRGB against ``nm.render_camera`` within 1e-4 (as in test_engine).
"""
from __future__ import annotations

import os
import shutil

import bmesh
import bpy
import numpy as np
import pytest

from helpers import add_camera, exact_colour_settings, f12_srgb, manual_K_c2w

W, H = 40, 32


def _other_texture_file(trained_field, path):
    """The trained field with another texture and another radiance decoder (as if trained on other
    colours), saved to ``path``."""
    import torch

    import neumesh_core as nm

    f = nm.load_field(trained_field)
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        f.tex_codes.normal_(0, 0.8, generator=g)
        f.mod_colours.copy_(torch.tensor([-0.3, 0.4, -0.3]).expand_as(f.mod_colours))
        for p in f.rad_decoder.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=g))
    nm.save_field(f, path)
    return path


def _load(path, name):
    assert bpy.ops.neumesh.load_field(filepath=path, new_object=True) == {"FINISHED"}
    obj = bpy.context.active_object
    obj.name = name
    return obj


def _group(obj, name, indices):
    g = obj.vertex_groups.new(name=name)
    g.add([int(i) for i in indices], 1.0, "REPLACE")
    return g


def _core_render(path, cam):
    import neumesh_core as nm

    K, c2w = manual_K_c2w(cam, W, H)
    return np.clip(nm.render_camera(nm.load_field(path), K, c2w, W, H).rgb, 0, 1)


def _f12(path):
    """F12 as display values in [0, 1] (a modification colour can push the field's output past 1;
    the EXR keeps that, a PNG or the screen clips it)."""
    return np.clip(f12_srgb(path), 0, 1)


def _setup(trained_field, tmp_path):
    tgt_path = str(tmp_path / "blob.neumesh")
    shutil.copy(trained_field, tgt_path)
    src_path = _other_texture_file(trained_field, str(tmp_path / "other.neumesh"))
    source = _load(src_path, "Source")
    source.neumesh.enabled = False            # it sits where the target is: render only the target
    target = _load(tgt_path, "Target")
    xs = np.array([v.co.x for v in target.data.vertices])
    region = np.nonzero(xs > 0.1)[0]
    _group(target, "region", region)
    _group(source, "region", region)
    cam = add_camera((0.0, -4.6, 0.8), lens=35.0)
    scene = bpy.context.scene
    scene.render.engine = "NEUMESH"
    exact_colour_settings(scene, W, H)
    bpy.context.view_layer.objects.active = target
    return target, source, tgt_path, src_path, cam, region


def test_swap_by_vertex_groups_renders_in_f12_and_undo_restores(addon, trained_field, tmp_path):
    import neumesh_core as nm

    target, source, tgt_path, src_path, cam, region = _setup(trained_field, tmp_path)
    before_bytes = open(tgt_path, "rb").read()
    original = _f12(tmp_path / "a.exr")
    assert bpy.ops.neumesh.swap_texture(target_group="region", source_object="Source",
                                        source_group="region") == {"FINISHED"}
    edited = addon.scene.props.field_abspath(target)
    assert edited == str(tmp_path / "blob.edit-001.neumesh") and open(tgt_path, "rb").read() == before_bytes
    g = nm.load_field(edited)
    assert g.num_decoders == 2 and set(g.decoder_id[region].tolist()) == {1}
    after = _f12(tmp_path / "b.exr")
    assert np.abs(after - _core_render(edited, cam)).max() <= 1e-4
    assert (np.abs(after - original).max(-1) > 0.05).sum() > 20   # the swap is visible
    # the same edit through the core API gives the same field
    api = nm.load_field(tgt_path)
    nm.swap_texture(api, region, nm.load_field(src_path), region)
    assert np.abs(g.tex_codes.detach().numpy() - api.tex_codes.detach().numpy()).max() < 1e-6
    assert bpy.ops.neumesh.undo_edit() == {"FINISHED"}
    assert addon.scene.props.field_abspath(target) == tgt_path
    assert np.abs(_f12(tmp_path / "c.exr") - original).max() <= 1e-4


def test_swap_with_pairs_selected_in_edit_mode(addon, trained_field, tmp_path):
    target, source, tgt_path, _, cam, region = _setup(trained_field, tmp_path)
    picks = region[[0, len(region) // 3, 2 * len(region) // 3, -1]]
    for obj in (source, target):   # the same vertices in the same order on both objects
        bm = bmesh.new()
        bm.from_mesh(obj.data)
        bm.verts.ensure_lookup_table()
        for v in bm.verts:
            v.select = False
        for i in picks:
            bm.verts[int(i)].select = True
            bm.select_history.add(bm.verts[int(i)])
        bm.to_mesh(obj.data)
        bm.free()
    assert addon.edit.swap_fill.selected_pairs(target, source).tolist() == [[int(i), int(i)] for i in picks]
    assert bpy.ops.neumesh.swap_texture(target_group="region", source_object="Source", source_group="region",
                                        use_pairs=True) == {"FINISHED"}
    info = addon.runtime.core.get().edit.edit_info(addon.scene.props.field_abspath(target))
    assert info["history"][-1]["info"]["pairs"] == 4
    np.testing.assert_allclose(np.asarray(info["history"][-1]["info"]["transform"]), np.eye(4), atol=1e-6)


def _spherical_uv_map(obj, name="Sphere"):
    me = obj.data
    uv = me.uv_layers.new(name=name)
    n = len(me.loops)
    vi = np.empty(n, np.int32)
    me.loops.foreach_get("vertex_index", vi)
    co = np.array([v.co[:] for v in me.vertices])
    u = (np.arctan2(co[:, 1], co[:, 0]) / (2 * np.pi)) % 1.0
    w = np.arccos(np.clip(co[:, 2] / np.linalg.norm(co, axis=1), -1, 1)) / np.pi
    uv.data.foreach_set("uv", np.stack([u[vi], w[vi]], 1).astype(np.float32).ravel())
    return co


def test_fill_by_uv_maps(addon, trained_field, tmp_path):
    nm = addon.runtime.core.get()   # the add-on's own (vendored) core: its CornerUVs is the one corner_uvs makes
    target, source, tgt_path, src_path, cam, region = _setup(trained_field, tmp_path)
    _spherical_uv_map(target)
    co = _spherical_uv_map(source)
    tmpl = np.nonzero(co[:, 0] < -0.1)[0]
    _group(source, "template", tmpl)
    original = _f12(tmp_path / "a.exr")
    assert bpy.ops.neumesh.fill_texture(target_group="region", target_uv="Sphere", template_object="Source",
                                        template_group="template", template_uv="Sphere", scale=2.0) == {"FINISHED"}
    edited = addon.scene.props.field_abspath(target)
    assert edited.endswith("blob.edit-001.neumesh")
    after = _f12(tmp_path / "b.exr")
    assert np.abs(after - _core_render(edited, cam)).max() <= 1e-4
    assert (np.abs(after - original).max(-1) > 0.05).sum() > 10
    # Blender's per-loop UVs are the corner UVs the core takes
    uvs = addon.edit.swap_fill.corner_uvs(source, "Sphere")
    api = nm.load_field(tgt_path)
    nm.fill_texture(api, region, addon.edit.swap_fill.corner_uvs(target, "Sphere"), nm.load_field(src_path), tmpl,
                    uvs, scale=2.0)
    assert np.abs(nm.load_field(edited).tex_codes.detach().numpy() - api.tex_codes.detach().numpy()).max() < 1e-6


def test_bad_input_reports_and_changes_nothing(addon, trained_field, tmp_path):
    target, source, tgt_path, _, _, region = _setup(trained_field, tmp_path)
    _group(target, "empty", [])
    bpy.ops.mesh.primitive_cube_add()
    cube = bpy.context.active_object
    cube.name = "Cube"
    bpy.context.view_layer.objects.active = target
    cases = [
        (dict(target_group="nope", source_object="Source", source_group="region"), "no vertex group 'nope'"),
        (dict(target_group="empty", source_object="Source", source_group="region"), "is empty"),
        (dict(target_group="", source_object="Source", source_group="region"), "choose a vertex group"),
        (dict(target_group="region", source_object="Cube", source_group="region"), "has no NeuMesh field"),
        (dict(target_group="region", source_object="Ghost", source_group="region"), "does not exist"),
        (dict(target_group="region", source_object="Source", source_group="region", use_pairs=True),
         "0 pairs selected"),
    ]
    for kwargs, msg in cases:
        with pytest.raises(RuntimeError, match=msg):
            bpy.ops.neumesh.swap_texture(**kwargs)
        assert addon.scene.props.field_abspath(target) == tgt_path
    with pytest.raises(RuntimeError, match="no UV map 'UVMissing'"):
        bpy.ops.neumesh.fill_texture(target_group="region", target_uv="UVMissing", template_group="region",
                                     template_uv="UVMissing")
    assert addon.scene.props.field_abspath(target) == tgt_path
    assert sorted(os.listdir(tmp_path)) == ["a.exr", "blob.neumesh", "other.neumesh"] or \
        not any(n.endswith(".edit-001.neumesh") for n in os.listdir(tmp_path))


def test_a_cancelled_background_edit_changes_nothing(addon, trained_field, tmp_path):
    """What Esc does in the modal operator: the job's progress callback answers False, the core raises
    Cancelled, the field copy is dropped and the object keeps its file."""
    nm = addon.runtime.core.get()
    target, _, tgt_path, _, _, region = _setup(trained_field, tmp_path)
    field, _ = addon.edit.base.field_for_edit(target)
    work = addon.edit.base.edit_copy(field)
    assert work is not field and work.num_vertices == field.num_vertices
    job = addon.runtime.jobs.Job("swap", lambda progress: [nm.swap_texture(work, region, work, region,
                                                                        progress=progress)])
    job.cancel()
    job.start().join()
    assert job.cancelled and job.result is None and job.error is None
    assert addon.scene.props.field_abspath(target) == tgt_path
    assert not any(".edit-" in n for n in os.listdir(tmp_path))


def test_a_region_swapped_onto_itself_changes_nothing_and_writes_no_file(addon, trained_field, tmp_path):
    """Swapping a region onto itself changes no row, so nothing is saved, the object keeps its file and
    the report counts no changed vertex."""
    target, _, tgt_path, _, _, region = _setup(trained_field, tmp_path)
    field, _ = addon.edit.base.field_for_edit(target)
    nm = addon.runtime.core.get()
    work = addon.edit.base.edit_copy(field)
    rec = nm.swap_texture(work, region, work, region)
    # the record holds every row it wrote; num_changed and count_changed count none of them
    assert len(rec.vertices) == len(region) and rec.num_changed == 0 and rec.count_changed() == 0
    other = addon.edit.base.edit_copy(field)
    import torch

    rec2 = nm.edit.EditRecord.begin("probe", other, region[:5], ("mod_colours",))
    with torch.no_grad():
        other.mod_colours[torch.as_tensor(region[:2])] += 0.25
    rec2.finish(other)
    assert rec2.count_changed() == 2   # the rows whose values moved, not all it wrote
    assert bpy.ops.neumesh.swap_texture(target_group="region", source_object="", source_group="region",
                                        nonrigid=False) == {"FINISHED"}
    assert addon.scene.props.field_abspath(target) == tgt_path
    assert not any(".edit-" in n for n in os.listdir(tmp_path))
