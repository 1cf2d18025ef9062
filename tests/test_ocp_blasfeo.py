"""fatrop's BLASFEO.  By default the wheel's, with its 4x4 dgemm kernel compiled for this processor:
that kernel must compute what BLASFEO's own does (numpy as the reference for both), a wrong one must
be refused, and fatrop's solves must reach it and iterate as on the wheel's kernels
(RSCASADI_BLASFEO=wheel).  The user's BLASFEO (RSCASADI_BLASFEO=path): loaded before the driver, it
must be the library fatrop's calls reach (not only a file that was opened), iterate as the wheel's
does, and a library that does not fit fatrop - no BLASFEO, other symbols, another matrix layout, a
larger struct - must be refused before it is used, naming the variable and the file.  No optimised
BLASFEO is installed here: the stand-in is a copy of the wheel's under another name, which is enough
to see which one is called (the speed is the benchmark's: benchmarks/bench_ocp.py)."""
import ctypes
import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from rscasadi.ocp import load_problem, solve_once
from rscasadi.ocp.fatrop import blasfeo
from rscasadi.ocp.fatrop.driver import casadi_dir, driver_library, tuned_kernels_library

from conftest import cc, problem

CHILD = """
import dataclasses, json, sys
from rscasadi.ocp import load_problem, solve_once
p = load_problem(sys.argv[1]).replace(solver="fatrop")
sol = solve_once(p, print_level=0, log=lambda m: None)
print(json.dumps({k: sol[k] for k in ("status", "iterations", "theta", "tau", "blasfeo")}))
"""


def _fatrop_problem(pitch_arm):
    return problem(pitch_arm, "blasfeo.toml", transcription={"intervals": 14, "compiled": True}, solver={"name": "fatrop"})


def test_the_users_blasfeo_is_the_one_fatrop_calls_and_it_iterates_alike(pitch_arm, tmp_path, monkeypatch):
    monkeypatch.delenv(blasfeo.ENV, raising=False)
    path = _fatrop_problem(pitch_arm)
    ours = solve_once(load_problem(path).replace(solver="fatrop"), print_level=0, log=lambda m: None)
    assert ours["success"] and ours["blasfeo"]["library"] == os.path.realpath(blasfeo.wheel_library())
    # a copy under another soname: with the wheel's soname the dynamic linker would hand the copy to
    # libfatrop as its dependency, and the global-scope binding would go untested (the same length:
    # the string table's offsets stay)
    data = blasfeo.wheel_library().read_bytes()
    assert data.count(b"libblasfeo.so.0\x00") == 1
    user = tmp_path / "libblasfeo_user.so"
    user.write_bytes(data.replace(b"libblasfeo.so.0\x00", b"libblasfeo.so.9\x00"))
    env = {**os.environ, blasfeo.ENV: str(user)}
    run = subprocess.run([sys.executable, "-c", CHILD, str(path)], capture_output=True, text=True, env=env, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    theirs = json.loads(run.stdout.strip().splitlines()[-1])
    assert theirs["blasfeo"]["library"] == os.path.realpath(user)       # dladdr of the driver's bound call
    assert theirs["status"] == "Solve_Succeeded" and theirs["iterations"] == ours["iterations"]
    for key in ("theta", "tau"):
        np.testing.assert_allclose(theirs[key], ours[key], rtol=0, atol=1e-12)


SHIM = r"""
#include <stddef.h>
#include <string.h>
struct dmat { double *mem, *pA, *dA; int m, n, pm, cn, use_dA, memsize; };
int blasfeo_processor_cpu_features(int* f) { *f = 0; return 1; }
void blasfeo_processor_library_features(int* f) { *f = 0; }
void blasfeo_processor_library_string(char* s) { strcpy(s, "shim"); }
size_t blasfeo_memsize_dmat(int m, int n) { return (size_t)(m * n) * 8 + 64; }
void blasfeo_create_dmat(int m, int n, struct dmat* A, void* mem) {
  A->mem = A->pA = (double*)mem; A->dA = 0; A->m = A->pm = m; A->n = A->cn = n; A->use_dA = 0;
  A->memsize = (int)blasfeo_memsize_dmat(m, n);
#ifdef LARGER
  ((double*)(A + 1))[0] = 1.0;               /* a field the wheel's struct does not have */
#endif
}
void blasfeo_pack_dmat(int m, int n, double* B, int ldb, struct dmat* A, int ai, int aj) {
  int i, j;                                  /* column-major: BLASFEO's MF_COLMAJ, not the wheel's panels */
  for (j = 0; j < n; ++j) for (i = 0; i < m; ++i) A->pA[(ai + i) + (aj + j) * A->m] = B[i + j * ldb];
}
"""


def _shim(tmp_path, name, defines=(), every_symbol=True):
    """A fake BLASFEO: the functions the checks call, and (every_symbol) stubs for the rest of what
    libfatrop and the driver import."""
    have = {"blasfeo_processor_cpu_features", "blasfeo_processor_library_features", "blasfeo_processor_library_string",
            "blasfeo_memsize_dmat", "blasfeo_create_dmat", "blasfeo_pack_dmat"}
    need = blasfeo._imports(str(casadi_dir() / "libfatrop.so"), "-") | blasfeo._imports(driver_library(lambda m: None), "-")
    stubs = "".join(f"void {s}(void) {{}}\n" for s in sorted(need - have)) if every_symbol else ""
    src = tmp_path / f"{name}.c"
    src.write_text(SHIM + stubs)
    lib = tmp_path / f"lib{name}.so"
    subprocess.run([cc(), "-shared", "-fPIC", *[f"-D{d}" for d in defines], str(src), "-o", str(lib)], check=True)
    return lib


@pytest.mark.parametrize("case,message", [
    ("missing", r"no such file"),
    ("not_a_library", r"cannot be loaded"),
    ("few_symbols", r"it lacks BLASFEO functions that fatrop calls: blasfeo_"),
    ("column_major", r"its matrix layout differs .* 5 x 3 matrix"),
    ("larger_struct", r"its struct blasfeo_dmat is larger"),
])
def test_a_blasfeo_that_does_not_fit_fatrop_is_refused_naming_it(tmp_path, case, message):
    path = {"missing": lambda: tmp_path / "libnothing.so",
            "not_a_library": lambda: (tmp_path / "libtext.so", (tmp_path / "libtext.so").write_text("not ELF"))[0],
            "few_symbols": lambda: _shim(tmp_path, "few", every_symbol=False),
            "column_major": lambda: _shim(tmp_path, "colmajor"),
            "larger_struct": lambda: _shim(tmp_path, "larger", defines=("LARGER",))}[case]()
    with pytest.raises(RuntimeError, match=rf"RSCASADI_BLASFEO={re.escape(str(path))}: {message}"):
        blasfeo.check(path, str(casadi_dir() / "libfatrop.so"), driver_library(lambda m: None))


def test_the_wheels_blasfeo_passes_the_checks(tmp_path):
    # the other side of the refusals above: the library fatrop was built with fits it
    lib = blasfeo.check(blasfeo.wheel_library(), str(casadi_dir() / "libfatrop.so"), driver_library(lambda m: None))
    assert blasfeo.features(lib) == ""                                    # the wheel's: GENERIC target


# ------------------------------------------------------------- the tuned kernel (the default)

_P = ctypes.POINTER(ctypes.c_double)


def _dgemm_nt_4x4(f, kmax, alpha, A, B, beta, C):
    D = np.full(16, np.nan)
    f(kmax, *(np.ascontiguousarray(v, dtype=float).ctypes.data_as(_P) for v in ([alpha], A, B, [beta], C, D)))
    return D.reshape(4, 4, order="F")


def test_the_tuned_kernel_computes_blasfeos_4x4_product():
    ours = ctypes.CDLL(tuned_kernels_library(lambda m: None)).kernel_dgemm_nt_4x4_lib4
    theirs = ctypes.CDLL(str(blasfeo.wheel_library())).kernel_dgemm_nt_4x4_lib4
    rng = np.random.default_rng(3)
    for kmax in (0, 1, 3, 4, 6, 15, 16, 40):
        for alpha, beta in ((1.0, 1.0), (-1.0, 0.0), (2.5, -0.5)):
            A, B, C = rng.standard_normal((kmax, 4)), rng.standard_normal((kmax, 4)), rng.standard_normal((4, 4))
            # panel-major: column k of a 4-row panel at 4 k, so the (kmax, 4) arrays are the panels
            want = beta * C + alpha * A.T @ B
            for f in (ours, theirs):
                got = _dgemm_nt_4x4(f, kmax, alpha, A.ravel(), B.ravel(), beta, C.ravel(order="F"))
                np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13 * (1 + kmax))
    # BLASFEO's generic kernel forms beta C even for beta = 0 (NaN in C stays): so does ours
    A, B, C = rng.standard_normal(8), rng.standard_normal(8), np.full(16, np.nan)
    for f in (ours, theirs):
        assert np.isnan(_dgemm_nt_4x4(f, 2, 1.0, A, B, 0.0, C)).all()



def test_the_tuned_nn_kernel_computes_blasfeos_4x4_product_from_any_row_of_a_panel():
    # D = beta C + alpha A B: B's kmax rows start offset rows into a panel of 4 rows and sdb columns
    ours = ctypes.CDLL(tuned_kernels_library(lambda m: None)).kernel_dgemm_nn_4x4_lib4
    theirs = ctypes.CDLL(str(blasfeo.wheel_library())).kernel_dgemm_nn_4x4_lib4
    rng = np.random.default_rng(5)
    for kmax in (0, 1, 3, 4, 5, 9, 16, 23):
        for offset in range(4 if kmax else 1):          # from an offset, BLASFEO's own reads a row past kmax = 0
            for sdb in (4, 8):
                rows = kmax + offset
                Bfull = rng.standard_normal((-(-rows // 4) * 4 + 4, sdb))      # a row-panelled matrix
                panels = np.concatenate([Bfull[4 * q:4 * q + 4].ravel(order="F") for q in range(len(Bfull) // 4)])
                A, C, alpha, beta = rng.standard_normal((kmax, 4)), rng.standard_normal((4, 4)), -0.7, 1.3
                want = beta * C + alpha * A.T @ Bfull[offset:offset + kmax, :4]
                for f in (ours, theirs):
                    D = np.full(16, np.nan)
                    f(kmax, np.array([alpha]).ctypes.data_as(_P), np.ascontiguousarray(A).ctypes.data_as(_P), offset,
                      panels.ctypes.data_as(_P), sdb, np.array([beta]).ctypes.data_as(_P),
                      np.asfortranarray(C).ravel(order="F").ctypes.data_as(_P), D.ctypes.data_as(_P))
                    np.testing.assert_allclose(D.reshape(4, 4, order="F"), want, rtol=1e-13, atol=1e-13 * (1 + kmax))


def _dgemv(f, kmax, alpha, A, x, beta, y, transposed, offset=0, sda=0):
    z = np.full(4, np.nan)
    al, be = np.array([alpha]), np.array([beta])
    if transposed:
        f(kmax, al.ctypes.data_as(_P), offset, ctypes.cast(A.ctypes.data + 8 * offset, _P), sda,
          *(v.ctypes.data_as(_P) for v in (x, be, y, z)))
    else:
        f(kmax, *(v.ctypes.data_as(_P) for v in (al, A, x, be, y, z)))
    return z


def test_the_tuned_matrix_vector_kernels_compute_blasfeos_from_any_row_of_a_panel():
    # z = beta y + alpha A x (n: A a 4-row panel) or alpha A' x (t: A's kmax rows from a row offset
    # into panels of 4 rows and sda columns); y is not read for beta = 0
    tuned = ctypes.CDLL(tuned_kernels_library(lambda m: None))
    wheel = ctypes.CDLL(str(blasfeo.wheel_library()))
    rng = np.random.default_rng(9)
    for name in ("kernel_dgemv_n_4_lib4", "kernel_dgemv_t_4_lib4"):
        transposed = "_t_" in name
        for kmax in (0, 1, 2, 3, 4, 5, 6, 9, 16, 31):
            for offset in range(4) if transposed else (0,):
                for alpha, beta in ((1.0, 1.0), (-0.6, 0.0), (1.7, -2.0)):
                    x = rng.standard_normal(kmax)
                    y = np.full(4, np.nan) if beta == 0 else rng.standard_normal(4)
                    if transposed:
                        sda = 5
                        M = rng.standard_normal((-(-(kmax + offset) // 4) * 4 + 4, sda))   # a row-panelled matrix
                        A = np.concatenate([M[4 * q:4 * q + 4].ravel(order="F") for q in range(len(M) // 4)])
                        want = alpha * M[offset:offset + kmax, :4].T @ x
                    else:
                        sda, M = 0, rng.standard_normal((4, kmax))
                        A, want = M.ravel(order="F"), alpha * M @ x
                    want = want + (beta * y if beta else 0)
                    for f in (getattr(tuned, name), getattr(wheel, name)):
                        got = _dgemv(f, kmax, alpha, A, x, beta, y, transposed, offset, sda)
                        np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13 * (1 + kmax))


def test_a_tuned_kernel_that_differs_from_the_wheels_is_refused(tmp_path):
    src = tmp_path / "wrong.c"
    src.write_text("void kernel_dgemm_nt_4x4_lib4(int kmax, double *alpha, double *A, double *B, double *beta, "
                   "double *C, double *D) { int i; for (i = 0; i < 16; ++i) D[i] = beta[0] * C[i] + "
                   "(kmax ? alpha[0] * A[i % 4] * B[i / 4] : 0); }\n")       # right for kmax <= 1 only
    lib = tmp_path / "libwrong.so"
    subprocess.run([cc(), "-shared", "-fPIC", str(src), "-o", str(lib)], check=True)
    wheel = ctypes.CDLL(str(blasfeo.wheel_library()))
    with pytest.raises(RuntimeError, match=rf"kernel_dgemm_nt_4x4_lib4 compiled for this processor \({re.escape(str(lib))}\) "
                                           r"differs from the CasADi wheel's \(kmax 2.*RSCASADI_BLASFEO=wheel"):
        blasfeo._same_kernel(ctypes.CDLL(str(lib)).kernel_dgemm_nt_4x4_lib4, wheel.kernel_dgemm_nt_4x4_lib4,
                             "kernel_dgemm_nt_4x4_lib4", lib)
    src.write_text("void kernel_dgemm_nn_4x4_lib4(int kmax, double *alpha, double *A, int offsetB, double *B, int sdb, "
                   "double *beta, double *C, double *D) { int i, k; (void)offsetB; (void)sdb; for (i = 0; i < 16; ++i) {"
                   " double s = 0; for (k = 0; k < kmax; ++k) s += A[4 * k + i % 4] * B[k + 4 * (i / 4)];"
                   " D[i] = beta[0] * C[i] + alpha[0] * s; } }\n")      # the offset ignored, no next panel
    subprocess.run([cc(), "-shared", "-fPIC", str(src), "-o", str(lib.with_name("libwrong_nn.so"))], check=True)
    with pytest.raises(RuntimeError, match=r"kernel_dgemm_nn_4x4_lib4 compiled for this processor .* differs .*\(kmax 1, "):
        blasfeo._same_kernel(ctypes.CDLL(str(lib.with_name("libwrong_nn.so"))).kernel_dgemm_nn_4x4_lib4,
                             wheel.kernel_dgemm_nn_4x4_lib4, "kernel_dgemm_nn_4x4_lib4", lib)
    src.write_text("void kernel_dgemv_t_4_lib4(int kmax, double *alpha, int offA, double *A, int sda, double *x, "
                   "double *beta, double *y, double *z) { int j, k; (void)offA; for (j = 0; j < 4; ++j) {"
                   " double s = 0; for (k = 0; k < kmax; ++k) s += A[k % 4 + 4 * j + 4 * sda * (k / 4)] * x[k];"
                   " z[j] = alpha[0] * s + (beta[0] == 0 ? 0 : beta[0] * y[j]); } }\n")    # panels crossed as from row 0
    subprocess.run([cc(), "-shared", "-fPIC", str(src), "-o", str(lib.with_name("libwrong_t.so"))], check=True)
    with pytest.raises(RuntimeError, match=r"kernel_dgemv_t_4_lib4 compiled for this processor .* differs .*\(kmax 2, offset 3"):
        blasfeo._same_kernel(ctypes.CDLL(str(lib.with_name("libwrong_t.so"))).kernel_dgemv_t_4_lib4,
                             wheel.kernel_dgemv_t_4_lib4, "kernel_dgemv_t_4_lib4", lib)


TUNED_CHILD = """
import ctypes, dataclasses, json, sys
from rscasadi.ocp import load_problem, solve_once
p = load_problem(sys.argv[1]).replace(solver="fatrop")
solve_once(p, print_level=0, log=lambda m: None)
tuned = None
import rscasadi.ocp.fatrop.blasfeo as b
if b._loaded.get("tuned"):
    tuned = ctypes.c_int.in_dll(ctypes.CDLL(b._loaded["tuned"]["library"]), "rsc_tuned_reached")
    tuned.value = 0                                  # the next solve must set it again
sol = solve_once(p, print_level=0, log=lambda m: None)
out = {k: sol[k] for k in ("status", "iterations", "theta", "tau", "blasfeo")}
out["reached_in_solve"] = None if tuned is None else tuned.value
print(json.dumps(out))
"""


def test_fatrop_reaches_the_tuned_kernel_and_iterates_as_on_the_wheels(pitch_arm):
    # in fresh processes: the kernel binds once per process, before the wheel's BLASFEO is first used
    path = _fatrop_problem(pitch_arm)
    runs = {}
    for mode in ("", blasfeo.WHEEL):
        env = {k: v for k, v in os.environ.items() if k != blasfeo.ENV} | ({blasfeo.ENV: mode} if mode else {})
        run = subprocess.run([sys.executable, "-c", TUNED_CHILD, str(path)], capture_output=True, text=True, env=env,
                             timeout=600)
        assert run.returncode == 0, run.stderr[-2000:]
        runs[mode] = json.loads(run.stdout.strip().splitlines()[-1])
    tuned, wheel = runs[""], runs[blasfeo.WHEEL]
    assert tuned["blasfeo"]["library"] == wheel["blasfeo"]["library"] == os.path.realpath(blasfeo.wheel_library())
    assert tuned["blasfeo"]["tuned_kernels"]["reached"] and tuned["reached_in_solve"] == 1
    assert wheel["blasfeo"]["tuned_kernels"] is None and wheel["reached_in_solve"] is None
    assert tuned["status"] == wheel["status"] == "Solve_Succeeded" and tuned["iterations"] == wheel["iterations"]
    for key in ("theta", "tau"):               # the same iterates up to the kernels' rounding
        np.testing.assert_allclose(tuned[key], wheel[key], rtol=0, atol=1e-9)
