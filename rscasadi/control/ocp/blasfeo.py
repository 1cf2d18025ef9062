"""Which BLASFEO fatrop's linear algebra runs on: the CasADi wheel's, or the user's (RSCASADI_BLASFEO).

The CasADi wheel ships BLASFEO built for its GENERIC target (plain C, no AVX); fatrop spends about
a third of a solve in it (its Riccati factorisation, 4x4 C kernels).  A BLASFEO built for the CPU
(e.g. acados' or BLASFEO's own build for X64_INTEL_HASWELL) can stand in: set
RSCASADI_BLASFEO=/path/to/libblasfeo.so before the first fatrop solve of the process.  It is loaded
into the process's global symbol scope before the fatrop driver, so that libfatrop's BLASFEO calls
bind to it (the dynamic linker looks there before a library's own dependencies).

It must be interchangeable with the wheel's, which libfatrop was compiled against: instructions this
CPU has, every BLASFEO symbol libfatrop and the driver import, the same struct blasfeo_dmat and the
same panel-major layout (a matrix packed by it must be bitwise the wheel's).  Anything else is
refused before fatrop can reach it, with a message naming the variable and the file.
"""
from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
from pathlib import Path

import casadi as ca
import numpy as np

ENV = "RSCASADI_BLASFEO"
_SIZES = ((5, 3), (13, 16), (17, 9))        # odd sizes: a panel height or column padding would show
_loaded: dict = {}                          # the user's library, once per process


class _DMat(ctypes.Structure):              # struct blasfeo_dmat (blasfeo_common.h, panel-major)
    _fields_ = [("mem", ctypes.c_void_p), ("pA", ctypes.c_void_p), ("dA", ctypes.c_void_p)] + [
        (k, ctypes.c_int) for k in ("m", "n", "pm", "cn", "use_dA", "memsize")]


def wheel_library() -> Path:
    """The wheel's BLASFEO as libfatrop loads it (by its soname)."""
    return Path(ca.__file__).parent / "libblasfeo.so.0"


def _refuse(path, why: str):
    raise RuntimeError(f"{ENV}={path}: {why}; unset {ENV} to use the BLASFEO of the CasADi wheel")


def _imports(binary: str, path) -> set:
    """The BLASFEO symbols `binary` imports (nm, from binutils, which gcc brings)."""
    if shutil.which("nm") is None:
        _refuse(path, "checking it needs `nm` (binutils) on the PATH")
    out = subprocess.run(["nm", "-D", "--undefined-only", binary], capture_output=True, text=True, check=True).stdout
    return {line.split()[-1].split("@")[0] for line in out.splitlines() if "blasfeo" in line}


def _packed(lib, m: int, n: int):
    """What `lib` makes of an m x n matrix (1, 2, 3, ... column-major): its memory size, the struct's
    sizes and the packed doubles; (None, ...) if it writes past struct blasfeo_dmat."""
    lib.blasfeo_memsize_dmat.restype = ctypes.c_size_t
    size = int(lib.blasfeo_memsize_dmat(m, n))
    mem = np.zeros(size // 8 + 16)
    start = mem.ctypes.data + (-mem.ctypes.data) % 64             # cache-line aligned, as BLASFEO asks
    guard = (ctypes.c_ubyte * (ctypes.sizeof(_DMat) + 64))(*([0xA5] * (ctypes.sizeof(_DMat) + 64)))
    lib.blasfeo_create_dmat(m, n, guard, ctypes.c_void_p(start))
    if any(b != 0xA5 for b in bytes(guard)[ctypes.sizeof(_DMat):]):
        return None, None, None
    M = _DMat.from_buffer(guard)
    A = np.arange(1.0, m * n + 1.0)
    lib.blasfeo_pack_dmat(m, n, A.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), m, guard, 0, 0)
    first = (M.pA - mem.ctypes.data) // 8
    return size, (M.m, M.n, M.pm, M.cn, M.memsize), mem[first:first + M.pm * M.cn].copy()


def check(path, fatrop: str, driver: str) -> ctypes.CDLL:
    """The user's BLASFEO at `path`, loaded locally and checked against the wheel's (module docstring)."""
    if not Path(path).is_file():
        _refuse(path, "no such file")
    try:
        lib = ctypes.CDLL(str(path))
    except OSError as e:
        _refuse(path, f"cannot be loaded ({e})")
    missing = sorted(s for s in _imports(fatrop, path) | _imports(driver, path) | {
        "blasfeo_processor_cpu_features", "blasfeo_processor_library_features"} if not hasattr(lib, s))
    if missing:
        _refuse(path, f"it lacks BLASFEO functions that fatrop calls: {', '.join(missing[:8])}")
    cpu, need = ctypes.c_int(0), ctypes.c_int(0)
    ok = lib.blasfeo_processor_cpu_features(ctypes.byref(cpu))
    lib.blasfeo_processor_library_features(ctypes.byref(need))
    if not ok or need.value & ~cpu.value:
        _refuse(path, f"it was built for instructions this CPU lacks (needs {features(lib)!r})")
    wheel = ctypes.CDLL(str(wheel_library()))
    for m, n in _SIZES:
        theirs, ours = _packed(lib, m, n), _packed(wheel, m, n)
        if theirs[0] is None:
            _refuse(path, "its struct blasfeo_dmat is larger than the one fatrop was compiled with")
        if theirs[:2] != ours[:2] or not np.array_equal(theirs[2], ours[2]):
            _refuse(path, f"its matrix layout differs from the one fatrop was compiled with (a {m} x {n} matrix: "
                          f"m, n, pm, cn, memsize {theirs[1]} against {ours[1]}; panel size or storage order)")
    return lib


def load(fatrop: str, driver: str):
    """Before the driver is loaded: the user's BLASFEO (RSCASADI_BLASFEO) into the global scope, if set."""
    path = os.environ.get(ENV)
    if not path or _loaded.get("path") == path:
        return
    if _loaded:
        raise RuntimeError(f"{ENV} changed to {path} after {_loaded['path']} was loaded: one BLASFEO per process")
    check(path, fatrop, driver)
    _loaded["lib"] = ctypes.CDLL(str(path), mode=os.RTLD_GLOBAL) # promotes the checked handle
    _loaded["path"] = path


def features(lib) -> str:
    """The instructions a BLASFEO library was built for ('' for the GENERIC target)."""
    text = ctypes.create_string_buffer(256)
    lib.blasfeo_processor_library_string(text)
    return text.value.decode(errors="replace").strip()


class _DlInfo(ctypes.Structure):
    _fields_ = [("dli_fname", ctypes.c_char_p), ("dli_fbase", ctypes.c_void_p),
                ("dli_sname", ctypes.c_char_p), ("dli_saddr", ctypes.c_void_p)]


def in_use(address: int) -> dict:
    """The BLASFEO that a function address (blasfeo_pack_dmat as the driver bound it) lies in, and
    what it was built for; an error if RSCASADI_BLASFEO asked for another one."""
    libc = ctypes.CDLL(None)
    dladdr = getattr(libc, "dladdr", None) or ctypes.CDLL("libdl.so.2").dladdr
    info = _DlInfo()
    dladdr(ctypes.c_void_p(address), ctypes.byref(info))
    path = os.path.realpath(info.dli_fname.decode()) if info.dli_fname else "?"
    if _loaded and path != os.path.realpath(_loaded["path"]):
        raise RuntimeError(f"{ENV}={_loaded['path']} was loaded, but fatrop's driver calls the BLASFEO in {path} "
                           f"(was fatrop loaded into this process before?)")
    return {"library": path, "features": features(ctypes.CDLL(path)) if path != "?" else "?"}
