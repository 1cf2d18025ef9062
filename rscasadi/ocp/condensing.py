"""Condensing: each interval's collocation equations solved inside the NLP's functions, so that
the solver sees only (x_k, tau_k, x_{k+1}) per stage, as in multiple shooting with a Radau step.

A lifted stage piece has variables z = (kept w, eliminated y) (y: the accelerations at the
collocation points) and rows (G, R): G(y; w) = 0 the collocation (dynamics) equations, square in
y, R the gap-closing and limit rows.  Condensed, y = y(w) by Newton's method and

    S = dy/dw = -G_y^{-1} G_w,   Z = dz/dw = [I; S],
    R_c(w) = R(w, y(w)),         dR_c/dw = dR/dz Z,            grad f_c = Z' grad f,
    nu = -G_y^{-T} (R_y' lam + lam_f f_y),   H_c = Z' d2(lam' R + nu' G + lam_f f)/dz2 Z,

(the implicit-function theorem; with nu so chosen the Lagrangian is stationary in y and the
curvature of y(w) drops out).  The calculus (the lifted piece's own chain-rule derivatives,
its model calls and task terms of the link angles evaluated once per call site) is CasADi SX
generated to C, composed with Z in C loops; the Newton loop, the 2nm x 2nm LU with partial
pivoting and a per-interval cache live in a small C kernel (`_KERNEL`): the solver evaluates
g, its Jacobian and the Hessian at the same point, and the cache (keyed on the exact inputs)
solves the collocation equations once per point, warm-started from the last solution of the
same interval.  Why: fatrop on the lifted NLP spends most of its time eliminating the 2nm
collocation equations in its generic dense algebra (0.13 of a 0.22 s solve, problem (b));
condensed it spends 0.027 s.

The kernel's functions follow CasADi's external-function convention, so they enter the NLP's MX
graph as `casadi.external` Functions (mapped over the intervals, the interval index an argument)
and the assembly (assembly.py) places their Jacobians and Hessians like any piece's.
"""
from __future__ import annotations

import ctypes
import hashlib
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from rscasadi.native.build import cached_library, casadi_units, compiler, indexed, native_flags, nlp_opt

NEWTON_MAX_ITER = 50
NEWTON_STEP_TOL = 1e-10         # relative: after such a step Newton's error is ~1e-20
SPURIOUS = 1e3                  # a warm-started root with a scaled acceleration beyond this is a
                                # spurious one (collocation's G(y) = 0 has roots with huge
                                # accelerations): solved again from y = 0


@dataclass
class Condensed:
    """The condensed piece's external Functions (fn: (w, *args, k) -> (R_c, f); first, objective,
    second as Piece.derivatives) and the shared library that holds them."""
    fn: ca.Function
    derivatives: tuple
    library: str
    newton: ca.Function         # (w, *args, k) -> y, the eliminated variables (for tests, output)
    prefix: str

    def reset(self):
        """Forget the kernel's cached solutions (this thread's): the next solve starts afresh."""
        getattr(ctypes.CDLL(self.library), self.prefix + "reset")()


def _dense_cols(sp: ca.Sparsity, rows, cols) -> list:
    """The columns among `cols` (positions in it) that have a nonzero in one of `rows`."""
    r, c = (np.array(v) for v in sp.get_triplet())
    hit = set(c[np.isin(r, rows)].tolist())
    return [i for i, j in enumerate(cols) if j in hit]


def _sx_functions(prefix: str, d1: ca.Function, f1: ca.Function, d2: ca.Function, split, keep, elim, grows):
    """The SX functions the kernel calls (their C is generated): lin, rows, first, objective,
    adjoint, the Hessian's y, mu and glue, and each model Function's value and curvature
    (module docstring for the formulas; split: assembly.SplitHessian)."""
    nz, nrows = d1.size1_in(0), d1.size1_out(0)
    z = ca.SX.sym("z", nz)
    args = [ca.SX.sym(d1.name_in(i), d1.sparsity_in(i)) for i in range(1, d1.n_in())]
    rows, J = d1(z, *args)
    f, gf = f1(z, *args)
    rk = [i for i in range(nrows) if i not in set(grows)]
    scols = _dense_cols(d1.sparsity_out(1), grows, keep)              # kept columns G depends on
    ny, ns, nk = len(elim), len(scols), len(keep)
    S = ca.SX.sym("S", ny, ns)
    Z = ca.SX(nz, nk)
    for i, j in enumerate(keep):
        Z[j, i] = 1
    for s, i in enumerate(scols):
        Z[elim, i] = S[:, s]
    lam, lam_f, lam_r = ca.SX.sym("lam", nrows), ca.SX.sym("lam_f"), ca.SX.sym("lam_r", len(rk))
    dcols = _curved(d2.sparsity_out(1), keep, scols)
    kd = [keep[i] for i in dcols]
    J_r = J[rk, :]
    opts = {"cse": True}
    F, Fy = (ca.SX.sym(split.d1.name_in(i), split.d1.sparsity_in(i)) for i in (len(args) + 1, len(args) + 2))
    rows_s, J_s = split.d1(z, *args, F, Fy)                 # the call sites' values and Jacobians given
    fns = {
        "lin": ca.Function(prefix + "lin", [z, *args, F, Fy],
                           [ca.densify(rows_s[grows]), ca.densify(J_s[grows, elim]),
                            ca.densify(J_s[grows, [keep[i] for i in scols]])], opts),
        "residual": ca.Function(prefix + "residual", [z, *args], [ca.densify(rows[grows])], opts),
        "rows": ca.Function(prefix + "rows", [z, *args], [rows[rk], f], opts),
        # the rows' Jacobian on the kept and the eliminated variables, the call sites given: the
        # kernel forms J_K + J_E S on the condensed pattern in sparse loops (as one SX product with
        # S symbolic it was 101k instructions, the kernel's largest function, on the Panda's shelf)
        "jac": ca.Function(prefix + "jac", [z, *args, F, Fy], [rows_s[rk], J_s[rk, keep], J_s[rk, elim]], opts),
        "objective": ca.Function(prefix + "objective", [z, *args, S], [f, ca.mtimes(Z.T, gf)], opts),
        # the gradient of lam' R + lam_f f on all of z: its y part is the adjoint equation's
        # right-hand side, its kept part (plus G_w' nu, in C) the condensed Lagrangian's gradient
        "adjoint": ca.Function(prefix + "adjoint", [z, *args, lam_r, lam_f],
                               [ca.densify(ca.mtimes(J_r.T, lam_r) + lam_f * gf)], opts),
    }
    # the lifted Hessian's blocks on the curved kept columns D and y alone (the gradient comes
    # from the adjoint); the kernel evaluates the model calls' compiled value and curvature at
    # each call site (at n = 7 one inlined copy per site made 134k instructions, 44 us; the
    # shared 27k-instruction curvature runs in 4.5 us) and forms Z' H Z in dense loops
    fns.update(_split_functions(prefix, split, z, args, lam, lam_f, kd, elim, opts))
    return fns, rk, scols, dcols, args


def _split_functions(prefix, split, z, args, lam, lam_f, kd, elim, opts) -> dict:
    """The split Hessian's Functions under the kernel's prefix: y, mu, glue (H's blocks on D and
    y) and value_k, curvature_k of each model Function k."""
    sym = lambda f, i: ca.SX.sym(f.name_in(i), f.sparsity_in(i))
    F, Fy, C = (sym(split.glue, i) for i in range(split.glue.n_in() - 3, split.glue.n_in()))
    H = split.glue(z, *args, lam, lam_f, F, Fy, C)
    out = {"y": ca.Function(prefix + "y", [z, *args], [split.y(z, *args)], opts),
           "mu": ca.Function(prefix + "mu", [z, *args, lam, lam_f, F], [split.mu(z, *args, lam, lam_f, F)], opts),
           "glue": ca.Function(prefix + "glue", [z, *args, lam, lam_f, F, Fy, C],
                               [ca.densify(H[kd, kd]), ca.densify(H[elim, kd]), ca.densify(H[elim, elim])], opts)}
    for k, (value, curv) in enumerate(zip(split.values, split.curvatures)):
        y, mu = sym(curv, 0), sym(curv, 1)
        out[f"value{k}"] = ca.Function(prefix + f"value{k}", [y], value(y), opts)
        out[f"curvature{k}"] = ca.Function(prefix + f"curvature{k}", [y, mu], [curv(y, mu)], opts)
    return out


def _sites_c(split) -> str:
    """C that evaluates every call site's model Function: values and Jacobians, then curvatures."""
    lines = ["static int site_values(const casadi_real* Y, casadi_real* F, casadi_real* Fy) {\n"]
    for k, y0, f0, ny, nf, fy0, c0 in split.sites:
        lines.append(f"  if (raw(P(value{k}), Y + {y0}, 0, F + {f0}, Fy + {fy0})) return 1;\n")
    lines.append("  return 0;\n}\n\nstatic int site_curvatures(const casadi_real* Y, const casadi_real* MU, "
                 "casadi_real* C) {\n")
    for k, y0, f0, ny, nf, fy0, c0 in split.sites:
        lines.append(f"  if (raw(P(curvature{k}), Y + {y0}, MU + {f0}, C + {c0}, 0)) return 1;\n")
    lines.append("  return 0;\n}\n")
    return "".join(lines)


def _curved(sp: ca.Sparsity, keep, scols) -> list:
    """D: the kept columns (positions in keep) where the condensed Hessian can be nonzero, those
    the lifted Hessian touches and those y depends on (scols)."""
    touched = set(np.array(sp.get_triplet()[1]).tolist())
    return sorted({i for i, j in enumerate(keep) if j in touched} | set(scols))


def _condensed_pattern(sp_H: ca.Sparsity, keep, elim, scols) -> ca.Sparsity:
    """The structural pattern of Z' H Z, Z = [I; S~] (S dense on the columns scols): no entry
    where the condensed Hessian is zero for every S (fatrop refuses a pattern coupling stages,
    e.g. x_k with x_{k+1} when only x_{k+1} is curved)."""
    nz, nk = sp_H.size1(), len(keep)
    rows = list(keep) + [e for _ in scols for e in elim]
    cols = list(range(nk)) + [c for c in scols for _ in elim]
    Z = ca.DM(ca.Sparsity.triplet(nz, nk, rows, cols), 1.0)
    return ca.mtimes([Z.T, ca.DM(sp_H, 1.0), Z]).sparsity()         # all entries positive: no cancellation


def _condensed_jacobian_pattern(jk: ca.Sparsity, je: ca.Sparsity, scols) -> ca.Sparsity:
    """The pattern of J_K + J_E S~ (S~ dense on the kept columns scols): J_K's, and every row of
    J_E with a nonzero in each column of scols."""
    rows = set(np.array(je.get_triplet()[0]).tolist())
    r, c = (np.array(v).tolist() for v in jk.get_triplet())
    extra = [(i, j) for i in sorted(rows) for j in scols]
    return ca.Sparsity.triplet(jk.size1(), jk.size2(), r + [i for i, _ in extra], c + [j for _, j in extra])


def _by_rows(sp: ca.Sparsity) -> list:
    """C arrays of a pattern's nonzeros row by row: JE_START (rows + 1), and per entry its place
    among the nonzeros (JE_ORDER) and its column (JE_OCOL)."""
    r, c = (np.array(v, dtype=int) for v in sp.get_triplet())
    order = np.argsort(r, kind="stable")
    start = np.concatenate([[0], np.cumsum(np.bincount(r, minlength=sp.size1()))])
    return [_int_array("JE_START", start), _int_array("JE_ORDER", order), _int_array("JE_OCOL", c[order])]


def _sparsity_c(name: str, sp: ca.Sparsity) -> str:
    return f"static const casadi_int {name}[] = {{{', '.join(str(v) for v in sp.compress())}}};\n"


def _int_array(name: str, values) -> str:
    return f"static const int {name}[] = {{{', '.join(str(int(v)) for v in values) or '0'}}};\n"


def _kernel_source(prefix, fns, keep, elim, rk, grows, args, scols, dcols, split, sp_H) -> str:
    """The C kernel: cache, Newton, LU, and the four external functions (module docstring)."""
    nk, ny, ns, nr, nrows = len(keep), len(elim), fns["lin"].size2_out(2), len(rk), fns["glue"].size1_in(len(args) + 1)
    nyall = fns["y"].nnz_out(0)
    nfall, nfy, nc = (fns["glue"].nnz_in(len(args) + 3 + i) for i in range(3))
    assert fns["adjoint"].size1_out(0) == fns["lin"].size1_in(0)
    na = len(args)
    arg_nnz = [a.nnz() for a in args]
    sz = {k: max(getattr(f, "sz_" + k)() for f in fns.values()) for k in ("arg", "res", "iw", "w")}
    hc = _condensed_pattern(sp_H, keep, elim, scols)                  # the Hessian's nonzeros, by position in D
    jk, je = fns["jac"].sparsity_out(1), fns["jac"].sparsity_out(2)
    jp = _condensed_jacobian_pattern(jk, je, scols)                   # J_K + J_E S~'s nonzeros
    hr, hcol = (np.array(v).tolist() for v in hc.get_triplet())
    lines = [f"/* condensed collocation kernel {prefix} (rscasadi/ocp/condensing.py) */\n",
             "#include <math.h>\n#include <stdlib.h>\n#include <string.h>\n",
             _declarations(fns),
             f"#define NK {nk}\n#define NY {ny}\n#define NS {ns}\n#define NR {nr}\n#define NROWS {nrows}\n"
             f"#define NZ {fns['lin'].size1_in(0)}\n#define ND {len(dcols)}\n#define NA {na}\n"
             f"#define NYALL {max(nyall, 1)}\n#define NFALL {max(nfall, 1)}\n#define NFY {max(nfy, 1)}\n#define NC {max(nc, 1)}\n#define NKEY {nk + sum(arg_nnz)}\n"
             f"#define SZ_ARG {sz['arg']}\n#define SZ_RES {sz['res']}\n#define SZ_IW {sz['iw'] + 1}\n#define SZ_W {sz['w'] + 1}\n"
             f"#define MAXIT {NEWTON_MAX_ITER}\n#define STEPTOL {NEWTON_STEP_TOL!r}\n#define SPURIOUS {SPURIOUS!r}\n"
             f"#define P(name) {prefix}##name\n",
             _int_array("KEEP", keep), _int_array("ELIM", elim), _int_array("RKEEP", rk), _int_array("GROWS", grows),
             _int_array("ARGNNZ", arg_nnz), _int_array("SCOLS", scols),
             _int_array("DS", [scols.index(i) if i in scols else -1 for i in dcols]),
             f"#define NJK {max(jk.nnz(), 1)}\n#define NJE {max(je.nnz(), 1)}\n#define NJP {jp.nnz()}\n"
             f"#define JK_NNZ {jk.nnz()}\n#define JE_NNZ {je.nnz()}\n",
             *_by_rows(je),
             *[_int_array(name, v) for name, v in zip(("JK_ROW", "JK_COL", "JP_ROW", "JP_COL"),
                                                      (*jk.get_triplet(), *jp.get_triplet()))],
             f"#define NHC {hc.nnz()}\n", _int_array("HROW", [dcols.index(i) for i in hr]),
             _int_array("HCOL", [dcols.index(j) for j in hcol]),
             _KERNEL_HEAD, _sites_c(split), _KERNEL]
    # sparsity of the externals' inputs and outputs
    sp_w = ca.Sparsity.dense(nk, 1)
    ins = [sp_w, *[a.sparsity() for a in args], ca.Sparsity.dense(1, 1)]
    outs = {"ext_rows": [fns["rows"].sparsity_out(0), fns["rows"].sparsity_out(1)],
            "ext_first": [fns["jac"].sparsity_out(0), jp],
            "ext_objective": [fns["objective"].sparsity_out(0), fns["objective"].sparsity_out(1)],
            "ext_second": [ca.Sparsity.dense(nk, 1), hc],
            "ext_newton": [ca.Sparsity.dense(ny, 1)]}
    extra = {"ext_second": [ca.Sparsity.dense(nr, 1), ca.Sparsity.dense(1, 1)]}
    for name, out in outs.items():
        inputs = ins + extra.get(name, [])
        for i, sp in enumerate(inputs):
            lines.append(_sparsity_c(f"{name}_in{i}", sp))
        for i, sp in enumerate(out):
            lines.append(_sparsity_c(f"{name}_out{i}", sp))
        lines.append(f"""
CASADI_SYMBOL_EXPORT casadi_int P({name}_n_in)(void) {{ return {len(inputs)}; }}
CASADI_SYMBOL_EXPORT casadi_int P({name}_n_out)(void) {{ return {len(out)}; }}
CASADI_SYMBOL_EXPORT const casadi_int* P({name}_sparsity_in)(casadi_int i) {{
  switch (i) {{ {' '.join(f'case {i}: return {name}_in{i};' for i in range(len(inputs)))} default: return 0; }} }}
CASADI_SYMBOL_EXPORT const casadi_int* P({name}_sparsity_out)(casadi_int i) {{
  switch (i) {{ {' '.join(f'case {i}: return {name}_out{i};' for i in range(len(out)))} default: return 0; }} }}
CASADI_SYMBOL_EXPORT int P({name}_work)(casadi_int* sz_arg, casadi_int* sz_res, casadi_int* sz_iw, casadi_int* sz_w) {{
  if (sz_arg) *sz_arg = {len(inputs)};
  if (sz_res) *sz_res = {len(out)};
  if (sz_iw) *sz_iw = 0;
  if (sz_w) *sz_w = 0;
  return 0;
}}
""")
    return "".join(lines)


KERNEL_C = (Path(__file__).with_name("templates") / "condensing_kernel.c").read_text().split("*/", 1)[1]
_KERNEL_HEAD, _KERNEL = KERNEL_C.split("@SITES@\n")


def _fingerprint(*parts) -> str:
    return hashlib.sha256("\n".join(str(p) for p in parts).encode()).hexdigest()[:12]


def condense(d1: ca.Function, f1: ca.Function, d2: ca.Function, split, keep, elim, grows, log=print,
             opt: str | None = None) -> Condensed:
    """The condensed piece of a lifted one given by its (rows, J), (f, grad f), (grad L, H)
    Functions and its split Hessian (assembly.SplitHessian): `keep` and `elim` index its
    variables, `grows` the rows G solved for y.  The kernel is generated, compiled (cached by the
    hash of its source) and loaded."""
    keep, elim, grows = (list(map(int, v)) for v in (keep, elim, grows))
    prefix = "rsc" + _fingerprint(d1.serialize(), f1.serialize(), d2.serialize(), keep, elim, grows,
                                  NEWTON_MAX_ITER, NEWTON_STEP_TOL, SPURIOUS) + "_"
    fns, rk, scols, dcols, args = _sx_functions(prefix, d1, f1, d2, split, keep, elim, grows)
    library = _compiled(prefix, fns, _kernel_source(prefix, fns, keep, elim, rk, grows, args, scols, dcols, split,
                                                    d2.sparsity_out(1)), log, opt)
    return loaded(library, prefix)


def loaded(library: str, prefix: str) -> Condensed:
    """The kernel in `library` under `prefix`, as external Functions."""
    ext = {name: ca.external(prefix + "ext_" + name, library) for name in ("rows", "first", "objective", "second", "newton")}
    return Condensed(ext["rows"], (ext["first"], ext["objective"], ext["second"]), library, ext["newton"], prefix)


# what generates a kernel: a change to any of these files is a new kernel
_GENERATOR = "".join(Path(__file__).with_name(name).read_text() for name in ("condensing.py", "assembly.py", "transcription.py"))
_GENERATOR += KERNEL_C
_KERNELS: dict[str, Condensed] = {}


def cached_kernel(stage_key: str, build, log=print) -> Condensed:
    """The condensed kernel of the stage piece whose serialisation hashes to `stage_key`: this
    process's, the cache's (indexed by that key, the generator's source and the build flags:
    no derivatives built, no C generated), or `build()`'s.  A refinement round or a new process
    on the same task then sets up in milliseconds (the Panda's obstacle task: 13 s of symbolic
    derivatives and 6 s of generated C otherwise)."""
    opt = nlp_opt()
    key = "\n".join([stage_key, hashlib.sha256(_GENERATOR.encode()).hexdigest(), ca.__version__, *compiler(), opt,
                     *native_flags(), str(NEWTON_MAX_ITER), repr(NEWTON_STEP_TOL), repr(SPURIOUS)])
    if key not in _KERNELS:
        def fresh():
            kernel = build()
            return [kernel.library, kernel.prefix]
        (library, prefix), _ = indexed(key, fresh)
        while len(_KERNELS) >= 4:
            _KERNELS.pop(next(iter(_KERNELS)))
        _KERNELS[key] = loaded(library, prefix)
    return _KERNELS[key]


def _declarations(fns: dict) -> str:
    """What the kernel's unit needs of CasADi's: its types and the SX functions' prototypes (their
    C is in units of their own, native.build.casadi_units)."""
    return ("#ifndef casadi_real\n#define casadi_real double\n#endif\n"
            "#ifndef casadi_int\n#define casadi_int long long int\n#endif\n"
            "#ifndef CASADI_SYMBOL_EXPORT\n#define CASADI_SYMBOL_EXPORT\n#endif\n"
            + "".join(f"int {f.name()}(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, "
                      f"int mem);\n" for f in fns.values()))


UNITS = 4     # CasADi's functions in this many C files, compiled in parallel (a 10 MB file at -O1 took
              # 75 s on 2 cores as one unit)


def _compiled(prefix: str, fns: dict, kernel: str, log, opt: str | None) -> str:
    """The kernel's library, for this processor, at `opt` or native.build.nlp_opt's level."""
    units = casadi_units(list(fns.values()), f"{prefix}part", UNITS) | {f"{prefix}kernel.c": kernel}
    size = sum(len(text) for text in units.values())
    return str(cached_library(units, [opt or nlp_opt(size), *native_flags()], name="kernel", log=log,
                              what=f"the condensing kernel ({size // 1000} kB of C in {len(units)} units; once per "
                                   "problem shape)"))
