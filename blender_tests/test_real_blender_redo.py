"""In a real window (Xvfb) with real input: a real click (xdotool, XTEST) on *Fill texture*
runs Fill; typing Scale 3 in *Adjust Last Operation* re-runs it; a real Ctrl+Z goes back; after each,
the Rendered viewport draws the new field within a second without the pointer moving. "Did it re-run /
redraw" is read from Fill's execute calls, the object's field file and the viewport engine's drawn
texture serial, not from screenshot pixels. Driven by real_blender_xdo.py; skipped without `blender`,
`xvfb-run` or `xdotool` (scripts/setup_blender.sh installs them)."""
from __future__ import annotations

import json
import os
import shutil

import pytest

from test_real_blender import BLENDER
from test_real_blender_ui import XVFB, run_in_window

XDOTOOL = shutil.which("xdotool")
pytestmark = [
    pytest.mark.skipif(not os.path.exists(BLENDER), reason="no blender binary; run scripts/setup_blender.sh"),
    pytest.mark.skipif(XVFB is None, reason="no xvfb-run (apt-get install xvfb); run scripts/setup_blender.sh"),
    pytest.mark.skipif(XDOTOOL is None, reason="no xdotool (apt-get install xdotool); run scripts/setup_blender.sh"),
]


def docs_pictures(keep, f, window_h=900):
    """The documentation's crops (docs/images) of the screenshots a run kept in ``keep``: Fill's redo
    panel opened over the viewport after the redo (addon_fill_redo.png), the Swap panel of a refused
    fit beside the viewport with the aligned source's wireframe (addon_swap_refused.png)."""
    from PIL import Image

    out = {}
    if "hud" in f and os.path.exists(os.path.join(keep, "fill_redone.png")):
        x, y, w, h = f["hud"]
        top = window_h - (y + h)
        img = Image.open(os.path.join(keep, "fill_redone.png")).convert("RGB")
        crop = img.crop((max(0, x - 60), max(0, top - 260), x + w + 300, min(window_h, top + h + 12)))
        out["addon_fill_redo.png"] = crop
    if "sidebar" in f and os.path.exists(os.path.join(keep, "swap_refused.png")):
        x, y, w, h = f["sidebar"]
        img = Image.open(os.path.join(keep, "swap_refused.png")).convert("RGB")
        crop = img.crop((max(0, x - 320), window_h - (y + h), x + w, window_h - y))
        out["addon_swap_refused.png"] = crop
    for name, im in out.items():   # 256 colours: small PNGs for the docs (< 150 KB)
        im.quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(os.path.join(keep, name), optimize=True)
    return sorted(out)


def _redrawn(f, key):
    """Timestamps taken inside Blender (the engine's view_draw, the edit module's refresh_viewports)."""
    assert f[key + "_drawn_s"] is not None, (key, f.get(key + "_draws"))
    assert f[key + "_asked_s"] <= 1.0, (key, f[key + "_asked_s"])
    assert f[key + "_wait_s"] <= 1.0, (key, f[key + "_wait_s"], f[key + "_render_s"])


def test_fill_click_redo_panel_and_ctrl_z_with_real_input(addon_zip, trained_field, tiny_dataset, tmp_path):
    r, log, f = run_in_window("real_blender_xdo.py", "xdo", addon_zip, trained_field, tiny_dataset, tmp_path, 480,
                              simulate=False)
    print(json.dumps(f, indent=1))
    assert f["errors"] == [], (f["errors"], log[-3000:])
    assert r.returncode == 0 and "Traceback" not in log, log[-4000:]
    # the located button is one row of the sidebar, and the click on it ran Fill as the interface does:
    # a file, the object points at it, the operator is the last one (the redo panel's)
    x0, y0, x1, y1 = f["fill_button"]
    assert f["fill_button_in_sidebar"] and 12 <= y1 - y0 <= 40 and x1 - x0 >= 60, f["fill_button"]
    assert f["after_path"] != f["before_path"] and f["files_after_edit"] == [os.path.basename(f["after_path"])]
    assert f["last_operator"] == "NEUMESH_OT_fill_texture"
    assert f["execute_calls_after_click"] == 0, "a click runs invoke (a modal job), not execute"
    # the viewport, nothing moved, asked for an image of the edited file within a second of the commit,
    # and drew it within a second of the preview thread finishing it (how long the render itself takes
    # depends on the machine: recorded, not held to a second)
    _redrawn(f, "edit")
    # the redo panel: typing 3 in Scale re-ran Fill's execute once, with Scale 3: a new file, the object
    # still selected and active, shown within a second
    assert [c["scale"] for c in f["execute_calls"]] == [3.0], f["execute_calls"]
    assert f["execute_calls"][0]["result"] == ["FINISHED"] and f["execute_calls"][0]["active"] == "blob"
    assert f["redo_path"] not in (f["after_path"], f["before_path"]) and len(f["files_after_redo"]) == 2
    assert f["selected_after_redo"] and f["active_after_redo"] == "blob"
    assert f["scale_after_redo"] == pytest.approx(3.0)
    _redrawn(f, "redo")
    # Ctrl+Z (a real key press) undid the redone Fill: the file from before Fill
    assert f["undo_path"] == f["before_path"]
    keep = os.environ.get("NEUMESH_UI_SCREENSHOT_DIR")
    if keep:
        os.makedirs(keep, exist_ok=True)
        for name in ("fill_redo.png", "fill_redo_typing.png", "fill_redone.png"):
            shutil.copy(tmp_path / "ui" / name, os.path.join(keep, name))
        with open(os.path.join(keep, "fill_redo.json"), "w") as fh:
            json.dump(f, fh)
        docs_pictures(keep, f)
    # ... drawn within a second, also when Ctrl+Z lands while the preview thread still renders the redone
    # field (4 of 10 runs kept the redone image before refresh_viewports re-checked after 0.25 s and 1 s)
    _redrawn(f, "undo")


def test_failed_swap_preview_in_a_real_window_shows_the_refusal_and_writes_nothing(addon_zip, trained_field,
                                                                                    tiny_dataset, tmp_path):
    """In the real window: the Swap panel of a failed automatic fit (pairs squeezing one cap
    onto the other) draws without error, with the aligned source as a wireframe object; no file."""
    r, log, f = run_in_window("real_blender_xdo.py", "swap", addon_zip, trained_field, tiny_dataset, tmp_path, 420,
                              simulate=False)
    print(json.dumps(f, indent=1))
    assert f["errors"] == [] and r.returncode == 0 and "Traceback" not in log, (f["errors"], log[-3000:])
    assert f["preview"] == ["FINISHED"] and f["ok"] is False
    assert "pair" in f["message"]
    assert len(f["wires"]) == 1
    assert f["after_path"] == f["before_path"] and f["files_after"] == f["files_before"]
    assert f["drawn"].get("NEUMESH_PT_swap_x", 0) >= 1
    keep = os.environ.get("NEUMESH_UI_SCREENSHOT_DIR")
    if keep:
        os.makedirs(keep, exist_ok=True)
        shutil.copy(f["screenshot"], os.path.join(keep, "swap_refused.png"))
        with open(os.path.join(keep, "swap_refused.json"), "w") as fh:
            json.dump(f, fh)
        docs_pictures(keep, f)


def test_render_from_a_timer_during_a_texture_paint_stroke_on_an_arap_object(addon_zip, trained_field, tiny_dataset,
                                                                             tmp_path):
    """In the real window with real input: ARAP deform on the field object, its handle moved (the next
    frame change solves again from rest and writes the live key), Texture Paint, a real stroke whose
    button stays down while a timer calls ``bpy.ops.render.render()`` (its frame changes run ARAP's
    handler), the stroke then going on for seconds.  Blender's projection paint reads the mesh evaluated
    when the stroke began: a key written under it freed that mesh and Blender segfaulted at the next
    dab (with freed memory filled, MALLOC_CONF=junk:true, 3 of 3 runs).  The key waits for the stroke's
    end, Blender runs on, the render shows the paint, and the key is solved from rest afterwards."""
    from test_real_blender import crash_report

    r, log, f = run_in_window("real_blender_tpaint_render.py", "tpf12", addon_zip, trained_field, tiny_dataset,
                              tmp_path, 300, simulate=False, args=("midstroke", "NEUMESH", "arap"),
                              env_extra={"MALLOC_CONF": "junk:true"})
    print(json.dumps(f, indent=1))
    assert r.returncode == 0, log[-3000:] + crash_report(tmp_path)
    assert f["errors"] == [] and "Traceback" not in log, (f["errors"], log[-3000:])
    assert f["arap_add"] == ["FINISHED"] and f["arap_before"] == "drag"
    assert f["texture_paint"] == ["FINISHED"] and f["mode"] == "TEXTURE_PAINT" and f["pushes"] >= 1
    assert f["stroke_at_render"] and f["render"] == ["FINISHED"] and f["frame_changes_in_render"] >= 1
    assert f["arap_after"] == "frame" and not f["stroke_after"]   # solved from rest once the stroke ended
    assert f["cyan_pixels"] > 20 and f["mode_after"] == "TEXTURE_PAINT"
