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
