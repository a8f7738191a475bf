"""In Blender: *Preview alignment* draws the aligned source as a temporary wireframe (a child
of the target, nothing written) with its fit figures; *Accept* applies exactly that alignment;
*Discard* removes it; a failed fit is refused with the core's message (what to do), and no file is
written, both by the Swap operator and by Accept, unless the fit check is skipped.
"""
from __future__ import annotations

import os

import bpy
import numpy as np
import pytest

from helpers import careless_cap_pairs
from test_texture_edit import _setup


def _edits(tmp_path):
    return sorted(n for n in os.listdir(tmp_path) if ".edit-" in n)


def _wires(addon):
    tag = addon.edit.swap_preview.WIRE_TAG
    return [ob for ob in bpy.data.objects if ob.get(tag)]


def _clear(addon):
    for name in list(addon.edit.swap_preview._PREVIEWS):
        addon.edit.swap_preview.discard(name)


def test_preview_draws_the_aligned_source_writes_nothing_and_accept_applies_it(addon, trained_field, tmp_path):
    nm = addon.runtime.core.get()
    _clear(addon)
    target, source, tgt_path, src_path, cam, region = _setup(trained_field, tmp_path)
    assert bpy.ops.neumesh.swap_preview(target_group="region", source_object="Source",
                                        source_group="region") == {"FINISHED"}
    assert _edits(tmp_path) == [] and addon.scene.props.field_abspath(target) == tgt_path
    p = addon.edit.swap_preview.preview_of(target)
    al = p["alignment"]
    assert al.ok and al.message == ""
    wire, = _wires(addon)
    assert wire.parent == target and wire.display_type == "WIRE" and wire.hide_render
    assert len(wire.data.vertices) == len(region) and len(wire.data.polygons) == len(al.faces) > 0
    co = np.array([v.co[:] for v in wire.data.vertices])
    np.testing.assert_allclose(co, al.points, atol=1e-5)
    # the same source placed on itself: the wireframe lies on the target's own vertices (local frame)
    local = np.array([target.data.vertices[int(i)].co[:] for i in region])
    assert np.abs(co - local).max() < 0.05 * np.ptp(local, 0).max()
    # the wire is in the target's frame: moving the target moves it along
    target.location.x += 1.0
    bpy.context.view_layer.update()
    np.testing.assert_allclose(np.array(wire.matrix_world), np.array(target.matrix_world), atol=1e-6)
    target.location.x -= 1.0
    bpy.context.view_layer.update()
    assert bpy.ops.neumesh.swap_accept() == {"FINISHED"}
    edited = addon.scene.props.field_abspath(target)
    assert edited.endswith("blob.edit-001.neumesh") and _wires(addon) == []
    assert addon.edit.swap_preview.preview_of(target) is None
    info = nm.edit.edit_info(edited)["history"][-1]["info"]
    np.testing.assert_allclose(np.asarray(info["transform"]), al.transform.matrix(), atol=1e-6)
    assert info["fit_ok"] is True and info["overlap"] == pytest.approx(al.figures.overlap)
    # the accepted swap is the swap the operator makes without a preview
    g = nm.load_field(edited)
    api = nm.load_field(tgt_path)
    nm.swap_texture(api, region, nm.load_field(src_path), region)
    assert np.abs(g.tex_codes.detach().numpy() - api.tex_codes.detach().numpy()).max() < 1e-5


def test_discard_removes_the_wireframe_and_nothing_else(addon, trained_field, tmp_path):
    _clear(addon)
    target, source, tgt_path, _, _, region = _setup(trained_field, tmp_path)
    n_obj = len(bpy.data.objects)
    assert bpy.ops.neumesh.swap_preview(target_group="region", source_object="Source",
                                        source_group="region") == {"FINISHED"}
    assert len(bpy.data.objects) == n_obj + 1
    assert bpy.ops.neumesh.swap_discard() == {"FINISHED"}
    assert len(bpy.data.objects) == n_obj and _wires(addon) == []
    assert addon.edit.swap_preview.preview_of(target) is None and _edits(tmp_path) == []
    assert not bpy.ops.neumesh.swap_accept.poll()   # nothing left to accept
    assert addon.scene.props.field_abspath(target) == tgt_path


def _failing(target):
    """Pairs that squeeze a cap of the blob onto a few neighbouring vertices of the opposite cap (as a
    careless pick would): the aligned source covers almost none of the target."""
    careless_cap_pairs(target)
    return dict(target_group="cap-", source_object="", source_group="cap+", use_pairs=True, nonrigid=False)


def test_a_failed_fit_is_refused_with_what_to_do_and_writes_no_file(addon, trained_field, tmp_path):
    _clear(addon)
    target, _, tgt_path, _, _, _ = _setup(trained_field, tmp_path)
    kw = _failing(target)
    with pytest.raises(RuntimeError, match="refused, nothing was changed.*pair.*Preview alignment") as exc:
        bpy.ops.neumesh.swap_texture(**kw)
    assert "Skip fit check" in str(exc.value)
    assert _edits(tmp_path) == [] and addon.scene.props.field_abspath(target) == tgt_path
    # the preview shows the failure and its message in full; Accept refuses it the same way
    assert bpy.ops.neumesh.swap_preview(**kw) == {"FINISHED"}
    al = addon.edit.swap_preview.preview_of(target)["alignment"]
    assert not al.ok and "each pair joins the same point" in al.message
    assert len(_wires(addon)) == 1
    with pytest.raises(RuntimeError, match="refused, nothing was changed"):
        bpy.ops.neumesh.swap_accept()
    assert _edits(tmp_path) == [] and len(_wires(addon)) == 1   # the preview stays to be judged
    # Skip fit check: applied anyway, the record keeps the failed figures
    assert bpy.ops.neumesh.swap_accept(check_fit=False) == {"FINISHED"}
    info = addon.runtime.core.get().edit.edit_info(addon.scene.props.field_abspath(target))
    assert info["history"][-1]["info"]["fit_ok"] is False and _wires(addon) == []


def test_the_swap_panel_draws_the_preview(addon, trained_field, tmp_path):
    """The panel's preview part draws without error for a passing and a failing preview (a layout
    stand-in records what it shows)."""
    _clear(addon)
    target, _, _, _, _, _ = _setup(trained_field, tmp_path)

    class Layout:
        def __init__(self):
            self.texts, self.ops, self.props = [], [], []
            self.enabled = True

        def column(self, **_):
            return self
        box = row = column

        def label(self, text="", **_):
            self.texts.append(text)

        def prop(self, _data, name, **_):
            self.props.append(name)

        def operator(self, idname, **_):
            self.ops.append(idname)
            return type("Op", (), {})()

    kw = _failing(target)
    assert bpy.ops.neumesh.swap_preview(**kw) == {"FINISHED"}
    lay = Layout()
    addon.edit.swap_preview.draw_preview(bpy.context, lay, target)
    assert "neumesh.swap_accept" in lay.ops and "neumesh.swap_discard" in lay.ops
    assert "swap_skip_fit_check" in lay.props
    joined = " ".join(lay.texts)
    assert "each pair joins the same point" in joined and joined.startswith("Overlap")
    _clear(addon)
