"""The one helper of the benchmark scripts: their common options, the one way they set torch's threads,
the one timing loop, and :func:`write_results`, which writes every results file with the machine record
(commit, dirty tree, CPU, cores, torch threads, load average at the start and the end, torch version)
in it, under ``"machine"``.

Where results go: ``benchmarks/results/log/`` (the experiment log; every run writes there unless
``--results-dir`` says otherwise) and ``benchmarks/results/figures/`` (the files a figures table of the
docs cites: a run becomes a cited figure when its file is moved there and a table names it;
``tests/test_docs.py`` checks both ways and holds each README headline to the code it measures).
"""
from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS_DIR = os.path.join(ROOT, "benchmarks", "results")
LOG_DIR = os.path.join(RESULTS_DIR, "log")
FIGURES_DIR = os.path.join(RESULTS_DIR, "figures")

# the run's start, as the scripts import this module first: the time, the load average and the tree
# (commit, uncommitted changes) then; ``_tree_state`` is defined below
_START = {"time": time.time(), "load": os.getloadavg()}

# the common options: name -> (flags, argparse keywords); a script overrides the keywords it needs
OPTIONS = {
    "data": (("--data",), dict(help="dataset folder (NeRF-synthetic, DTU, or a capture with its photos)")),
    "field": (("--field",), dict(help="trained field (.neumesh)")),
    "mesh": (("--mesh",), dict(help="a mesh (.ply/.obj)")),
    "threads": (("--threads",), dict(type=int, default=None,
                                     help="torch's CPU threads (0: one per core; default: torch's own)")),
    "device": (("--device",), dict(default="cpu", help="cpu | cuda | auto")),
    "name": (("--name",), dict(default=None, help="results name (default: from the input)")),
    "results_dir": (("--results-dir",), dict(default=None, help="folder for the results JSON (default: "
                                                                "benchmarks/results/log)")),
}


def add_options(ap, *names: str, **overrides: dict) -> None:
    """Add the common options ``names`` (keys of :data:`OPTIONS`) to the ArgumentParser ``ap``;
    ``overrides[name]`` replaces argparse keywords of one (a default, ``required``, a help text)."""
    for name in names:
        flags, kw = OPTIONS[name]
        ap.add_argument(*flags, **{**kw, **overrides.get(name, {})})


def use_threads(threads: Optional[int]) -> int:
    """Set torch's CPU threads for this run, the one way the scripts do: None keeps torch's own
    choice, 0 one per core, n > 0 n.  Returns the threads torch uses."""
    import torch

    if threads is not None:
        torch.set_num_threads(int(threads) if int(threads) > 0 else (os.cpu_count() or 1))
    return torch.get_num_threads()


@dataclass
class Timing:
    """Wall-clock seconds of each timed call, and the last call's result."""

    times: list = field(default_factory=list)
    result: Any = None

    @property
    def best(self) -> float:
        return min(self.times)

    @property
    def median(self) -> float:
        return statistics.median(self.times)

    @property
    def mean(self) -> float:
        return sum(self.times) / len(self.times)


def timed(fn: Callable[[], Any], repeats: int = 1, warmup: int = 0, sync: Optional[Callable[[], Any]] = None
          ) -> Timing:
    """The scripts' one timing loop: ``warmup`` untimed calls of ``fn()``, then ``repeats`` timed ones
    (``time.perf_counter``); ``sync()`` runs inside each timed span after the call (e.g.
    ``torch.cuda.synchronize``, so that a GPU's queued work counts).  Report ``best`` on a busy machine
    (what the code can do), ``median`` or ``mean`` where the spread is the point."""
    out = Timing()
    for _ in range(int(warmup)):
        fn()
        if sync is not None:
            sync()
    for _ in range(int(repeats)):
        t = time.perf_counter()
        out.result = fn()
        if sync is not None:
            sync()
        out.times.append(time.perf_counter() - t)
    return out


def _git(*args: str) -> Optional[str]:
    try:
        run = subprocess.run(["git", "-C", ROOT, *args], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return run.stdout.strip() if run.returncode == 0 else None


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _tree_state() -> tuple:
    """(commit, whether tracked files have uncommitted changes) of the checkout, or of
    ``NEUMESH_COMMIT`` / ``NEUMESH_DIRTY`` where there is no git checkout (a copy of the tree on a lent
    GPU machine)."""
    commit = _git("rev-parse", "HEAD") or os.environ.get("NEUMESH_COMMIT")
    status = _git("status", "--porcelain", "--untracked-files=no")
    dirty = bool(status) if status is not None else (
        None if "NEUMESH_DIRTY" not in os.environ else os.environ["NEUMESH_DIRTY"] not in ("", "0"))
    return commit, dirty


_START["tree"] = _tree_state()


def machine_record() -> dict:
    """What the run measured on: the commit and whether the tree had uncommitted changes to tracked
    files when the run started (the code it ran; files the run writes itself, such as the
    documentation's pictures, come later; ``tree_at_end`` says when the tree changed during the run),
    CPU model, cores, torch's threads and version, the GPU, the load average at the start of the run
    and now, and the command."""
    commit, dirty = _START["tree"]
    rec = {"commit": commit, "dirty": dirty, "cpu": _cpu_model(), "cores": os.cpu_count(),
           "python": platform.python_version(), "platform": platform.platform()}
    try:
        rec["cores_usable"] = len(os.sched_getaffinity(0))
    except AttributeError:   # not on Linux
        pass
    try:
        import torch

        rec.update(torch=torch.__version__, torch_threads=torch.get_num_threads(),
                   gpu=torch.cuda.get_device_name() if torch.cuda.is_available() else None)
    except ImportError:
        rec.update(torch=None, torch_threads=None, gpu=None)
    now = time.time()
    end = _tree_state()
    if end != (commit, dirty):
        rec["tree_at_end"] = {"commit": end[0], "dirty": end[1]}
    rec.update(load_start=[round(x, 2) for x in _START["load"]], load_end=[round(x, 2) for x in os.getloadavg()],
               started=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(_START["time"])),
               finished=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(now)),
               argv=[os.path.relpath(sys.argv[0], ROOT) if sys.argv and sys.argv[0] else ""] + sys.argv[1:])
    return rec


def write_results(result: dict, name: str, folder: Optional[str] = None, default=None) -> str:
    """Write ``result`` with the machine record (:func:`machine_record`, under ``"machine"``; what a
    script put there itself stays beside it, the record's keys win) as ``folder/name``, atomically (a
    killed run never leaves half a file); print and return the path.  ``folder``: default
    ``benchmarks/results/log``.  ``default`` converts values json cannot (as in :func:`json.dump`)."""
    folder = folder or LOG_DIR
    own = result.get("machine")
    own = own if isinstance(own, dict) else ({} if own is None else {"note": own})
    result = {**result, "machine": {**own, **machine_record()}}
    os.makedirs(folder, exist_ok=True)
    path = os.path.join(folder, name)
    tmp = path + ".tmp"
    with open(tmp, "w") as fh:
        json.dump(result, fh, indent=2, default=default)
    os.replace(tmp, path)
    print(f"wrote {path}")
    return path
