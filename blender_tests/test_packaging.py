"""The zip from build_addon.py is a valid Blender extension, a legacy add-on, and vendors the core."""
from __future__ import annotations

import ast
import os
import sys
import zipfile

import addon_utils
import bpy

from conftest import ADDON_MODULE


def test_zip_layout(addon_zip):
    with zipfile.ZipFile(addon_zip) as zf:
        names = set(zf.namelist())
        manifest = zf.read("neumesh/blender_manifest.toml").decode()
        init = zf.read("neumesh/__init__.py").decode()
    assert "neumesh/neumesh_core/__init__.py" in names
    for room in ("runtime", "scene", "render", "train", "edit", "ui"):   # the add-on's sub-packages
        assert f"neumesh/{room}/__init__.py" in names, room
    assert {"neumesh/runtime/deps.py", "neumesh/render/engine.py", "neumesh/bake/material.py"} <= names
    assert any(n.startswith("neumesh/neumesh_core/render/") for n in names)
    assert not any("__pycache__" in n or n.endswith(".pyc") for n in names)
    import tomllib

    m = tomllib.loads(manifest)
    assert m["schema_version"] == "1.0.0" and m["id"] == "neumesh" and m["type"] == "add-on"
    assert m["license"] and all(x.startswith("SPDX:") for x in m["license"])
    assert "files" in m["permissions"]
    # legacy add-on metadata, parsed the way Blender < 4.2 reads it (ast, without importing)
    bl_info = next(ast.literal_eval(n.value) for n in ast.parse(init).body
                   if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "bl_info")
    assert bl_info["blender"] <= (3, 4, 0) and bl_info["name"] == "NeuMesh"


def test_zip_is_reproducible(tmp_path):
    import build_addon

    one = build_addon.build(str(tmp_path / "one.zip"))
    two = build_addon.build(str(tmp_path / "two.zip"))
    assert open(one, "rb").read() == open(two, "rb").read()


def test_blender_extension_validator_accepts_zip(addon_zip):
    import build_addon

    assert build_addon.validate(addon_zip) is True


def test_validator_rejects_a_broken_manifest(addon_zip, tmp_path):
    """The validation step above can fail: a manifest with a bad id is refused."""
    import build_addon

    bad = tmp_path / "bad.zip"
    with zipfile.ZipFile(addon_zip) as src, zipfile.ZipFile(bad, "w") as dst:
        for item in src.infolist():
            data = src.read(item)
            if item.filename.endswith("blender_manifest.toml"):
                data = data.replace(b'id = "neumesh"', b'id = "neu mesh!"')
            dst.writestr(item, data)
    assert build_addon.validate(str(bad)) is False


def test_installs_and_enables_headless(addon):
    assert addon.__name__ == ADDON_MODULE
    assert ADDON_MODULE in {a.module for a in bpy.context.preferences.addons}
    assert hasattr(bpy.types.Object, "neumesh") and hasattr(bpy.types.Scene, "neumesh")
    bpy.context.scene.render.engine = "NEUMESH"
    assert bpy.context.scene.render.engine == "NEUMESH"
    assert hasattr(bpy.ops.neumesh, "train") and hasattr(bpy.ops.neumesh, "render_images")
    # the vendored core is the one the add-on uses
    from importlib import util

    assert util.find_spec(ADDON_MODULE + ".neumesh_core") is not None


def test_disable_and_enable_again(addon):
    addon_utils.disable(ADDON_MODULE, default_set=True)
    assert not hasattr(bpy.types.Object, "neumesh")
    addon_utils.enable(ADDON_MODULE, default_set=True)
    assert hasattr(bpy.types.Object, "neumesh")
    assert sys.modules[ADDON_MODULE] is not None


_NEXT_PROCESS = r'''
import sys, bpy, addon_utils
mode = sys.argv[1]
if mode == "install":
    r = bpy.ops.extensions.package_install_files(filepath=sys.argv[2], repo="user_default", enable_on_install=True)
    assert r == {"FINISHED"}, r
    if sys.argv[3] == "save":
        assert bpy.ops.wm.save_userpref() == {"FINISHED"}
elif mode == "read_userpref":
    bpy.ops.wm.read_userpref()
elif mode == "enable":
    addon_utils.enable("bl_ext.user_default.neumesh", default_set=True)
print("NEUMESH_ENABLED", "bl_ext.user_default.neumesh" in bpy.context.preferences.addons
      and hasattr(bpy.types.Object, "neumesh"))
'''


def test_bpy_module_next_process_has_the_extension_after_save_and_read_userpref(addon_zip, tmp_path):
    """bpy as a Python module does not load the saved preferences on import: an extension installed
    with enable_on_install=True is on disk but not enabled in the next Python process. What works (as
    docs/addon.md says): save_userpref() after installing, then read_userpref() in each new process;
    or addon_utils.enable(...) in each new process."""
    import subprocess

    script = tmp_path / "next.py"
    script.write_text(_NEXT_PROCESS)

    def run(home, *args):
        env = dict(os.environ)
        for var, sub in (("BLENDER_USER_RESOURCES", "res"), ("XDG_CACHE_HOME", "cache"), ("TMPDIR", "tmp"),
                         ("HOME", "home"), ("XDG_CONFIG_HOME", "config")):
            env[var] = str(home / sub)
            os.makedirs(env[var], exist_ok=True)
        r = subprocess.run([sys.executable, str(script), *args], env=env, capture_output=True, text=True,
                           timeout=240)
        assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
        return next(l.split()[1] for l in r.stdout.splitlines() if l.startswith("NEUMESH_ENABLED")) == "True"

    home = tmp_path / "a"
    assert run(home, "install", addon_zip, "save")
    assert not run(home, "none")              # the plain import: not enabled
    assert run(home, "read_userpref")         # the saved preferences enable it
    assert run(home, "enable")                # or enabling it by name
    other = tmp_path / "b"                    # installed without saving the preferences
    assert run(other, "install", addon_zip, "nosave")
    assert not run(other, "read_userpref") and run(other, "enable")
