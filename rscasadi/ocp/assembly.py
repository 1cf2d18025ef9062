"""The NLP's derivatives assembled from its pieces' own, instead of CasADi's AD of the whole graph.

An optimal-control NLP is a sum of pieces of few variables each: a stage couples (x_k, u_k,
x_{k+1}), the start touches x_0, the end x_N.  Its constraint Jacobian is the pieces' Jacobians
placed at their rows and columns, its Lagrangian Hessian the sum of the pieces' Hessians (each
piece weighted by its own rows' multipliers):

    J = sum_i  E_rows(i) J_i E_cols(i)^T,     H = sum_i E_cols(i) H_i(lam_rows(i), lam_f) E_cols(i)^T.

Each J_i, H_i is an SX Jacobian/Hessian with numeric seeds (CasADi colours the piece and folds
the seeds into straight-line code); the placement is a gather of nonzeros (a sum where Hessian
blocks overlap).  Why: CasADi differentiates a *mapped* stage by directional derivatives with
symbolic seeds (fwd25_stage, fwd15_adj1_stage), which cannot simplify: at N = 100 (minimum
effort, Radau 3, one machine) nlp_jac_g takes 4.1 ms and nlp_hess_l 5.6 ms per call that way,
against 0.8 and 2.0 ms assembled; that way they would be half of a fatrop solve.

A piece whose model calls were recorded (Calls) is differentiated by the chain rule through them
instead: AD of the piece around the calls, and each call's own Jacobian and Hessian at its
arguments (chain_rule_derivatives; a stage's derivatives 2.4x fewer instructions).

`solver_functions` returns the functions a compiled solver loads by name (nlp_jac_g,
nlp_hess_l, nlp_grad_f ...), with CasADi's own signatures.
"""
from __future__ import annotations

import contextlib
import io
import sys
from dataclasses import dataclass

import casadi as ca
import numpy as np


@dataclass
class Piece:
    """`count` instances of fn(z, *args) -> (rows, f): z the piece's variables (global indices
    cols[k] in instance k), rows its constraints (global rows[k]), f its share of the objective;
    args its parameters (MX; matrices of `count` columns for per-instance values)."""
    fn: ca.Function
    cols: np.ndarray          # (count, nz)
    rows: np.ndarray          # (count, nr)
    args: list
    derivatives: tuple | None = None     # its own (first, objective, second); by AD of fn if None
    library: str | None = None           # the shared library of fn's C kernel (condensing.py), if any
    # where its functions are in `library` for a caller that evaluates the pieces itself
    # (ocp/fatrop/driver.c): the C symbols of "value" (rows, f), "first", "objective", "second"
    symbols: dict | None = None
    # and its parameters there: (offset in the NLP's parameter vector, length, step per instance;
    # a step < 0: the instance's index as a number)
    arg_places: list | None = None

    @property
    def count(self):
        return self.cols.shape[0]

    def call(self, fn: ca.Function, w: ca.MX, *extra, parallel: str = "serial"):
        """fn (mapped over the instances: "serial", or "openmp" for generated C) at the piece's
        variables of w and its parameters."""
        z = ca.reshape(w[self.cols.ravel().tolist()], self.cols.shape[1], self.count)
        f = fn if self.count == 1 else _mapped(fn, self.count, parallel)
        return f(z, *self.args, *extra)


def _mapped(fn: ca.Function, count: int, parallel: str) -> ca.Function:
    """fn.map(count, parallel), without the warning an "openmp" map gives in a CasADi built
    without OpenMP (its own evaluation is serial; the generated C has the parallel loop)."""
    if parallel == "serial":
        return fn.map(count, parallel)
    out = io.StringIO()                          # sys.stdout swapped: only while compiling (a lock)
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        f = fn.map(count, parallel)
    other = [line for line in out.getvalue().splitlines() if "WITH_OPENMP" not in line]
    if other:
        print("\n".join(other), file=sys.stderr)
    return f


def symbols(fn: ca.Function):
    """Symbols for fn's inputs: the piece's variables z and its parameters (MX for an external)."""
    S = ca.SX if fn.is_a("SXFunction") else ca.MX
    return S.sym("z", fn.size1_in(0)), [S.sym(fn.name_in(i), fn.sparsity_in(i)) for i in range(1, fn.n_in())]


def derivative_functions(piece: Piece):
    """The piece's (rows, J), (f, grad f) and (grad L, H) Functions, L = lam' rows + lam_f f: its
    own, or by AD of fn.  The objective apart, so that nlp_f and nlp_grad_f evaluate no dynamics."""
    if piece.derivatives is not None:
        return piece.derivatives
    fn = piece.fn
    z, args = symbols(fn)
    rows, f = fn(z, *args)
    lam, lam_f = ca.SX.sym("lam", rows.numel()), ca.SX.sym("lam_f")
    H, grad = ca.hessian(ca.dot(lam, rows) + lam_f * f, z)
    return (ca.Function(fn.name() + "_d1", [z, *args], [rows, ca.jacobian(rows, z)]),
            ca.Function(fn.name() + "_f1", [z, *args], [f, ca.gradient(f, z)]),
            ca.Function(fn.name() + "_d2", [z, *args, lam, lam_f], [grad, H]))


class Calls:
    """Records a piece's model calls as opaque nodes while it is built: each call's outputs
    become symbols F_j and its arguments y_j (expressions of the piece's inputs) are kept."""
    def __init__(self):
        self.items = []                 # (fn, sizes of its arguments, y_j, F_j)

    def __call__(self, fn: ca.Function, args: list) -> list:
        outs = [ca.SX.sym(f"F{len(self.items)}_{i}", fn.sparsity_out(i)) for i in range(fn.n_out())]
        args = [ca.vec(ca.SX(a)) for a in args]                    # SX or numbers (e.g. zero speeds)
        self.items.append((fn, tuple(a.numel() for a in args), ca.vertcat(*args), ca.vertcat(*outs)))
        return outs


def _call_derivatives(fn: ca.Function, sizes: tuple):
    """y -> (F, dF/dy) and (y, mu) -> d2(mu' F)/dy2 of one model Function on its stacked arguments."""
    y = ca.SX.sym("y", sum(sizes))
    F = ca.vertcat(*fn.call(ca.vertsplit(y, np.cumsum((0,) + sizes).tolist())))
    mu = ca.SX.sym("mu", F.numel())
    H, _ = ca.hessian(ca.dot(mu, F), y)
    return (ca.Function(fn.name() + "_value", [y], [F, ca.jacobian(F, y)], {"cse": True}),
            ca.Function(fn.name() + "_curvature", [y, mu], [H], {"cse": True}))


@dataclass
class SplitHessian:
    """A piece's Hessian with its model calls left as calls, for a C kernel that evaluates each
    model Function's compiled value and curvature once per call site (the same code for all,
    small enough to stay in the cache) instead of inlining them: per call site j, `sites[j]` =
    (index into `values`/`curvatures`, y's offset, F's offset, y's size, F's size, Fy's and C's
    offset in the flat nonzeros).  `y`: (z, *args) -> all y_j; `d1`: (z, *args, F, Fy) ->
    (rows, J); `mu`: (z, *args, lam, lam_f, F) -> all mu_j; `glue`: (z, *args, lam, lam_f, F,
    Fy, C) -> H, with F the values, Fy the Jacobians' and C the curvatures' nonzeros stacked."""
    y: ca.Function
    d1: ca.Function
    mu: ca.Function
    glue: ca.Function
    values: list
    curvatures: list
    sites: list


def chain_rule_derivatives(fn: ca.Function, z, args, rows, f, calls: Calls, split: bool = False):
    """fn's (rows, J), (f, grad f) and (grad L, H) by the chain rule through its recorded calls
    F_j = fn_j(y_j(z)): with D_j = dF_j/dy T_j, T_j = dy_j/dz, W = [1; D], mu_j = dL/dF_j,

        J = dr/dz + sum_j dr/dF_j D_j,
        H = W' d2L/d(z, F)2 W + sum_j T_j' d2(mu_j' F_j)/dy2 T_j + d2(sum_j g_j' y_j)/dz2,

    g_j = (dF_j/dy)' mu_j held constant in the last term (zero where y_j is linear in z, i.e. at a
    fixed step).  Why: a Radau stage's Hessian by AD of the inlined stage took 34 792 SX
    instructions (n = 3, minimum effort), through the three forward-dynamics Hessians (51
    nonzeros each on 15 arguments) 14 701.  split: also the SplitHessian."""
    lam, lam_f = ca.SX.sym("lam", rows.numel()), ca.SX.sym("lam_f")
    L = ca.dot(lam, rows) + lam_f * f
    F = ca.vertcat(*[item[3] for item in calls.items])
    keys, fns, sites, D, curvature, g_sym, g_val, mus, Fy_syms, C_syms = [], [], [], [], 0, [], [], [], [], []
    offsets = np.zeros(4, int)                          # y, F, Fy, C
    for fn_j, sizes, y, Fj in calls.items:
        key = (fn_j.name(), sizes)
        if key not in keys:                             # one per model Function of this piece, not per call
            keys.append(key)
            fns.append(_call_derivatives(fn_j, sizes))
        value, curv = fns[keys.index(key)]
        Fy = ca.SX.sym("Fy", value.sparsity_out(1))     # the call's Jacobian and curvature, symbols
        C = ca.SX.sym("C", curv.sparsity_out(0))
        sites.append((keys.index(key), *offsets[:2], y.numel(), Fj.numel(), *offsets[2:]))
        offsets += [y.numel(), Fj.numel(), Fy.nnz(), C.nnz()]
        T = ca.jacobian(y, z)
        D.append(ca.mtimes(Fy, T))
        mu = ca.gradient(L, Fj)
        mus.append(mu)
        Fy_syms.append(Fy)
        C_syms.append(C)
        curvature += ca.mtimes([T.T, C, T])
        g_sym.append(ca.SX.sym("g", y.numel()))
        g_val.append(ca.densify(ca.mtimes(Fy.T, mu)))
    D = ca.vertcat(*D)
    W = ca.vertcat(ca.SX.eye(z.numel()), D)
    H0, _ = ca.hessian(L, ca.vertcat(z, F))
    Hy, _ = ca.hessian(sum(ca.dot(gs, item[2]) for gs, item in zip(g_sym, calls.items)), z)
    H = ca.mtimes([W.T, H0, W]) + curvature + ca.substitute(Hy, ca.vertcat(*g_sym), ca.vertcat(*g_val))
    J = ca.jacobian(rows, z) + ca.mtimes(ca.jacobian(rows, F), D)
    grad = ca.gradient(L, z) + ca.mtimes(D.T, ca.gradient(L, F))
    grad_f = ca.gradient(f, z) + ca.mtimes(D.T, ca.gradient(f, F))
    # the calls' symbols replaced by the calls (inlined), then their values
    called = [fns[keys.index((item[0].name(), item[1]))] for item in calls.items]
    evaluated = [value(item[2]) for (value, _), item in zip(called, calls.items)]          # (F, dF/dy)
    Fys = [Fy for _, Fy in evaluated]
    Cs = [curv(item[2], mu) for (_, curv), item, mu in zip(called, calls.items, mus)]
    Fvs = ca.vertcat(*[Fv for Fv, _ in evaluated])
    symbols, exprs = Fy_syms + C_syms, Fys + Cs
    out = ca.substitute(ca.substitute([rows, J, f, grad_f, grad, H], symbols, exprs), [F], [Fvs])
    name, opts = fn.name(), {"cse": True}
    derivatives = (ca.Function(name + "_d1", [z, *args], out[:2], opts),
                   ca.Function(name + "_f1", [z, *args], out[2:4], opts),
                   ca.Function(name + "_d2", [z, *args, lam, lam_f], out[4:], opts))
    if not split:
        return derivatives
    flat = lambda ms: ca.vertcat(*[ca.vec(m.nz[:]) if m.nnz() else ca.SX(0, 1) for m in ms]) if ms else ca.SX(0, 1)
    Fy_all, C_all = ca.SX.sym("Fy", int(offsets[2])), ca.SX.sym("C", int(offsets[3]))
    H_flat, rows_flat, J_flat = ca.substitute([H, rows, J], [ca.vertcat(flat(Fy_syms), flat(C_syms))],
                                              [ca.vertcat(Fy_all, C_all)])
    return derivatives + (SplitHessian(
        ca.Function(name + "_y", [z, *args], [ca.vertcat(*[item[2] for item in calls.items])], opts),
        ca.Function(name + "_d1", [z, *args, F, Fy_all], [rows_flat, J_flat], opts),
        ca.Function(name + "_mu", [z, *args, lam, lam_f, F], [ca.vertcat(*mus)], opts),
        ca.Function(name + "_glue", [z, *args, lam, lam_f, F, Fy_all, C_all], [H_flat], opts),
        [value for value, _ in fns], [curv for _, curv in fns], sites),)


def _placement(sp: ca.Sparsity, rows: np.ndarray, cols: np.ndarray):
    """Global (row, col) of every nonzero of every instance of a local pattern sp."""
    r, c = (np.array(v, dtype=np.int64) for v in sp.get_triplet())
    R, C = rows[:, r], cols[:, c]                      # (count, nnz) each, instance-major
    return R.ravel(), C.ravel()


def _in_column(index: np.ndarray):
    """Places of the entries of a column vector: rows `index`, column 0."""
    return index.ravel(), np.zeros(index.size, dtype=np.int64)


def _scatter(values: list, places: list, shape) -> ca.MX:
    """A sparse MX of `shape` from nonzero vectors and their global places (duplicates summed)."""
    R = np.concatenate([p[0] for p in places])
    C = np.concatenate([p[1] for p in places])
    src = ca.vertcat(*values)
    key = C * shape[0] + R                             # column-major order, as CasADi stores
    uniq, inv = np.unique(key, return_inverse=True)
    sp = ca.Sparsity.triplet(shape[0], shape[1], (uniq % shape[0]).tolist(), (uniq // shape[0]).tolist())
    if len(uniq) == len(key):                          # a permutation: a gather
        order = np.empty(len(key), dtype=np.int64)
        order[inv] = np.arange(len(key))
        return ca.MX(sp, src[order.tolist()])
    # overlapping blocks: each place's first source gathered, the few others added (a sparse
    # product over every source had cost 2 % of a condensed fatrop solve)
    first = np.full(len(uniq), -1, dtype=np.int64)
    first[inv[::-1]] = np.arange(len(key))[::-1]       # the lowest source index of each place
    extra = np.setdiff1d(np.arange(len(key)), first)
    S = ca.DM(ca.Sparsity.triplet(len(uniq), len(extra), inv[extra].tolist(), list(range(len(extra)))), 1.0)
    return ca.MX(sp, src[first.tolist()] + ca.mtimes(S, src[extra.tolist()]))


def _nz(m: ca.MX) -> ca.MX:
    """m's nonzeros as a column (a reinterpretation, no copy in the generated C)."""
    return ca.sparsity_cast(m, ca.Sparsity.dense(m.nnz(), 1)) if m.nnz() else ca.MX(0, 1)


def constraints_and_objective(pieces: list, w: ca.MX, n_g: int, parallel: str = "serial"):
    """g (in its global row order) and f of the NLP made of the pieces."""
    rows, places, f = [], [], 0
    for piece in pieces:
        z, args = symbols(piece.fn)
        r, fi = piece.fn(z, *args)
        name = piece.fn.name()               # rows and objective apart: f evaluates no dynamics
        rows.append(ca.vec(piece.call(ca.Function(name + "_rows", [z, *args], [r]), w, parallel=parallel)))
        places.append(_in_column(piece.rows))
        f += ca.sum2(piece.call(ca.Function(name + "_f", [z, *args], [fi]), w, parallel=parallel))
    return ca.densify(_scatter(rows, places, (n_g, 1))), f


def places(pieces: list) -> tuple:
    """The global (rows, cols) of each piece's Jacobian and Hessian nonzeros, in the order its
    mapped derivative functions output them (instance-major)."""
    jac, hess = [], []
    for piece in pieces:
        first, _, second = derivative_functions(piece)
        jac.append(_placement(first.sparsity_out(1), piece.rows, piece.cols))
        hess.append(_placement(second.sparsity_out(1), piece.cols, piece.cols))
    return jac, hess


def assembled(pieces: list, w: ca.MX, lam_f: ca.MX, lam_g: ca.MX, n_g: int, parallel: str = "serial") -> dict:
    """grad f, J, grad L, H and triu(H) of the NLP made of the pieces, as MX of w (and of the
    parameters the pieces take); "jac_parts", "hess_parts": each piece's nonzeros as its map
    outputs them (places(pieces) says where they go)."""
    n_w = w.numel()
    Jp, Hp = places(pieces)
    J, gf, gl, gp, H, U, Up = ([] for _ in range(7))
    for piece, (R, C) in zip(pieces, Hp):
        first, objective, second = derivative_functions(piece)
        _, Ji = piece.call(first, w, parallel=parallel)
        _, gfi = piece.call(objective, w, parallel=parallel)
        lam = ca.reshape(lam_g[piece.rows.ravel().tolist()], piece.rows.shape[1], piece.count)
        gli, Hi = piece.call(second, w, lam, lam_f, parallel=parallel)
        J.append(_nz(Ji))
        gf.append(ca.vec(gfi))
        gl.append(ca.vec(gli))
        gp.append(_in_column(piece.cols))
        upper = np.flatnonzero(R <= C)                 # each symmetric pair once, on the upper side
        H.append(_nz(Hi))
        U.append(H[-1][upper.tolist()] if len(upper) else ca.MX(0, 1))
        Up.append((R[upper], C[upper]))
    dense = lambda parts, places: ca.densify(_scatter(parts, places, (n_w, 1)))
    return {"grad_f": dense(gf, gp), "jac_g": _scatter(J, Jp, (n_g, n_w)), "grad_l": dense(gl, gp),
            "hess": _scatter(H, Hp, (n_w, n_w)), "triu_hess": _scatter(U, Up, (n_w, n_w)),
            "jac_parts": J, "hess_parts": H}


ASSEMBLY_VERSION = "assembled-6"        # part of the compiled-NLP cache key
NAMES = ("nlp_f", "nlp_g", "nlp_grad_f", "nlp_jac_g", "nlp_hess_l", "nlp_grad")
# the same derivatives unscattered, for a caller that places them itself (ocp/fatrop/driver.c): each
# piece's nonzeros as its map writes them, one output per piece (their places: places(pieces))
RAW_NAMES = ("raw_jac_g", "raw_hess_l")


def solver_functions(plain: ca.Function, nlp: dict, pieces: list, parallel: str = "serial", raw: bool = False) -> list:
    """The functions the compiled solver `plain` loads by name, with its signatures; g, f and
    the first and second derivatives assembled from the pieces, their maps over the intervals
    `parallel` (nlp_grad, called once for the parameter multipliers, as CasADi makes it); with
    `raw`, RAW_NAMES too: (x, p) -> (J_1, ..., J_m) and (x, p, lam_f, lam_g) -> (grad L, H_1,
    ..., H_m); g apart, its caller has it from the same point ("nlp" gives f and g).  Why: at
    N = 100 the scatter copied the Jacobian's 46 840 nonzeros five times, serially, in every
    call (6 of a 63 ms fatrop solve)."""
    w, P, n_g = nlp["x"], nlp["p"], nlp["g"].numel()
    lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", n_g)
    a = assembled(pieces, w, lam_f, lam_g, n_g, parallel)
    g, f = constraints_and_objective(pieces, w, n_g, parallel)
    expr = {"f": f, "g": g, "grad_f_x": a["grad_f"], "jac_g_x": a["jac_g"],
            "grad_gamma_x": a["grad_l"], "hess_gamma_x_x": a["hess"], "triu_hess_gamma_x_x": a["triu_hess"]}
    sym = {"x": w, "p": P, "lam_f": lam_f, "lam_g": lam_g}
    out = [ca.Function("nlp", [w, P], [f, g], ["x", "p"], ["f", "g"])]
    if raw:
        out += [ca.Function("raw_jac_g", [w, P], a["jac_parts"]),
                ca.Function("raw_hess_l", [w, P, lam_f, lam_g], [a["grad_l"], *a["hess_parts"]])]
    for name in NAMES:
        try:
            ref = plain.get_function(name)
        except RuntimeError:
            continue                                   # e.g. no Hessian with limited-memory
        if name == "nlp_grad" or not all(o in expr for o in ref.name_out()):
            out.append(ref)
            continue
        out.append(ca.Function(name, [sym[i] for i in ref.name_in()], [expr[o] for o in ref.name_out()],
                               ref.name_in(), ref.name_out()))
    return out
