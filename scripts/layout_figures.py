#!/usr/bin/env python3
"""Layout figures: files over 400 lines and functions over 100 lines (neumesh_core, and the add-on
beside it), import arrows that run back up the layers, import circles, results files without a
commit in their machine record, and the house's words: names spelled two ways and source files that
mention an issue number. Pure `ast`, `tokenize` and json (nothing is imported). tests/test_layers.py
uses the same rules and holds the package to LONG_FILES / LONG_FUNCTIONS below.

    python scripts/layout_figures.py [--root CHECKOUT] [--label now] [--json benchmarks/results/figures/layout.json]
"""
from __future__ import annotations

import argparse
import ast
import io
import json
import os
import re
import sys
import tokenize

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PKG = "neumesh_core"

# room -> layer (a room is a top-level module or subpackage of neumesh_core). Lower may not import higher.
LAYERS = {
    "errors": 0, "mesh": 0, "imageio": 0, "metrics": 0, "device": 0,
    "data": 1,
    "field": 2, "sampling": 2, "kernels": 2,
    "render": 3,
    "train": 4, "reconstruct": 4, "deform": 4,
    "edit": 5, "semantics": 5, "bake": 5, "evaluate": 5,
    "fit": 6,
    "cli": 7,
    "": 8,  # the package root (neumesh_core/__init__.py): only cli/ may import it
}
# reconstruct/'s earlier name, so that older checkouts (--root) measure too
OLD_ROOMS = {"scaffold": "reconstruct"}


def modules(pkg_dir: str) -> dict[str, str]:
    """dotted name (without the package prefix; '' for the root) -> file path"""
    out = {}
    for dirpath, dirnames, filenames in os.walk(pkg_dir):
        dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
        for fn in sorted(filenames):
            if not fn.endswith(".py"):
                continue
            rel = os.path.relpath(os.path.join(dirpath, fn), pkg_dir)[:-3].replace(os.sep, ".")
            if rel == "__init__":
                rel = ""
            elif rel.endswith(".__init__"):
                rel = rel[: -len(".__init__")]
            out[rel] = os.path.join(dirpath, fn)
    return out


def room_of(mod: str) -> str:
    for old, room in OLD_ROOMS.items():
        if mod == old or mod.startswith(old + "."):
            return room
    return mod.split(".")[0]


def imports(mod: str, path: str, known: set[str]) -> list[tuple[str, int, str]]:
    """(imported module inside the package, line, kind) for every import statement, lazy ones included.
    kind: 'module' or 'root' (the package root itself) or 'bpy'."""
    tree = ast.parse(open(path, encoding="utf-8").read(), path)
    is_pkg = os.path.basename(path) == "__init__.py"
    base = mod.split(".") if mod else []
    if not is_pkg:
        base = base[:-1]
    out = []

    def resolve(name: str) -> str:
        # longest known prefix of the dotted name
        parts = name.split(".") if name else []
        while parts and ".".join(parts) not in known:
            parts = parts[:-1]
        return ".".join(parts)

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                top = a.name.split(".")[0]
                if top == "bpy":
                    out.append(("bpy", node.lineno, "bpy"))
                elif top == PKG:
                    sub = a.name[len(PKG) + 1:]
                    out.append((resolve(sub), node.lineno, "root" if not sub else "module"))
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                name = node.module or ""
                top = name.split(".")[0]
                if top == "bpy":
                    out.append(("bpy", node.lineno, "bpy"))
                    continue
                if top != PKG:
                    continue
                sub = name[len(PKG) + 1:]
            else:
                anchor = base[: len(base) - (node.level - 1)] if node.level > 1 else base
                sub = ".".join(anchor + ([node.module] if node.module else []))
            if sub == "" and node.module is None and node.level:
                # "from . import x" at the root, or "from .. import x": each name may be a module
                for a in node.names:
                    full = ".".join(filter(None, [sub, a.name]))
                    out.append((full, node.lineno, "module") if full in known else ("", node.lineno, "root"))
                continue
            if sub == "":
                out.append(("", node.lineno, "root"))
                continue
            for a in node.names:
                full = sub + "." + a.name
                out.append((full if full in known else resolve(sub), node.lineno, "module"))
    return out


def graph(pkg_dir: str):
    mods = modules(pkg_dir)
    known = set(mods)
    edges = {}
    for m, p in mods.items():
        edges[m] = [(t, ln, kind) for t, ln, kind in imports(m, p, known) if t != m]
    return mods, edges


def upward(edges) -> list[str]:
    bad = []
    for m, outs in edges.items():
        src_room = room_of(m)
        if m == "":
            continue  # the root re-exports everything
        for t, ln, kind in outs:
            if kind == "bpy":
                continue
            dst_room = room_of(t) if t else ""
            if dst_room == src_room or (src_room == "cli" and dst_room == ""):
                continue
            if LAYERS.get(dst_room, 99) > LAYERS.get(src_room, 99):
                line = (f"{m or PKG}:{ln} -> {t or PKG} ({src_room} {LAYERS.get(src_room)} -> "
                           f"{dst_room or 'root'} {LAYERS.get(dst_room)})")
                if line not in bad:
                    bad.append(line)
    return bad


def _sccs(nodes, succ):
    index, low, on, stack, out, i = {}, {}, set(), [], [], [0]

    def visit(v):  # Tarjan (recursion depth is tiny here)
        index[v] = low[v] = i[0]
        i[0] += 1
        stack.append(v)
        on.add(v)
        for w in succ.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))
    for v in sorted(nodes):
        if v not in index:
            visit(v)
    return out


def room_cycles(edges) -> list[list[str]]:
    """import circles between rooms (subpackages / top-level modules), the package root left out"""
    succ = {}
    for m, outs in edges.items():
        if m == "":
            continue
        a = room_of(m)
        for t, _, kind in outs:
            if kind == "bpy" or not t:
                continue
            b = room_of(t)
            if a != b:
                succ.setdefault(a, set()).add(b)
    nodes = set(succ) | {b for s in succ.values() for b in s}
    return _sccs(nodes, succ)


def module_cycles(edges) -> list[list[str]]:
    """import circles between modules (a package's __init__ re-exporting its own modules is no circle)"""
    succ = {}
    for m, outs in edges.items():
        for t, _, kind in outs:
            if kind == "bpy" or not t or m == "":
                continue
            if m and t.startswith(m + "."):
                continue  # a package importing its own submodules
            succ.setdefault(m, set()).add(t)
    nodes = set(succ) | {b for s in succ.values() for b in s}
    return _sccs(nodes, succ)


# The package's files over 400 lines and functions over 100 lines, each a candidate to split; the
# layout test fails on one not listed (split it, or list it here with the reason it stays long) and on
# one listed that is no longer long (take it off).
LONG_FILES = {
    "neumesh_core/deform/arap.py": "the ARAP solver: set-up, constrained local-global solve, cage, one algorithm",
    "neumesh_core/render/renderer.py": "render_rays, render_camera and their output types",
    "neumesh_core/semantics/extractors.py": "the 2D feature extractors, a class each",
    "neumesh_core/semantics/geometry.py": "the shape features of selection and their cache",
}
LONG_FUNCTIONS: dict = {}


def _lines(path: str) -> int:
    with open(path, encoding="utf-8") as fh:
        return sum(1 for _ in fh)


def long_files(pkg_dir: str, limit: int = 400) -> dict[str, int]:
    """Files of the package (or any folder of .py files) over ``limit`` lines: path -> lines."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(pkg_dir):
        dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
        for fn in filenames:
            if fn.endswith(".py"):
                p = os.path.join(dirpath, fn)
                n = _lines(p)
                if n > limit:
                    out[os.path.relpath(p, os.path.dirname(pkg_dir)).replace(os.sep, "/")] = n
    return dict(sorted(out.items()))


def long_functions(pkg_dir: str, limit: int = 100) -> dict[str, int]:
    """Functions and methods over ``limit`` lines (decorators and docstrings counted):
    "path:Class.name" -> lines."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(pkg_dir):
        dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
        for fn in filenames:
            if not fn.endswith(".py"):
                continue
            p = os.path.join(dirpath, fn)
            rel = os.path.relpath(p, os.path.dirname(pkg_dir)).replace(os.sep, "/")
            tree = ast.parse(open(p, encoding="utf-8").read(), p)

            def visit(node, prefix):
                for child in ast.iter_child_nodes(node):
                    if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                        first = min([child.lineno] + [d.lineno for d in child.decorator_list])
                        n = child.end_lineno - first + 1
                        if n > limit:
                            out[f"{rel}:{prefix}{child.name}"] = n
                        visit(child, f"{prefix}{child.name}.")
                    elif isinstance(child, ast.ClassDef):
                        visit(child, f"{prefix}{child.name}.")
                    else:
                        visit(child, prefix)
            visit(tree, "")
    return dict(sorted(out.items()))


def results_without_commit(root: str = ROOT) -> list[str]:
    """Results files (benchmarks/results/**/*.json) whose machine record names no commit."""
    base = os.path.join(root, "benchmarks", "results")
    out = []
    for dirpath, _, filenames in os.walk(base):
        for fn in filenames:
            if fn.endswith(".json"):
                p = os.path.join(dirpath, fn)
                try:
                    with open(p, encoding="utf-8") as fh:
                        machine = json.load(fh).get("machine")
                except (ValueError, AttributeError):   # not JSON, or not an object
                    machine = None
                if not (isinstance(machine, dict) and machine.get("commit")):
                    out.append(os.path.relpath(p, root).replace(os.sep, "/"))
    return sorted(out)


# --- the house's words ------------------------------------------------------------------------------------
# One word per thing, one spelling. Identifiers spell British (DEVELOPERS.md, "One word, one meaning");
# the libraries' own names (bpy, torch, OpenCV, PIL, trimesh) keep theirs and are not counted.
SPELLINGS = {   # a word's other spelling -> the house's
    "color": "colour", "colors": "colours", "colored": "coloured", "center": "centre", "centers": "centres",
    "gray": "grey", "neighbor": "neighbour", "neighbors": "neighbours", "normalize": "normalise",
    "normalized": "normalised", "optimize": "optimise", "optimizer": "optimiser", "behavior": "behaviour",
    "initialize": "initialise", "analyze": "analyse", "visualize": "visualise", "favor": "favour",
    "license": "licence",
    "distil": "distill",   # the core's package, function and command spell it distill; the add-on follows
}
LIBRARY_NAMES = {"color", "color_attributes", "colorspace_settings", "active_color", "diffuse_color", "color_mode",
                 "color_type", "use_unified_color", "color_depth", "colorspace", "normalize", "Optimizer",
                 "optimize", "COLOR_BGR2GRAY", "cvtColor", "baseColorTexture"}
# former names kept working for saved .blend files, keymaps and user scripts, each beside the current one
ALIAS_NAMES = {"distil_semantics", "distil_cancel", "NEUMESH_OT_distil_semantics", "NEUMESH_OT_distil_cancel"}
CODE_DIRS = ("neumesh_core", "addon", "tests", "blender_tests", "benchmarks", "scripts")
TEXT_EXT = (".py", ".sh", ".toml", ".md", ".txt", ".cfg", ".yml", ".yaml", ".json")
# an issue number, a mention of an issue's report or a round of work, in a source or doc file
ISSUE_MENTION = re.compile(r"(?i)\bissues?\s*#?\s*\d+|(?:^|[\s(])#\d{2,3}\b|\bthe[ ]issue'?s?\b|\bround[ ]\d\b")
_WORD = re.compile(r"[A-Z]+(?![a-z])|[A-Z]?[a-z]+|\d+")


def _source_files(root: str, exts=TEXT_EXT, dirs=None):
    """Files of the checkout (relative paths), caches, environments and benchmark results left out."""
    skip = {".git", ".venv", "__pycache__", "node_modules", "build", "dist", ".pytest_cache", ".ruff_cache"}
    for top in (dirs or [""]):
        base = os.path.join(root, top)
        if os.path.isfile(base):
            yield top
            continue
        for dirpath, dirnames, filenames in os.walk(base):
            rel = os.path.relpath(dirpath, root).replace(os.sep, "/")
            dirnames[:] = sorted(d for d in dirnames if d not in skip and not d.startswith(".")
                                 and f"{rel}/{d}".lstrip("./") != "benchmarks/results")
            for fn in sorted(filenames):
                if fn.endswith(exts):
                    yield os.path.relpath(os.path.join(dirpath, fn), root).replace(os.sep, "/")


def identifiers(path: str) -> set[str]:
    """The names a Python file spells (tokenize's NAME tokens: variables, functions, attributes, keywords
    of calls), strings and comments left out."""
    with open(path, "rb") as fh:
        toks = tokenize.tokenize(io.BytesIO(fh.read()).readline)
        try:
            return {t.string for t in toks if t.type == tokenize.NAME}
        except (tokenize.TokenError, SyntaxError):
            return set()


def _house_form(name: str) -> str:
    """``name`` with every word in the house's spelling, lower case: the key two spellings share."""
    return "_".join(SPELLINGS.get(w.lower(), w.lower()) for w in _WORD.findall(name))


def _plain_form(name: str) -> str:
    """``name``'s words in lower case: case and underscores aside, one spelling."""
    return "_".join(w.lower() for w in _WORD.findall(name))


def spellings(root: str = ROOT) -> dict:
    """Names spelled two ways in the code: identifiers that differ only in a word's spelling
    (``mod_colors`` / ``mod_colours``), and words that appear in both spellings across identifiers
    (colour in one name, color in another), the libraries' own names and the declared aliases left out."""
    names = set()
    for rel in _source_files(root, (".py",), [d for d in CODE_DIRS if os.path.exists(os.path.join(root, d))]
                             + [f for f in ("build_addon.py",) if os.path.exists(os.path.join(root, f))]):
        names |= identifiers(os.path.join(root, rel))
    names -= LIBRARY_NAMES | ALIAS_NAMES
    forms: dict[str, set] = {}
    for n in names:
        forms.setdefault(_house_form(n), set()).add(n)
    twins = {k: sorted(v) for k, v in sorted(forms.items()) if len({_plain_form(x) for x in v}) > 1}
    used: dict[str, set] = {}
    house_words = set(SPELLINGS.values())
    for n in names:
        for w in _WORD.findall(n):
            w = w.lower()
            if w in SPELLINGS or w in house_words:
                used.setdefault(SPELLINGS.get(w, w).removesuffix("s"), set()).add(w.removesuffix("s"))
    two_ways = {k: sorted(v) for k, v in sorted(used.items()) if len(v) > 1}
    return {"identifiers_spelled_two_ways": len(twins), "identifier_twins": twins,
            "words_spelled_two_ways": len(two_ways), "word_spellings": two_ways}


def issue_mentions(root: str = ROOT) -> dict[str, list[str]]:
    """Source and doc files that mention an issue number, an issue's report or a round of work, by area
    (neumesh_core, addon, tests, blender_tests, other); benchmark results files left out."""
    out: dict[str, list[str]] = {}
    for rel in _source_files(root):
        try:
            with open(os.path.join(root, rel), encoding="utf-8") as fh:
                text = fh.read()
        except (UnicodeDecodeError, OSError):
            continue
        if ISSUE_MENTION.search(text):
            top = rel.split("/")[0]
            out.setdefault(top if top in CODE_DIRS[:4] else "other", []).append(rel)
    return out


def figures(root: str = ROOT) -> dict:
    pkg_dir = os.path.join(root, PKG)
    mods, edges = graph(pkg_dir)
    up = upward(edges)
    rc, mc = room_cycles(edges), module_cycles(edges)
    lf = long_files(pkg_dir)
    fns = long_functions(pkg_dir)
    addon = os.path.join(root, "addon")
    addon_files = long_files(addon) if os.path.isdir(addon) else {}
    addon_fns = long_functions(addon) if os.path.isdir(addon) else {}
    nocommit = results_without_commit(root)
    words, issues = spellings(root), issue_mentions(root)
    return {**words, "files_mentioning_an_issue": sum(len(v) for v in issues.values()),
            "files_mentioning_an_issue_by_area": {k: len(v) for k, v in sorted(issues.items())},
            "issue_mention_files": issues,
            "modules": len(mods), "files_over_400_lines": len(lf), "long_files": lf,
            "functions_over_100_lines": len(fns), "long_functions": fns,
            "addon_files_over_400_lines": len(addon_files), "addon_functions_over_100_lines": len(addon_fns),
            "addon_long_functions": addon_fns,
            "results_files": sum(1 for _ in _json_files(root)), "results_without_commit": len(nocommit),
            "upward_imports": len(up), "upward": up, "room_cycles": len(rc), "room_cycle_list": rc,
            "module_cycles": len(mc), "module_cycle_list": mc,
            "bpy_imports": sum(1 for outs in edges.values() for t in outs if t[2] == "bpy")}


def _json_files(root: str):
    for dirpath, _, filenames in os.walk(os.path.join(root, "benchmarks", "results")):
        yield from (f for f in filenames if f.endswith(".json"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default=ROOT, help="checkout to measure (default: this one)")
    ap.add_argument("--label", default="now", help="key in the JSON file (e.g. before / now)")
    ap.add_argument("--json", default=None, help="merge the figures into this JSON file under --label")
    a = ap.parse_args(argv)
    f = figures(a.root)
    for k in ("modules", "files_over_400_lines", "functions_over_100_lines", "addon_files_over_400_lines",
              "addon_functions_over_100_lines", "results_files", "results_without_commit", "upward_imports",
              "room_cycles", "module_cycles", "bpy_imports", "identifiers_spelled_two_ways",
              "words_spelled_two_ways", "files_mentioning_an_issue"):
        print(f"{k:30s} {f[k]}")
    for p, n in f["long_files"].items():
        print(f"  long file: {p} {n}")
    for p, n in {**f["long_functions"], **f["addon_long_functions"]}.items():
        print(f"  long function: {p} {n}")
    for u in f["upward"]:
        print(f"  up:   {u}")
    for c in f["room_cycle_list"] + f["module_cycle_list"]:
        print(f"  circle: {' <-> '.join(c)}")
    for k, v in f["identifier_twins"].items():
        print(f"  name spelled two ways: {' / '.join(v)}")
    for k, v in f["word_spellings"].items():
        print(f"  word spelled two ways in names: {' / '.join(v)}")
    for area, files in f["issue_mention_files"].items():
        print(f"  mentions an issue ({area}, {len(files)}): {' '.join(files)}")
    if a.json:
        data = {}
        if os.path.exists(a.json):
            with open(a.json, encoding="utf-8") as fh:
                data = json.load(fh)
        data[a.label] = f
        sys.path.insert(0, ROOT)
        from benchmarks._results import write_results

        path = os.path.abspath(a.json)
        write_results(data, os.path.basename(path), os.path.dirname(path))
    return 0


if __name__ == "__main__":
    sys.exit(main())
