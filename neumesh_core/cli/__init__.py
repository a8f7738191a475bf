"""`neumesh` command line: train, render, eval, demo, bake, scaffold, edit, semantics, fit, poses.

One module per command (or group); shared option groups and helpers in :mod:`.common`. The only place in
neumesh_core that imports the package root (``import neumesh_core as nm``).
"""
from __future__ import annotations

import argparse
import sys

from . import bake, demo, edit, fit, poses, render, scaffold, semantics, train
from . import eval as eval_cmd
from .common import Progress, turntable_cameras  # noqa: F401  (public: benchmarks and scripts use them)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="neumesh", description="NeuMesh++ editable neural radiance fields "
                                 "on mesh scaffolds (CPU-first).")
    sub = ap.add_subparsers(dest="command", required=True)
    for mod in (train, render, eval_cmd, demo, bake, scaffold, edit, semantics, fit, poses):  # order of `--help`
        mod.add_commands(sub)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from ..errors import NeuMeshError

    try:
        return int(args.func(args) or 0)
    except NeuMeshError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\ninterrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
