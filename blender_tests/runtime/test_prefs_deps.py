"""Add-on preferences: dependency status, pip install into the add-on's own folder, error paths."""
from __future__ import annotations

import os
import subprocess
import sys
import zipfile

import bpy
import pytest

from conftest import ADDON_MODULE


def test_preferences_report_dependency_versions(addon):
    import numpy
    import torch

    prefs = addon.runtime.prefs
    p = prefs.get_prefs()
    assert p is not None and type(p).bl_idname == ADDON_MODULE
    assert bpy.ops.neumesh.check_dependencies() == {"FINISHED"}
    st = {s.name: s for s in prefs._status_cache["statuses"]}
    assert set(st) >= {"torch", "numpy", "scipy", "trimesh", "pykdtree"}
    assert st["torch"].found and st["torch"].version == torch.__version__
    assert st["numpy"].found and st["numpy"].version == numpy.__version__
    assert addon.runtime.deps.missing_required(list(st.values())) == []


def test_dependency_check_without_environment_and_with_env_var(addon, tmp_path):
    """In a Python without site-packages torch is reported missing; NEUMESH_PYTHONPATH fixes it."""
    deps_dir = os.path.dirname(addon.runtime.deps.__file__)
    site = os.path.dirname(os.path.dirname(__import__("numpy").__file__))
    code = (
        "import sys, importlib.util; spec = importlib.util.spec_from_file_location('d', sys.argv[1]);"
        "d = importlib.util.module_from_spec(spec); spec.loader.exec_module(d);"
        "print('BEFORE', d.missing_required()); d.configure_sys_path();"
        "print('AFTER', d.missing_required(), [s.version for s in d.check_dependencies() if s.name=='torch'])"
    )
    env = {"PATH": os.environ.get("PATH", ""), "NEUMESH_PYTHONPATH": site}
    out = subprocess.run([sys.executable, "-S", "-c", code, os.path.join(deps_dir, "deps.py")],
                         env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    before = next(l for l in out.stdout.splitlines() if l.startswith("BEFORE"))
    after = next(l for l in out.stdout.splitlines() if l.startswith("AFTER"))
    assert "torch" in before and "numpy" in before
    assert after.startswith("AFTER []") and "2.13" in after


def _make_wheel(dirpath, name="neumesh_fakedep", version="0.1"):
    """A minimal pure-Python wheel built by hand (no network, no build backend)."""
    whl = os.path.join(dirpath, f"{name}-{version}-py3-none-any.whl")
    di = f"{name}-{version}.dist-info"
    files = {
        f"{name}/__init__.py": f"__version__ = '{version}'\n",
        f"{di}/METADATA": f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n",
        f"{di}/WHEEL": "Wheel-Version: 1.0\nGenerator: hand\nRoot-Is-Purelib: true\nTag: py3-none-any\n",
    }
    record = "".join(f"{k},,\n" for k in files) + f"{di}/RECORD,,\n"
    with zipfile.ZipFile(whl, "w") as zf:
        for k, v in files.items():
            zf.writestr(k, v)
        zf.writestr(f"{di}/RECORD", record)
    return whl


def test_install_dependencies_operator_uses_blenders_python_and_own_folder(addon, tmp_path):
    _make_wheel(str(tmp_path))
    res = bpy.ops.neumesh.install_dependencies(
        requirements=f"--no-index --find-links {tmp_path} neumesh_fakedep==0.1", wait=True)
    assert res == {"FINISHED"}
    job = addon.runtime.install.current_install()
    assert job.state == "DONE", job.log_lines[-10:]
    assert job.command[0] == sys.executable and "--target" in job.command
    target = addon.runtime.deps.addon_deps_dir(ADDON_MODULE)
    assert job.target == target and target.startswith(os.environ["BLENDER_USER_RESOURCES"])
    assert os.path.isfile(os.path.join(target, "neumesh_fakedep", "__init__.py"))
    assert target in sys.path
    import neumesh_fakedep

    assert neumesh_fakedep.__version__ == "0.1"
    requirements = addon.runtime.deps.PIP_REQUIREMENTS
    assert requirements[0] == "torch==2.13.0" and "numpy<2" in requirements


def test_install_dependencies_failure_is_reported(addon, tmp_path):
    with pytest.raises(RuntimeError, match="pip failed"):
        bpy.ops.neumesh.install_dependencies(
            requirements=f"--no-index --find-links {tmp_path} neumesh-no-such-package==9.9", wait=True)
    job = addon.runtime.install.current_install()
    assert job.state == "ERROR" and "no-such-package" in " ".join(job.log_lines).lower().replace("_", "-")


def test_existing_environment_preference_goes_on_sys_path(addon, tmp_path):
    env = tmp_path / "site-packages"
    (env / "neumesh_envprobe").mkdir(parents=True)
    (env / "neumesh_envprobe" / "__init__.py").write_text("X = 42\n")
    p = addon.runtime.prefs.get_prefs()
    p.env_path = str(env)
    try:
        assert sys.path[0] == str(env)
        import neumesh_envprobe

        assert neumesh_envprobe.X == 42
    finally:
        p.env_path = ""
    assert str(env) not in sys.path


def test_core_unavailable_message_says_what_to_do(addon, monkeypatch):
    monkeypatch.setattr(addon.runtime.deps, "missing_required", lambda statuses=None: ["torch"])
    monkeypatch.setattr(addon.runtime.core, "_nm", None)
    with pytest.raises(addon.runtime.core.CoreUnavailable, match="Install dependencies"):
        addon.runtime.core.get()


def test_the_measured_matrix_multiply_rate_is_judged_against_the_docs_machine(addon):
    """Check dependencies' GFLOP/s figure says what it means: about the 2-core machine of
    docs/benchmarks.md (180 GFLOP/s) or faster is fast; a few times below it, renders and training that
    much slower; far below it (13 GFLOP/s on a loaded machine), slow, with what to do."""
    prefs = addon.runtime.prefs

    def message(gflops):
        return prefs.speed_message({"own": True, "gflops": gflops, "rebind": {}, "sgemm": "", "remedy": ""})

    fast, moderate, slow = message(300.0), message(60.0), message(13.0)
    assert fast.startswith("matrix multiply 300 GFLOP/s with torch's own BLAS: fast")
    assert "moderate: 3x below the 180 GFLOP/s" in moderate and "~2 s instead of ~0.7 s" in moderate
    assert slow.startswith("matrix multiply 13 GFLOP/s with torch's own BLAS: slow: 14x below")
    assert "up to ~10 s" in slow and "CPU threads" in slow and "CUDA" in slow
    assert [prefs.speed_level(g) for g in (None, 13.0, 60.0, 300.0)] == ["", "slow", "moderate", "fast"]
    assert "(rebound from" not in slow and message(None) == "matrix multiply with torch's own BLAS"


def test_existing_environment_marks_the_preferences_unsaved_and_a_background_run_saves_nothing(addon, tmp_path):
    """Setting Existing environment marks the preferences unsaved (so Blender's auto-save, or the
    add-on at once, keeps it); in a background run (bpy, `blender -b`) the add-on writes nothing."""
    persist = addon.runtime.persist
    p = addon.runtime.prefs.get_prefs()
    saved = os.path.join(bpy.utils.resource_path("USER"), "config", "userpref.blend")

    def stamp():
        return os.stat(saved).st_mtime_ns if os.path.exists(saved) else None

    before = stamp()
    bpy.context.preferences.is_dirty = False
    p.env_path = str(tmp_path)
    try:
        assert bpy.context.preferences.is_dirty
        assert persist.persist() == "skipped" and persist.unsaved_note() == ""
        assert stamp() == before
    finally:
        p.env_path = ""
