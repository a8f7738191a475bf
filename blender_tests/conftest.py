"""pytest inside Blender's Python (bpy==5.0.1 from PyPI, installed in the venv).

bpy writes user configuration, caches and temp files under $HOME; everything is redirected into one
temporary folder BEFORE bpy is imported. The add-on is built with build_addon.py, installed from the
zip as an extension (user_default repository) and re-enabled after every factory reset.
"""
from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import user_dirs  # noqa: E402

_BASE = user_dirs.redirect("neumesh_btests_")

import pytest  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

import bpy  # noqa: E402
import addon_utils  # noqa: E402

ADDON_MODULE = "bl_ext.user_default.neumesh"


def pytest_report_header(config):
    return f"bpy {bpy.app.version_string}; blender user dir {_BASE}"


@pytest.fixture(scope="session")
def base_dir():
    return _BASE


@pytest.fixture(scope="session")
def addon_zip(tmp_path_factory):
    import build_addon

    return build_addon.build(str(tmp_path_factory.mktemp("dist") / "neumesh.zip"))


@pytest.fixture(scope="session")
def addon(addon_zip):
    """The installed, enabled add-on package (module object)."""
    res = bpy.ops.extensions.package_install_files(filepath=addon_zip, repo="user_default",
                                                   enable_on_install=True, overwrite=True)
    assert res == {"FINISHED"}
    mod = sys.modules.get(ADDON_MODULE)
    assert mod is not None, "extension was installed but not enabled"
    assert os.path.dirname(mod.__file__).startswith(os.environ["BLENDER_USER_RESOURCES"])
    return mod


@pytest.fixture(autouse=True)
def fresh_scene(request, tmp_path):
    """Empty factory scene for every test; the add-on (if installed) is enabled again, and the scene's
    Edits folder is the test's tmp_path (the .blend is unsaved: without a folder, edits refuse to
    start; a test of that default sets it back to '')."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if ADDON_MODULE in sys.modules:
        addon_utils.enable(ADDON_MODULE, default_set=True)
        bpy.context.scene.neumesh.edits_dir = str(tmp_path)
    yield


def enable_addon():
    addon_utils.enable(ADDON_MODULE, default_set=True)
    return sys.modules[ADDON_MODULE]


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """The core's default scene, tiny: 32 px, 8 training views, 642-vertex scaffold (mesh.ply)."""
    import neumesh_core as nm

    d = str(tmp_path_factory.mktemp("dataset"))
    nm.make_default_scene(d, resolution=32, n_train=8, n_val=1, n_test=1, mesh_subdiv=3)
    return d


@pytest.fixture(scope="session")
def trained_field(tiny_dataset, tmp_path_factory):
    """A field trained briefly with the core directly (so renders are not blank); path to the file."""
    import neumesh_core as nm

    field = nm.create_field(nm.load_mesh(os.path.join(tiny_dataset, "mesh.ply")), nm.FieldConfig())
    scene = nm.load_scene(tiny_dataset)
    nm.train(field, scene, nm.TrainConfig(steps=TRAIN_STEPS, rays_per_batch=512, log_every=1))
    path = str(tmp_path_factory.mktemp("fields") / "blob.neumesh")
    nm.save_field(field, path)
    return path


TRAIN_STEPS = 40
