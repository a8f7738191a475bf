"""Render passes, render settings and "Composite with scene" (bpy 5.0.1 in-process; the real
`blender -b -a` run is in test_real_blender.py).

Tolerances (stated):
* Depth pass against the core's ray depth turned into camera-axis Z: 1e-4 relative (float32).
* Depth pass against Cycles' Z of the scaffold mesh itself (opaque proxy), where the field is opaque
  (opacity > 0.9) and Cycles hits the mesh: median |dz| <= 0.75 and 90th percentile <= 1.25 field
  radii (radius 0.40, camera 4 away). The Z of a field is its opacity-weighted
  expected depth and its surface is learned, not the scaffold's: the 40-step test blob is a soft shell
  whose weight lies ~0.2 behind the scaffold.
* Border / resolution percentage: the image size Cycles gives, and the same pixels as the
  corresponding part of the full frame (EXR, 1e-5).
* Composite: every pixel equals the Z-combination of the separate Cycles and NeuMesh renders (1e-3),
  the cube where it is in front of the field, the field (alpha > 0.9, mixed over the cube by its
  alpha) where it is in front of the cube.
"""
from __future__ import annotations

import math

import bpy
import numpy as np
import pytest

from helpers import (add_camera, bar_through_field, combine_expected, cycles_fast, exact_colour_settings,
                     read_exr, render_pass)

W, H = 64, 48


def _field_object(field_path):
    assert bpy.ops.neumesh.load_field(filepath=field_path, new_object=True) == {"FINISHED"}
    return bpy.context.active_object


def _scene(addon, field_path, cam_at=(0.0, -4.0, 0.6)):
    obj = _field_object(field_path)
    cam = add_camera(cam_at, lens=35.0)
    scene = bpy.context.scene
    scene.render.engine = "NEUMESH"
    exact_colour_settings(scene, W, H)
    bpy.context.view_layer.use_pass_z = True
    return obj, cam, scene


def _core(addon, field_path, scene, cam, transparent=True):
    """The core's render of the frame (vertices, K, c2w as the engine takes them)."""
    import neumesh_core as nm

    dg = bpy.context.evaluated_depsgraph_get()
    items = addon.render.field_cache.collect(dg)
    K, c2w, w, h = addon.scene.camera.camera_K_c2w(cam, scene, dg)
    field = nm.load_field(field_path)
    field.set_vertices(items[0].vertices)
    return nm.render_camera(field, K, c2w, w, h, background=None if transparent else (1, 1, 1)), K, c2w, field


def test_depth_pass_is_camera_axis_distance_and_matches_cycles_of_the_scaffold(addon, trained_field, tmp_path):
    obj, cam, scene = _scene(addon, trained_field)
    cam.data.shift_x, cam.data.shift_y, cam.data.sensor_fit = 0.08, -0.05, "VERTICAL"   # as Cycles projects
    cam.data.sensor_height = 30.0
    scene.render.film_transparent = True
    z = render_pass(addon.render.composite, scene, "Depth", tmp_path / "z.exr")[..., 0]
    alpha = render_pass(addon.render.composite, scene, "Alpha", tmp_path / "a.exr")[..., 0]
    mod = render_pass(addon.render.composite, scene, addon.render.engine.MOD_PASS, tmp_path / "m.exr")[..., :3]
    ref, K, c2w, field = _core(addon, trained_field, scene, cam)
    np.testing.assert_allclose(mod, ref.mod_colour, atol=1e-5)   # the modification-colour layer
    hit = np.isfinite(ref.depth)
    assert hit.mean() > 0.2 and (~hit).mean() > 0.2
    # alpha is the field's opacity (Film > Transparent)
    np.testing.assert_allclose(alpha, ref.opacity, atol=1e-4)
    # the Z of each hit point, worked out here: the point along the pixel's ray, projected on the axis
    import neumesh_core as nm

    o, d = nm.pixel_rays(K, c2w, W, H)
    pts = o.numpy() + d.numpy() * np.where(hit, ref.depth, 0.0).reshape(-1, 1)
    forward = c2w[:3, 2] / np.linalg.norm(c2w[:3, 2])
    z_axis = ((pts - c2w[:3, 3]) @ forward).reshape(H, W)
    np.testing.assert_allclose(z[hit], z_axis[hit], rtol=1e-4)
    assert np.all(z[~hit] > 1e9)   # empty: infinitely far
    # Cycles' Z of the scaffold mesh itself (an opaque proxy at the field's surface)
    cycles_fast(scene, samples=1)
    zc = render_pass(addon.render.composite, scene, "Depth", tmp_path / "zc.exr")[..., 0]
    both = (ref.opacity > 0.9) & (zc < 1e9)
    dz = np.abs(z - zc)[both] / float(field.config.radius)
    print(f"Z vs Cycles of the scaffold: median {np.median(dz):.3f}, p90 {np.percentile(dz, 90):.3f} radii "
          f"(radius {float(field.config.radius):.3f}, {both.sum()} px); Cycles' empty Z {zc[~hit].min():.3g}")
    assert both.sum() > 100
    assert np.median(dz) <= 0.75 and np.percentile(dz, 90) <= 1.25
    assert np.all(zc[~hit] >= 1e10)   # Cycles' "nothing there" (the field's is inf: both beyond anything)


def _render_exr(scene, path):
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True, scene=scene.name)
    return read_exr(str(path))


def _set_border(scene, on=True, crop=True):
    r = scene.render
    r.use_border, r.use_crop_to_border = on, crop
    r.border_min_x, r.border_max_x, r.border_min_y, r.border_max_y = 0.21, 0.77, 0.13, 0.62


def test_border_and_resolution_percentage_give_cycles_sizes_and_the_same_pixels(addon, trained_field, tmp_path):
    obj, cam, scene = _scene(addon, trained_field)
    scene.render.film_transparent = True
    scene.render.resolution_percentage = 50
    full = _render_exr(scene, tmp_path / "full.exr")
    assert full.shape[:2] == (H // 2, W // 2) and full[..., 3].max() > 0.5
    sizes = {}
    for crop in (True, False):
        _set_border(scene, crop=crop)
        scene.render.engine = "NEUMESH"
        got = _render_exr(scene, tmp_path / f"nm_{crop}.exr")
        cycles_fast(scene, samples=1)
        sizes[crop] = (got.shape[:2], _render_exr(scene, tmp_path / f"cy_{crop}.exr").shape[:2])
        w, h = W // 2, H // 2
        x0, x1 = int(0.21 * w), int(0.77 * w)
        r0, r1 = h - int(0.62 * h), h - int(0.13 * h)
        part = full[r0:r1, x0:x1]
        if crop:
            assert got.shape[:2] == part.shape[:2]
            np.testing.assert_allclose(got, part, atol=1e-5)
        else:   # the frame's size, the region in place, nothing outside it
            assert got.shape[:2] == full.shape[:2]
            np.testing.assert_allclose(got[r0:r1, x0:x1], part, atol=1e-5)
            outside = np.ones(got.shape[:2], bool)
            outside[r0:r1, x0:x1] = False
            assert got[outside].max() == 0.0
        _set_border(scene, on=False)
    for crop, (nm_size, cy_size) in sizes.items():
        assert nm_size == cy_size, (crop, nm_size, cy_size)
    assert sizes[True][0] != sizes[False][0]


def test_holdout_object_cuts_the_field_and_leaves_a_hole(addon, trained_field, tmp_path):
    obj, cam, scene = _scene(addon, trained_field)
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=(-0.5, -1.5, 0.3), rotation=(math.radians(90), 0, 0))
    plane = bpy.context.active_object   # in front of the left part of the field, facing the camera
    scene.render.film_transparent = False
    free = {s: render_pass(addon.render.composite, scene, s, tmp_path / f"free_{s}.exr") for s in ("Image", "Depth")}
    plane.is_holdout = True
    held = {s: render_pass(addon.render.composite, scene, s, tmp_path / f"held_{s}.exr") for s in ("Image", "Depth")}
    # where the plane is: its own Z (Cycles' Z of the same plane, made opaque), alpha 0, no field
    plane.is_holdout = False
    obj.hide_render = True
    cycles_fast(scene, samples=1)
    zp = render_pass(addon.render.composite, scene, "Depth", tmp_path / "plane_z.exr")[..., 0]
    on_plane = zp < 1e9
    assert on_plane.mean() > 0.05 and (free["Image"][..., 3] == 1).all()
    np.testing.assert_allclose(held["Depth"][..., 0][on_plane], zp[on_plane], rtol=1e-4)
    assert held["Image"][..., 3][on_plane].max() == 0.0 and np.abs(held["Image"][on_plane]).max() == 0.0
    # elsewhere the frame is unchanged
    np.testing.assert_allclose(held["Image"][~on_plane], free["Image"][~on_plane], atol=1e-6)
    field_there = on_plane & (free["Depth"][..., 0] < 1e9)
    assert field_there.sum() > 20
    # a holdout behind the field hides nothing of it: only the background around the field is cut
    obj.hide_render = False
    scene.render.engine = "NEUMESH"
    plane.location, plane.scale = (-0.5, 2.5, 0.3), (4.0, 4.0, 4.0)
    plane.is_holdout = True
    behind = render_pass(addon.render.composite, scene, "Image", tmp_path / "behind.exr")
    ref, *_ = _core(addon, trained_field, scene, cam)
    a = behind[..., 3]
    kept = a == 1.0   # no holdout there: the frame as before
    np.testing.assert_allclose(behind[kept], free["Image"][kept], atol=1e-6)
    # over the holdout: alpha is the field's opacity, the field in front of it is whole
    np.testing.assert_allclose(a[~kept], ref.opacity[~kept], atol=1e-4)
    assert ((~kept) & (ref.opacity > 0.9)).sum() > 20
    assert (a < 1e-4).sum() > 20   # the plane's hole where no field is in front of it


def test_composite_with_scene_occludes_both_ways_and_survives_reload(addon, trained_field, tmp_path):
    obj, cam, scene = _scene(addon, trained_field)
    bar_through_field()
    cycles_fast(scene, samples=4)
    assert bpy.ops.neumesh.composite_with_scene() == {"FINISHED"}
    comp = scene.neumesh.composite_scene
    assert comp is not None and comp.render.engine == "NEUMESH" and comp.camera is cam
    assert obj.name in comp.objects and scene.render.engine == "CYCLES"
    assert bpy.ops.neumesh.composite_with_scene() == {"FINISHED"}   # again: updates, nothing doubled
    assert len([s for s in bpy.data.scenes if s.name.startswith(scene.name + " NeuMesh")]) == 1
    tree = addon.render.composite.compositor_tree(scene, create=False)
    assert len([n for n in tree.nodes if n.bl_idname == "CompositorNodeZcombine"]) == 1
    got = _render_exr(scene, tmp_path / "comp.exr")
    # the separate renders: the Cycles layer (without the field's scaffold) and the field layer
    cyc = render_pass(addon.render.composite, scene, "Image", tmp_path / "cyc.exr")
    zc = render_pass(addon.render.composite, scene, "Depth", tmp_path / "zc.exr")[..., 0]
    fld = render_pass(addon.render.composite, comp, "Image", tmp_path / "fld.exr")
    zf = render_pass(addon.render.composite, comp, "Depth", tmp_path / "zf.exr")[..., 0]
    bar = zc < 1e9
    field = fld[..., 3] > 0.9
    bar_front = bar & field & (zc < zf)
    field_front = bar & field & (zf < zc)
    assert bar_front.sum() >= 15 and field_front.sum() >= 15, (bar_front.sum(), field_front.sum())
    np.testing.assert_allclose(got[bar_front], cyc[bar_front], atol=1e-3)
    a = fld[..., 3:4]   # the field (premultiplied, alpha > 0.9) over the bar
    np.testing.assert_allclose(got[field_front][:, :3], (fld + cyc * (1 - a))[field_front][:, :3], atol=1e-3)
    assert np.abs(got - cyc)[field_front].max() > 0.1
    diff = np.abs(got - combine_expected(cyc, zc, fld, zf)).max()
    assert diff <= 1e-3, diff
    # saved and opened again: the companion scene, the tree and the same picture
    path = str(tmp_path / "comp.blend")
    bpy.ops.wm.save_as_mainfile(filepath=path)
    bpy.ops.wm.open_mainfile(filepath=path)
    scene = bpy.context.scene
    assert scene.neumesh.composite_scene is not None
    again = _render_exr(scene, tmp_path / "again.exr")
    np.testing.assert_allclose(again, got, atol=1e-5)


def test_field_object_stays_editable_in_the_artists_scene(addon, trained_field, tmp_path):
    """After Composite with Scene the field object is still in the main scene's view layer
    (visible, selectable; the edit panels draw their tools for it), its edit collection is off in renders
    (Cycles does not render the scaffold), the companion scene renders it; a bake goes to the artist's
    active collection, never to the edit collection; an older file's layout (excluded collection) is
    changed to this one."""
    from helpers import draw_panel

    comp_mod = addon.render.composite
    obj, cam, scene = _scene(addon, trained_field)
    bar_through_field()
    cycles_fast(scene, samples=2)
    # the earlier layout: the fields collection linked in the main scene and excluded there
    old = bpy.data.collections.new(comp_mod.FIELDS_COLLECTION)
    scene.collection.children.link(old)
    scene.view_layers[0].layer_collection.children[old.name].exclude = True
    assert bpy.ops.neumesh.composite_with_scene() == {"FINISHED"}
    comp = scene.neumesh.composite_scene
    vl = bpy.context.view_layer
    edit = bpy.data.collections[comp_mod.EDIT_COLLECTION]
    assert old.name not in scene.collection.children              # moved out of the main scene
    assert obj.name in vl.objects and obj.visible_get(view_layer=vl) and edit.hide_render
    assert obj.name in comp.objects and not bpy.data.collections[comp_mod.FIELDS_COLLECTION].hide_render
    assert set(obj.users_collection) == {edit, bpy.data.collections[comp_mod.FIELDS_COLLECTION]}
    vl.objects.active = obj
    obj.select_set(True)
    labels, ops = draw_panel(bpy.types.NEUMESH_PT_edit, bpy.context)
    assert "neumesh.undo_edit" in ops and not any("Select an object" in t for t in labels)
    assert "neumesh.select_by_click" in draw_panel(bpy.types.NEUMESH_PT_semantics, bpy.context)[1]
    # the main scene's Cycles layer has no scaffold: its depth is the bar's alone
    zc = render_pass(comp_mod, scene, "Depth", tmp_path / "zc.exr")[..., 0]
    obj.hide_render = True
    try:
        bar_only = render_pass(comp_mod, scene, "Depth", tmp_path / "bar.exr")[..., 0]
    finally:
        obj.hide_render = False
    assert np.array_equal(zc < 1e9, bar_only < 1e9)
    fld = render_pass(comp_mod, comp, "Image", tmp_path / "fld.exr")
    assert fld[..., 3].max() > 0.9                                # the companion still renders the field
    # a bake lands in the artist's active collection; with the edit collection active, in the scene's
    mine = bpy.data.collections.new("props")
    scene.collection.children.link(mine)
    vl.active_layer_collection = vl.layer_collection.children["props"]
    assert addon.bake.material.output_collection(bpy.context) is mine
    vl.active_layer_collection = vl.layer_collection.children[edit.name]
    assert addon.bake.material.output_collection(bpy.context) is scene.collection
    # with nothing selected the panel's message is wrapped, not cut
    vl.objects.active = None
    labels, _ = draw_panel(bpy.types.NEUMESH_PT_paint, bpy.context)
    labels, _ = draw_panel(bpy.types.NEUMESH_PT_bake, bpy.context)
    assert " ".join(labels).split() == "Select an object with a field".split() or \
        any("Select an" in t for t in labels)


def test_each_view_layer_renders_its_own_visible_fields(addon, trained_field, tmp_path):
    """Per-view-layer visibility: a second view layer that excludes the field's collection renders
    nothing of it; the first still shows it (each layer's passes go to its own render layer)."""
    obj, cam, scene = _scene(addon, trained_field)
    scene.render.film_transparent = True
    coll = bpy.data.collections.new("fields")
    scene.collection.children.link(coll)
    coll.objects.link(obj)
    scene.collection.objects.unlink(obj)
    other = scene.view_layers.new("without field")
    other.layer_collection.children["fields"].exclude = True
    first = render_pass(addon.render.composite, scene, "Alpha", tmp_path / "first.exr", scene.view_layers[0].name)
    second = render_pass(addon.render.composite, scene, "Alpha", tmp_path / "second.exr", "without field")
    assert first[..., 0].max() > 0.5 and second[..., 0].max() == 0.0


def test_composite_with_scene_keeps_eevee_and_says_what_is_missing(addon, trained_field):
    scene = bpy.context.scene
    with pytest.raises(RuntimeError, match="no object with a NeuMesh field"):
        add_camera((0.0, -4.0, 0.6))
        bpy.ops.neumesh.composite_with_scene()
    scene.camera = None
    _field_object(trained_field)
    with pytest.raises(RuntimeError, match="no camera"):
        bpy.ops.neumesh.composite_with_scene()
    scene.camera = bpy.data.objects["cam"]
    eevee = next(e for e in ("BLENDER_EEVEE_NEXT", "BLENDER_EEVEE")
                 if e in {i.identifier for i in scene.render.bl_rna.properties["engine"].enum_items})
    scene.render.engine = eevee
    assert bpy.ops.neumesh.composite_with_scene() == {"FINISHED"}
    assert scene.render.engine == eevee and scene.neumesh.composite_scene.render.engine == "NEUMESH"
    tree = addon.render.composite.compositor_tree(scene, create=False)
    names = {n.name for n in tree.nodes}
    comp = addon.render.composite
    assert {comp.NODE_SCENE, comp.NODE_FIELDS, comp.NODE_ZCOMBINE} <= names
    assert all(vl.use_pass_z for vl in scene.view_layers)


def test_cycles_without_a_denoiser_gets_denoising_switched_off(addon):
    """Debian's Blender 3.4 Cycles has no denoiser (its `denoiser` enum is empty) and would stop the
    first composite F12 with "Build without OpenImageDenoiser". Composite with Scene switches
    denoising off there, and says so; a build with a denoiser keeps it."""
    from types import SimpleNamespace as NS

    check = addon.render.composite.cycles_denoising_check
    without = NS(render=NS(engine="CYCLES"), cycles=NS(use_denoising=True, denoiser=""))
    assert "no denoiser" in check(without) and without.cycles.use_denoising is False
    assert check(without) == ""   # already off: nothing more to do
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    assert scene.cycles.denoiser == "OPENIMAGEDENOISE" and scene.cycles.use_denoising
    assert check(scene) == "" and scene.cycles.use_denoising   # this build has OpenImageDenoise
    eevee = NS(render=NS(engine="BLENDER_EEVEE"), cycles=NS(use_denoising=True, denoiser=""))
    assert check(eevee) == "" and eevee.cycles.use_denoising
