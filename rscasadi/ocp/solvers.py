"""The NLP solvers: fatrop (exploits the stage structure; a Riccati-based interior point) or
IPOPT (general sparse, MUMPS), on the NLP's functions generated to C and compiled once
(cached by the hash of the source), or in CasADi's virtual machine."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

import casadi as ca

from rscasadi.native.build import cache_dir, cached_library, casadi_c, compiler
from rscasadi.native.parallel import openmp_flags
from rscasadi.ocp.fatrop.driver import DirectFatrop
from rscasadi.ocp.assembly import ASSEMBLY_VERSION, assembled, places, solver_functions
from rscasadi.ocp.problem import Problem
from rscasadi.ocp.transcription import Transcription


def options(problem: Problem, tr: Transcription, print_level: int, extra: dict | None = None) -> dict:
    """Solver options: tolerances alike for both, so that their times compare."""
    extra = extra or {}
    if problem.solver.name == "fatrop":
        return {**tr.structure(), "print_time": False, "expand": False,
                "fatrop": {"print_level": (10 if print_level > 5 else 5) if print_level else 0, "tol": 1e-8, "max_iter": 1000,
                           # condensed, a smaller first barrier: min time 33-37 iterations instead of
                           # 40-53 (N = 50-200), min effort 18-20 instead of 19-22; lifted: no gain
                           "mu_init": 1e-2 if tr.condensed else 1e-1, **extra}}
    return {"print_time": False, "ipopt.print_level": print_level, "ipopt.sb": "yes", "ipopt.max_iter": 1000,
            "ipopt.tol": 1e-8, "ipopt.mu_strategy": "adaptive",
            "ipopt.mumps_pivot_order": 0,          # AMD: min-time N = 100 in 1.8 s instead of 4.5 s here
            "ipopt.hessian_approximation": problem.solver.hessian, **{f"ipopt.{k}": v for k, v in extra.items()}}


def make_solver(problem: Problem, tr: Transcription, nlp: dict, log=print, print_level: int = 5,
                extra: dict | None = None):
    """(solver, objective(x, p) Function) for this problem's NLP."""
    opts = options(problem, tr, print_level, extra)
    objective = ca.Function("f", [nlp["x"], nlp["p"]], [nlp["f"]])
    if tr.condensed:
        # the kernel's functions have no AD: the parameters' multipliers (by AD) are not asked for
        opts["calc_lam_p"] = False
    if not problem.transcription.compiled and not tr.condensed:      # condensed: its kernel is C anyway
        return ca.nlpsol("ocp", problem.solver.name, nlp, opts), objective
    library = compiled_nlp(problem.solver.name, nlp, opts, tr.pieces, log)
    if direct(problem):
        return DirectFatrop(library, tr.structure(), opts["fatrop"], log, places(tr.pieces)), objective
    return ca.nlpsol("ocp", problem.solver.name, library, opts), objective


def direct(problem: Problem) -> bool:
    """fatrop through its own C interface (ocp/fatrop/driver.py): on the compiled NLP, unless asked otherwise."""
    return problem.solver.name == "fatrop" and problem.solver.interface == "direct" and problem.transcription.compiled


def compiled_nlp(solver: str, nlp: dict, opts: dict, pieces: list, log=print, opt: str | None = None) -> str:
    """The shared library of the NLP's functions for `solver`, compiled once and cached; at -O1
    by default (RSCASADI_NLP_OPT, e.g. -O2, for the fastest solves at a longer compile).  Its
    first and second derivatives are assembled from the NLP's pieces' own (assembly.py), its
    loops over the intervals OpenMP-parallel when the compiler has OpenMP (threads: set_threads)."""
    opt = opt or os.environ.get("RSCASADI_NLP_OPT", "-O1")
    cc = compiler()
    omp = list(openmp_flags(tuple(cc)))
    # generating the C just to hash it takes seconds: an index keyed by the serialised NLP finds
    # a library built before (sweep tasks, repeated solves) without generating anything
    graph = ca.Function("nlp", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]]).serialize()
    index = cache_dir() / "lib" / ("index_" + hashlib.sha256((graph + solver + opt + repr(sorted(opts.items()))
                                                             + " ".join(cc + omp) + ca.__version__
                                                             + ASSEMBLY_VERSION).encode()).hexdigest()[:24])
    if index.exists() and Path(index.read_text()).exists():
        log(f"compiled NLP: cache hit {index.read_text()}")
        return index.read_text()
    libraries = sorted({piece.library for piece in pieces if piece.library})
    # the solver's own functions give the signatures; with kernels (no AD) from a stand-in NLP
    plain = ca.nlpsol("ocp", solver, nlp if not libraries else _stand_in(nlp, pieces), opts)
    # fatrop's library also has the unscattered derivatives its direct interface reads
    source = casadi_c(solver_functions(plain, nlp, pieces, "openmp" if omp else "serial", raw=solver == "fatrop"),
                      "rscasadi_nlp.c")
    link = [a for lib_ in libraries for a in (lib_, f"-Wl,-rpath,{Path(lib_).parent}")]
    lib = cached_library({"rscasadi_nlp.c": source}, [opt, *omp], link, name="nlp", what="the NLP", log=log, cc=cc)
    index.write_text(str(lib))
    return str(lib)


def _stand_in(nlp: dict, pieces: list) -> dict:
    """An NLP with the same variables, parameters, sizes and Jacobian pattern (fatrop checks its
    stage structure), and nothing to differentiate."""
    x, P, n_g = nlp["x"], nlp["p"], nlp["g"].numel()
    pattern = assembled(pieces, x, ca.MX.sym("lam_f"), ca.MX.sym("lam_g", n_g), n_g)["jac_g"].sparsity()
    return {"x": x, "p": P, "f": ca.sumsqr(x) + ca.sum1(P), "g": ca.densify(ca.mtimes(ca.DM(pattern, 1.0), x))}
