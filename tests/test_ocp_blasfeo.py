"""fatrop on the user's BLASFEO (RSCASADI_BLASFEO): loaded before the driver, it must be the library
fatrop's calls reach (not only a file that was opened), iterate as the wheel's does, and a library
that does not fit fatrop - no BLASFEO, other symbols, another matrix layout, a larger struct - must be
refused before it is used, naming the variable and the file.  No optimised BLASFEO is installed here:
the stand-in is a copy of the wheel's under another name, which is enough to see which one is called
(the speed is the benchmark's: benchmarks/bench_ocp.py)."""
import dataclasses
import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from rscasadi.control.ocp import blasfeo, load_problem, solve_once
from rscasadi.control.ocp.fatrop_direct import casadi_dir, driver_library

from conftest import cc, problem

CHILD = """
import dataclasses, json, sys
from rscasadi.control.ocp import load_problem, solve_once
p = dataclasses.replace(load_problem(sys.argv[1]), solver="fatrop")
sol = solve_once(p, print_level=0, log=lambda m: None)
print(json.dumps({k: sol[k] for k in ("status", "iterations", "theta", "tau", "blasfeo")}))
"""


def _fatrop_problem(pitch_arm):
    return problem(pitch_arm, "blasfeo.toml", transcription={"intervals": 14, "compiled": True}, solver={"name": "fatrop"})


def test_the_users_blasfeo_is_the_one_fatrop_calls_and_it_iterates_alike(pitch_arm, tmp_path, monkeypatch):
    monkeypatch.delenv(blasfeo.ENV, raising=False)
    path = _fatrop_problem(pitch_arm)
    ours = solve_once(dataclasses.replace(load_problem(path), solver="fatrop"), print_level=0, log=lambda m: None)
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
