"""The benchmark scripts' one helper (benchmarks/_results.py) and that every script uses it: the common
options, torch's threads set one way, the results written with the machine record.  The scripts are
read with ``ast`` (none is run end to end: they need data, Blender or a GPU)."""
import ast
import json
import os

import pytest

from benchmarks import _results as R

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BENCH = os.path.join(ROOT, "benchmarks")
# scripts that measure and write a results file: every one goes through the helper
SCRIPTS = sorted(os.path.join(BENCH, d, f) for d in ("bench", "diagnose")
                 for f in os.listdir(os.path.join(BENCH, d)) if f.endswith(".py"))
# bench_real*.py are adapted with the real-capture work (they already write through write_results);
# f12_worker.py sets threads by the add-on's own rule, which it imitates
OWN_THREADS = {os.path.join(BENCH, "bench_real.py"), os.path.join(BENCH, "workers", "f12_worker.py")}


def _calls_and_imports(path):
    tree = ast.parse(open(path, encoding="utf-8").read(), path)
    calls = {n.func.attr if isinstance(n.func, ast.Attribute) else getattr(n.func, "id", "")
             for n in ast.walk(tree) if isinstance(n, ast.Call)}
    imports = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    return calls, imports


def test_the_scripts_are_found():
    names = {os.path.basename(p) for p in SCRIPTS}
    assert {"bench_core.py", "bench_fit.py", "kernel_resources.py"} <= names and len(names) >= 20


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: os.path.relpath(p, BENCH))
def test_every_script_uses_the_helper(path):
    calls, imports = _calls_and_imports(path)
    assert "benchmarks._results" in imports, "import the helper: from benchmarks._results import ..."
    assert "write_results" in calls, "write the results with write_results (the machine record goes in)"
    assert "add_options" in calls, "declare the common options with add_options"


def test_only_the_helper_sets_torchs_threads():
    bad = []
    for folder in (BENCH, os.path.join(ROOT, "scripts")):
        for dirpath, dirnames, files in os.walk(folder):
            dirnames[:] = [d for d in dirnames if d != "results"]
            for f in files:
                p = os.path.join(dirpath, f)
                if f.endswith(".py") and p != os.path.abspath(R.__file__) and p not in OWN_THREADS:
                    if "set_num_threads" in _calls_and_imports(p)[0]:
                        bad.append(os.path.relpath(p, ROOT))
    assert not bad, f"set torch's threads with benchmarks._results.use_threads: {bad}"


def test_write_results_adds_the_machine_record(tmp_path):
    path = R.write_results({"figure": 1.5, "machine": "a note"}, "x.json", str(tmp_path))
    with open(path, encoding="utf-8") as fh:
        data = json.load(fh)
    m = data["machine"]
    assert data["figure"] == 1.5 and m["note"] == "a note"
    for key in ("commit", "dirty", "cpu", "cores", "torch", "torch_threads", "load_start", "load_end", "argv"):
        assert key in m, key
    assert len(m["load_start"]) == 3 and m["cores"] >= 1
    assert m["commit"] is None or len(m["commit"]) == 40          # None only outside a git checkout
    assert not os.path.exists(path + ".tmp")
    # a script's own machine facts stay beside the record; the record's keys win
    path = R.write_results({"machine": {"floors": 2.0, "cores": -1}}, "y.json", str(tmp_path))
    with open(path, encoding="utf-8") as fh:
        m = json.load(fh)["machine"]
    assert m["floors"] == 2.0 and m["cores"] >= 1


def test_the_record_names_the_tree_the_run_started_on(tmp_path, monkeypatch):
    """A run that writes tracked files itself (the documentation's pictures) measured a clean tree: the
    record keeps the state at the start and says how the tree ended."""
    monkeypatch.setitem(R._START, "tree", ("a" * 40, False))
    monkeypatch.setattr(R, "_tree_state", lambda: ("a" * 40, True))
    with open(R.write_results({}, "z.json", str(tmp_path)), encoding="utf-8") as fh:
        m = json.load(fh)["machine"]
    assert m["commit"] == "a" * 40 and m["dirty"] is False
    assert m["tree_at_end"] == {"commit": "a" * 40, "dirty": True}
    monkeypatch.setattr(R, "_tree_state", lambda: ("a" * 40, False))
    with open(R.write_results({}, "z.json", str(tmp_path)), encoding="utf-8") as fh:
        assert "tree_at_end" not in json.load(fh)["machine"]


def test_write_results_defaults_to_the_log():
    assert R.LOG_DIR == os.path.join(ROOT, "benchmarks", "results", "log")
    assert R.FIGURES_DIR == os.path.join(ROOT, "benchmarks", "results", "figures")
    assert os.path.isdir(R.LOG_DIR) and os.path.isdir(R.FIGURES_DIR)


def test_common_options_and_threads():
    import argparse

    import torch

    ap = argparse.ArgumentParser()
    R.add_options(ap, "data", "threads", "results_dir", data=dict(required=True), threads=dict(default=1))
    a = ap.parse_args(["--data", "d"])
    assert (a.data, a.threads, a.results_dir) == ("d", 1, None)
    with pytest.raises(SystemExit):
        ap.parse_args([])                                          # --data required by this script
    saved = torch.get_num_threads()
    try:
        assert R.use_threads(1) == 1 and torch.get_num_threads() == 1
        assert R.use_threads(None) == 1                            # None keeps what torch has
        assert R.use_threads(0) == (os.cpu_count() or 1)           # 0: one per core
    finally:
        torch.set_num_threads(saved)


def test_the_timing_loop():
    calls = []
    t = R.timed(lambda: calls.append("x") or len(calls), repeats=3, warmup=2, sync=lambda: calls.append("s"))
    assert len(t.times) == 3 and t.result == 9 and calls.count("x") == 5 and calls.count("s") == 5
    assert t.best <= t.median <= max(t.times) and t.best <= t.mean


def test_bench_real_scores_object_and_room_apart(blob_mesh):
    """The real-capture benchmark splits each photo's PSNR where the field's object covers the frame
    and where it does not: a photo equal to the render inside the object and off by 0.1 outside
    scores ~20 dB on the room and far higher on the object."""
    import numpy as np
    import torch

    from benchmarks.bench_real import score_views
    from neumesh_core.data.cameras import Cameras, intrinsics_from_fov
    from neumesh_core.data.scene import ImageSet
    from neumesh_core.data.synthetic import look_at_opencv
    from neumesh_core.render.renderer import render_camera
    from tests.conftest import textured_field

    torch.set_num_threads(1)
    field = textured_field(blob_mesh)
    w = h = 24
    K = intrinsics_from_fov(0.8, w, h)[None]
    c2w = np.asarray(look_at_opencv(np.array([0.0, -3.0, 0.5]), np.zeros(3)), np.float32)[None]
    out = render_camera(field, K[0], c2w[0], w, h, background=(0.0, 0.0, 0.0))
    obj = out.opacity > 0.5
    assert 0.1 < obj.mean() < 0.9
    photo = np.clip(out.rgb, 0, 1).copy()
    assert photo[~obj].max() < 0.9
    photo[~obj] += 0.1
    r = score_views(field, ImageSet(Cameras(K, c2w, w, h), photo[None].astype(np.float32), names=["v"]))
    v = r["views"][0]
    assert abs(v["object_share"] - obj.mean()) < 1e-6
    assert abs(v["psnr_room"] - 20.0) < 0.5
    assert v["psnr_object"] > 40.0
    assert r["mean"]["psnr"] < v["psnr_object"]
