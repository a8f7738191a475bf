"""Drive the real `blender` binary (Debian's 3.4 in CI) headless: install the add-on zip as a legacy
add-on, build a scene with a keyed armature, then `blender -b scene.blend -E NEUMESH -s 1 -e 2 -a`.

torch for that Blender comes from `pip install --target <repo>/.blender_torch` (scripts/setup_blender.sh),
found by the add-on through NEUMESH_PYTHONPATH.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess

import numpy as np
import pytest

BLENDER = shutil.which("blender") or "/usr/bin/blender"
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TORCH_DIR = os.environ.get("NEUMESH_BLENDER_TORCH", os.path.join(ROOT, ".blender_torch"))
HERE = os.path.dirname(os.path.abspath(__file__))

pytestmark = pytest.mark.skipif(not os.path.exists(BLENDER), reason="no blender binary (/usr/bin/blender); "
                                "install it with scripts/setup_blender.sh")


def _env(tmp):
    env = dict(os.environ)
    for k in ("BLENDER_USER_RESOURCES",):
        env.pop(k, None)
    env.update({
        "BLENDER_USER_CONFIG": str(tmp / "config"), "BLENDER_USER_SCRIPTS": str(tmp / "scripts"),
        "BLENDER_USER_DATAFILES": str(tmp / "datafiles"), "BLENDER_USER_RESOURCES": str(tmp / "resources"),
        "HOME": str(tmp / "home"), "TMPDIR": str(tmp), "NEUMESH_PYTHONPATH": TORCH_DIR,
        "PYTHONNOUSERSITE": "1", "NEUMESH_FAULT_LOG": str(tmp / "python_faults.txt"),
    })
    os.makedirs(env["HOME"], exist_ok=True)
    return env


def crash_report(tmp) -> str:
    """What a crashed `blender` left in ``tmp`` (empty when nothing): every thread's Python stack at the
    fault (real_blender_common's fault handler, the crashing thread first as "Current thread") and
    Blender's own *.crash.txt reports."""
    import glob

    parts = []
    fault = os.path.join(str(tmp), "python_faults.txt")
    if os.path.exists(fault) and os.path.getsize(fault):
        parts.append("python_faults.txt:\n" + open(fault, errors="replace").read()[-6000:])
    for f in sorted(glob.glob(os.path.join(str(tmp), "**", "*.crash.txt"), recursive=True)):
        parts.append(f"{f}:\n" + open(f, errors="replace").read()[-3000:])
    return "\n".join(parts)


def _run(cmd, env, timeout=240):
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    log = r.stdout + r.stderr
    assert r.returncode == 0, log[-4000:] + crash_report(env["TMPDIR"])
    return log


def _project(K, c2w, pts):
    w2c = np.linalg.inv(c2w)
    p = pts @ w2c[:3, :3].T + w2c[:3, 3]
    uv = p[:, :2] / p[:, 2:3] @ np.diag([K[0, 0], K[1, 1]]) + K[:2, 2]
    return uv


def test_real_blender_renders_animation_with_neumesh_engine(addon_zip, trained_field, tmp_path):
    if not os.path.isdir(os.path.join(TORCH_DIR, "torch")):
        pytest.fail(f"torch for the blender binary is missing in {TORCH_DIR}: run scripts/setup_blender.sh")
    env = _env(tmp_path)
    out = tmp_path / "out"
    log = _run([BLENDER, "-b", "--factory-startup", "--python", os.path.join(HERE, "real_blender_scene.py"),
                "--", addon_zip, trained_field, str(out)], env)
    facts = json.loads(next(l for l in log.splitlines() if l.startswith("NEUMESH_FACTS "))[14:])
    assert facts["load_field"] == ["FINISHED"] and facts["field_path"].startswith("//")
    # second process: the saved .blend, the engine from the command line, the add-on from user prefs
    log = _run([BLENDER, "-b", str(out / "scene.blend"), "-E", "NEUMESH", "-o", str(out / "frame_####"),
                "-s", "1", "-e", "2", "-a"], env)
    assert "NeuMesh:" not in log or "error" not in log.lower(), log[-3000:]
    from PIL import Image

    f1 = np.asarray(Image.open(out / "frame_0001.png").convert("RGB"), np.float32) / 255
    f2 = np.asarray(Image.open(out / "frame_0002.png").convert("RGB"), np.float32) / 255
    assert f1.shape == f2.shape == (40, 48, 3)
    assert f1.std() > 0.02  # the field is in the picture

    # the same file saved with Filmic and another engine; `-E NEUMESH` on the command line does not reach
    # the interface's engine-change message, so the first NeuMesh render of a scene sets the
    # photographic view (as choosing the engine in the interface does): the batch frame has the pixels
    # of the Standard-view file, and the log says why.
    filmic = str(out / "filmic.blend")
    expr = ("import bpy; s = bpy.context.scene; s.view_settings.view_transform = 'Filmic'; "
            "s.render.engine = 'CYCLES'; s.neumesh.photo_colour_set = False; "
            f"bpy.ops.wm.save_as_mainfile(filepath={filmic!r})")
    _run([BLENDER, "-b", str(out / "scene.blend"), "--python-expr", expr], env)
    log = _run([BLENDER, "-b", filmic, "-E", "NEUMESH", "-o", str(out / "filmic_####"), "-f", "1"], env)
    assert "View Transform set to 'Standard'" in log, log[-3000:]
    g1 = np.asarray(Image.open(out / "filmic_0001.png").convert("RGB"), np.float32) / 255
    assert np.abs(g1 - f1).max() <= 1.0 / 255

    # where the mesh is (image-space footprint of each part), from the vertices Blender evaluated
    import neumesh_core as nm  # noqa: F401  (same conventions as the add-on)

    V1, V2 = np.load(out / "verts_1.npy"), np.load(out / "verts_2.npy")
    tip = np.load(out / "idx_tip.npy")
    assert np.abs(V1[tip] - V2[tip]).max() > 0.3
    root = np.setdiff1d(np.arange(len(V1)), tip)
    np.testing.assert_allclose(V1[root], V2[root], atol=1e-5)
    # camera of the scene script: at (0,-4.6,0.8) looking at the origin, lens 35 mm, 36 mm sensor
    from helpers import manual_K_c2w  # noqa: F401
    import mathutils

    loc = mathutils.Vector((0.0, -4.6, 0.8))
    rot = (mathutils.Vector((0, 0, 0)) - loc).to_track_quat("-Z", "Y").to_matrix().to_4x4()
    M = np.array(mathutils.Matrix.Translation(loc) @ rot)
    c2w = M @ np.diag([1.0, -1.0, -1.0, 1.0])
    f = 35.0 / 36.0 * 48
    K = np.array([[f, 0, 24], [0, f, 20], [0, 0, 1]])
    # pixels farther than the field's reach from every tip vertex in both frames must not change (the
    # neighbour radius is 2.5 mean edge lengths, ~6 px here: 7 px margin); pixels covered by the tip
    # must change a lot
    ys, xs = np.mgrid[0:40, 0:48]
    pix = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], -1)

    def near(uv, r):
        d = np.min(np.linalg.norm(pix[:, None, :] - uv[None, :, :], axis=-1), axis=1)
        return (d < r).reshape(40, 48)

    tip1, tip2 = _project(K, c2w, V1[tip]), _project(K, c2w, V2[tip])
    far = ~near(np.concatenate([tip1, tip2]), 7.0)
    root_px = far & near(_project(K, c2w, V1[root]), 1.5)  # undeformed part of the surface
    assert far.sum() > 200 and root_px.sum() > 40
    diff = np.abs(f1 - f2).max(-1)
    assert diff[far].max() <= 2.0 / 255, diff[far].max()
    assert f1[root_px].std() > 0.02  # those pixels show the field, not background
    tip_px = near(np.concatenate([tip1, tip2]), 3.0)
    assert (diff[tip_px] > 0.1).sum() >= 10 and diff[tip_px].max() > 0.25


def _facts(log):
    return json.loads(next(l for l in log.splitlines() if l.startswith("NEUMESH_FACTS "))[14:])


def _need_torch():
    if not os.path.isdir(os.path.join(TORCH_DIR, "torch")):
        pytest.fail(f"torch for the blender binary is missing in {TORCH_DIR}: run scripts/setup_blender.sh")


def test_check_dependencies_exits_cleanly_and_uses_torchs_blas(addon_zip, tmp_path):
    """'Check dependencies' imports torch: Blender must still exit normally (it segfaulted at exit,
    code 139, when torch was imported without the add-on's guard), and torch's matrix multiplies must
    run on torch's own BLAS even where this Blender links another one (Debian's links the reference
    libblas.so.3); with the rebinding switched off the check names the slow library and the launcher
    command, and that command works."""
    _need_torch()
    env = _env(tmp_path)
    cmd = [BLENDER, "-b", "--factory-startup", "--python", os.path.join(HERE, "real_blender_deps.py"), "--",
           addon_zip]
    log = _run(cmd, env)  # asserts exit code 0
    f = _facts(log)
    assert f["result"] == ["FINISHED"] and f["missing"] == [] and f["rebind_error"] == ""
    assert f["own"] and f["sgemm"] == f["torch_lib"] and f["gflops"] > 0 and f["remedy"] == ""
    assert "NeuMesh: matrix multiply" in log and "with torch's own BLAS" in log

    off = _facts(_run(cmd, dict(env, NEUMESH_NO_BLAS_REBIND="1")))
    if off["own"]:
        pytest.skip(f"this blender ({BLENDER}) does not link another BLAS: nothing to rebind")
    # what the user is told without the rebinding, and the remedy it names
    assert os.path.basename(off["sgemm"]).startswith(("libblas", "libopenblas", "libcblas", "libatlas"))
    assert off["remedy"] == f"LD_PRELOAD={f['torch_lib']} blender"
    assert "slow BLAS" in off["message"]
    assert any(os.path.realpath(p) == os.path.realpath(off["sgemm"]) for p in f["foreign"]), f["foreign"]
    assert f["rebound"] >= 1
    preloaded = dict(env, NEUMESH_NO_BLAS_REBIND="1", LD_PRELOAD=f["torch_lib"])
    pre = _facts(_run(cmd, preloaded))
    assert pre["own"] and pre["sgemm"] == f["torch_lib"] and pre["remedy"] == ""


def test_save_as_to_another_folder_keeps_the_field(addon_zip, trained_field, tmp_path):
    """Blender 3.x gives save handlers no file name (save_pre gets (None, None)): a Save As into
    another folder must still leave a file whose field is found, in a new Blender process."""
    _need_torch()
    env = _env(tmp_path)
    out = tmp_path / "work"
    field = tmp_path / "fields" / "blob.neumesh"
    field.parent.mkdir()
    shutil.copy(trained_field, field)
    f = _facts(_run([BLENDER, "-b", "--factory-startup", "--python", os.path.join(HERE, "real_blender_saveas.py"),
                     "--", addon_zip, str(field), str(out)], env))
    assert f["path_first"] == "//../../fields/blob.neumesh"
    assert f["path_after_save_as"] == "//../../../fields/blob.neumesh"
    if tuple(f["version"]) < (4, 0, 0):
        assert f["save_pre_args"][-1] == [None, None]  # what made the bug: no target path
    # a new process opens the moved file, says where its field is, and renders it
    expr = ("import bpy; print('FIELD_PATH', [o.neumesh.field_path for o in bpy.data.objects "
            "if o.type == 'MESH'])")
    log = _run([BLENDER, "-b", f["second"], "--python-expr", expr, "-E", "NEUMESH",
                "-o", str(out / "frame_####"), "-f", "1"], env)
    assert "not found" not in log, log[-3000:]
    assert "FIELD_PATH ['//../../../fields/blob.neumesh']" in log, log[-3000:]
    from PIL import Image

    img = np.asarray(Image.open(out / "frame_0001.png").convert("RGB"), np.float32) / 255
    assert img.shape == (40, 48, 3) and img.std() > 0.02  # the field is in the picture


def test_f12_equals_the_core_render_with_one_copy_hand_off_threads_and_allocator(addon_zip, trained_field,
                                                                                 tmp_path):
    """F12 in the real binary: the pixels equal the core's render of the same frame (EXR, 1e-4) and reach
    Blender in one copy (3.x: foreach_set of the (W*H, 4) rows; no Python list of pixels, which cost
    0.35-0.45 s at 400x400), torch runs with the *CPU threads* preference, and where Blender's malloc is
    jemalloc every arena keeps its freed pages during the render (decay -1; the oversize arena had 0)
    and has its own decay times back afterwards."""
    _need_torch()
    env = _env(tmp_path)
    f = _facts(_run([BLENDER, "-b", "--factory-startup", "--python", os.path.join(HERE, "real_blender_f12.py"),
                     "--", addon_zip, trained_field, str(tmp_path / "out")], env))
    assert f["error"] == ""
    assert f["ref_std"] > 0.02 and f["max_diff"] <= 1e-4, f
    assert f["handoff"] in ("flat", "rows"), f
    if tuple(f["version"]) < (4, 0, 0):
        assert f["handoff"] == "rows"
    assert f["torch_threads"] == 1
    if f["jemalloc"]:   # Debian's 3.4 (and Blender's own Linux builds) link jemalloc
        m = f["malloc"]
        assert m["error"] == "", m

        def times(d):   # {arena: (dirty ms, muzzy ms)} back from JSON
            return {int(k): tuple(v) for k, v in d.items()}

        before, during, after = times(m["before"]), times(m["during"]), times(m["after"])
        assert set(during.values()) == {(-1, -1)} and len(during) >= 2, m   # arena 0 + the oversize one
        assert (0, 0) in before.values(), m                                  # the oversize arena's
        default = tuple(m["default_before"])
        assert after == {k: before.get(k, default) for k in after} and set(before) <= set(after), m
        now = times(f["decay_now"])   # at the end of the script: arenas made since have the default
        assert now == {k: after.get(k, default) for k in now}


def test_composite_with_scene_renders_with_blender_b_a(addon_zip, trained_field, tmp_path):
    """"Composite with Scene" in the real binary, then `blender -b scene.blend -a` in a new process:
    frames 1 and 3 (step 2), each the Z-combination of the Cycles layer and the NeuMesh layer rendered
    separately (1e-3): the bar where it is in front of the field, the field where it is in front."""
    _need_torch()
    from helpers import combine_expected, read_exr

    env = _env(tmp_path)
    out = tmp_path / "out"
    f = _facts(_run([BLENDER, "-b", "--factory-startup", "--python",
                     os.path.join(HERE, "real_blender_composite.py"), "--", addon_zip, trained_field, str(out)], env))
    assert f["result"] == ["FINISHED"] and f["companion"].endswith(" NeuMesh"), f
    if tuple(f["version"]) < (5, 0, 0):
        assert f["tree"] == "node_tree"
    log = _run([BLENDER, "-b", str(out / "scene.blend"), "-o", str(out / "frame_####"), "-a"], env)
    assert "NeuMesh:" not in log or "error" not in log.lower(), log[-3000:]
    frames = sorted(p.name for p in out.glob("frame_*"))
    assert frames == ["frame_0001.exr", "frame_0003.exr"], frames
    cyc, zc, fld, zf = (np.load(out / f"{k}.npy") for k in ("cyc", "zc", "fld", "zf"))
    expected = combine_expected(cyc, zc, fld, zf)
    bar, field = zc < 1e9, fld[..., 3] > 0.9
    bar_front, field_front = bar & field & (zc < zf), bar & field & (zf < zc)
    assert bar_front.sum() >= 15 and field_front.sum() >= 15, (bar_front.sum(), field_front.sum())
    for name in frames:
        got = read_exr(str(out / name))
        assert got.shape == (48, 64, 4)
        assert np.abs(got - expected).max() <= 1e-3
        np.testing.assert_allclose(got[bar_front], cyc[bar_front], atol=1e-3)
        assert np.abs(got - cyc)[field_front].max() > 0.1


def test_semantics_and_bake_work_or_name_their_missing_packages(addon_zip, tmp_path):
    """In Blender 3.4 each of Distill semantics and Bake either works (the packages are in the torch
    folder: scripts/setup_blender.sh installs the add-on's whole list) or refuses before starting,
    naming the package in full (never dying in its thread on `No module named 'skimage'`)."""
    _need_torch()
    env = _env(tmp_path)
    f = _facts(_run([BLENDER, "-b", "--factory-startup", "--python", os.path.join(HERE, "real_blender_features.py"),
                     "--", addon_zip, str(tmp_path / "out")], env, timeout=600))
    if f["missing"]["semantics"]:
        assert "Distill semantics needs the Python package" in f["distill"], f
        assert all(p in f["distill"] for p in f["missing"]["semantics"]) and f["distill_job"] is None, f
    else:
        assert f["distill"] == ["FINISHED"] and f["distill_job"][0] == "DONE", f
    if f["missing"]["bake"]:
        assert "Bake to material needs the Python package xatlas" in f["bake"] and not f["baked"], f
    else:
        assert f["bake"] == ["FINISHED"] and f["baked"], f


def test_import_cameras_of_a_colmap_capture_in_real_blender(addon_zip, tmp_path):
    """In the real binary: a COLMAP folder (written here) imports as cameras with their
    photos, the sparse points drawn as points by the Mesh to Points node group (built with the 3.x
    node-group API there, the 4+ one in bpy 5), and the NeuMesh Box."""
    _need_torch()
    pytest.importorskip("pycolmap")
    from tests.data.test_capture import write_colmap

    if "pycolmap" not in os.listdir(TORCH_DIR):
        pytest.skip("pycolmap is not in the blender's torch folder (scripts/setup_blender.sh installs it)")
    root = str(tmp_path / "cap")
    write_colmap(root, "PINHOLE", n=5, points=30)
    env = _env(tmp_path)
    f = _facts(_run([BLENDER, "-b", "--factory-startup", "--python", os.path.join(HERE, "real_blender_capture.py"),
                     "--", addon_zip, root], env, timeout=300))
    assert f["result"] == ["FINISHED"] and f["cameras"] == 5 and f["backgrounds"] == 5, f
    assert f["points"] == 30 and f["colour"] == "Color" and f["modifiers"] == ["NODES"], f
    assert "Radius" in f["node_inputs"] and f["box"] is not None, f


def test_real_blender_arap_deform_renders_keyed_handle(addon_zip, trained_field, tmp_path):
    """In Debian's Blender 3.4: Add ARAP deform, a keyed handle Empty, then
    `blender -b arap.blend -E NEUMESH -a`: frame 2 shows the bent field, frame 1 the rest."""
    _need_torch()
    env = _env(tmp_path)
    out = tmp_path / "out"
    log = _run([BLENDER, "-b", "--factory-startup", "--python", os.path.join(HERE, "real_blender_arap.py"),
                "--", addon_zip, trained_field, str(out)], env)
    facts = _facts(log)
    assert facts["arap_add"] == ["FINISHED"] and "NeuMesh ARAP" in facts["keys"], log[-3000:]
    rest, V1, V2 = (np.load(out / n) for n in ("arap_rest.npy", "arap_verts_1.npy", "arap_verts_2.npy"))
    anchors, handles = np.load(out / "arap_anchors.npy"), np.load(out / "arap_handles.npy")
    np.testing.assert_allclose(V1, rest, atol=1e-4)
    np.testing.assert_allclose(V2[anchors], rest[anchors], atol=1e-4)
    assert np.abs(V2[handles] - rest[handles]).max() > 0.4
    log = _run([BLENDER, "-b", str(out / "arap.blend"), "-E", "NEUMESH", "-o", str(out / "arap_####"),
                "-s", "1", "-e", "2", "-a"], env)
    assert "NeuMesh ARAP" not in log, log[-3000:]   # the handler printed no error
    from PIL import Image

    f1 = np.asarray(Image.open(out / "arap_0001.png").convert("RGB"), np.float32) / 255
    f2 = np.asarray(Image.open(out / "arap_0002.png").convert("RGB"), np.float32) / 255
    assert f1.std() > 0.02 and np.abs(f1 - f2).max() > 0.2


@pytest.mark.parametrize("auto_save", [True, False], ids=["auto_save", "manual_save"])
def test_batch_render_right_after_the_install_steps_with_the_window_still_open(addon_zip, trained_field, tmp_path,
                                                                                auto_save):
    """README steps 1-2 in a real window (Install…, the tick, Existing environment) with the artist's
    own preferences, then `blender -b file.blend -E NEUMESH -o OUT -f 1` while that Blender is still
    open: with Auto-Save Preferences on (Blender's default) the add-on saved them at once and the
    frame renders (torch from the saved Existing environment); with it off nothing is saved behind
    the artist's back, the preferences say that they must be saved, and the batch render has no
    NeuMesh engine."""
    import shutil as _shutil

    if not os.path.isdir(os.path.join(TORCH_DIR, "torch")):
        pytest.fail(f"torch for the blender binary is missing in {TORCH_DIR}: run scripts/setup_blender.sh")
    xvfb = _shutil.which("xvfb-run")
    if xvfb is None:
        pytest.skip("no xvfb-run (apt-get install xvfb); run scripts/setup_blender.sh")
    scene_dir = tmp_path / "scene"
    _run([BLENDER, "-b", "--factory-startup", "--python", os.path.join(HERE, "real_blender_scene.py"),
          "--", addon_zip, trained_field, str(scene_dir)], _env(tmp_path / "setup"))
    env = _env(tmp_path / "artist")          # a new user: nothing installed, nothing saved
    env.pop("NEUMESH_PYTHONPATH")
    out = tmp_path / "out"
    r = subprocess.run([xvfb, "-a", "-s", "-screen 0 1280x900x24", BLENDER, "--python",
                        os.path.join(HERE, "real_blender_prefs.py"), "--", addon_zip, TORCH_DIR,
                        str(scene_dir / "scene.blend"), str(out)] + ([] if auto_save else ["manual"]),
                       env=env, capture_output=True, text=True, timeout=400)
    log = r.stdout + r.stderr
    lines = [l for l in r.stdout.splitlines() if l.startswith("NEUMESH_FACTS ")]
    assert lines, log[-4000:]
    f = json.loads(lines[-1][14:])
    assert f["errors"] == [] and f["install"] == ["FINISHED"] and f["enable"] == ["FINISHED"], f
    if auto_save:
        assert f["enabled"] == ["saved", False] and f["env_path"] == ["saved", False] and f["note"] == "", f
        assert f["batch_rc"] == 0 and "not available" not in f["batch_log"], f["batch_log"]
        assert f["frames"] == ["frame_0001.png"], f
        from PIL import Image

        img = np.asarray(Image.open(out / "frame_0001.png").convert("RGB"), np.float32) / 255
        assert img.shape == (40, 48, 3) and img.std() > 0.02   # the field is in the picture
    else:
        assert f["enabled"] == ["manual", True] and f["env_path"] == ["manual", True], f
        assert "Save Preferences" in f["note"], f
        assert "engine not found 'NEUMESH'" in f["batch_log"] and f["frames"] == [], f["batch_log"]
