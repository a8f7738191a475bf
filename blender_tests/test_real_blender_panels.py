"""The add-on's panels at Blender's default widths in a real window (Debian's 3.4 under Xvfb, driven by
real_blender_panels.py): every panel draws without an error; the Field & Render panel says which pass
the Rendered viewport shows, level by level; the Edit field panels after an applied painting, with
Texture Paint and ARAP deform set up; the preferences with optional packages missing; the file browsers
of Import Cameras (a capture: no split offered) and Import Mesh (opens in the dataset folder, lists
.ply/.obj), whose button imports the mesh as a background job.

NEUMESH_UI_SCREENSHOT_DIR=<folder> keeps the screenshots and the crops docs/addon.md shows
(addon_viewport_pass.png, addon_edit_applied.png, addon_edit_more.png, addon_render_props.png,
addon_prefs_rows.png, addon_browser_capture.png)."""
from __future__ import annotations

import os
import shutil
import subprocess

import pytest

from test_real_blender import BLENDER, HERE, TORCH_DIR, _env, crash_report
from test_real_blender_ui import WINDOW, XVFB, _facts

pytestmark = [
    pytest.mark.skipif(not os.path.exists(BLENDER), reason="no blender binary; run scripts/setup_blender.sh"),
    pytest.mark.skipif(XVFB is None, reason="no xvfb-run (apt-get install xvfb); run scripts/setup_blender.sh"),
]

# crops for the documentation: (name, screenshot, box (left, top, right, bottom) in window pixels)
CROPS = (("addon_viewport_pass.png", "sidebar.png", (830, 80, 1060, 330)),
         ("addon_edit_applied.png", "edit.png", (830, 80, 1060, 590)),
         ("addon_edit_more.png", "edit_more.png", (830, 80, 1060, 745)),
         ("addon_render_props.png", "render_props.png", (1040, 330, 1280, 660)),
         ("addon_prefs_rows.png", "prefs.png", (175, 265, 687, 541)),
         ("addon_browser_capture.png", "browser_capture.png", (250, 0, 1104, 625)))


def test_panels_at_default_widths_in_a_real_window(addon_zip, trained_field, tiny_dataset, tmp_path):
    from tests.data.test_capture import write_transforms

    if not os.path.isdir(os.path.join(TORCH_DIR, "torch")):
        pytest.fail(f"torch for the blender binary is missing in {TORCH_DIR}: run scripts/setup_blender.sh")
    env = _env(tmp_path)
    out = tmp_path / "ui"
    capture = str(tmp_path / "capture")
    write_transforms(capture, n=18, missing=(3, 5))
    shutil.copy(os.path.join(tiny_dataset, "mesh.ply"), os.path.join(capture, "mesh.ply"))
    r = subprocess.run([BLENDER, "-b", "--factory-startup", "--python", os.path.join(HERE, "real_blender_ui.py"),
                        "--", "setup", addon_zip, trained_field, tiny_dataset, str(out)], env=env,
                       capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, (r.stdout + r.stderr)[-4000:]
    shots = tmp_path / "shots"
    shots.mkdir()
    r = subprocess.run([XVFB, "-a", "-s", "-screen 0 %dx%dx24" % WINDOW, BLENDER, str(out / "ui.blend"),
                        "--enable-event-simulate", "--python", os.path.join(HERE, "real_blender_panels.py"), "--",
                        "panels", str(shots), capture], env=env, capture_output=True, text=True, timeout=560)
    log = r.stdout + r.stderr
    f = _facts(r.stdout, tmp_path)
    assert r.returncode == 0, log[-4000:] + crash_report(tmp_path)
    assert f["errors"] == [], f["errors"]
    assert "Traceback" not in log, log[-4000:]
    for panel in ("NEUMESH_PT_field", "NEUMESH_PT_edit", "NEUMESH_PT_paint", "NEUMESH_PT_texture_paint",
                  "NEUMESH_PT_arap", "NEUMESH_PT_render"):
        assert f["drawn"].get(panel, 0) >= 1, f["drawn"]
    # the viewport's passes, coarse to fine, then the finest
    levels = f["viewport_level"]
    assert any("1/8 resolution" in x and "finest 1/2 to come" in x for x in levels), levels
    assert any("1/2 resolution" in x and "the finest" in x for x in levels), levels
    # the painting went to the edits folder beside ui.blend; the panels drew what it left
    assert f["apply"] == ["FINISHED"] and f["edited"] == "//ui_neumesh/blob.edit-001.neumesh"
    labels = f["labels"]
    assert "Applied; paint more to apply again" in labels and "Empty: the folder ui_neumesh beside the .blend" in labels
    assert any(t.endswith("texels not saved in the field yet") for t in labels), sorted(labels)
    assert any(t.startswith("for ") and "Build scaffold" in t for t in labels)   # a missing optional package
    # the file browsers
    assert f["browse_cameras"] == ["RUNNING_MODAL"] and f["browse_mesh"] == ["RUNNING_MODAL"]
    assert any(t.startswith("A capture: every photo becomes a camera") for t in labels)
    assert f["mesh_browser"] == {"directory": os.path.join(capture, ""), "filter_glob": "*.ply;*.obj",
                                 "use_filter": True}
    assert f["browser_execute"] == ["FINISHED"] and f["objects_after"] == f["objects_before"] + 1
    assert f["imported"] == "mesh"
    assert "Info: NeuMesh: imported mesh.ply (" in log and "642 vertices, 1,280 faces as 'mesh'" in log
    keep = os.environ.get("NEUMESH_UI_SCREENSHOT_DIR")
    if keep:
        from PIL import Image

        os.makedirs(keep, exist_ok=True)
        for name in f["shots"]:
            shutil.copy(shots / name, os.path.join(keep, name))
        for name, src, box in CROPS:
            Image.open(shots / src).convert("RGB").crop(box).save(os.path.join(keep, name), optimize=True)
