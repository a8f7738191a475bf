"""Figures of the add-on's layout: pairs of repeated code (`duplicates`), files over 400
lines, import circles, modules per room, and back doors into the core. Prints them and writes
benchmarks/results/log/addon_layout.json.

Usage: .venv/bin/python benchmarks/diagnose/addon_layout.py [--rev REV]   (REV: measure a commit instead of the
working tree, e.g. d28bebc for the flat add-on)
"""
from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "blender_tests"))
from benchmarks._results import add_options, write_results  # noqa: E402
from test_layout import addon_modules, find_cycle, import_graph, private_core_uses  # noqa: E402


def measure(addon_dir: str) -> dict:
    mods = addon_modules(addon_dir)
    lines = {m or "__init__": sum(1 for _ in open(p, encoding="utf-8")) for m, p in mods.items()}
    dup = subprocess.run(["duplicates", "--repo", addon_dir, "--most", "200"], capture_output=True, text=True)
    first = (dup.stdout.splitlines() or [""])[0]
    m = re.match(r"(\d+) pairs", first)
    pairs = int(m.group(1)) if m else (0 if first.startswith("no duplicates") else None)
    graph = import_graph(mods)
    cycles, g = [], {k: set(v) for k, v in graph.items()}
    while (c := find_cycle(g)) is not None and len(cycles) < 50:   # count circles by breaking each once
        cycles.append(" -> ".join(c))
        g[c[0]].discard(c[1])
    back = []
    for p in mods.values():
        with open(p, encoding="utf-8") as f:
            back += private_core_uses(f.read(), os.path.relpath(p, addon_dir))
    rooms = {}
    for mod in mods:
        rooms.setdefault(mod.split(".")[0] if "." in mod else "(top)", []).append(mod)
    return {"modules": len(mods), "lines": sum(lines.values()), "duplicate_pairs": pairs,
            "duplicates_summary": first, "files_over_400_lines": sorted(k for k, v in lines.items() if v > 400),
            "largest_file_lines": max(lines.values()), "import_circles": len(cycles), "circles": cycles,
            "private_core_imports": back, "rooms": {k: len(v) for k, v in sorted(rooms.items())}}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rev", action="append", default=[], help="a commit to measure as well (repeatable)")
    add_options(ap, "name", "results_dir",
                name=dict(default="addon_layout", help="results name (default addon_layout)"))
    a = ap.parse_args(argv)
    out = {"worktree": measure(os.path.join(ROOT, "addon"))}
    for rev in a.rev:
        tmp = tempfile.mkdtemp(prefix="addon_layout_")
        try:
            subprocess.run(f"git -C {ROOT} archive {rev} addon | tar -x -C {tmp}", shell=True, check=True)
            out[rev] = measure(os.path.join(tmp, "addon"))
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    for k, r in out.items():
        print(f"{k}: {r['modules']} modules, {r['lines']} lines; duplicate pairs {r['duplicate_pairs']}; "
              f"files over 400 lines {len(r['files_over_400_lines'])} {r['files_over_400_lines']}; "
              f"import circles {r['import_circles']}; private core imports {len(r['private_core_imports'])}")
    write_results(out, f"{a.name}.json", a.results_dir)


if __name__ == "__main__":
    main()
