"""The NLP solvers: fatrop (exploits the stage structure; a Riccati-based interior point) or
IPOPT (general sparse, MUMPS), on the NLP's functions generated to C and compiled once
(cached by the hash of the source), or in CasADi's virtual machine."""
from __future__ import annotations

import fcntl
import hashlib
import os
import subprocess
import time
from pathlib import Path

import casadi as ca

from ...codegen import _compiler, cache_dir
from ...codegen.parallel import openmp_flags
from .fatrop_direct import DirectFatrop
from .assembly import ASSEMBLY_VERSION, assembled, places, solver_functions
from .problem import Problem
from .transcription import Transcription


def options(problem: Problem, tr: Transcription, print_level: int, extra: dict | None = None) -> dict:
    """Solver options: tolerances alike for both, so that their times compare."""
    extra = extra or {}
    if problem.solver == "fatrop":
        return {**tr.structure(), "print_time": False, "expand": False,
                "fatrop": {"print_level": 10 if print_level else 0, "tol": 1e-8, "max_iter": 1000,
                           # condensed, a smaller first barrier: min time 33-37 iterations instead of
                           # 40-53 (N = 50-200), min effort 18-20 instead of 19-22; lifted: no gain
                           "mu_init": 1e-2 if tr.condensed else 1e-1, **extra}}
    return {"print_time": False, "ipopt.print_level": print_level, "ipopt.sb": "yes", "ipopt.max_iter": 1000,
            "ipopt.tol": 1e-8, "ipopt.mu_strategy": "adaptive",
            "ipopt.mumps_pivot_order": 0,          # AMD: min-time N = 100 in 1.8 s instead of 4.5 s here
            "ipopt.hessian_approximation": problem.hessian, **{f"ipopt.{k}": v for k, v in extra.items()}}


def make_solver(problem: Problem, tr: Transcription, nlp: dict, log=print, print_level: int = 5,
                extra: dict | None = None):
    """(solver, objective(x, p) Function) for this problem's NLP."""
    opts = options(problem, tr, print_level, extra)
    objective = ca.Function("f", [nlp["x"], nlp["p"]], [nlp["f"]])
    if tr.condensed:
        # the kernel's functions have no AD: the parameters' multipliers (by AD) are not asked for
        opts["calc_lam_p"] = False
    if not problem.compiled and not tr.condensed:      # condensed: its kernel is C anyway
        return ca.nlpsol("ocp", problem.solver, nlp, opts), objective
    library = compiled_nlp(problem.solver, nlp, opts, tr.pieces, log)
    if direct(problem):
        return DirectFatrop(library, tr.structure(), opts["fatrop"], log, problem.barrier, places(tr.pieces)), objective
    return ca.nlpsol("ocp", problem.solver, library, opts), objective


def direct(problem: Problem) -> bool:
    """fatrop through its own C interface (fatrop_direct.py): on the compiled NLP, unless asked otherwise."""
    return problem.solver == "fatrop" and problem.interface == "direct" and problem.compiled


def compiled_nlp(solver: str, nlp: dict, opts: dict, pieces: list, log=print, opt: str | None = None) -> str:
    """The shared library of the NLP's functions for `solver`, compiled once and cached; at -O1
    by default (RSCASADI_NLP_OPT, e.g. -O2, for the fastest solves at a longer compile).  Its
    first and second derivatives are assembled from the NLP's pieces' own (assembly.py), its
    loops over the intervals OpenMP-parallel when the compiler has OpenMP (threads: set_threads)."""
    opt = opt or os.environ.get("RSCASADI_NLP_OPT", "-O1")
    cc = _compiler()
    omp = list(openmp_flags(tuple(cc)))
    directory = cache_dir() / "nlp"
    directory.mkdir(parents=True, exist_ok=True)
    # generating the C just to hash it takes seconds: an index keyed by the serialised NLP finds
    # a library built before (sweep tasks, repeated solves) without generating anything
    graph = ca.Function("nlp", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]]).serialize()
    index = directory / ("index_" + hashlib.sha256((graph + solver + opt + repr(sorted(opts.items())) + " ".join(cc + omp)
                                                     + ca.__version__ + ASSEMBLY_VERSION).encode()).hexdigest()[:24])
    if index.exists() and Path(index.read_text()).exists():
        log(f"compiled NLP: cache hit {index.read_text()}")
        return index.read_text()
    libraries = sorted({piece.library for piece in pieces if piece.library})
    # the solver's own functions give the signatures; with kernels (no AD) from a stand-in NLP
    plain = ca.nlpsol("ocp", solver, nlp if not libraries else _stand_in(nlp, pieces), opts)
    # CasADi writes into the working directory and prefixes internal symbols with the file name,
    # so the name must be fixed (or the source, and its hash, change every run); a lock keeps
    # two processes from writing it at once.
    src = directory / f"rscasadi_nlp_{os.getpid()}.c"
    with open(directory / "generate.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        cg = ca.CodeGenerator("rscasadi_nlp.c", {"with_header": False})
        # fatrop's library also has the unscattered derivatives its direct interface reads
        for f in solver_functions(plain, nlp, pieces, "openmp" if omp else "serial", raw=solver == "fatrop"):
            cg.add(f)
        cg.generate()
        Path("rscasadi_nlp.c").replace(src)
    key = hashlib.sha256((src.read_text() + " ".join(cc + omp) + opt + ca.__version__ + " ".join(libraries)).encode()).hexdigest()[:24]
    lib = directory / f"nlp_{key}.so"
    if lib.exists():
        log(f"compiled NLP: cache hit {lib}")
        src.unlink()
        index.write_text(str(lib))
        return str(lib)
    t0 = time.perf_counter()
    part = lib.with_suffix(f".{os.getpid()}.part")
    link = [a for lib_ in libraries for a in (lib_, f"-Wl,-rpath,{Path(lib_).parent}")]
    run = subprocess.run([*cc, opt, *omp, "-fPIC", "-shared", str(src), "-o", str(part), *link, "-lm"],
                         capture_output=True, text=True)
    src.unlink()
    if run.returncode != 0:
        raise RuntimeError(f"compiling the NLP failed:\n{run.stderr[-2000:]}")
    part.replace(lib)
    index.write_text(str(lib))
    log(f"compiled NLP in {time.perf_counter() - t0:.1f} s: {lib}")
    return str(lib)


def _stand_in(nlp: dict, pieces: list) -> dict:
    """An NLP with the same variables, parameters, sizes and Jacobian pattern (fatrop checks its
    stage structure), and nothing to differentiate."""
    x, P, n_g = nlp["x"], nlp["p"], nlp["g"].numel()
    pattern = assembled(pieces, x, ca.MX.sym("lam_f"), ca.MX.sym("lam_g", n_g), n_g)["jac_g"].sparsity()
    return {"x": x, "p": P, "f": ca.sumsqr(x) + ca.sum1(P), "g": ca.mtimes(ca.DM(pattern, 1.0), x)}
