"""The add-on's layout: it reaches the core only through ``neumesh_core``'s public names, its
modules import each other without a circle, and each room (sub-package) imports only the rooms below it
(DEVELOPERS.md, "addon/"). Static checks with ast: nothing is imported or run."""
from __future__ import annotations

import ast
import os

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ADDON = os.path.join(ROOT, "addon")
# the rooms from the bottom up; a room may import its own modules and the rooms before it
ROOMS = ("runtime", "scene", "render", "train", "edit", "semantics", "bake", "deform", "ui")
# public sub-modules of neumesh_core (besides the names in neumesh_core.__all__)
PUBLIC_SUBMODULES = {"edit", "semantics", "bake", "deform"}


def addon_modules(root=ADDON) -> dict:
    """{dotted module name below the add-on ('' for the package, 'render.field_cache', ...): file path}."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = [d for d in dirnames if not d.startswith((".", "__pycache__"))]
        for fn in filenames:
            if fn.endswith(".py"):
                rel = os.path.relpath(os.path.join(dirpath, fn), root)[:-3].replace(os.sep, ".")
                out[rel[:-len("__init__")].rstrip(".") if rel.endswith("__init__") else rel] = os.path.join(dirpath, fn)
    return out


def private_core_uses(source: str, where: str = "<source>") -> list[str]:
    """Back doors into the core in ``source``: imports of dotted ``neumesh_core.x`` modules (or of a
    sub-module by ``from neumesh_core import x`` that is not public), and ``importlib.import_module(...)``
    calls whose name is built with ``+ ".x"`` or an f-string (a core module found at run time)."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [f"{where}:{node.lineno}: import {a.name}" for a in node.names if a.name.startswith("neumesh_core.")]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.startswith("neumesh_core."):
                out.append(f"{where}:{node.lineno}: from {node.module} import ...")
        elif isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            if name == "import_module" and node.args:
                arg = node.args[0]
                dotted = (isinstance(arg, ast.BinOp) and isinstance(arg.right, ast.Constant)
                          and str(arg.right.value).startswith(".")) or isinstance(arg, ast.JoinedStr)
                if dotted:
                    out.append(f"{where}:{node.lineno}: importlib.import_module({ast.unparse(arg)})")
    return out


def core_attribute_uses(source: str, where: str = "<source>") -> list[tuple[str, str]]:
    """(place, name) of every ``nm.<name>`` where ``nm = core.get()`` (or ``core.get().<name>``)."""
    tree = ast.parse(source)
    holders = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call):
            f = node.value.func
            if isinstance(f, ast.Attribute) and f.attr == "get" and getattr(f.value, "id", "") == "core":
                holders |= {t.id for t in node.targets if isinstance(t, ast.Name)}
    out = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute):
            continue
        v = node.value
        is_core_get = isinstance(v, ast.Call) and isinstance(v.func, ast.Attribute) and v.func.attr == "get" \
            and getattr(v.func.value, "id", "") == "core"
        if ((isinstance(v, ast.Name) and v.id in holders) or is_core_get) and not node.attr.startswith("__"):
            out.append((f"{where}:{node.lineno}", node.attr))
    return out


def _public_core_names() -> set:
    import neumesh_core

    return set(neumesh_core.__all__) | PUBLIC_SUBMODULES


def test_addon_imports_no_private_core_module():
    bad = []
    for mod, path in addon_modules().items():
        with open(path, encoding="utf-8") as f:
            bad += private_core_uses(f.read(), os.path.relpath(path, ROOT))
    assert bad == [], "the add-on reaches into core internals; use nm.<public name>:\n" + "\n".join(bad)


def test_addon_uses_only_public_core_names():
    public = _public_core_names()
    bad = []
    for mod, path in addon_modules().items():
        with open(path, encoding="utf-8") as f:
            bad += [f"{w}: nm.{n}" for w, n in core_attribute_uses(f.read(), os.path.relpath(path, ROOT))
                    if n not in public]
    assert bad == [], "names the core does not export (neumesh_core.__all__):\n" + "\n".join(bad)


def test_the_checks_find_back_doors():
    """The two checks above can fail: each kind of back door in a snippet is found."""
    snippet = (
        "import importlib\nimport neumesh_core.field.remap\nfrom neumesh_core.render import raster\n"
        "m = importlib.import_module(nm.__name__ + '.bake')\nn = importlib.import_module(f'{p}.data.cameras')\n"
        "import neumesh_core\nfrom neumesh_core import load_field\n"
        "def f():\n    nm = core.get()\n    return nm.field.remap, nm.load_field, core.get().scaffold\n")
    found = private_core_uses(snippet)
    assert len(found) == 4 and "neumesh_core.field.remap" in found[0]
    names = [n for _w, n in core_attribute_uses(snippet)]
    assert sorted(names) == ["field", "load_field", "scaffold"]
    public = _public_core_names()
    assert sorted(n for n in names if n not in public) == ["field", "scaffold"]


def import_graph(modules=None) -> dict:
    """{module: {modules it imports, at the top or inside functions}} for the add-on's own modules."""
    modules = modules or addon_modules()
    graph = {m: set() for m in modules}
    for mod, path in modules.items():
        pkg = mod if path.endswith("__init__.py") else mod.rpartition(".")[0]
        with open(path, encoding="utf-8") as f:
            tree = ast.parse(f.read())
        for node in ast.walk(tree):
            if not (isinstance(node, ast.ImportFrom) and node.level):
                continue
            base = pkg
            for _ in range(node.level - 1):
                base = base.rpartition(".")[0]
            target = ".".join(p for p in (base, node.module or "") if p)
            for a in node.names:
                sub = ".".join(p for p in (target, a.name) if p)
                dep = sub if sub in modules else target
                if dep != mod and dep in modules:
                    graph[mod].add(dep)
    return graph


def find_cycle(graph: dict):
    """One import circle as a list of modules, or None."""
    state, stack = {}, []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            # a package's __init__ importing its own modules is how rooms register; a module importing its
            # package (``from . import x``) resolves to x, so package -> member edges are not circles
            if state.get(d) == 1:
                return stack[stack.index(d):] + [d]
            if d not in state:
                c = visit(d)
                if c:
                    return c
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state:
            c = visit(m)
            if c:
                return c
    return None


def test_no_import_circle_in_the_addon():
    assert find_cycle(import_graph()) is None, " -> ".join(find_cycle(import_graph()))


def test_the_circle_check_finds_a_circle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_rooms_import_only_downward():
    graph = import_graph()
    bad = []
    for mod, deps in graph.items():
        room = mod.split(".")[0]
        if room not in ROOMS:   # the package itself registers every room
            continue
        for d in deps:
            other = d.split(".")[0]
            if other in ROOMS and ROOMS.index(other) > ROOMS.index(room):
                bad.append(f"{mod} imports {d}")
    assert bad == [], "\n".join(bad)


def test_every_module_lives_in_a_room():
    loose = [m for m in addon_modules() if m and m.split(".")[0] not in ROOMS]
    assert loose == [], f"modules outside the rooms {ROOMS}: {loose}"
