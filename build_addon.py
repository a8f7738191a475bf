#!/usr/bin/env python3
"""Build the installable NeuMesh add-on zip.

The zip holds one folder ``neumesh/`` with
  * the add-on (``addon/``: ``__init__.py`` and its sub-packages runtime/, scene/, render/, train/,
    edit/, semantics/, bake/, deform/, ui/), including ``blender_manifest.toml`` -> a Blender 4.2+ extension, and
    ``bl_info`` in ``__init__.py`` -> a legacy add-on for Blender 3.x/4.0/4.1;
  * ``neumesh_core`` vendored as the subpackage ``neumesh/neumesh_core`` (imported by ``addon/runtime/core.py``).
torch & co are not bundled (see the add-on preferences / docs/addon.md).

Usage:
  python build_addon.py                    # -> dist/neumesh-<version>.zip
  python build_addon.py --out X.zip --validate   # also run Blender's extension validator (needs bpy 4.2+)
"""
from __future__ import annotations

import argparse
import os
import re
import sys
import time
import zipfile

ROOT = os.path.dirname(os.path.abspath(__file__))
ADDON_DIR = os.path.join(ROOT, "addon")
CORE_DIR = os.path.join(ROOT, "neumesh_core")
PKG = "neumesh"
_SKIP_DIRS = {"__pycache__", ".pytest_cache", ".mypy_cache"}
_SKIP_EXT = {".pyc", ".pyo", ".so~"}
# a fixed timestamp makes the zip reproducible (same inputs -> same bytes)
_DATE = (2024, 1, 1, 0, 0, 0)


def manifest_version() -> str:
    with open(os.path.join(ADDON_DIR, "blender_manifest.toml"), encoding="utf-8") as f:
        m = re.search(r'^version\s*=\s*"([^"]+)"', f.read(), re.M)
    if not m:
        raise SystemExit("addon/blender_manifest.toml has no version")
    return m.group(1)


def _walk(src: str):
    for dirpath, dirnames, filenames in os.walk(src):
        dirnames[:] = sorted(d for d in dirnames if d not in _SKIP_DIRS and not d.startswith("."))
        for fn in sorted(filenames):
            if os.path.splitext(fn)[1] in _SKIP_EXT or fn.startswith("."):
                continue
            full = os.path.join(dirpath, fn)
            yield full, os.path.relpath(full, src).replace(os.sep, "/")


def build(out: str | None = None, core_dir: str = CORE_DIR) -> str:
    version = manifest_version()
    out = out or os.path.join(ROOT, "dist", f"{PKG}-{version}.zip")
    os.makedirs(os.path.dirname(os.path.abspath(out)) or ".", exist_ok=True)
    if not os.path.isfile(os.path.join(core_dir, "__init__.py")):
        raise SystemExit(f"{core_dir}/__init__.py missing: the core package is not there to vendor")
    tmp = out + ".tmp"
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        def add(full, arc):
            zi = zipfile.ZipInfo(arc, date_time=_DATE)
            zi.compress_type = zipfile.ZIP_DEFLATED
            zi.external_attr = 0o644 << 16
            with open(full, "rb") as f:
                zf.writestr(zi, f.read())

        for full, rel in _walk(ADDON_DIR):
            if rel.split("/")[0] == "neumesh_core":  # never a stale copy inside addon/
                continue
            add(full, f"{PKG}/{rel}")
        for full, rel in _walk(core_dir):
            add(full, f"{PKG}/neumesh_core/{rel}")
    os.replace(tmp, out)
    return out


def validate(zip_path: str) -> bool:
    """Run Blender's own extension validator (what `blender --command extension validate` runs)."""
    import bpy  # noqa: F401  (loads bl_pkg)

    if bpy.app.version < (4, 2, 0):
        raise SystemExit("extension validation needs Blender/bpy 4.2+")
    import importlib

    try:
        cli = importlib.import_module("bl_pkg.bl_extension_cli")
    except ImportError:
        import addon_utils

        sys.path.extend(addon_utils.paths())
        cli = importlib.import_module("bl_pkg.bl_extension_cli")
    rc = cli.cli_extension_handler(["validate", os.path.abspath(zip_path)])
    return rc == 0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", help="output zip path (default dist/neumesh-<version>.zip)")
    ap.add_argument("--validate", action="store_true", help="validate with bpy's extension validator")
    a = ap.parse_args(argv)
    t = time.time()
    path = build(a.out)
    print(f"built {path} ({os.path.getsize(path) / 1024:.0f} KiB, {time.time() - t:.2f}s)")
    if a.validate:
        ok = validate(path)
        print("validate:", "OK" if ok else "FAILED")
        return 0 if ok else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
