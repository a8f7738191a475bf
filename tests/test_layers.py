"""The layout's rules, checked on the source with `ast` (nothing is imported):

* no `bpy` anywhere in neumesh_core;
* the files over 400 lines and the functions over 100 lines are the ones scripts/layout_figures.py
  declares (LONG_FILES, LONG_FUNCTIONS: split candidates), computed from the code;
* imports run down the layers only (DEVELOPERS.md, "Layout"): a room (top-level module or subpackage)
  never imports a room of a higher layer;
* no import circle between rooms, nor between modules;
* only `neumesh_core/cli/` imports the package root (`import neumesh_core`, `from .. import x`);
* the add-on reaches the core only through the package root (`core.get()`), never a private module.
"""
import ast
import os
import re
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "scripts"))
import layout_figures as lf  # noqa: E402

PKG_DIR = os.path.join(ROOT, "neumesh_core")


@pytest.fixture(scope="module")
def graph():
    return lf.graph(PKG_DIR)


def test_every_room_has_a_layer(graph):
    mods, _ = graph
    rooms = {lf.room_of(m) for m in mods}
    assert rooms <= set(lf.LAYERS), f"rooms without a layer in scripts/layout_figures.py: {rooms - set(lf.LAYERS)}"


def test_no_bpy_in_the_core(graph):
    _, edges = graph
    bad = [f"{m}:{ln}" for m, outs in edges.items() for t, ln, kind in outs if kind == "bpy"]
    assert not bad, f"neumesh_core imports bpy (the core must run without Blender): {bad}"


def test_imports_run_down_the_layers(graph):
    _, edges = graph
    assert lf.upward(edges) == []


def test_no_import_circles(graph):
    _, edges = graph
    assert lf.room_cycles(edges) == []
    assert lf.module_cycles(edges) == []


def test_only_the_cli_imports_the_package_root(graph):
    _, edges = graph
    bad = [f"{m}:{ln}" for m, outs in edges.items() if m and lf.room_of(m) != "cli"
           for t, ln, kind in outs if kind == "root"]
    assert not bad, f"modules outside neumesh_core/cli/ import the package root: {bad}"


def test_the_checker_sees_upward_arrows_and_circles(tmp_path):
    """The rules above must be able to fail: a lower room importing a higher one, a circle, the root
    imported from below, bpy."""
    pkg = tmp_path / "neumesh_core"
    for d in ("", "data", "field", "cli"):
        (pkg / d).mkdir(parents=True, exist_ok=True)
        (pkg / d / "__init__.py").write_text("")
    (pkg / "mesh.py").write_text("from .data.scene import Scene\n")           # base -> data: up
    (pkg / "data" / "scene.py").write_text("from ..field.field import F\nimport bpy\n")  # data -> field: up
    (pkg / "field" / "field.py").write_text("import neumesh_core as nm\nfrom ..data.scene import Scene\n")
    (pkg / "cli" / "main.py").write_text("import neumesh_core as nm\n")          # allowed
    _, edges = lf.graph(str(pkg))
    up = lf.upward(edges)
    assert any(u.startswith("mesh:1 -> data.scene") for u in up)
    assert any(u.startswith("data.scene:1 -> field.field") for u in up)
    assert any(u.startswith("field.field:1 -> neumesh_core") for u in up)
    assert not any(u.startswith("cli.") for u in up)
    assert ["data", "field"] in lf.room_cycles(edges)
    assert ["data.scene", "field.field"] in lf.module_cycles(edges)
    assert sum(1 for outs in edges.values() for t in outs if t[2] == "bpy") == 1


def test_long_files_and_functions_are_the_declared_ones():
    """A new file over 400 lines or function over 100 fails: split it, or declare it with the reason it
    stays long; a declared one that got short leaves the list."""
    files, functions = lf.long_files(PKG_DIR), lf.long_functions(PKG_DIR)
    assert not set(files) - set(lf.LONG_FILES), (
        f"files over 400 lines: {sorted(set(files) - set(lf.LONG_FILES))}; split them, or list them in "
        "scripts/layout_figures.py LONG_FILES with the reason")
    assert not set(functions) - set(lf.LONG_FUNCTIONS), (
        f"functions over 100 lines: { {k: functions[k] for k in sorted(set(functions) - set(lf.LONG_FUNCTIONS))} }; "
        "split them, or list them in scripts/layout_figures.py LONG_FUNCTIONS with the reason")
    gone = sorted(set(lf.LONG_FILES) - set(files)) + sorted(set(lf.LONG_FUNCTIONS) - set(functions))
    assert not gone, f"no longer long (or gone): take them off scripts/layout_figures.py's lists: {gone}"


def test_the_length_checker_sees_long_files_and_functions(tmp_path):
    pkg = tmp_path / "neumesh_core"
    (pkg / "render").mkdir(parents=True)
    body = "".join(f"    x{i} = {i}\n" for i in range(100))
    (pkg / "render" / "big.py").write_text("class A:\n    @staticmethod\n    def f():\n" + "    " + body.replace(
        "\n    ", "\n        ") + "\n" * 300)
    (pkg / "small.py").write_text("def g():\n" + "".join(f"    y{i} = {i}\n" for i in range(98)))
    assert lf.long_files(str(pkg)) == {"neumesh_core/render/big.py": 403}
    assert lf.long_functions(str(pkg)) == {"neumesh_core/render/big.py:A.f": 102}


# --- the add-on ------------------------------------------------------------------------------------------

_DOTTED = re.compile(r"\bneumesh_core\.[A-Za-z_]")


def _private_core_uses(path: str) -> list[str]:
    """Uses of a core module other than the package root in one add-on file: `import neumesh_core.x`,
    `from neumesh_core.x import`, `from neumesh_core import x` where x is a module, and
    `importlib.import_module(<anything> + ".x")` (how the add-on reaches a vendored core's modules)."""
    src = open(path, encoding="utf-8").read()
    tree = ast.parse(src, path)
    core_modules = {m.split(".")[0] for m in lf.modules(PKG_DIR) if m}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [f"{node.lineno}: import {a.name}" for a in node.names if a.name.startswith("neumesh_core.")]
        elif isinstance(node, ast.ImportFrom) and node.module:
            if node.module.startswith("neumesh_core."):
                out.append(f"{node.lineno}: from {node.module} import ...")
            elif node.module == "neumesh_core":
                out += [f"{node.lineno}: from neumesh_core import {a.name}" for a in node.names
                        if a.name in core_modules]
        elif isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            if name == "import_module" and node.args:
                arg = node.args[0]
                for c in ast.walk(arg):
                    if isinstance(c, ast.Constant) and isinstance(c.value, str) and c.value.startswith("."):
                        out.append(f"{node.lineno}: import_module(... + {c.value!r})")
                if isinstance(arg, ast.Constant) and isinstance(arg.value, str) and _DOTTED.match(arg.value):
                    out.append(f"{node.lineno}: import_module({arg.value!r})")
            if name == "_core_module":   # addon/render.py's helper over import_module
                out.append(f"{node.lineno}: _core_module(...)")
    return out


def test_addon_private_core_scan_finds_uses(tmp_path):
    p = tmp_path / "x.py"
    p.write_text("import importlib\nfrom neumesh_core.field import remap\n"
                 "m = importlib.import_module(nm.__name__ + '.edit')\nimport neumesh_core\n")
    uses = _private_core_uses(str(p))
    assert len(uses) == 2 and uses[0].startswith("2:") and "'.edit'" in uses[1]


def test_addon_uses_only_the_public_core():
    addon = os.path.join(ROOT, "addon")
    bad = []
    for dirpath, _, files in os.walk(addon):
        for fn in sorted(files):
            if fn.endswith(".py"):
                p = os.path.join(dirpath, fn)
                bad += [f"{os.path.relpath(p, ROOT)}:{u}" for u in _private_core_uses(p)]
    assert not bad, "the add-on imports private core modules (use nm.<name> from core.get()):\n" + "\n".join(bad)
