"""addon/runtime/blas.py: torch's own BLAS in a process that links another one (Debian's Blender links the
reference libblas.so.3; a plain Python with that library preloaded is in the same situation)."""
from __future__ import annotations

import ctypes.util
import importlib.util
import json
import os
import subprocess
import sys

import pytest

from conftest import ROOT

BLAS_PY = os.path.join(ROOT, "addon", "runtime", "blas.py")


def _blas_module():
    spec = importlib.util.spec_from_file_location("neumesh_addon_blas", BLAS_PY)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_nothing_to_do_where_torch_already_calls_its_own_blas():
    import torch  # noqa: F401

    blas = _blas_module()
    lib = blas.torch_cpu_library()
    assert lib.endswith("libtorch_cpu.so")
    assert blas.sgemm_binding() == lib
    rep = blas.rebind_torch_blas(dry_run=True)
    assert rep["error"] == "" and rep["foreign"] == [] and rep["rebound"] == []
    st = blas.status(measure=True)
    assert st["own"] and st["remedy"] == "" and st["gflops"] > 0
    # the relocations read from the file name torch's BLAS entry points, each defined in the file
    _machine, slots = blas._elf_slots(lib)
    names = {n for n, _off, _val in slots}
    assert {"sgemm_", "dgemm_", "sgemv_"} <= names


_CHILD = r"""
import importlib.util, json, sys
spec = importlib.util.spec_from_file_location("b", sys.argv[1]); blas = importlib.util.module_from_spec(spec)
spec.loader.exec_module(blas)
import torch
torch.manual_seed(0)
a, b = torch.randn(300, 200), torch.randn(200, 100)
m = torch.randn(60, 60, dtype=torch.float64) + 60 * torch.eye(60, dtype=torch.float64)
rhs = torch.randn(60, 3, dtype=torch.float64)
def results():
    return [(a @ b).tolist(), torch.linalg.solve(m, rhs).tolist(), torch.linalg.svdvals(m).tolist()]
before_lib, before = blas.sgemm_binding(), results()
rep = blas.rebind_torch_blas()
after_lib, after = blas.sgemm_binding(), results()
again = blas.rebind_torch_blas()
print("RESULT " + json.dumps(dict(before_lib=before_lib, after_lib=after_lib, torch_lib=blas.torch_cpu_library(),
      rep=rep, again=again, before=before, after=after)))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or not ctypes.util.find_library("blas"),
                    reason="needs Linux and a system libblas.so.3")
def test_rebinding_in_a_process_that_links_the_reference_blas(tmp_path):
    import numpy as np

    # what Debian's blender links: the reference BLAS and LAPACK
    libs = [ctypes.util.find_library("blas")] + ([ctypes.util.find_library("lapack")]
                                                 if ctypes.util.find_library("lapack") else [])
    env = dict(os.environ, LD_PRELOAD=" ".join(libs))
    r = subprocess.run([sys.executable, "-c", _CHILD, BLAS_PY], env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(next(l for l in r.stdout.splitlines() if l.startswith("RESULT "))[7:])
    assert os.path.basename(res["before_lib"]).startswith("libblas")  # bound to the preloaded library
    assert res["after_lib"] == res["torch_lib"]
    rep = res["rep"]
    assert rep["error"] == "" and "sgemm_" in rep["rebound"]
    assert any(os.path.basename(f).startswith("libblas") for f in rep["foreign"])
    if len(libs) == 2:  # LAPACK calls (solve, SVD) go back to torch's too
        assert "dgesdd_" in rep["rebound"] and "dgetrf_" in rep["rebound"]
    assert res["again"]["rebound"] == []  # idempotent: nothing left to rewrite
    # the same products, solves and singular values, computed by the other library (rounding differs)
    for x, y, tol in zip(res["before"], res["after"], (1e-4, 1e-10, 1e-10)):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=tol, atol=tol)
