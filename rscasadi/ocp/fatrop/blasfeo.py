"""Which BLASFEO fatrop's linear algebra runs on: the CasADi wheel's with its hottest kernels compiled
for this processor (the default), the wheel's as shipped (RSCASADI_BLASFEO=wheel), or the user's
(RSCASADI_BLASFEO=/path/to/libblasfeo.so).

The CasADi wheel ships BLASFEO built for its GENERIC target (plain C, no AVX); fatrop spends about
a third of a solve in it (its Riccati factorisation, 4x4 C kernels), and one kernel, the 4x4
product D = beta C + alpha A B', was 14 % of a solve of problem (b).  By default that kernel, its
sibling D = beta C + alpha A B and the 4-row matrix-vector kernels (A x, A' x) are compiled for
this processor (native.build.blasfeo_kernels, GCC vector extensions, -march=native), checked
against the wheel's own on random panels, and loaded into the process's global scope before the
driver: the wheel's library calls its kernels through its procedure linkage table, so its calls
bind to them (checked: a call into the wheel's library must reach them).

A BLASFEO built for the CPU (e.g. acados' or BLASFEO's own build for X64_INTEL_HASWELL) can stand
in for the whole library: set RSCASADI_BLASFEO=/path/to/libblasfeo.so before the first fatrop solve
of the process.  It is loaded into the global scope before the fatrop driver, so that libfatrop's
BLASFEO calls bind to it (the dynamic linker looks there before a library's own dependencies).
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
from rscasadi.errors import Failed

ENV = "RSCASADI_BLASFEO"
WHEEL = "wheel"                             # RSCASADI_BLASFEO=wheel: the wheel's BLASFEO as shipped
TUNED = ("kernel_dgemm_nt_4x4_lib4", "kernel_dgemm_nn_4x4_lib4",    # the kernels native.build.blasfeo_kernels replaces
         "kernel_dgemv_n_4_lib4", "kernel_dgemv_t_4_lib4")
_SIZES = ((5, 3), (13, 16), (17, 9))        # odd sizes: a panel height or column padding would show
_loaded: dict = {}                          # once per process: RSCASADI_BLASFEO (path), the user's lib or the tuned kernels


class _DMat(ctypes.Structure):              # struct blasfeo_dmat (blasfeo_common.h, panel-major)
    _fields_ = [("mem", ctypes.c_void_p), ("pA", ctypes.c_void_p), ("dA", ctypes.c_void_p)] + [
        (k, ctypes.c_int) for k in ("m", "n", "pm", "cn", "use_dA", "memsize")]


def wheel_library() -> Path:
    """The wheel's BLASFEO as libfatrop loads it (by its soname)."""
    return Path(ca.__file__).parent / "libblasfeo.so.0"


def _refuse(path, why: str):
    raise Failed(f"{ENV}={path}: {why}; unset {ENV} to use the BLASFEO of the CasADi wheel")


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


def check(path, *binaries: str, user: str = "fatrop") -> ctypes.CDLL:
    """The user's BLASFEO at `path`, loaded locally and checked against the wheel's (module
    docstring) for `binaries` (the libraries that call it, e.g. libfatrop and the driver) of `user`."""
    if not Path(path).is_file():
        _refuse(path, "no such file")
    try:
        lib = ctypes.CDLL(str(path))
    except OSError as e:
        _refuse(path, f"cannot be loaded ({e})")
    missing = sorted(s for s in set().union(*(_imports(b, path) for b in binaries)) | {
        "blasfeo_processor_cpu_features", "blasfeo_processor_library_features"} if not hasattr(lib, s))
    if missing:
        _refuse(path, f"it lacks BLASFEO functions that {user} calls: {', '.join(missing[:8])}")
    cpu, need = ctypes.c_int(0), ctypes.c_int(0)
    ok = lib.blasfeo_processor_cpu_features(ctypes.byref(cpu))
    lib.blasfeo_processor_library_features(ctypes.byref(need))
    if not ok or need.value & ~cpu.value:
        _refuse(path, f"it was built for instructions this CPU lacks (needs {features(lib)!r})")
    wheel = ctypes.CDLL(str(wheel_library()))
    for m, n in _SIZES:
        theirs, ours = _packed(lib, m, n), _packed(wheel, m, n)
        if theirs[0] is None:
            _refuse(path, f"its struct blasfeo_dmat is larger than the one {user} was compiled with")
        if theirs[:2] != ours[:2] or not np.array_equal(theirs[2], ours[2]):
            _refuse(path, f"its matrix layout differs from the one {user} was compiled with (a {m} x {n} matrix: "
                          f"m, n, pm, cn, memsize {theirs[1]} against {ours[1]}; panel size or storage order)")
    return lib


def load(fatrop: str, driver: str, tuned):
    """Before the driver is loaded: the user's BLASFEO (RSCASADI_BLASFEO) into the global scope, or,
    unless RSCASADI_BLASFEO=wheel, the tuned kernel (`tuned()`: its library) if the wheel's BLASFEO
    is the GENERIC build.  Once per process."""
    path = os.environ.get(ENV, "")
    if _loaded:
        if _loaded["path"] != path:
            raise Failed(f"{ENV} changed to {path!r} after {_loaded['path'] or 'the default'!r} was loaded: "
                               "one BLASFEO per process")
        return
    if path and path != WHEEL:
        check(path, fatrop, driver)
        _loaded["lib"] = ctypes.CDLL(str(path), mode=os.RTLD_GLOBAL) # promotes the checked handle
    elif not path:
        wheel = _lazily(wheel_library())
        if not features(wheel):
            _loaded["tuned"] = _load_tuned(tuned(), wheel)
    _loaded["path"] = path


def _libc(name: str):
    libc = ctypes.CDLL(None)
    return getattr(libc, name, None) or getattr(ctypes.CDLL("libdl.so.2"), name)


def _lazily(path):
    """`path` loaded with lazy binding (ctypes binds every call at load): its calls into other
    libraries bind at their first use, so that they can still reach what is loaded after it."""
    dlopen = _libc("dlopen")
    dlopen.restype, dlopen.argtypes = ctypes.c_void_p, [ctypes.c_char_p, ctypes.c_int]
    handle = dlopen(str(path).encode(), os.RTLD_LAZY | os.RTLD_LOCAL)
    if not handle:
        raise Failed(f"cannot load the CasADi wheel's BLASFEO {path}")
    return ctypes.CDLL(str(path), handle=handle)


def _same_kernel(ours, theirs, name: str, path) -> None:
    """`ours` computes what the wheel's kernel `theirs` computes, up to rounding, on random panels:
    B' (nt) as kmax columns of a panel, B (nn) as kmax rows from an offset into panels of
    stride sdb; the matrix-vector kernels by _same_gemv."""
    if name.startswith("kernel_dgemv"):
        return _same_gemv(ours, theirs, name, path)
    rng = np.random.default_rng(7)
    P = ctypes.POINTER(ctypes.c_double)
    nn = name.startswith("kernel_dgemm_nn")
    for kmax in (0, 1, 2, 3, 4, 5, 7, 8, 13, 16, 33):
        for (alpha, beta), offset in zip(((1.0, 1.0), (-1.0, 0.0), (0.7, -1.3)), (0, 1, 3)):
            A, C, sdb = rng.standard_normal(4 * kmax + 1), rng.standard_normal(16), 6
            offset = offset if kmax else 0          # BLASFEO's own kernel reads a row past kmax = 0 from an offset
            if nn:                                   # row k of B at its panel's start + its row in it
                B = rng.standard_normal((kmax + offset) // 4 * 4 * sdb + 4 * sdb)
                rows = np.array([(offset + k) // 4 * 4 * sdb + (offset + k) % 4 for k in range(kmax)], int)
                Bk = B[rows[:, None] + 4 * np.arange(4)]             # kmax x 4
            else:
                B = rng.standard_normal(4 * kmax + 1)
                Bk = B[:4 * kmax].reshape(-1, 4)
            al, be, D = np.array([alpha]), np.array([beta]), [np.full(16, np.nan) for _ in range(2)]
            for f, out in zip((ours, theirs), D):
                if nn:
                    f(kmax, al.ctypes.data_as(P), A.ctypes.data_as(P), offset, B.ctypes.data_as(P), sdb,
                      *(v.ctypes.data_as(P) for v in (be, C, out)))
                else:
                    f(kmax, *(v.ctypes.data_as(P) for v in (al, A, B, be, C, out)))
            scale = abs(alpha) * (np.abs(A[:4 * kmax]).reshape(-1, 4).T @ np.abs(Bk)).ravel("F") + abs(beta) * np.abs(C)
            if not np.all(np.abs(D[0] - D[1]) <= 1e-14 * (1 + scale)):
                raise _differs(name, path, f"kmax {kmax}, alpha {alpha}, beta {beta}", D)


def _differs(name, path, detail: str, D) -> Failed:
    return Failed(f"BLASFEO's {name} compiled for this processor ({path}) differs from the CasADi wheel's ({detail}: "
                  f"largest difference {np.nanmax(np.abs(D[0] - D[1])):.3g}); set {ENV}={WHEEL} to run on the "
                  "wheel's kernels")


def _same_gemv(ours, theirs, name: str, path) -> None:
    """The 4-row matrix-vector kernels (z = beta y + alpha A x, n; alpha A' x, t) against the
    wheel's on random panels: A' from a row offset into panels of stride sda; y NaN for beta = 0
    (the wheel's does not read it)."""
    rng = np.random.default_rng(11)
    P = ctypes.POINTER(ctypes.c_double)
    transposed = name.startswith("kernel_dgemv_t")
    for kmax in (0, 1, 2, 3, 4, 5, 7, 8, 13, 16, 33):
        for (alpha, beta), offset in zip(((1.0, 1.0), (-1.0, 0.0), (0.7, -1.3), (2.0, 0.0)), (0, 1, 3, 2)):
            offset = offset if transposed else 0
            sda, x = 6, rng.standard_normal(kmax + 1)
            A = rng.standard_normal(((offset + kmax) // 4 + 1) * 4 * sda if transposed else 4 * kmax + 1)
            y = np.full(4, np.nan) if beta == 0 else rng.standard_normal(4)
            al, be, D = np.array([alpha]), np.array([beta]), [np.full(4, np.nan) for _ in range(2)]
            for f, out in zip((ours, theirs), D):
                if transposed:
                    f(kmax, al.ctypes.data_as(P), offset, ctypes.cast(A.ctypes.data + 8 * offset, P), sda,
                      *(v.ctypes.data_as(P) for v in (x, be, y, out)))
                else:
                    f(kmax, *(v.ctypes.data_as(P) for v in (al, A, x, be, y, out)))
            if not np.all(np.abs(D[0] - D[1]) <= 1e-14 * (1 + np.abs(D[1]) + np.abs(A).sum())):
                raise _differs(name, path, f"kmax {kmax}, offset {offset}, alpha {alpha}, beta {beta}", D)


def _load_tuned(path: str, wheel) -> dict:
    """The tuned kernels, checked against the wheel's, into the global scope; whether the wheel's
    calls reach them (its 4x4 edge kernel calls the full one through its linkage table)."""
    lib = ctypes.CDLL(path)
    for name in TUNED:
        _same_kernel(getattr(lib, name), getattr(wheel, name), name, path)
    ctypes.CDLL(path, mode=os.RTLD_GLOBAL)                           # promotes the checked handle
    flag = ctypes.c_int.in_dll(lib, "rsc_tuned_reached")
    flag.value = 0
    P = ctypes.POINTER(ctypes.c_double)
    one, A, D = np.ones(1), np.ones(8), np.zeros(16)
    wheel.kernel_dgemm_nt_4x4_vs_lib4(2, *(v.ctypes.data_as(P) for v in (one, A, A, one, D, D)), 4, 4)
    return {"library": path, "kernels": list(TUNED), "reached": bool(flag.value)}


def wheel_is_generic() -> bool:
    """Whether the wheel's BLASFEO is its GENERIC build (loaded lazily: its calls still bind to
    kernels loaded after it)."""
    return not features(_lazily(wheel_library()))


def features(lib) -> str:
    """The instructions a BLASFEO library was built for ('' for the GENERIC target)."""
    text = ctypes.create_string_buffer(256)
    lib.blasfeo_processor_library_string(text)
    return text.value.decode(errors="replace").strip()


class _DlInfo(ctypes.Structure):
    _fields_ = [("dli_fname", ctypes.c_char_p), ("dli_fbase", ctypes.c_void_p),
                ("dli_sname", ctypes.c_char_p), ("dli_saddr", ctypes.c_void_p)]


def in_use(address: int) -> dict:
    """The BLASFEO that a function address (blasfeo_dgese as the driver bound it) lies in, and
    what it was built for, and the tuned kernels in front of it (None: none); an error if
    RSCASADI_BLASFEO asked for another one."""
    dladdr = _libc("dladdr")
    info = _DlInfo()
    dladdr(ctypes.c_void_p(address), ctypes.byref(info))
    path = os.path.realpath(info.dli_fname.decode()) if info.dli_fname else "?"
    if _loaded.get("lib") and path != os.path.realpath(_loaded["path"]):
        raise Failed(f"{ENV}={_loaded['path']} was loaded, but fatrop's driver calls the BLASFEO in {path} "
                           f"(was fatrop loaded into this process before?)")
    return {"library": path, "features": features(ctypes.CDLL(path)) if path != "?" else "?",
            "tuned_kernels": dict(_loaded["tuned"]) if _loaded.get("tuned") else None}
