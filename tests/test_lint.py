"""The tree passes ruff with the configuration in pyproject.toml ([tool.ruff]: line length 120, unused
imports and variables, undefined names, pycodestyle's errors).  setup.sh installs ruff (the extra
``.[lint]``), so CI runs it here; where it is not installed the check is skipped with the reason."""
import importlib.util
import os
import re
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_setup_installs_the_linter():
    with open(os.path.join(ROOT, "setup.sh"), encoding="utf-8") as fh:
        installs = [ln for ln in fh if re.search(r"install .*-e \"\.\[", ln)]
    assert installs and all("lint" in re.search(r"\.\[([^\]]*)\]", ln).group(1).split(",") for ln in installs)
    with open(os.path.join(ROOT, "pyproject.toml"), encoding="utf-8") as fh:
        assert re.search(r'^lint = \["ruff', fh.read(), re.M)


def test_the_tree_passes_ruff():
    if importlib.util.find_spec("ruff") is None:
        pytest.skip("ruff is not installed: pip install -e '.[lint]' (setup.sh installs it)")
    run = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise", ROOT],
                         capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert run.returncode == 0, "ruff check found problems (fix them, or see pyproject.toml's [tool.ruff]):\n" + \
        run.stdout[-6000:] + run.stderr[-2000:]
