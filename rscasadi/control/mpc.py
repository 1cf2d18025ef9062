"""Nonlinear MPC on the complete model, generated to C (`rscasadi mpc PROBLEM.toml --out DIR`).

Multiple shooting on the complete model: a state plan X (4n x N+1, at the ends of N intervals of
length h) and a torque plan U (n x N, held on each interval); each interval is `substeps` RK4
steps of `step`, its sensitivities from the structured `step_jacobian` (codegen.generate).
Gauss-Newton SQP: the QP of each iteration is condensed onto dU (Bock & Plitt; the gaps of the
shooting nodes enter its affine part); its motor-torque box is solved by a fixed number of
primal-dual interior-point iterations (`box_qp`: no data-dependent loops, no allocation). `sqp_iterations = 1` is
the real-time iteration (Diehl et al.: one full step per sample); more iterations take the
longest of a fixed set of step sizes whose simulated rollout lowers the cost (else the shortest),
so the work per sample is bounded. After the iterations the plan is shifted by one sample.

Cost (per interval end k = 1..N): w_theta |theta_k - theta_ref_k|^2 + w_dtheta |dtheta_k -
dtheta_ref_k|^2 + w_tau |tau_k|^2, and a penalty w_limits (|c| - 0.9 c_max)^2 on the SEA
deflection psi and the slow-side speed dphi beyond 90 % of their limits (Gauss-Newton on the
part active at the linearisation point); the motor torques are hard bounds.

Problem file and C interface: docs/model.md section 6 (`problems/mpc_arm3.toml` is an example).

Generated (DIR): `mpc_rti.c` (CasADi: mpc_rti(x, reference, X, U) -> tau, X_next, U_next and
mpc_hold(x) -> X, U), `rscasadi_mpc.c` and `rscasadi_mpc.h` (the controller: static
buffers, `mpc_init(x_measured)`, `mpc_step(x_measured, reference, tau_out)` for a trajectory,
`mpc_step_to(x_measured, theta_target, tau_out)` for a target pose), `librscasadi_mpc.so`,
`manifest.json`.  reference is 2n x N, column-major: theta_ref then dtheta_ref at t + k h.
"""
from __future__ import annotations

import functools
import re
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from ..dynamics.arm import Arm, load
from ..model.modelfile import field_checker, read_toml

TOP = {"model", "trajectory", "sample_time", "horizon", "interval", "substeps", "sqp_iterations", "qp_iterations",
       "weights"}
WEIGHTS = {"theta": 1e5, "dtheta": 1.0, "tau": 1e-3, "limits": 1e5}
SOFT = 0.9                   # penalties start at this fraction of the psi and dphi limits
LINE_SEARCH = (1.0, 0.5, 0.25, 0.125)   # step sizes tried when sqp_iterations > 1


@dataclass
class MPCProblem:
    path: Path
    model_path: Path
    trajectory: Path | None = None
    sample_time: float = 1e-3
    horizon: int = 10
    interval: float = 0.01
    substeps: int = 5
    sqp_iterations: int = 1
    qp_iterations: int = 16
    weights: dict = field(default_factory=lambda: dict(WEIGHTS))


def load_mpc_problem(path) -> MPCProblem:
    path = Path(path)
    d = read_toml(path, "MPC problem")

    fail = field_checker(path, d, TOP)
    if not isinstance(d.get("model"), str):
        fail("model", "missing, or not the path of a model file")
    p = MPCProblem(path, (path.parent / d["model"]).resolve())
    if "trajectory" in d:
        if not isinstance(d["trajectory"], str):
            fail("trajectory", "expected the path of a trajectory file")
        p.trajectory = (path.parent / d["trajectory"]).resolve()
    for key in ("sample_time", "interval"):
        v = d.get(key, getattr(p, key))
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v <= 0:
            fail(key, f"must be a positive number, got {v!r}")
        setattr(p, key, float(v))
    for key, lo in (("horizon", 1), ("substeps", 1), ("sqp_iterations", 1), ("qp_iterations", 1)):
        v = d.get(key, getattr(p, key))
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            fail(key, f"must be an integer >= {lo}, got {v!r}")
        setattr(p, key, v)
    w = d.get("weights", {})
    if not isinstance(w, dict):
        fail("weights", "expected a table")
    for key, v in w.items():
        if key not in WEIGHTS:
            fail(f"weights.{key}", f"unknown weight (allowed: {', '.join(WEIGHTS)})")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
            fail(f"weights.{key}", f"must be a number >= 0, got {v!r}")
        p.weights[key] = float(v)
    return p


def interval_functions(arm: Arm, h: float, substeps: int):
    """F: (x, tau) -> (x after h, A = dx/dx0, B = dx/dtau): `substeps` RK4 steps and their
    structured Jacobians chained (A = A_s ... A_1, B = A_s (...) B_1 + ... + B_s); Fx: the state alone.
    One substep (step, Jacobian and the chain's products) is one Function, straight-line SX when
    the step Jacobian is SX (small arms), called `substeps` times: its C is generated once, so
    the controller compiles in a fifth of the time of one straight-line interval, as fast."""
    from ..codegen.generate import step_functions
    n, hs = arm.n, h / substeps
    step, step_jac = step_functions(arm)
    sym = ca.SX if step_jac.is_a("SXFunction") else ca.MX
    if sym is ca.SX:
        step = step.expand()
    z, tau, A, B = sym.sym("x", 4 * n), sym.sym("tau", n), sym.sym("A", 4 * n, 4 * n), sym.sym("B", 4 * n, n)
    Ai, Bi = step_jac(z, tau, hs)
    opts = {"cse": True} if sym is ca.SX else {}
    substep = ca.Function("substep", [z, tau, A, B], [step(z, tau, hs), ca.mtimes(Ai, A), ca.mtimes(Ai, B) + Bi], opts)
    substep_x = ca.Function("substep_x", [z, tau], [step(z, tau, hs)], opts)
    x, u = ca.MX.sym("x", 4 * n), ca.MX.sym("tau", n)
    zk, Ak, Bk, z_only = x, ca.MX.eye(4 * n), ca.MX.zeros(4 * n, n), x
    for _ in range(substeps):
        zk, Ak, Bk = substep(zk, u, Ak, Bk)
        z_only = substep_x(z_only, u)
    return ca.Function("interval", [x, u], [zk, Ak, Bk]), ca.Function("interval_x", [x, u], [z_only])


def limit_arrays(arm: Arm) -> dict:
    """The motor-torque, deflection and slow-side speed limits per joint (inf where none)."""
    return {key: np.array([jt.limits.get(key, 1e3 if key == "tau" else np.inf) for jt in arm.model.joints])
            for key in ("tau", "psi", "dphi")}


def stage_residual(n: int, p: MPCProblem, limits: dict) -> ca.Function:
    """(x_k, reference_k) -> (r, dr/dx): the weighted residual whose half squared norm is the stage
    cost: tracking errors, and the psi and dphi excess beyond 90 % of their limits."""
    x, ref = ca.SX.sym("x", 4 * n), ca.SX.sym("reference", 2 * n)
    w = p.weights
    parts = [np.sqrt(w["theta"]) * (x[:n] - ref[:n]), np.sqrt(w["dtheta"]) * (x[2 * n:3 * n] - ref[n:])]
    for c, cmax in ((x[n:2 * n] - x[:n], limits["psi"]), (x[3 * n:], limits["dphi"])):
        finite = np.isfinite(cmax)
        if finite.any():
            excess = ca.fmax(ca.fabs(c) - SOFT * np.where(finite, cmax, 1.0), 0) * ca.sign(c)
            parts.append(np.sqrt(w["limits"]) * finite * excess)
    r = ca.vertcat(*parts)
    return ca.Function("stage_residual", [x, ref], [r, ca.jacobian(r, x)])


class _Linearisation:
    """The Gauss-Newton QP of the multiple-shooting NLP at (X, U), condensed (Bock & Plitt):
    dx_0 = x_measured - X_0 (initial-value embedding); dx_{k+1} = A_k dx_k + B_k du_k + c_k with the
    gap c_k = F(X_k, U_k) - X_{k+1}; so dx_k = E_k + G_k dU, and the QP is in dU alone."""

    def __init__(self, F, residual, p: MPCProblem, xm, ref, X, U):
        n, N = U.shape[0], p.horizon
        nx = X.shape[0]
        self.H, self.g = p.weights["tau"] * ca.MX.eye(n * N), p.weights["tau"] * ca.vec(U)
        E, G = xm - X[:, 0], ca.MX.zeros(nx, n * N)
        self.E, self.G = [E], [G]
        for k in range(N):
            xp, A, B = F(X[:, k], U[:, k])
            E = ca.mtimes(A, E) + xp - X[:, k + 1]
            G = ca.horzcat(ca.mtimes(A, G[:, :n * k]), B, ca.MX.zeros(nx, n * (N - k - 1)))
            self.E.append(E)
            self.G.append(G)
            r, Jx = residual(X[:, k + 1] + E, ref[:, k])
            J = ca.mtimes(Jx, G)
            self.H += ca.mtimes(J.T, J)
            self.g += ca.mtimes(J.T, r)

    def step(self, dU):
        """dX = (E_k + G_k dU)_k."""
        return ca.horzcat(*[E + ca.mtimes(G, dU) for E, G in zip(self.E, self.G)])


def rollout(Fx, residual, p: MPCProblem, xm, ref, U):
    """The NLP's cost along the plan's states simulated from the measured state, and those states:
    the measure of progress of the line search (a condensed, hence gap-free, merit function)."""
    xs, total = [xm], 0.5 * p.weights["tau"] * ca.sumsqr(U)
    for k in range(p.horizon):
        xs.append(Fx(xs[-1], U[:, k]))
        total += 0.5 * ca.sumsqr(residual(xs[-1], ref[:, k])[0])
    return total, ca.horzcat(*xs)


def _max_step(v, dv, fraction: float):
    """The longest step <= 1 keeping v + a dv > 0, times the fraction to the boundary."""
    neg = dv < 0
    ratios = neg * (-v / (dv - (1 - neg))) + (1 - neg) * 1e30
    return ca.fmin(1.0, fraction * ca.mmin(ratios))


@functools.lru_cache(maxsize=None)
def _ipm_iteration(m: int) -> ca.Function:
    """One Mehrotra predictor-corrector iteration (Nocedal & Wright, alg. 16.4) of box_qp on the
    (scaled) QP of size m, as straight-line SX: the reduced KKT matrix is factored once (Cholesky)
    and its factor serves both the predictor and the corrector."""
    H, g, lo, hi, d, sl, su, zl, zu = (ca.SX.sym(name, *shape) for name, shape in (
        ("H", (m, m)), ("g", (m, 1)), ("lo", (m, 1)), ("hi", (m, 1)), ("d", (m, 1)),
        ("sl", (m, 1)), ("su", (m, 1)), ("zl", (m, 1)), ("zu", (m, 1))))
    rd, rl, ru = ca.mtimes(H, d) + g - zl + zu, d - lo - sl, hi - d - su
    mu = (ca.dot(sl, zl) + ca.dot(su, zu)) / (2 * m)
    R = ca.chol(H + ca.diag(zl / sl + zu / su))                       # R' R = K

    def newton(sigma_mu, cl, cu):                                     # the reduced KKT system, eq. (16.58)
        rhs = -rd + (sigma_mu - sl * zl - cl - zl * rl) / sl - (sigma_mu - su * zu - cu - zu * ru) / su
        dd = ca.solve(R, ca.solve(R.T, rhs))
        dsl, dsu = dd + rl, ru - dd
        return dd, dsl, dsu, (sigma_mu - sl * zl - cl - zl * dsl) / sl, (sigma_mu - su * zu - cu - zu * dsu) / su

    def longest(dsl, dsu, dzl, dzu, fraction):
        return ca.fmin(ca.fmin(_max_step(sl, dsl, fraction), _max_step(su, dsu, fraction)),
                       ca.fmin(_max_step(zl, dzl, fraction), _max_step(zu, dzu, fraction)))

    dd, dsl, dsu, dzl, dzu = newton(0, 0, 0)                          # predictor (affine scaling)
    a = longest(dsl, dsu, dzl, dzu, 1)
    mu_aff = (ca.dot(sl + a * dsl, zl + a * dzl) + ca.dot(su + a * dsu, zu + a * dzu)) / (2 * m)
    dd, dsl, dsu, dzl, dzu = newton((mu_aff / mu) ** 3 * mu, dsl * dzl, dsu * dzu)     # corrector
    a = longest(dsl, dsu, dzl, dzu, 0.995)
    return ca.Function("box_qp_iteration", [H, g, lo, hi, d, sl, su, zl, zu],
                       [d + a * dd, sl + a * dsl, su + a * dsu, zl + a * dzl, zu + a * dzu], {"cse": True})


def box_qp(H, g, lo, hi, iterations: int):
    """min 1/2 d' H d + g' d subject to lo <= d <= hi: `iterations` primal-dual interior-point
    iterations with Mehrotra's predictor-corrector (`_ipm_iteration`), slacks for both bounds, the
    QP scaled to O(1) first.  Fixed work and no allocation in C.  On this MPC's cold steps to far
    poses it reaches qpOASES' solution to 3e-9 in 15 iterations (tests/test_mpc.py).
    Why not a generated solver: CasADi's qrqp returned bound-violating 'successes' on these QPs
    (casadi issue 3141), DAQP's generated C allocates in every call, and projected Newton without
    a line search cycles (with one it stalls at this conditioning, ~1e8)."""
    m = g.shape[0]
    c = ca.mmax(ca.fabs(g)) + ca.mmax(ca.diag(H))
    H, g = H / c, g / c
    d = ca.fmin(ca.fmax(ca.MX.zeros(m), lo), hi)
    sl, su, zl, zu = (ca.MX.ones(m) for _ in range(4))
    iteration = _ipm_iteration(m)
    for _ in range(iterations):
        d, sl, su, zl, zu = iteration(H, g, lo, hi, d, sl, su, zl, zu)
    return ca.fmin(ca.fmax(d, lo), hi)


def shifted(Z, alpha: float):
    """The plan moved forward by alpha intervals (one sample): linear interpolation, last column held."""
    Zn = ca.horzcat(Z[:, 1:], Z[:, -1])
    return (1 - alpha) * Z + alpha * Zn


def rti_function(arm: Arm, p: MPCProblem) -> ca.Function:
    """mpc_rti(x, reference, X, U) -> (tau, X_next, U_next): `sqp_iterations`
    Gauss-Newton SQP iterations of the multiple-shooting NLP (1: the real-time iteration; more:
    each with a line search on the rollout's cost), then the plan shifted by one sample."""
    n, N, nx = arm.n, p.horizon, 4 * arm.n
    F, Fx = interval_functions(arm, p.interval, p.substeps)
    limits = limit_arrays(arm)
    residual = stage_residual(n, p, limits)
    xm, ref = ca.MX.sym("x", nx), ca.MX.sym("reference", 2 * n, N)
    X0, U0 = ca.MX.sym("X", nx, N + 1), ca.MX.sym("U", n, N)
    X, U, phi0 = X0, U0, None
    tau_max = np.tile(limits["tau"], N)
    for _ in range(p.sqp_iterations):
        lin = _Linearisation(F, residual, p, xm, ref, X, U)
        dU = box_qp(lin.H, lin.g, -tau_max - ca.vec(U), tau_max - ca.vec(U), p.qp_iterations)
        dX = lin.step(dU)
        if p.sqp_iterations == 1:                                         # RTI: the full step
            X, U = X + dX, U + ca.reshape(dU, n, N)
            continue
        # step sizes tried in a fixed set (fixed work in C): the longest whose rollout lowers the
        # cost, else the shortest; the states become that rollout (the gaps close), and its cost
        # is the next iteration's reference
        if phi0 is None:
            phi0 = rollout(Fx, residual, p, xm, ref, U)[0]
        dU = ca.reshape(dU, n, N)
        alpha = ca.MX(LINE_SEARCH[-1])
        phi_new, X_new = rollout(Fx, residual, p, xm, ref, U + alpha * dU)
        for a in reversed(LINE_SEARCH[:-1]):
            phi, Xa = rollout(Fx, residual, p, xm, ref, U + a * dU)
            better = phi < phi0
            alpha, phi_new, X_new = ca.if_else(better, a, alpha), ca.if_else(better, phi, phi_new), ca.if_else(better, Xa, X_new)
        X, U, phi0 = X_new, U + alpha * dU, phi_new
    X = ca.horzcat(xm, X[:, 1:])
    alpha = p.sample_time / p.interval
    return ca.Function("mpc_rti", [xm, ref, X0, U0], [U[:, 0], shifted(X, alpha), shifted(U, alpha)],
                       ["x", "reference", "X", "U"], ["tau", "X_next", "U_next"])


def hold_function(arm: Arm, p: MPCProblem) -> ca.Function:
    """mpc_hold(x) -> (X, U): the initial plan, the arm held where it is over the horizon."""
    n = arm.n
    x = ca.SX.sym("x", 4 * n)
    z = ca.SX.zeros(n)
    tau = arm.inverse_dynamics()(x[:n], x[n:2 * n], z, z, z, z)[0]
    return ca.Function("mpc_hold", [x], [ca.repmat(x, 1, p.horizon + 1), ca.repmat(tau, 1, p.horizon)],
                       ["x"], ["X", "U"])


WRAPPER_H = """/* rscasadi MPC for {model} ({n} joints): multiple shooting, Gauss-Newton SQP ({iters}), generated
 * by rscasadi mpc.  mpc_init once with the measured state, then mpc_step (or mpc_step_to) every
 * {ts} s.  No allocation; not reentrant (one controller per process: its plan is static).
 * x: theta, phi, dtheta, dphi ({nx}); reference: {nref} values, column-major 2n x N: theta_ref
 * then dtheta_ref at t + k * {h} s, k = 1..{N}; theta_target: {n} link angles (a pose to reach
 * and hold); tau_out: {n} motor torques.  Return 0 on success; MPC_NOT_FINITE if the new plan
 * is not finite (e.g. a NaN in x_measured or reference), MPC_FAILED if the generated function
 * failed: then the plan is kept and tau_out is its first torque (within the limits).
 * mpc_step_seconds: the duration of the last mpc_step or mpc_step_to (CLOCK_MONOTONIC). */
#ifndef RSCASADI_MPC_H
#define RSCASADI_MPC_H
#define MPC_NX {nx}
#define MPC_NU {n}
#define MPC_HORIZON {N}
#define MPC_NREF {nref}
#define MPC_NOT_FINITE 2
#define MPC_FAILED 3
int mpc_init(const double *x_measured);
int mpc_step(const double *x_measured, const double *reference, double *tau_out);
int mpc_step_to(const double *x_measured, const double *theta_target, double *tau_out);
double mpc_step_seconds(void);
#endif
"""

WRAPPER_C = """#define _POSIX_C_SOURCE 199309L
#include <math.h>
#include <time.h>
#include "rscasadi_mpc.h"
#include "mpc_rti.h"

#define MAX(a, b) ((a) > (b) ? (a) : (b))
#define NXP (MPC_NX * (MPC_HORIZON + 1))
#define NUP (MPC_NU * MPC_HORIZON)
static casadi_real X[NXP], U[NUP], X_next[NXP], U_next[NUP];
static casadi_real target_reference[MPC_NREF];
static casadi_real w[MAX(mpc_rti_SZ_W, mpc_hold_SZ_W) + 1];
static casadi_int iw[MAX(mpc_rti_SZ_IW, mpc_hold_SZ_IW) + 1];
static double last_step_seconds;

static double now(void) {{
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}}

double mpc_step_seconds(void) {{ return last_step_seconds; }}

int mpc_init(const double *x_measured) {{
  const casadi_real *arg[mpc_hold_SZ_ARG + 1] = {{x_measured}};
  casadi_real *res[mpc_hold_SZ_RES + 1] = {{X, U}};
  return mpc_hold(arg, res, iw, w, 0);
}}

static int step(const double *x_measured, const double *reference, double *tau_out) {{
  const casadi_real *arg[mpc_rti_SZ_ARG + 1] = {{x_measured, reference, X, U}};
  casadi_real *res[mpc_rti_SZ_RES + 1] = {{tau_out, X_next, U_next}};
  int finite = 1;
  if (mpc_rti(arg, res, iw, w, 0) != 0) {{
    for (int i = 0; i < MPC_NU; ++i) tau_out[i] = U[i];
    return MPC_FAILED;
  }}
  for (int i = 0; i < NXP; ++i) finite = finite && isfinite(X_next[i]);
  for (int i = 0; i < NUP; ++i) finite = finite && isfinite(U_next[i]);
  if (!finite) {{                          /* e.g. a NaN measurement: keep the plan, its first torque */
    for (int i = 0; i < MPC_NU; ++i) tau_out[i] = U[i];
    return MPC_NOT_FINITE;
  }}
  for (int i = 0; i < NXP; ++i) X[i] = X_next[i];
  for (int i = 0; i < NUP; ++i) U[i] = U_next[i];
  return 0;
}}

int mpc_step(const double *x_measured, const double *reference, double *tau_out) {{
  const double t0 = now();
  const int flag = step(x_measured, reference, tau_out);
  last_step_seconds = now() - t0;
  return flag;
}}

int mpc_step_to(const double *x_measured, const double *theta_target, double *tau_out) {{
  for (int k = 0; k < MPC_HORIZON; ++k)
    for (int i = 0; i < MPC_NU; ++i) {{
      target_reference[2 * MPC_NU * k + i] = theta_target[i];
      target_reference[2 * MPC_NU * k + MPC_NU + i] = 0.0;
    }}
  return mpc_step(x_measured, target_reference, tau_out);
}}
"""


def generate_mpc(problem_file, out, opt: str = "-O2", log=print, model=None) -> dict:
    """Write the MPC's C, header, library and manifest into `out` (whole or not at all); `model`
    (a model file) replaces the problem's, e.g. an identified model."""
    import subprocess
    from ..codegen import _compiler
    from ..files import fresh_directory, write_json
    p = load_mpc_problem(problem_file)
    if model is not None:
        p.model_path = Path(model).resolve()
    arm = load(p.model_path)
    if p.interval / p.substeps > 2e-3:
        log(f"note: {p.interval / p.substeps * 1e3:.1f} ms RK4 steps: the SEA damping (d/k1 ~ 1 ms) may make them unstable")
    rti, hold = rti_function(arm, p), hold_function(arm, p)
    out = Path(out)
    with fresh_directory(out, "manifest.json") as tmp:
        gen = ca.CodeGenerator("mpc_rti.c", {"with_header": True})
        gen.add(rti)
        gen.add(hold)
        gen.generate(str(tmp) + "/")
        n = arm.n
        # the model's file name goes into a C comment: only characters that cannot end one
        model_name = re.sub(r"[^A-Za-z0-9._-]", "_", Path(arm.model.path).name)
        (tmp / "rscasadi_mpc.h").write_text(WRAPPER_H.format(model=model_name, n=n, nx=4 * n,
                                                           N=p.horizon, nref=2 * n * p.horizon, ts=p.sample_time,
                                                           h=p.interval, iters="real-time iteration" if
                                                           p.sqp_iterations == 1 else f"{p.sqp_iterations} iterations"))
        (tmp / "rscasadi_mpc.c").write_text(WRAPPER_C.format())
        cc = _compiler()
        log(f"compiling the MPC ({opt}) ...")
        run = subprocess.run([*cc, opt, "-std=c99", "-fPIC", "-shared", "mpc_rti.c", "rscasadi_mpc.c", "-o",
                              "librscasadi_mpc.so", "-lm"], cwd=tmp, capture_output=True, text=True)
        if run.returncode != 0:
            raise RuntimeError(f"compiling the MPC failed:\n{run.stderr[-2000:]}")
        manifest = {"model": str(p.model_path), "problem": str(p.path), "header": "rscasadi_mpc.h",
                    "library": "librscasadi_mpc.so", "sources": ["mpc_rti.c", "rscasadi_mpc.c"],
                    "api": {"mpc_init": ["x_measured"], "mpc_step": ["x_measured", "reference", "tau_out"],
                            "mpc_step_to": ["x_measured", "theta_target", "tau_out"], "mpc_step_seconds": []},
                    "sizes": {"x": 4 * n, "tau": n, "reference": [2 * n, p.horizon]},
                    "horizon": p.horizon, "interval": p.interval, "substeps": p.substeps,
                    "sample_time": p.sample_time, "sqp_iterations": p.sqp_iterations, "qp_iterations": p.qp_iterations, "weights": p.weights,
                    "compiler": cc + [opt]}
        write_json(tmp / "manifest.json", manifest, indent=2)
    log(f"wrote {out / 'librscasadi_mpc.so'}, rscasadi_mpc.h and manifest.json")
    return manifest


# ------------------------------------------------------------------ closed-loop evidence

def heavier_tip(arm: Arm, factor: float = 1.2) -> Arm:
    """The same arm with its last link's mass (and inertia) scaled: the plant of the mismatch study."""
    import dataclasses
    from ..model.modelfile import Body
    last = arm.model.joints[-1]
    link = Body(last.link.mass * factor, last.link.com, last.link.inertia * factor)
    joints = arm.model.joints[:-1] + (dataclasses.replace(last, link=link),)
    return Arm(dataclasses.replace(arm.model, joints=joints, name=arm.model.name + f"-tip-x{factor:g}"))


class CompiledMPC:
    """The generated C controller through ctypes: init(x), step(x, reference) -> tau, seconds
    (the step's duration measured in C, by mpc_step_seconds), flag."""

    def __init__(self, directory):
        import ctypes
        self.lib = ctypes.CDLL(str(Path(directory) / "librscasadi_mpc.so"))
        self.lib.mpc_step_seconds.restype = ctypes.c_double
        self.c_double_p = ctypes.POINTER(ctypes.c_double)

    def _p(self, a):
        return np.ascontiguousarray(a, float).ctypes.data_as(self.c_double_p)

    def init(self, x):
        assert self.lib.mpc_init(self._p(x)) == 0

    def step(self, x, reference):
        """reference: 2n x N (theta_ref over dtheta_ref, a column per interval end)."""
        return self._call(self.lib.mpc_step, x, np.asarray(reference, float).T.ravel())

    def step_to(self, x, theta_target):
        return self._call(self.lib.mpc_step_to, x, np.asarray(theta_target, float))

    def _call(self, fn, x, data):
        tau = np.zeros(len(x) // 4)
        x, data = np.ascontiguousarray(x, float), np.ascontiguousarray(data, float)
        flag = fn(self._p(x), self._p(data), tau.ctypes.data_as(self.c_double_p))
        return tau, self.lib.mpc_step_seconds(), flag


def plant_step(plant: Arm, dt: float) -> ca.Function:
    """(x, tau) -> x after dt: the simulated arm, four RK4 steps of its complete model."""
    from ..codegen import rk4
    n, fd = plant.n, plant.forward_dynamics()
    xs, us = ca.SX.sym("x", 4 * n), ca.SX.sym("u", n)
    z = xs
    for _ in range(4):
        z = rk4(lambda v: ca.vertcat(v[2 * n:], *fd(*ca.vertsplit(v, n), us)), z, dt / 4)[0]
    return ca.Function("advance", [xs, us], [z])


def reach_pose(problem_file, mpc_dir, theta_target, seconds: float = 1.0, plant: Arm | None = None) -> dict:
    """From rest at theta = 0 to a target pose with the C MPC's mpc_step_to, on the problem's arm
    (or `plant`), exact measurements: final angle error and speed, largest limit violation
    (fraction of the limit beyond it), the torques and the time per step."""
    p = load_mpc_problem(problem_file)
    arm = load(p.model_path) if plant is None else plant
    from .ocp import rest_state
    n, advance, limits = arm.n, plant_step(arm, p.sample_time), limit_arrays(arm)
    target = np.asarray(theta_target, float)
    mpc = CompiledMPC(mpc_dir)
    x = rest_state(arm, np.zeros(n))
    mpc.init(x)
    violation, taus, times = 0.0, [], []
    for _ in range(int(round(seconds / p.sample_time))):
        tau, t, flag = mpc.step_to(x, target)
        if flag != 0:
            raise RuntimeError(f"mpc_step_to returned {flag}")
        taus.append(tau)
        times.append(t)
        x = np.array(advance(x, tau)).ravel()
        violation = max(violation, float(np.max(np.abs(x[n:2 * n] - x[:n]) / limits["psi"] - 1)),
                        float(np.max(np.abs(x[3 * n:]) / limits["dphi"] - 1)))
    return {"final_angle_error": float(np.max(np.abs(x[:n] - target))), "final_speed": float(np.max(np.abs(x[2 * n:]))),
            "max_limit_violation": max(violation, 0.0), "tau": np.array(taus),
            "step_median_s": float(np.median(times)), "step_worst_s": float(np.max(times))}


def closed_loop(problem_file, mpc_dir, duration: float | None = None, tip_factor: float = 1.2,
                log=print, model=None, plant: Arm | None = None, quantised: bool = True,
                traces: dict | None = None) -> dict:
    """Controllers from one model (the problem's, or the model file `model`, e.g. an identified
    one; the C MPC in `mpc_dir` must be generated from it) on a plant that differs (`plant`, by
    default the model with a heavier tip), at 1 kHz, encoders quantised (speeds by backward
    differences; `quantised=False`: the exact state): feedforward alone, feedforward + motor-side PD, the C MPC.  Returns per
    controller the tracking error (max, RMS), the largest limit violation and, for the MPC, its
    time per step (measured in C); `traces`, if given, receives per controller the time, the error
    over time and (MPC) the step times, for `plot_closed_loop`."""
    from ..identification.synthetic import LINK_COUNTS, MOTOR_COUNTS       # the same encoders as the logs
    from .simulation import feedforward
    from .trajectory import load_trajectory
    p = load_mpc_problem(problem_file)
    nominal = load(p.model_path if model is None else model)
    plant = heavier_tip(nominal, tip_factor) if plant is None else plant
    traj = load_trajectory(p.trajectory)
    n, dt = nominal.n, p.sample_time
    T = traj.duration if duration is None else duration
    K = int(round(T / dt))
    t = np.arange(K + 1) * dt
    ff = feedforward(nominal, traj, t)
    advance = plant_step(plant, dt)
    mu = nominal.model.column("gear_ratio")
    q_link, q_motor = 2 * np.pi / LINK_COUNTS, 2 * np.pi / MOTOR_COUNTS / mu
    B = np.array([jt.rotor_inertia for jt in nominal.model.joints])
    wn = 2 * np.pi * 4.0
    kp, kd = B * wn ** 2, 2 * 0.8 * B * wn
    limits = limit_arrays(plant)
    mpc = CompiledMPC(mpc_dir)
    results = {}
    for name in ("feedforward", "feedforward + PD", "MPC (C)"):
        x = ff["x0"].copy()
        meas_prev = np.concatenate([np.round(x[:n] / q_link) * q_link, np.round(x[n:2 * n] / q_motor) * q_motor])
        errors, violation, times = [], 0.0, []
        if name == "MPC (C)":
            mpc.init(x)
        for k in range(K):
            meas = np.concatenate([np.round(x[:n] / q_link) * q_link, np.round(x[n:2 * n] / q_motor) * q_motor])
            speeds = (meas - meas_prev) / dt if k else x[2 * n:]
            meas_prev = meas
            if not quantised:
                meas, speeds = x[:2 * n], x[2 * n:]
            if name == "MPC (C)":
                tk = t[k] + p.interval * np.arange(1, p.horizon + 1)
                q, dq = traj(np.minimum(tk, traj.duration))[:2]
                tau, seconds, flag = mpc.step(np.concatenate([meas, speeds]), np.vstack([q, dq]))
                times.append(seconds)
            else:
                tau = ff["tau"][:, k].copy()
                if name == "feedforward + PD":
                    tau -= (kp * (ff["phi"][:, k] - meas[n:]) + kd * (ff["dphi"][:, k] - speeds[n:])) / mu
            tau = np.clip(tau, -limits["tau"], limits["tau"])
            x = np.array(advance(x, tau)).ravel()
            errors.append(np.max(np.abs(x[:n] - ff["theta_d"][:, k + 1])))
            violation = max(violation, float(np.max(np.abs(x[n:2 * n] - x[:n]) / limits["psi"] - 1)),
                            float(np.max(np.abs(x[3 * n:]) / limits["dphi"] - 1)))
        e = np.array(errors)
        if traces is not None:
            traces[name] = {"t": t[1:K + 1], "error": e, "step_s": np.array(times)}
        results[name] = {"max_error": float(e.max()), "max_error_at_s": float(t[1 + int(np.argmax(e))]),
                         "rms_error": float(np.sqrt(np.mean(e ** 2))),
                         "max_limit_violation": max(violation, 0.0)}
        if times:
            results[name].update(step_median_s=float(np.median(times)), step_worst_s=float(np.max(times)))
        log(f"{name:18s} max error {e.max():.2e} rad, RMS {results[name]['rms_error']:.2e} rad, "
            f"limit violation {max(violation, 0.0):.1e}"
            + (f", step median {np.median(times) * 1e6:.0f} us, worst {np.max(times) * 1e6:.0f} us" if times else ""))
    return results


def study(problem_file, build, identified_model=None, true_arm: Arm | None = None, log=print,
          figure: Path | None = None) -> dict:
    """The closed-loop evidence, whole trajectory: the problem's model against a 20 % heavier tip;
    if given, the identified model's controllers (MPC generated into `build`) against the true arm
    that produced the identification logs.  `figure`: where to draw them (plot_closed_loop)."""
    build = Path(build)
    res, traces = {}, {}
    log("closed loop: the model's controllers on a plant with a 20 % heavier tip, quantised encoders")
    generate_mpc(problem_file, build / "mpc", log=log)
    res["heavier_tip"] = closed_loop(problem_file, build / "mpc", log=log, traces=traces.setdefault("heavier_tip", {}))
    if identified_model is not None:
        log("closed loop: the identified model's controllers on the true arm, quantised encoders")
        generate_mpc(problem_file, build / "mpc_identified", log=log, model=identified_model)
        res["identified_on_true_arm"] = closed_loop(problem_file, build / "mpc_identified", log=log,
                                                    model=identified_model, plant=true_arm,
                                                    traces=traces.setdefault("identified_on_true_arm", {}))
    if figure is not None:
        plot_closed_loop(traces, figure)
        log(f"wrote {figure}")
    return res


CASES = {"heavier_tip": "controllers' model, plant with a 20 % heavier tip",
         "identified_on_true_arm": "identified model, true arm"}


def plot_closed_loop(traces: dict, path: Path):
    """Per case (a column): the tracking error of each controller over time (log scale), and the
    C MPC's time per step against the 1 ms budget of 1 kHz."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, len(traces), figsize=(6 * len(traces), 6.5), squeeze=False)
    for col, (case, ctrl) in enumerate(traces.items()):
        ax = axes[0, col]
        for name, tr in ctrl.items():
            ax.semilogy(tr["t"], np.maximum(tr["error"], 1e-9), label=name, lw=1)
        ax.set(title=CASES.get(case, case), xlabel="t (s)", ylabel="max |theta - theta_d| (rad)")
        ax.legend(fontsize=8)
        ax = axes[1, col]
        steps = ctrl["MPC (C)"]["step_s"] * 1e6
        ax.plot(ctrl["MPC (C)"]["t"], steps, ".", ms=1.5)
        ax.axhline(1000.0, color="r", lw=1, label="1 ms (1 kHz)")
        ax.set(xlabel="t (s)", ylabel="mpc_step in C (us)", ylim=(0, max(1100.0, steps.max() * 1.05)),
               title=f"median {np.median(steps):.0f} us, worst {steps.max():.0f} us")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
