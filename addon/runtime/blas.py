"""torch's own BLAS inside a Blender that links another one (no bpy; Linux/ELF only).

Debian's ``blender`` links the reference BLAS (``libblas.so.3``, one un-vectorised loop per
element). torch's CPU library (``libtorch_cpu.so``) carries its own optimised BLAS and LAPACK (MKL
on x86-64) but calls them as ordinary exported symbols (``sgemm_``, ``dgetrf_`` ...) through its
procedure linkage table. The dynamic linker binds such a call to the first definition in the
process's global scope, and in that Blender that is the executable's own ``libblas.so.3``: every
torch matrix multiply then runs on the reference BLAS, an order of magnitude slower, and so does a
NeuMesh render. ``LD_PRELOAD=<torch>/lib/libtorch_cpu.so blender`` fixes it
from outside, but cannot be done from inside a running Blender.

:func:`rebind_torch_blas` does the equivalent for torch alone, in-process: it reads the dynamic
relocations of the loaded ``libtorch_cpu.so`` (the ELF file on disk), and for every BLAS/LAPACK
symbol that torch both calls and defines itself, and that the linker bound (or will bind) to a
library such as ``libblas.so.3``, it writes the address of torch's own definition into torch's slot
of the global offset table -- exactly what the preload makes the linker do, limited to torch's own
calls (Blender keeps its libblas). Each slot is checked before it is written (it must hold the
foreign definition or torch's own lazy-binding stub) and read back after. :func:`status` reports
which library torch's ``sgemm_`` calls and measures the matrix-multiply rate, for the add-on's
dependency check. Nothing here runs before torch is imported, and nothing happens where the
process has no foreign BLAS (bpy from PyPI, Blender's official builds, other platforms).

``NEUMESH_NO_BLAS_REBIND=1`` turns the rebinding off (to measure the difference, or as an escape
hatch).
"""
from __future__ import annotations

import ctypes
import os
import re
import struct
import sys
import time

DISABLE_ENV = "NEUMESH_NO_BLAS_REBIND"

# libraries whose BLAS/LAPACK definitions torch must not call instead of its own
_BLAS_LIBS = ("libblas", "libcblas", "liblapack", "libopenblas", "libatlas", "libf77blas", "libflexiblas",
              "libblis", "libgoto", "libsatlas", "libtatlas")
_FORTRAN_NAME = re.compile(rb"^[a-z][a-z0-9]*_$")  # sgemm_, dgetrf_, xerbla_ ...
_SLOT_TYPES = {62: (6, 7), 183: (1025, 1026)}      # e_machine: (GLOB_DAT, JUMP_SLOT) on x86-64, aarch64

_report: dict | None = None


class _DlInfo(ctypes.Structure):
    _fields_ = [("dli_fname", ctypes.c_char_p), ("dli_fbase", ctypes.c_void_p),
                ("dli_sname", ctypes.c_char_p), ("dli_saddr", ctypes.c_void_p)]


def _libc():
    return ctypes.CDLL(None, use_errno=True)


def library_of(address: int) -> str:
    """Path of the loaded object that contains ``address`` ('' if unknown)."""
    if not address:
        return ""
    info = _DlInfo()
    try:
        dladdr = _libc().dladdr
    except AttributeError:  # glibc < 2.34 keeps it in libdl
        dladdr = ctypes.CDLL("libdl.so.2").dladdr
    dladdr.argtypes = [ctypes.c_void_p, ctypes.POINTER(_DlInfo)]
    if not dladdr(ctypes.c_void_p(address), ctypes.byref(info)) or not info.dli_fname:
        return ""
    return os.path.realpath(info.dli_fname.decode(errors="replace"))


def global_address(name: str) -> int:
    """Address the dynamic linker gives ``name`` in the process's global scope (0 if undefined)."""
    try:
        return ctypes.cast(getattr(_libc(), name), ctypes.c_void_p).value or 0
    except AttributeError:
        return 0


def is_blas_library(path: str) -> bool:
    return os.path.basename(path).startswith(_BLAS_LIBS)


def torch_cpu_library() -> str:
    """Path of the ``libtorch_cpu`` that the imported torch uses ('' if torch is not imported)."""
    torch = sys.modules.get("torch")
    f = getattr(torch, "__file__", None) if torch is not None else None
    if not f:
        return ""
    libdir = os.path.join(os.path.dirname(f), "lib")
    for name in ("libtorch_cpu.so", "libtorch_cpu.dylib", "torch_cpu.dll"):
        p = os.path.join(libdir, name)
        if os.path.isfile(p):
            return os.path.realpath(p)
    return ""


# ------------------------------------------------------------------------------------------------ ELF
def _elf_slots(path: str, wanted=_FORTRAN_NAME):
    """(machine, [(name, slot_vaddr, symbol_value)]) for the GLOB_DAT/JUMP_SLOT relocations of
    ``path`` whose symbol matches ``wanted`` and is defined in the file itself."""
    with open(path, "rb") as fh:
        ident = fh.read(64)
        if len(ident) < 64 or ident[:4] != b"\x7fELF" or ident[4] != 2 or ident[5] != 1:
            raise ValueError(f"{path} is not a 64-bit little-endian ELF file")
        (_t, machine, _v, _e, _ph, shoff, _f, _eh, _phs, _phn, shentsize, shnum,
         _shstr) = struct.unpack_from("<HHIQQQIHHHHHH", ident, 16)
        if machine not in _SLOT_TYPES:
            raise ValueError(f"{path}: unsupported machine {machine}")
        fh.seek(shoff)
        raw = fh.read(shentsize * shnum)
        secs = [struct.unpack_from("<IIQQQQIIQQ", raw, i * shentsize) for i in range(shnum)]
        dynsym_i = next(i for i, s in enumerate(secs) if s[1] == 11)  # SHT_DYNSYM
        _n, _ty, _fl, _a, sym_off, sym_size, str_i, _in, _al, sym_ent = secs[dynsym_i]
        fh.seek(sym_off)
        symtab = fh.read(sym_size)
        fh.seek(secs[str_i][4])
        strtab = fh.read(secs[str_i][5])
        glob_dat, jump_slot = _SLOT_TYPES[machine]
        out = []
        for s in secs:
            if s[1] != 4 or s[6] != dynsym_i:  # SHT_RELA against .dynsym
                continue
            fh.seek(s[4])
            rela = fh.read(s[5])
            for r_offset, r_info, _add in struct.iter_unpack("<QQq", rela):
                rtype = r_info & 0xFFFFFFFF
                if rtype != jump_slot and rtype != glob_dat:
                    continue
                st_name, _info, _other, shndx, value, _size = struct.unpack_from(
                    "<IBBHQQ", symtab, (r_info >> 32) * sym_ent)
                if shndx == 0 or value == 0:  # not defined in this file
                    continue
                end = strtab.index(b"\0", st_name)
                name = strtab[st_name:end]
                if wanted.match(name):
                    out.append((name.decode(), r_offset, value))
    return machine, out


def _page_perms(address: int) -> str:
    with open("/proc/self/maps") as fh:
        for line in fh:
            rng, perms = line.split()[:2]
            lo, hi = (int(x, 16) for x in rng.split("-"))
            if lo <= address < hi:
                return perms
    return ""


def _write_pointer(address: int, value: int):
    perms = _page_perms(address)
    if not perms:
        raise OSError(f"address {address:#x} is not mapped")
    cell = ctypes.c_uint64.from_address(address)
    if "w" in perms:
        cell.value = value
        return
    libc = _libc()
    page = os.sysconf("SC_PAGESIZE")
    start = address & ~(page - 1)
    mprotect = libc.mprotect
    mprotect.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    prot_rw = 0x1 | 0x2
    if mprotect(ctypes.c_void_p(start), page, prot_rw) != 0:
        raise OSError(ctypes.get_errno(), f"mprotect({start:#x}) failed")
    try:
        cell.value = value
    finally:
        prot = (0x1 if "r" in perms else 0) | (0x4 if "x" in perms else 0)
        mprotect(ctypes.c_void_p(start), page, prot)


def rebind_torch_blas(lib_path: str | None = None, dry_run: bool = False) -> dict:
    """Point torch's own BLAS/LAPACK calls at torch's own definitions where the process bound them
    to another library. Returns a dict: ``lib`` (libtorch_cpu path), ``foreign`` (sorted paths of the
    libraries torch's calls were bound to), ``rebound`` (symbols rewritten), ``skipped`` (symbol:
    why), ``error`` ('' or what went wrong; nothing is written after an error)."""
    rep = {"lib": "", "foreign": [], "rebound": [], "skipped": {}, "error": ""}
    if not sys.platform.startswith("linux"):
        rep["error"] = "only needed and implemented on Linux"
        return rep
    lib_path = lib_path or torch_cpu_library()
    rep["lib"] = lib_path
    if not lib_path:
        rep["error"] = "torch is not imported"
        return rep
    try:
        handle = ctypes.CDLL(lib_path, mode=os.RTLD_NOLOAD | os.RTLD_LAZY)
    except OSError as exc:
        rep["error"] = f"{lib_path} is not loaded: {exc}"
        return rep
    try:
        _machine, slots = _elf_slots(lib_path)
    except (OSError, ValueError, StopIteration, struct.error) as exc:
        rep["error"] = f"cannot read the relocations of {lib_path}: {exc}"
        return rep
    bias = None
    plan = []
    foreign = set()
    for name, r_offset, value in slots:
        try:
            own = ctypes.cast(handle[name], ctypes.c_void_p).value or 0
        except AttributeError:
            continue
        if bias is None:
            bias = own - value
            if library_of(own) != os.path.realpath(lib_path):
                rep["error"] = f"{name} of {lib_path} resolves to {library_of(own)}; file and process differ"
                return rep
        if own - value != bias:
            rep["skipped"][name] = "symbol address does not match the file"
            continue
        slot = bias + r_offset
        current = ctypes.c_uint64.from_address(slot).value
        if current == own:
            continue
        target = global_address(name)
        owner = library_of(target)
        if not owner or not is_blas_library(owner):
            rep["skipped"][name] = f"bound to {owner or 'nothing'}"
            continue
        lazy_stub = library_of(current) == os.path.realpath(lib_path)
        if current != target and not lazy_stub:
            rep["skipped"][name] = f"slot holds an unexpected address {current:#x}"
            continue
        foreign.add(owner)
        plan.append((name, slot, own))
    rep["foreign"] = sorted(foreign)
    if dry_run:
        rep["rebound"] = [p[0] for p in plan]
        return rep
    for name, slot, own in plan:
        try:
            _write_pointer(slot, own)
        except OSError as exc:
            rep["error"] = f"cannot rewrite the slot of {name}: {exc}"
            break
        if ctypes.c_uint64.from_address(slot).value != own:
            rep["error"] = f"the slot of {name} did not take the new address"
            break
        rep["rebound"].append(name)
    return rep


def sgemm_binding(lib_path: str | None = None) -> str:
    """Path of the library whose ``sgemm_`` torch's matrix multiplies call ('' if unknown)."""
    lib_path = lib_path or torch_cpu_library()
    if not lib_path or not sys.platform.startswith("linux"):
        return ""
    try:
        _m, slots = _elf_slots(lib_path, re.compile(rb"^sgemm_$"))
        handle = ctypes.CDLL(lib_path, mode=os.RTLD_NOLOAD | os.RTLD_LAZY)
        own = ctypes.cast(handle["sgemm_"], ctypes.c_void_p).value
    except (OSError, ValueError, StopIteration, AttributeError, struct.error):
        return ""
    for _name, r_offset, value in slots:
        current = ctypes.c_uint64.from_address(own - value + r_offset).value
        where = library_of(current)
        if where == os.path.realpath(lib_path) and current != own:  # lazy stub: bound on first call
            where = library_of(global_address("sgemm_")) or where
        return where
    return os.path.realpath(lib_path)  # torch calls sgemm_ directly (no slot)


def ensure() -> dict:
    """Rebind once per process (after torch is imported); returns the report of the first call."""
    global _report
    if _report is not None and not _report.get("error") == "torch is not imported":
        return _report
    if os.environ.get(DISABLE_ENV, "") not in ("", "0"):
        _report = {"lib": torch_cpu_library(), "foreign": [], "rebound": [], "skipped": {},
                   "error": f"disabled by {DISABLE_ENV}"}
        return _report
    try:
        _report = rebind_torch_blas()
    except Exception as exc:  # noqa: BLE001 - never break an import over a speed fix
        _report = {"lib": torch_cpu_library(), "foreign": [], "rebound": [], "skipped": {},
                   "error": f"{type(exc).__name__}: {exc}"}
    if _report["rebound"]:
        print(f"NeuMesh: torch's BLAS calls rebound from {', '.join(_report['foreign'])} to "
              f"{os.path.basename(_report['lib'])} ({len(_report['rebound'])} symbols)")
    return _report


def matmul_gflops(n: int = 512, seconds: float = 0.25) -> float:
    """float32 matrix-multiply rate of torch in this process (GFLOP/s), best of repeated n x n."""
    import torch

    a = torch.randn(n, n)
    b = torch.randn(n, n)
    c = a @ b
    best = float("inf")
    t_end = time.perf_counter() + seconds
    reps = 0
    while reps < 3 or (time.perf_counter() < t_end and reps < 50):
        t = time.perf_counter()
        torch.mm(a, b, out=c)
        best = min(best, time.perf_counter() - t)
        reps += 1
    return 2.0 * n ** 3 / best / 1e9


def preload_command(lib_path: str | None = None) -> str:
    lib_path = lib_path or torch_cpu_library() or "<site-packages>/torch/lib/libtorch_cpu.so"
    return f"LD_PRELOAD={lib_path} blender"


def status(measure: bool = True) -> dict:
    """What the dependency check shows: ``sgemm`` (library torch's sgemm_ calls), ``own`` (it is
    torch's own), ``gflops`` (measured, None when not measured), ``rebind`` (the report of
    :func:`ensure`) and ``remedy`` (the launcher command, '' when nothing is wrong)."""
    rep = ensure()
    lib = torch_cpu_library()
    where = sgemm_binding(lib)
    own = not where or where == lib
    st = {"sgemm": where, "own": own, "gflops": matmul_gflops() if measure else None, "rebind": rep,
          "remedy": "" if own else preload_command(lib)}
    return st
