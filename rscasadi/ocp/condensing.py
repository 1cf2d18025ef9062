"""Condensing: each interval's collocation equations solved inside the NLP's functions, so that
the solver sees only (x_k, tau_k, x_{k+1}) per stage, as in multiple shooting with a Radau step.

A lifted stage piece has variables z = (kept w, eliminated y) (y: the accelerations at the
collocation points) and rows (G, R): G(y; w) = 0 the collocation (dynamics) equations, square in
y, R the gap-closing and limit rows.  Condensed, y = y(w) by Newton's method and

    S = dy/dw = -G_y^{-1} G_w,   Z = dz/dw = [I; S],
    R_c(w) = R(w, y(w)),         dR_c/dw = dR/dz Z,            grad f_c = Z' grad f,
    nu = -G_y^{-T} (R_y' lam + lam_f f_y),   H_c = Z' d2(lam' R + nu' G + lam_f f)/dz2 Z,

(the implicit-function theorem; with nu so chosen the Lagrangian is stationary in y and the
curvature of y(w) drops out).  The calculus (the lifted piece's own chain-rule derivatives
composed with Z) is CasADi SX generated to C; the Newton loop, the 2nm x 2nm LU with partial
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
import os
from dataclasses import dataclass

import casadi as ca
import numpy as np

from rscasadi.native.build import cached_library, casadi_c, native_flags

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
        "first": ca.Function(prefix + "first", [z, *args, S], [rows[rk], ca.mtimes(J_r, Z)], opts),
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
    hr, hcol = (np.array(v).tolist() for v in hc.get_triplet())
    lines = [f"/* condensed collocation kernel {prefix} (rscasadi/ocp/condensing.py) */\n",
             "#include <stdlib.h>\n#include <string.h>\n",
             f"#define NK {nk}\n#define NY {ny}\n#define NS {ns}\n#define NR {nr}\n#define NROWS {nrows}\n"
             f"#define NZ {fns['lin'].size1_in(0)}\n#define ND {len(dcols)}\n#define NA {na}\n"
             f"#define NYALL {max(nyall, 1)}\n#define NFALL {max(nfall, 1)}\n#define NFY {max(nfy, 1)}\n#define NC {max(nc, 1)}\n#define NKEY {nk + sum(arg_nnz)}\n"
             f"#define SZ_ARG {sz['arg']}\n#define SZ_RES {sz['res']}\n#define SZ_IW {sz['iw'] + 1}\n#define SZ_W {sz['w'] + 1}\n"
             f"#define MAXIT {NEWTON_MAX_ITER}\n#define STEPTOL {NEWTON_STEP_TOL!r}\n#define SPURIOUS {SPURIOUS!r}\n"
             f"#define P(name) {prefix}##name\n",
             _int_array("KEEP", keep), _int_array("ELIM", elim), _int_array("RKEEP", rk), _int_array("GROWS", grows),
             _int_array("ARGNNZ", arg_nnz), _int_array("SCOLS", scols),
             _int_array("DS", [scols.index(i) if i in scols else -1 for i in dcols]),
             f"#define NHC {hc.nnz()}\n", _int_array("HROW", [dcols.index(i) for i in hr]),
             _int_array("HCOL", [dcols.index(j) for j in hcol]),
             _KERNEL_HEAD, _sites_c(split), _KERNEL]
    # sparsity of the externals' inputs and outputs
    sp_w = ca.Sparsity.dense(nk, 1)
    ins = [sp_w, *[a.sparsity() for a in args], ca.Sparsity.dense(1, 1)]
    outs = {"ext_rows": [fns["rows"].sparsity_out(0), fns["rows"].sparsity_out(1)],
            "ext_first": [fns["first"].sparsity_out(0), fns["first"].sparsity_out(1)],
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
  if (sz_arg) *sz_arg = {len(inputs)}; if (sz_res) *sz_res = {len(out)}; if (sz_iw) *sz_iw = 0; if (sz_w) *sz_w = 0; return 0; }}
""")
    return "".join(lines)


_KERNEL_HEAD = r"""
/* Per thread: the SX functions' work arrays and, per interval, the last solution.  Nothing in
   the result depends on the cache beyond Newton's tolerance: it only chooses the starting point
   and skips the solve when the inputs are bitwise those of the last call. */
/* the dense loops vectorised even when the generated SX code around them is built at -O1
   (its size makes -O2 cost minutes) */
#if defined(__GNUC__) && !defined(__clang__)
#define DENSE __attribute__((optimize("O3")))
#else
#define DENSE
#endif
typedef struct { long generation; int seen, valid, factored, derived; casadi_real key[NKEY]; casadi_real y[NY];
                 casadi_real lu[NY * NY]; int piv[NY]; casadi_real S[NY * NS], Gs[NY * NS];
                 casadi_real Y[NYALL], F[NFALL], Fy[NFY]; } entry_t;     /* the call sites at the last linearisation */
static long generation = 1;            /* reset() starts a new one: every thread's entries go stale */
static __thread entry_t* cache = 0;
static __thread long cache_size = 0;
static __thread const casadi_real* w_arg[SZ_ARG];
static __thread casadi_real* w_res[SZ_RES];
static __thread casadi_int w_iw[SZ_IW];
static __thread casadi_real w_w[SZ_W];
static __thread casadi_real zf[NZ];

static entry_t* entry(long k) {
  if (k < 0) return 0;
  if (k >= cache_size) {
    long size = k + 1 > 2 * cache_size ? k + 1 : 2 * cache_size;
    entry_t* grown = (entry_t*)realloc(cache, (size_t)size * sizeof(entry_t));
    if (!grown) return 0;
    memset(grown + cache_size, 0, (size_t)(size - cache_size) * sizeof(entry_t));
    cache = grown;
    cache_size = size;
  }
  return cache + k;
}

/* LU with partial pivoting of the dense column-major n x n matrix a, in place. */
DENSE static int lu_factor(casadi_real* a, int* piv, int n) {
  int i, j, k;
  for (k = 0; k < n; ++k) {
    int p = k;
    casadi_real big = fabs(a[k + k * n]);
    for (i = k + 1; i < n; ++i) if (fabs(a[i + k * n]) > big) { big = fabs(a[i + k * n]); p = i; }
    if (!(big > 0)) return 1;
    piv[k] = p;
    if (p != k) for (j = 0; j < n; ++j) { casadi_real t = a[k + j * n]; a[k + j * n] = a[p + j * n]; a[p + j * n] = t; }
    for (i = k + 1; i < n; ++i) a[i + k * n] /= a[k + k * n];
    for (j = k + 1; j < n; ++j) {
      casadi_real akj = a[k + j * n];
      if (akj != 0) for (i = k + 1; i < n; ++i) a[i + j * n] -= a[i + k * n] * akj;
    }
  }
  return 0;
}

/* x := A^{-1} x (trans = 0) or A^{-T} x (trans = 1) with the factors of lu_factor. */
DENSE static void lu_solve(const casadi_real* a, const int* piv, int n, casadi_real* x, int trans) {
  int i, j;
  if (!trans) {
    for (i = 0; i < n; ++i) if (piv[i] != i) { casadi_real t = x[i]; x[i] = x[piv[i]]; x[piv[i]] = t; }
    for (j = 0; j < n; ++j) for (i = j + 1; i < n; ++i) x[i] -= a[i + j * n] * x[j];
    for (j = n - 1; j >= 0; --j) { x[j] /= a[j + j * n]; for (i = 0; i < j; ++i) x[i] -= a[i + j * n] * x[j]; }
  } else {
    for (j = 0; j < n; ++j) { for (i = 0; i < j; ++i) x[j] -= a[i + j * n] * x[i]; x[j] /= a[j + j * n]; }
    for (j = n - 1; j >= 0; --j) for (i = j + 1; i < n; ++i) x[j] -= a[i + j * n] * x[i];
    for (i = n - 1; i >= 0; --i) if (piv[i] != i) { casadi_real t = x[i]; x[i] = x[piv[i]]; x[piv[i]] = t; }
  }
}

/* S := -G_y^{-1} Gs (NY x NS, column-major) with the factors of lu_factor: rows of a row-major
   copy updated as vectors (the NS right-hand sides at once) */
DENSE static void sensitivities(const casadi_real* a, const int* piv, const casadi_real* Gs, casadi_real* S) {
  casadi_real T[NY][NS], t;
  int i, j, c;
  for (i = 0; i < NY; ++i) for (c = 0; c < NS; ++c) T[i][c] = -Gs[i + c * NY];
  for (i = 0; i < NY; ++i) if (piv[i] != i) for (c = 0; c < NS; ++c) { t = T[i][c]; T[i][c] = T[piv[i]][c]; T[piv[i]][c] = t; }
  for (j = 0; j < NY; ++j) for (i = j + 1; i < NY; ++i) {
    casadi_real l = a[i + j * NY];
    if (l != 0) for (c = 0; c < NS; ++c) T[i][c] -= l * T[j][c];
  }
  for (j = NY - 1; j >= 0; --j) {
    casadi_real d = 1 / a[j + j * NY];
    for (c = 0; c < NS; ++c) T[j][c] *= d;
    for (i = 0; i < j; ++i) {
      casadi_real u = a[i + j * NY];
      if (u != 0) for (c = 0; c < NS; ++c) T[i][c] -= u * T[j][c];
    }
  }
  for (i = 0; i < NY; ++i) for (c = 0; c < NS; ++c) S[i + c * NY] = T[i][c];
}

/* the full variables z from the kept w and the entry's y */
static void full_z(const casadi_real* w, const casadi_real* y) {
  int i;
  for (i = 0; i < NK; ++i) zf[KEEP[i]] = w ? w[i] : 0;
  for (i = 0; i < NY; ++i) zf[ELIM[i]] = y[i];
}

/* call an SX function: z, the piece's arguments, then `extra` inputs */
static int call(int (*f)(const casadi_real**, casadi_real**, casadi_int*, casadi_real*, int),
                const casadi_real** args, const casadi_real** extra, int n_extra, casadi_real** res, int n_res) {
  int i;
  w_arg[0] = zf;
  for (i = 0; i < NA; ++i) w_arg[1 + i] = args[i];
  for (i = 0; i < n_extra; ++i) w_arg[1 + NA + i] = extra[i];
  for (i = 0; i < SZ_RES; ++i) w_res[i] = i < n_res ? res[i] : 0;          /* outputs not asked for: none */
  return f(w_arg, w_res, w_iw, w_w, 0);
}

/* call a model Function (value or curvature at a call site): two inputs, two outputs */
static int raw(int (*f)(const casadi_real**, casadi_real**, casadi_int*, casadi_real*, int),
               const casadi_real* a0, const casadi_real* a1, casadi_real* r0, casadi_real* r1) {
  int i;
  for (i = 0; i < SZ_RES; ++i) w_res[i] = 0;
  w_arg[0] = a0; w_arg[1] = a1; w_res[0] = r0; w_res[1] = r1;
  return f(w_arg, w_res, w_iw, w_w, 0);
}
"""

_KERNEL = r"""
/* the key of a call: the kept variables and the piece's arguments, bitwise */
static void make_key(casadi_real* key, const casadi_real* w, const casadi_real** args) {
  int i, j, off = NK;
  for (i = 0; i < NK; ++i) key[i] = w ? w[i] : 0;
  for (j = 0; j < NA; ++j) { for (i = 0; i < ARGNNZ[j]; ++i) key[off + i] = args[j] ? args[j][i] : 0; off += ARGNNZ[j]; }
}

/* G_y (factored into e->lu) and G_w at (w, e->y); G the residual there */
static int linearise(entry_t* e, const casadi_real* w, const casadi_real** args, casadi_real* G, casadi_real* Gs) {
  const casadi_real* extra[2];
  casadi_real* out[3];
  full_z(w, e->y);
  out[0] = e->Y;                                 /* the call sites' values and Jacobians, kept */
  if (call(P(y), args, 0, 0, out, 1) || site_values(e->Y, e->F, e->Fy)) return 1;
  extra[0] = e->F; extra[1] = e->Fy;
  out[0] = G; out[1] = e->lu; out[2] = Gs;
  if (call(P(lin), args, extra, 2, out, 3)) return 1;
  e->factored = 1;
  return lu_factor(e->lu, e->piv, NY);
}

/* Newton from e->y: steps with the last factors of G_y (a chord method: each step one residual,
   no Jacobian), linearised afresh when there are none or the steps stop shrinking fast; 0 when
   converged */
static int newton(entry_t* e, const casadi_real* w, const casadi_real** args) {
  casadi_real G[NY], Gs[NY * NS];
  casadi_real* out[1];
  casadi_real last = 0;
  int i, it, fresh = 0;
  out[0] = G;
  for (it = 0; it < MAXIT; ++it) {
    casadi_real step = 0, size = 0;
    if (!e->factored || fresh) {
      if (linearise(e, w, args, G, Gs)) { e->factored = 0; return 1; }
      fresh = 0;
    } else {
      full_z(w, e->y);
      if (call(P(residual), args, 0, 0, out, 1)) return 1;
    }
    lu_solve(e->lu, e->piv, NY, G, 0);
    for (i = 0; i < NY; ++i) {
      if (!(fabs(G[i]) < 1e300)) return 1;                          /* not finite */
      e->y[i] -= G[i];
      step = fabs(G[i]) > step ? fabs(G[i]) : step;
      size = fabs(e->y[i]) > size ? fabs(e->y[i]) : size;
    }
    if (step <= STEPTOL * (1 + size)) return 0;
    if (it > 0 && step > 0.25 * last) fresh = 1;                      /* slow contraction: new factors */
    last = step;
  }
  return 1;
}

/* Whether a root has a scaled acceleration no motion within the limits could have. */
static int spurious(const entry_t* e) {
  int i;
  for (i = 0; i < NY; ++i) if (fabs(e->y[i]) > SPURIOUS) return 1;
  return 0;
}

/* The entry of interval k with y solved from G(y; w) = 0 at (w, args), or 0 if Newton failed.
   Start: the last solution moved along its sensitivity S (first order in the change of w); if
   Newton fails from there (a far jump of w), once more from y = 0 with fresh factors. */
static entry_t* solved(const casadi_real* w, const casadi_real** args, long k) {
  casadi_real key[NKEY], dw[NS];
  int i, j, cold;
  entry_t* e = entry(k);
  if (!e) return 0;
  if (e->generation != __atomic_load_n(&generation, __ATOMIC_RELAXED)) {
    e->generation = __atomic_load_n(&generation, __ATOMIC_RELAXED);
    e->seen = e->valid = e->factored = e->derived = 0;
  }
  make_key(key, w, args);
  if (e->valid && !memcmp(key, e->key, sizeof key)) return e;
  cold = !e->seen;
  if (cold) { memset(e->y, 0, sizeof e->y); e->seen = 1; e->factored = 0; }
  else if (e->derived) {                                              /* y += S dw */
    for (j = 0; j < NS; ++j) dw[j] = (w ? w[SCOLS[j]] : 0) - e->key[SCOLS[j]];
    for (j = 0; j < NS; ++j) for (i = 0; i < NY; ++i) e->y[i] += e->S[i + j * NY] * dw[j];
  }
  e->valid = e->derived = 0;
  if (newton(e, w, args) || (!cold && spurious(e))) {              /* from y = 0, with fresh factors */
    memset(e->y, 0, sizeof e->y);
    e->factored = 0;
    if (cold || newton(e, w, args)) { e->seen = 0; return 0; }
  }
  memcpy(e->key, key, sizeof key);
  e->valid = 1;
  return e;
}

/* ... and with G_y factored and S = -G_y^{-1} G_w at that y (for the derivatives) */
static entry_t* derived(const casadi_real* w, const casadi_real** args, long k) {
  casadi_real G[NY];
  entry_t* e = solved(w, args, k);
  if (!e || e->derived) return e;
  if (linearise(e, w, args, G, e->Gs)) return 0;
  sensitivities(e->lu, e->piv, e->Gs, e->S);
  e->derived = 1;
  return e;
}

/* forget every thread's solutions: the next solve starts from scratch, its results independent
   of earlier solves in the process */
CASADI_SYMBOL_EXPORT void P(reset)(void) { __atomic_add_fetch(&generation, 1, __ATOMIC_RELAXED); }

#define EXTERNAL(name) CASADI_SYMBOL_EXPORT int P(name)(const casadi_real** arg, casadi_real** res, \
                                                             casadi_int* iw, casadi_real* w, int mem)
static long index_of(const casadi_real** arg) { return arg[1 + NA] ? (long)arg[1 + NA][0] : 0; }

EXTERNAL(ext_newton) {
  entry_t* e = solved(arg[0], arg + 1, index_of(arg));
  if (!e) return 1;
  if (res[0]) memcpy(res[0], e->y, sizeof e->y);
  return 0;
}

EXTERNAL(ext_rows) {
  entry_t* e = solved(arg[0], arg + 1, index_of(arg));
  if (!e) return 1;
  full_z(arg[0], e->y);
  return call(P(rows), arg + 1, 0, 0, res, 2);
}

/* an SX function of (z, args, S) at the solved and derived entry of this call */
static int with_sensitivities(int (*f)(const casadi_real**, casadi_real**, casadi_int*, casadi_real*, int),
                              const casadi_real** arg, casadi_real** res) {
  const casadi_real* extra[1];
  entry_t* e = derived(arg[0], arg + 1, index_of(arg));
  if (!e) return 1;
  full_z(arg[0], e->y);
  extra[0] = e->S;
  return call(f, arg + 1, extra, 1, res, 2);
}

EXTERNAL(ext_first) { return with_sensitivities(P(first), arg, res); }

EXTERNAL(ext_objective) { return with_sensitivities(P(objective), arg, res); }

/* the lifted Hessian's blocks at a derived entry: the multipliers mu of the call sites' outputs,
   their curvatures (the sites' values and Jacobians are the entry's), then the glue
   (assembly.SplitHessian) */
static int split_hessian(const entry_t* e, const casadi_real** args, const casadi_real** lam, casadi_real* Hdd,
                         casadi_real* Hyd, casadi_real* Hyy) {
  static __thread casadi_real MU[NFALL], C[NC];
  const casadi_real* extra[5];
  casadi_real* out[3];
  extra[0] = lam[0]; extra[1] = lam[1]; extra[2] = e->F; extra[3] = e->Fy; extra[4] = C;
  out[0] = MU;
  if (call(P(mu), args, extra, 3, out, 1) || site_curvatures(e->Y, MU, C)) return 1;
  out[0] = Hdd; out[1] = Hyd; out[2] = Hyy;
  return call(P(glue), args, extra, 5, out, 3);
}

/* Hc = H_DD + M + M' on the curved columns D, M = S~' (H_YY S~ / 2 + H_YD): Z' H Z with Z = [I; S~],
   S~ = S on D (zero where y does not depend on the column); dense loops, the inner one over
   independent outputs (they vectorise without reassociation) */
DENSE static void condensed_hessian(const casadi_real* Hdd, const casadi_real* Hyd, const casadi_real* Hyy,
                              const casadi_real* S, casadi_real* Hc) {
  static __thread casadi_real V[NY * ND], St[ND * NY], M[ND * ND];
  int i, j, a, b, k;
  for (b = 0; b < ND; ++b) {                                   /* V = H_YY S~ / 2 + H_YD */
    casadi_real* v = V + b * NY;
    for (i = 0; i < NY; ++i) v[i] = Hyd[i + b * NY];
    if (DS[b] < 0) continue;
    for (j = 0; j < NY; ++j) {
      casadi_real s = 0.5 * S[j + DS[b] * NY];
      for (i = 0; i < NY; ++i) v[i] += Hyy[i + j * NY] * s;
    }
  }
  for (i = 0; i < NY; ++i) for (a = 0; a < ND; ++a) St[a + i * ND] = DS[a] < 0 ? 0 : S[i + DS[a] * NY];
  memset(M, 0, sizeof M);                                      /* M = S~' V */
  for (b = 0; b < ND; ++b) for (i = 0; i < NY; ++i) {
    casadi_real v = V[i + b * NY];
    for (a = 0; a < ND; ++a) M[a + b * ND] += St[a + i * ND] * v;
  }
  for (k = 0; k < NHC; ++k) {                                   /* the pattern's entries, in order */
    a = HROW[k]; b = HCOL[k];
    Hc[k] = (a <= b ? Hdd[a + b * ND] : Hdd[b + a * ND]) + M[a + b * ND] + M[b + a * ND];
  }
}

/* the Hessian of lam' R + lam_f f: nu from the adjoint equation, then Z' H(lam, nu) Z */
EXTERNAL(ext_second) {
  static __thread casadi_real Hdd[ND * ND], Hyd[NY * ND], Hyy[NY * NY];
  casadi_real g[NZ], nu[NY], lam[NROWS], zero = 0;
  const casadi_real* extra[3];
  casadi_real* out[3];
  int i, j;
  entry_t* e = derived(arg[0], arg + 1, index_of(arg));
  if (!e) return 1;
  full_z(arg[0], e->y);
  extra[0] = arg[2 + NA];
  extra[1] = arg[3 + NA] ? arg[3 + NA] : &zero;
  out[0] = g;
  if (call(P(adjoint), arg + 1, extra, 2, out, 1)) return 1;
  for (i = 0; i < NY; ++i) nu[i] = -g[ELIM[i]];
  lu_solve(e->lu, e->piv, NY, nu, 1);                        /* nu = -G_y^-T (R_y' lam + lam_f f_y) */
  if (res[0]) {                                              /* grad_w L = its kept part + G_w' nu */
    for (i = 0; i < NK; ++i) res[0][i] = g[KEEP[i]];
    for (j = 0; j < NS; ++j) for (i = 0; i < NY; ++i) res[0][SCOLS[j]] += e->Gs[i + j * NY] * nu[i];
  }
  if (!res[1]) return 0;
  for (i = 0; i < NR; ++i) lam[RKEEP[i]] = arg[2 + NA] ? arg[2 + NA][i] : 0;
  for (i = 0; i < NY; ++i) lam[GROWS[i]] = nu[i];
  extra[0] = lam;
  if (split_hessian(e, arg + 1, extra, Hdd, Hyd, Hyy)) return 1;
  condensed_hessian(Hdd, Hyd, Hyy, e->S, res[1]);
  return 0;
}
"""


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
    ext = {name: ca.external(prefix + "ext_" + name, library) for name in ("rows", "first", "objective", "second", "newton")}
    return Condensed(ext["rows"], (ext["first"], ext["objective"], ext["second"]), library, ext["newton"], prefix)


def _compiled(prefix: str, fns: dict, kernel: str, log, opt: str | None) -> str:
    """The kernel's library: at -O1 unless RSCASADI_NLP_OPT says otherwise, for this processor."""
    opt = opt or os.environ.get("RSCASADI_NLP_OPT", "-O1")
    name = prefix + "kernel.c"
    source = casadi_c(fns.values(), name) + kernel
    return str(cached_library({name: source}, [opt, *native_flags()], name="kernel", log=log,
                              what=f"the condensing kernel ({len(source) // 1000} kB of C; once per problem shape)"))
