"""Smoke test of the command line's help: `neumesh --help` and every subcommand's `--help`, nested ones
included (`neumesh edit swap|fill|paint`, `neumesh semantics`), exit 0 and print a usage line.
In-process (argparse main), plus one run of the installed `neumesh` entry point."""
import argparse
import os
import shutil
import subprocess
import sys

import pytest

from neumesh_core.cli import build_parser, main


def _commands(parser, prefix=()):
    """Every command path of ``parser``'s subparsers, depth first: ("train",), ("edit",), ("edit", "swap")..."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out.append(prefix + (name,))
                out.extend(_commands(sub, prefix + (name,)))
    return out


COMMANDS = _commands(build_parser())


def test_the_commands_the_readme_names_exist():
    for cmd in [("train",), ("render",), ("eval",), ("demo",), ("scaffold",), ("fit",), ("edit",),
                ("edit", "swap"), ("edit", "fill"), ("edit", "paint"), ("semantics",)]:
        assert cmd in COMMANDS, f"neumesh {' '.join(cmd)} is missing: {COMMANDS}"


@pytest.mark.parametrize("cmd", [()] + COMMANDS, ids=lambda c: " ".join(c) or "neumesh")
def test_help_exits_0(cmd, capsys):
    with pytest.raises(SystemExit) as e:
        main(list(cmd) + ["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: neumesh" + "".join(" " + c for c in cmd))
    assert "--help" in out


def test_installed_entry_point_prints_help():
    exe = os.path.join(os.path.dirname(sys.executable), "neumesh")
    exe = exe if os.path.exists(exe) else shutil.which("neumesh")
    if exe is None:
        pytest.skip("no `neumesh` entry point installed (pip install -e .)")
    r = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    for cmd in ("train", "render", "eval", "demo", "scaffold", "fit", "edit", "semantics"):
        assert cmd in r.stdout
