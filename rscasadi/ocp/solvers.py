"""The NLP solvers: fatrop (exploits the stage structure; a Riccati-based interior point) or
IPOPT (general sparse, MUMPS), on the NLP's functions generated to C and compiled once
(cached by the hash of the source), or in CasADi's virtual machine.

Compiled, the NLP is made of each piece's functions (a stage's rows, objective and their
derivatives, or its condensing kernel; the start's and the end's), which do not depend on the
mesh, each compiled once into its own library cached by its own hash.  fatrop's direct driver
evaluates the pieces itself, stage by stage (ocp/fatrop/driver.c): a refinement round or another
number of intervals compiles nothing.  IPOPT and CasADi's fatrop plugin take a library of the
whole NLP, the pieces' maps over the intervals and the placement of their nonzeros (its glue,
compiled per number of intervals: arm3's minimum-time NLP, lifted, 1.2-3.3 s a round)."""
from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import casadi as ca

from rscasadi.files import sources_digest
from rscasadi.native import build
from rscasadi.native.build import cached_library, casadi_c, casadi_units, compiler, indexed, nlp_level, nlp_opt
from rscasadi.native.parallel import openmp_flags
from rscasadi.ocp.fatrop.driver import DirectFatrop, NativePieces
from rscasadi.ocp.assembly import ASSEMBLY_VERSION, Piece, assembled, derivative_functions, places, solver_functions, symbols
from rscasadi.ocp.problem import Problem
from rscasadi.ocp.transcription import Transcription


def options(problem: Problem, tr: Transcription, print_level: int, extra: dict | None = None) -> dict:
    """Solver options: tolerances alike for both, so that their times compare."""
    extra = extra or {}
    if problem.solver.name == "fatrop":
        return {**tr.structure(), "print_time": False, "expand": False,
                "fatrop": {"print_level": (10 if print_level > 5 else 5) if print_level else 0, "tol": 1e-8, "max_iter": 1000,
                           # condensed, a smaller first barrier: min time 33-37 iterations instead of
                           # 40-53 (N = 50-200), min effort 18-20 instead of 19-22; lifted: no gain.
                           # Around obstacles smaller still: the barrier of thousands of clearance
                           # rows drove T from 1 s to 3.6-4.5 s before it came down (the Panda's
                           # shelf task: 55-58 iterations at 3e-6-3e-5 against 250-309 at 1e-2;
                           # reach_around 51-68 against 143)
                           "mu_init": (1e-5 if problem.task.obstacles else 1e-2) if tr.condensed else 1e-1, **extra}}
    return {"print_time": False, "ipopt.print_level": print_level, "ipopt.sb": "yes", "ipopt.max_iter": 1000,
            "ipopt.tol": 1e-8, "ipopt.mu_strategy": "adaptive",
            "ipopt.mumps_pivot_order": 0,          # AMD: min-time N = 100 in 1.8 s instead of 4.5 s here
            "ipopt.hessian_approximation": problem.solver.hessian, **{f"ipopt.{k}": v for k, v in extra.items()}}


def make_solver(problem: Problem, tr: Transcription, nlp: dict, log=print, print_level: int = 5,
                extra: dict | None = None):
    """(solver, objective(x, p) Function) for this problem's NLP."""
    opts = options(problem, tr, print_level, extra)
    objective = ca.Function("f", [nlp["x"], nlp["p"]], [nlp["f"]])
    if not problem.transcription.compiled and not tr.condensed:      # condensed: its kernel is C anyway
        return ca.nlpsol("ocp", problem.solver.name, nlp, opts), objective
    # the compiled pieces have no AD: the parameters' multipliers (by AD) are not asked for
    opts["calc_lam_p"] = False
    if direct(problem):                # the driver evaluates the compiled pieces: nothing compiled per mesh
        pieces = [piece if piece.library else compiled_piece(piece, nlp_opt(), log) for piece in tr.pieces]
        native = NativePieces(pieces, nlp["x"].numel(), nlp["g"].numel(), nlp["p"].numel())
        return DirectFatrop(None, tr.structure(), opts["fatrop"], log, places(pieces), native), objective
    library = compiled_nlp(problem.solver.name, nlp, opts, tr.pieces, log)
    return ca.nlpsol("ocp", problem.solver.name, library, opts), objective


def direct(problem: Problem) -> bool:
    """fatrop through its own C interface (ocp/fatrop/driver.py): on the compiled NLP, unless asked otherwise."""
    return problem.solver.name == "fatrop" and problem.solver.interface == "direct" and problem.transcription.compiled


def compiled_nlp(solver: str, nlp: dict, opts: dict, pieces: list, log=print, opt: str | None = None) -> str:
    """The shared library of the NLP's functions for `solver`, compiled once and cached; at
    native.build.nlp_opt's level by default (RSCASADI_NLP_OPT, e.g. -O2, for the fastest solves
    at a longer compile).  Its
    first and second derivatives are assembled from the NLP's pieces' own (assembly.py), its
    loops over the intervals OpenMP-parallel when the compiler has OpenMP (threads: set_threads)."""
    opt = opt or nlp_opt()
    cc = compiler()
    omp = list(openmp_flags(tuple(cc)))
    # generating the C just to hash it takes seconds: the index keyed by the serialised NLP finds
    # a library built before (sweep tasks, repeated solves) without generating anything
    graph = ca.Function("nlp", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]]).serialize()
    key = graph + solver + opt + repr(sorted(opts.items())) + " ".join(cc + omp) + ca.__version__ + ASSEMBLY_VERSION

    def build():
        compiled = [piece if piece.library else compiled_piece(piece, opt, log) for piece in pieces]
        libraries = sorted({piece.library for piece in compiled if piece.library})
        # the solver's own functions give the signatures, from a stand-in NLP (the pieces: no AD)
        plain = ca.nlpsol("ocp", solver, _stand_in(nlp, compiled), opts)
        # fatrop's library also has the unscattered derivatives its direct interface reads
        source = casadi_c(solver_functions(plain, nlp, compiled, "openmp" if omp else "serial", raw=solver == "fatrop"),
                          "rscasadi_nlp.c")
        link = [a for lib_ in libraries for a in (lib_, f"-Wl,-rpath,{Path(lib_).parent}")]
        return [cached_library({"rscasadi_nlp.c": source}, [nlp_level(opt, len(source)), *omp], link, name="nlp",
                               what="the NLP", log=log, cc=cc)]
    (lib,), found = indexed(key, build)
    if found:
        log(f"compiled NLP: cache hit {lib}")
    return lib


def _stand_in(nlp: dict, pieces: list) -> dict:
    """An NLP with the same variables, parameters, sizes and Jacobian pattern (fatrop checks its
    stage structure), and nothing to differentiate."""
    x, P, n_g = nlp["x"], nlp["p"], nlp["g"].numel()
    pattern = assembled(pieces, x, ca.MX.sym("lam_f"), ca.MX.sym("lam_g", n_g), n_g)["jac_g"].sparsity()
    return {"x": x, "p": P, "f": ca.sumsqr(x) + ca.sum1(P), "g": ca.densify(ca.mtimes(ca.DM(pattern, 1.0), x))}


# what generates a piece's library: a change to either file is a new library
_PIECE_GENERATOR = sources_digest(__file__, build.__file__)

# the compiled pieces of this process, with the functions they stand for (a refinement round's
# stage has the same Function objects: transcription._DERIVATIVES); kept, so their ids stay theirs
_PIECES: dict[tuple, tuple] = {}


def compiled_piece(piece: Piece, opt: str, log=print) -> Piece:
    """The piece with its functions (rows, objective, and their first and second derivatives)
    compiled into a library of their own, cached by its hash and named by the functions' (so that
    pieces of any mesh link side by side), and loaded as `casadi.external`s; `opt` "auto": by
    the size of their C (native.build.nlp_opt)."""
    originals = (piece.fn, *derivative_functions(piece))
    key = tuple(id(f) for f in originals)
    if key in _PIECES and all(a is b for a, b in zip(_PIECES[key][0], originals)):
        kept = _PIECES[key][1]
        return dataclasses.replace(piece, fn=kept.fn, derivatives=kept.derivatives, library=kept.library,
                                   symbols=kept.symbols)
    z, args = symbols(piece.fn)
    r, f = piece.fn(z, *args)
    fns = {"rows": ca.Function("rows", [z, *args], [r]), "f": ca.Function("f", [z, *args], [f]),
           "value": ca.Function("value", [z, *args], [r, f]),
           "first": originals[1], "objective": originals[2], "second": originals[3]}
    prefix = "rsp" + hashlib.sha256("".join(fn.serialize() for fn in fns.values()).encode()).hexdigest()[:16] + "_"
    # indexed by the functions' serialisation: a new process finds the library without generating
    # its C to hash it (0.25 s for the Panda's pieces)
    index_key = "\n".join(["piece", prefix, opt, *compiler(), ca.__version__, _PIECE_GENERATOR])

    def build():
        units = casadi_units([_renamed(fn, prefix + k) for k, fn in fns.items()], prefix, units=4)
        return [cached_library(units, [nlp_level(opt, sum(map(len, units.values())))], name="piece",
                               what=f"the {piece.fn.name()}'s functions (for any mesh)",
                               log=log)]
    (lib, *_), _ = indexed(index_key, build)
    ext = {k: ca.external(prefix + k, lib) for k in fns}
    zm, am = symbols(ext["rows"])
    fn = ca.Function(piece.fn.name(), [zm, *am], [ext["rows"](zm, *am), ext["f"](zm, *am)],
                     piece.fn.name_in(), piece.fn.name_out())
    out = dataclasses.replace(piece, fn=fn, derivatives=(ext["first"], ext["objective"], ext["second"]), library=lib,
                              symbols={k: prefix + k for k in ("value", "first", "objective", "second")})
    _PIECES[key] = (originals, out)
    while len(_PIECES) > 16:
        _PIECES.pop(next(iter(_PIECES)))
    return out


def _renamed(fn: ca.Function, name: str) -> ca.Function:
    """fn (SX) under another name: the same expressions."""
    sym = fn.sx_in()
    return ca.Function(name, sym, fn.call(sym), fn.name_in(), fn.name_out())
