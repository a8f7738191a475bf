"""runtime/: the one background-job class, what *Install dependencies* installs (only what Blender
lacks, never a numpy over Blender's own), and the check that names a feature's missing packages
before its job starts (rather than the job dying in its thread on `No module named 'skimage'`)."""
from __future__ import annotations

import os
import time

import bpy
import pytest

from conftest import ROOT


# ------------------------------------------------------------------------------------------- jobs
def test_job_states_result_error_and_cancel(addon):
    Job = addon.runtime.jobs.Job
    ok = Job("t", lambda progress: (progress(0.5), 42)[1]).start()
    assert ok.join(timeout=30) and ok.state == "DONE" and ok.result == 42 and ok.fraction == 0.5

    def user_error(progress):
        raise addon.runtime.errors.UserError("choose a vertex group")
    bad = Job("t", user_error).start()
    bad.join(timeout=30)
    assert bad.state == "ERROR" and bad.message == "choose a vertex group" and bad.result is None

    def crash(progress):
        raise KeyError("x")
    boom = Job("t", crash).start()
    boom.join(timeout=30)
    assert boom.state == "ERROR" and boom.message.startswith("KeyError")

    class Cancelled(Exception):
        pass

    def long(progress):
        t_end = time.time() + 30
        while time.time() < t_end:
            if not progress(0.1):
                raise Cancelled()
            time.sleep(0.01)
        return "ran out"
    job = Job("t", long).start()
    assert job.running
    job.cancel()
    assert job.join(timeout=30) and job.cancelled and job.result is None



# ------------------------------------------------------------------------------------------ quiet
def test_held_waits_for_a_running_job_to_park_and_lets_it_go_on(addon):
    """runtime/quiet.py: an operator under a context override runs only while the add-on's Python
    threads wait at a checkpoint (their progress callback), and they go on afterwards."""
    quiet, Job = addon.runtime.quiet, addon.runtime.jobs.Job
    ticks = []

    def work(progress):
        t_end = time.time() + 30
        while time.time() < t_end and len(ticks) < 400:
            ticks.append(time.time())
            if not progress(0.5):
                break
            time.sleep(0.002)
        return len(ticks)

    job = Job("q", work).start()
    while len(ticks) < 5:
        time.sleep(0.005)
    assert quiet.state()["workers"] == 1
    with quiet.held(timeout=10) as all_parked:
        n = len(ticks)
        time.sleep(0.2)
        assert all_parked and quiet.state()["parked"] == 1 and len(ticks) == n   # nothing ran meanwhile
    assert job.join(timeout=30) and job.state == "DONE" and job.result == 400
    assert quiet.state() == {"closed": 0, "workers": 0, "parked": 0}
    # a worker that never reaches a checkpoint: held goes ahead after its timeout
    with quiet.worker():   # this thread as a worker would deadlock itself: held only counts others
        pass
    t = time.time()
    with quiet.held(timeout=0.05) as all_parked:
        assert all_parked   # no worker now
    assert time.time() - t < 1.0


def test_the_blender_crash_quiet_prevents(tmp_path):
    """Why runtime/quiet.py exists: bpy.ops under temp_override while another Python thread runs
    crashes Blender 3.4 (Python heap corruption); the same thread parked at a checkpoint does not."""
    import subprocess

    from test_real_blender import BLENDER, _env
    if not os.path.exists(BLENDER):
        pytest.skip("no blender binary")
    code = (
        "import sys, threading, time, bpy\n"
        "sys.path.insert(0, %r)\n"
        "import quiet\n"
        "stop = [False]; n = [0]\n"
        "def spin():\n"
        "    with quiet.worker():\n"
        "        while not stop[0]:\n"
        "            d = {'a': [1, 2, 3], 'b': str(n[0])}; n[0] += 1\n"
        "            if n[0] %% 2000 == 0: quiet.checkpoint()\n"
        "t = threading.Thread(target=spin, daemon=True); t.start()\n"
        "time.sleep(0.1); t0 = time.time(); calls = 0\n"
        "while time.time() - t0 < 4:\n"
        "    with quiet.held(timeout=5), bpy.context.temp_override():\n"
        "        bpy.ops.object.location_clear()\n"
        "    calls += 1\n"
        "stop[0] = True; t.join()\n"
        "print('QUIET_OK', calls, n[0], flush=True)\n"
        "import os; os._exit(0)\n"
    ) % os.path.join(ROOT, "addon", "runtime")
    script = tmp_path / "quiet_probe.py"
    script.write_text(code)
    r = subprocess.run([BLENDER, "-b", "--factory-startup", "--python", str(script)], env=_env(tmp_path),
                       capture_output=True, text=True, timeout=120)
    out = r.stdout + r.stderr
    assert r.returncode == 0 and "QUIET_OK" in out, out[-3000:]
    calls, spins = (int(x) for x in out.split("QUIET_OK")[1].split()[:2])
    assert calls > 100 and spins > 10000   # both threads ran, in turn

def test_every_background_job_is_the_one_job_class(addon):
    Job = addon.runtime.jobs.Job
    assert issubclass(addon.train.worker.TrainJob, Job)
    assert issubclass(addon.semantics.distill.DistillJob, Job)
    assert issubclass(addon.runtime.install.InstallJob, Job)
    assert not addon.runtime.install.InstallJob.uses_torch


# ------------------------------------------------------------------------------------------- deps
def _statuses(deps, missing=()):
    out = []
    for imp, dist, req, _pip, _f in deps.DEPENDENCIES:
        s = deps.DepStatus(imp, dist, req)
        s.found = dist not in missing
        out.append(s)
    return out


def test_install_plan_installs_only_what_blender_lacks(addon):
    deps = addon.runtime.deps
    assert deps.install_plan(statuses=_statuses(deps), blender_numpy="1.26.4") == ([], [])
    # Blender ships numpy: the missing feature packages are resolved against its version, and numpy
    # is taken out of the folder again (a copy there would shadow Blender's own)
    reqs, keep_out = deps.install_plan(statuses=_statuses(deps, ("scikit-image", "xatlas")), blender_numpy="2.1.0")
    assert reqs == ["scikit-image", "xatlas", "numpy==2.1.0"] and keep_out == ["numpy"]
    # Debian's Blender 3.4 has no numpy: numpy 1.26 with the rest; Blender 5: numpy 2
    everything = [d[1] for d in deps.DEPENDENCIES]
    reqs, keep_out = deps.install_plan(statuses=_statuses(deps, everything), blender_version=(3, 4, 1),
                                       blender_numpy=None)
    assert "numpy<2" in reqs and "torch==2.13.0" in reqs and keep_out == []
    assert {"scikit-image", "scikit-learn", "xatlas"} <= set(reqs)
    reqs, _ = deps.install_plan(statuses=_statuses(deps, everything), blender_version=(5, 0, 1), blender_numpy=None)
    assert "numpy>=2" in reqs and "numpy<2" not in reqs
    # one feature's packages only
    reqs, _ = deps.install_plan(["xatlas"], statuses=_statuses(deps, everything), blender_numpy=None)
    assert reqs == ["xatlas"]


def test_blenders_own_numpy_is_found_outside_the_addons_folders(addon):
    import numpy

    assert addon.runtime.deps.own_numpy_version() == numpy.__version__


def test_setup_script_reads_the_same_list(addon):
    """scripts/setup_blender.sh runs deps.py with runpy: it must load without the add-on package."""
    import runpy

    d = runpy.run_path(os.path.join(ROOT, "addon", "runtime", "deps.py"))
    assert d["full_requirements"]((3, 4, 1)) == addon.runtime.deps.full_requirements((3, 4, 1))
    with open(os.path.join(ROOT, "scripts", "setup_blender.sh"), encoding="utf-8") as f:
        script = f.read()
    assert "full_requirements" in script and "torch==2.13.0" not in script   # no second copy of the list


def test_removing_numpy_from_the_install_folder(addon, tmp_path):
    for name in ("numpy", "numpy.libs", "numpy-1.26.4.dist-info", "numpyro", "scipy", "scipy-1.17.1.dist-info"):
        (tmp_path / name).mkdir()
    removed = addon.runtime.install.remove_distributions(str(tmp_path), ["numpy"])
    assert sorted(removed) == ["numpy", "numpy-1.26.4.dist-info", "numpy.libs"]
    assert sorted(os.listdir(tmp_path)) == ["numpyro", "scipy", "scipy-1.17.1.dist-info"]


def test_a_feature_names_its_missing_packages_in_full(addon, monkeypatch):
    deps = addon.runtime.deps
    assert deps.missing_for("bake", _statuses(deps, ("xatlas",))) == ["xatlas"]
    assert deps.missing_for("semantics", _statuses(deps, ("scikit-image",))) == ["scikit-image"]
    assert deps.missing_for("bake", _statuses(deps)) == []
    assert deps.missing_for("semantics") == []   # this environment has them all
    monkeypatch.setattr(deps, "missing_for", lambda feature, statuses=None: ["scikit-image", "scikit-learn"])
    with pytest.raises(addon.runtime.errors.UserError) as exc:
        addon.runtime.core.require("semantics")
    msg = str(exc.value)
    assert "Distill semantics needs the Python packages scikit-image, scikit-learn" in msg
    assert "'Install these 2'" in msg and "Install dependencies" in msg
    assert addon.runtime.deps.install_label(["xatlas"]) == "Install xatlas"


def test_install_button_of_a_feature_installs_nothing_when_present(addon):
    assert bpy.ops.neumesh.install_dependencies(packages="xatlas scikit-image", wait=True) == {"FINISHED"}
    job = addon.runtime.install.current_install()
    assert job is None or job.requirements != ["xatlas", "scikit-image"]   # nothing was started


def test_distill_and_bake_refuse_to_start_without_their_packages(addon, monkeypatch, tmp_path):
    """The check runs before any job: the message names the package; no thread dies later."""
    deps = addon.runtime.deps
    monkeypatch.setattr(deps, "missing_for", lambda feature, statuses=None: {
        "semantics": ["scikit-image"], "bake": ["xatlas"]}.get(feature, []))
    import neumesh_core as nm

    d = str(tmp_path / "data")
    nm.make_default_scene(d, resolution=16, n_train=2, n_val=1, n_test=1, mesh_subdiv=2)
    field = nm.create_field(nm.load_mesh(os.path.join(d, "mesh.ply")))
    path = str(tmp_path / "f.neumesh")
    nm.save_field(field, path)
    assert bpy.ops.neumesh.load_field(filepath=path, new_object=True) == {"FINISHED"}
    bpy.context.scene.neumesh.dataset_path = d
    with pytest.raises(RuntimeError, match="Distill semantics needs the Python package scikit-image"):
        bpy.ops.neumesh.distill_semantics(wait=True)
    assert addon.semantics.distill.current_job() is None or not addon.semantics.distill.current_job().running
    with pytest.raises(RuntimeError, match="Bake to material needs the Python package xatlas"):
        bpy.ops.neumesh.bake_material(resolution=64)
