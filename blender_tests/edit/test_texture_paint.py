"""Blender's Texture Paint on a field's paint atlas (addon/edit/texture_paint.py): the paint layer is
an ordinary image on the UV map "NeuMesh Paint"; pixels written through ``image.pixels`` reach the
field the viewport renders (the rendered colour at the painted texel changes, nothing far from it
does), Blender's undo of the pixels is followed, Save paint writes the field with the paint (a new
file; the core loads the same paint), F12 of a painted field equals the core's render of the saved
file also when the stroke was pushed while a render was sampling the atlas, and a mesh that is not
the field's scaffold is refused."""
from __future__ import annotations

import importlib
import shutil
import threading

import bpy
import numpy as np
import pytest

from helpers import add_camera, exact_colour_settings, f12_srgb, manual_K_c2w

W, H = 48, 40
GREEN = (0.05, 0.9, 0.1)


def _scene(trained_field, tmp_path):
    path = str(tmp_path / "A.neumesh")
    shutil.copy(trained_field, path)
    return _scene_of(path)


def _scene_of(path):
    """The field at ``path`` on a new object, a camera, the NeuMesh engine at W x H."""
    assert bpy.ops.neumesh.load_field(filepath=path, new_object=True) == {"FINISHED"}
    obj = bpy.context.active_object
    cam = add_camera((0, -4.8, 0.6), look_at=(0, 0, 0), lens=35.0)
    scene = bpy.context.scene
    scene.render.engine = "NEUMESH"
    scene.render.resolution_x, scene.render.resolution_y = W, H
    bpy.context.view_layer.objects.active = obj
    bpy.context.view_layer.update()
    return obj, cam, path


def _render(field, cam):
    import neumesh_core as nm

    K, c2w = manual_K_c2w(cam, W, H)
    return nm.render_camera(field, K, c2w, W, H), K, c2w


def _texel_under(field, K, c2w, out, y, x):
    """The atlas texel (row from the top, column) the render looks up at pixel (y, x)."""
    import torch
    import neumesh_core as nm

    o, d = nm.pixel_rays(K, c2w, W, H, pixels=torch.as_tensor([[x, y]]))
    p = (o + d * float(out.depth[y, x])).numpy()
    face, bary, _ = field.paint_atlas.closest_faces(field, p)
    tx, ty = field.paint_atlas.texel_coords(field.paint_atlas.uv_at(face, bary))[0]
    return int(ty), int(tx)


def _write_block(img, row, col, half, rgba):
    """Write a square of pixels around atlas texel (row from the top, col) through image.pixels."""
    w, h = img.size
    px = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(px)
    px = px.reshape(h, w, 4)
    r = h - 1 - row                                        # Blender's rows run bottom to top
    old = px[r - half:r + half + 1, col - half:col + half + 1].copy()
    px[r - half:r + half + 1, col - half:col + half + 1] = rgba
    img.pixels.foreach_set(px.ravel())
    img.update()
    return old


def test_texture_paint_pixels_reach_the_rendered_field_undo_and_save(addon, trained_field, tmp_path):
    import neumesh_core as nm

    tp = addon.edit.texture_paint
    obj, cam, path = _scene(trained_field, tmp_path)
    assert bpy.ops.neumesh.texture_paint(resolution=512) == {"FINISHED"}
    img = tp.paint_image(obj)
    assert img is not None and tuple(img.size) == (512, 512) and img.packed_file is not None
    assert obj.data.uv_layers.active.name == tp.UV_NAME
    assert bpy.context.scene.tool_settings.image_paint.canvas == img
    assert obj.mode == "TEXTURE_PAINT"
    field = addon.render.field_cache.get_field(obj.name_full, path)     # the field the viewport renders
    assert field.paint_atlas is not None and field.paint_atlas.is_empty
    # the UV map is the atlas's: loop corners carry the atlas UVs of the field's faces
    uv = np.empty(len(obj.data.loops) * 2, np.float32)
    obj.data.uv_layers[tp.UV_NAME].data.foreach_get("uv", uv)
    loops = tp.triangles(obj.data)[1]
    np.testing.assert_allclose(uv.reshape(-1, 2)[loops], field.paint_atlas.uv.numpy(), atol=1e-6)

    before, K, c2w = _render(field, cam)
    ys, xs = np.nonzero(before.opacity > 0.9 * before.opacity.max())
    y, x = int(np.median(ys)), int(np.median(xs))
    row, col = _texel_under(field, K, c2w, before, y, x)
    old = _write_block(img, row, col, 3, (*GREEN, 1.0))
    assert img.is_dirty
    n = tp.tick()                                   # the timer's poll (timers do not run in bpy scripts)
    assert n >= tp.POLL_S and tp.STATS["texels"] == 49
    after, _, _ = _render(field, cam)
    a = float(before.opacity[y, x])                   # the paint over the field, the white background behind
    assert np.abs(after.rgb[y, x] - (a * np.array(GREEN) + (1 - a))).max() < 0.03
    assert np.abs(after.rgb[y, x] - before.rgb[y, x]).max() > 0.1
    assert np.abs(after.rgb - before.rgb).max(-1)[before.opacity < 0.01].max() == 0   # the background is not painted
    changed = np.abs(after.rgb - before.rgb).max(-1) > 1 / 255
    assert 0 < changed.sum() < 0.2 * (before.opacity > 0.5).sum()
    # Blender's undo of the stroke puts the old pixels back: the field follows (undo_post handler)
    _write_block(img, row, col, 3, old)
    tp.on_undo()
    np.testing.assert_allclose(_render(field, cam)[0].rgb, before.rgb, atol=1e-6)
    # paint again, then Save paint: a new file beside the field's own, with the same paint
    _write_block(img, row, col, 3, (*GREEN, 1.0))
    assert bpy.ops.neumesh.save_paint() == {"FINISHED"}
    out = addon.scene.props.field_abspath(obj)
    assert out != path and out.endswith(".neumesh")
    saved = nm.load_field(out)
    assert getattr(nm.load_field(path), "paint_atlas", None) is None
    w, h = img.size
    px = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(px)
    np.testing.assert_allclose(saved.paint_atlas.image.numpy(), px.reshape(h, w, 4)[::-1], atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(_render(saved, cam)[0].rgb, after.rgb, atol=2 / 255)
    assert bpy.ops.neumesh.save_paint() == {"CANCELLED"}          # nothing new: nothing written


def test_f12_of_a_stroke_pushed_during_a_render_equals_the_core_render_of_the_saved_file(addon, trained_field,
                                                                                       tmp_path, monkeypatch):
    """A stroke is pushed into the field while the viewport's render builds the atlas's sampled copy
    (held there after the colours were read, as on a big atlas where the build takes seconds); after
    Save paint, F12 equals the core's render of the saved file within 1/255, and the stroke renders
    in the brush's colour, not black."""
    import neumesh_core as nm

    tp, fields, frame = addon.edit.texture_paint, addon.render.field_cache, addon.render.frame
    obj, cam, path = _scene(trained_field, tmp_path)
    scene = bpy.context.scene
    scene.camera = cam
    exact_colour_settings(scene, W, H)
    assert bpy.ops.neumesh.texture_paint(resolution=512) == {"FINISHED"}
    img = tp.paint_image(obj)
    field = fields.get_field(obj.name_full, path)
    before, K, c2w = _render(field, cam)
    solid = before.opacity > 0.9 * before.opacity.max()
    y = int(np.median(np.nonzero(solid)[0]))
    xs = np.nonzero(solid[y])[0][2:-2:3]                       # a band across the object
    band = [_texel_under(field, K, c2w, before, y, int(x)) for x in xs]
    assert len(band) >= 3
    field.paint_atlas.changed()             # no sampled copy yet, as on an atlas just made
    cyan = (0.0, 1.0, 1.0)
    copy_mod = importlib.import_module(addon.runtime.core.get().__name__ + ".field.paint_copy")
    plain, read_colour, pushed = copy_mod.premultiply, threading.Event(), threading.Event()

    def held(rows):                          # the render's build, held after reading the colours
        if rows.ndim == 3:
            rgb = rows[..., :3] * rows[..., 3:]
            read_colour.set()
            pushed.wait(60)
            return np.concatenate([rgb, rows[..., 3:]], -1).astype(np.float16)
        return plain(rows)

    monkeypatch.setattr(copy_mod, "premultiply", held)
    items = fields.collect(bpy.context.evaluated_depsgraph_get(), for_render=False)
    render = threading.Thread(target=frame.render_items, args=(items, K, c2w, W, H))
    render.start()
    assert read_colour.wait(60)
    for row, col in band:                    # the stroke, pushed piece by piece as the watcher does
        _write_block(img, row, col, 2, (*cyan, 1.0))
        assert tp.sync_object(obj) > 0
    pushed.set()
    render.join(120)
    assert not render.is_alive()
    monkeypatch.setattr(copy_mod, "premultiply", plain)
    assert bpy.ops.neumesh.save_paint() == {"FINISHED"}
    saved = addon.scene.props.field_abspath(obj)
    assert saved != path
    f12 = f12_srgb(tmp_path / "f12.exr")
    core = nm.render_camera(nm.load_field(saved), K, c2w, W, H)
    assert np.abs(f12 - core.rgb).max() <= 1 / 255
    a = before.opacity[y, xs][:, None]
    assert np.abs(f12[y, xs] - (a * np.array(cyan) + (1 - a))).max() < 0.05   # cyan over white


def test_texture_paint_refuses_a_mesh_that_is_not_the_scaffold(addon, trained_field, tmp_path):
    obj, cam, path = _scene(trained_field, tmp_path)
    bpy.ops.object.mode_set(mode="EDIT")
    bpy.ops.mesh.select_all(action="SELECT")
    bpy.ops.mesh.flip_normals()                      # the same vertices, faces wound the other way
    bpy.ops.object.mode_set(mode="OBJECT")
    with pytest.raises(RuntimeError, match="Load field > New object"):
        bpy.ops.neumesh.texture_paint()
    assert addon.edit.texture_paint.paint_image(obj) is None


def test_paint_on_view_paints_the_atlas_of_a_field_that_has_one(addon, trained_field, tmp_path):
    """Apply painting (Paint on view) writes into the field's paint atlas when it has one, at the
    painted image's resolution, from the surface of the render painted on; the modification colours
    stay as they were."""
    import neumesh_core as nm
    from neumesh_core.edit import create_paint_atlas

    src = nm.load_field(trained_field)
    create_paint_atlas(src, resolution=256)
    path = str(tmp_path / "atlas.neumesh")
    nm.save_field(src, path)
    obj, cam, _ = _scene_of(path)
    assert bpy.ops.neumesh.paint_view() == {"FINISHED"}
    paint = addon.edit.paint
    img = bpy.data.images[paint.PAINT_IMAGE]
    assert img.name in paint._SURFACE
    px = paint._image_pixels(img)
    px[16:22, 18:30, :3] = GREEN
    paint._set_pixels(img, px)
    assert bpy.ops.neumesh.apply_paint() == {"FINISHED"}
    out = addon.scene.props.field_abspath(obj)
    assert out != path
    edited = nm.load_field(out)
    assert not edited.paint_atlas.is_empty
    np.testing.assert_allclose(edited.mod_colours.detach().numpy(), src.mod_colours.detach().numpy(), atol=0)
    K, c2w = manual_K_c2w(cam, W, H)
    before = nm.render_camera(src, K, c2w, W, H)
    after = nm.render_camera(edited, K, c2w, W, H)
    solid = before.opacity[16:22, 18:30] > 0.9 * before.opacity.max()
    a = before.opacity[16:22, 18:30][solid][:, None]
    assert solid.sum() > 10
    assert np.abs(after.rgb[16:22, 18:30][solid] - (a * np.array(GREEN) + (1 - a))).max() < 0.03
    far = np.ones((H, W), bool)
    far[13:25, 15:33] = False
    assert (np.abs(after.rgb - before.rgb).max(-1)[far] <= 1 / 255).all()
