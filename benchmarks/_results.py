"""Where benchmark figures go: one JSON file per run, in benchmarks/results/ unless a folder is named."""
from __future__ import annotations

import json
import os

RESULTS_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")


def write_results(result: dict, name: str, folder: str | None = None, default=None) -> str:
    """Write ``result`` as ``folder/name`` (atomically: a killed run never leaves half a file), print
    and return the path.  ``default`` converts values json cannot (as in :func:`json.dump`)."""
    folder = folder or RESULTS_DIR
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, name)
    tmp = path + ".tmp"
    with open(tmp, "w") as fh:
        json.dump(result, fh, indent=2, default=default)
    os.replace(tmp, path)
    print(f"wrote {path}")
    return path
