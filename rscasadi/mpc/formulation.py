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
deflection psi and the slow-side speed dphi beyond 90 % of their limits, and w_angle_limits on the
link angles beyond 90 % of their range's half-width about its middle (Gauss-Newton on the part
active at the linearisation point); the motor torques are hard bounds (every joint must give
its torque limit: mpc_model refuses a model without one).  In task space the
tracking terms are the frame's: w_position |p_k - p_ref_k|^2 + w_velocity |J dtheta_k -
v_ref_k|^2 (+ w_orientation |skew(R_ref^T R_k)|^2), and w_posture |theta_k - theta_posture|^2
holds a redundant arm's null space (the posture: the measured angles at mpc_init, or set).
Obstacles are soft: w_obstacles max(0, -clearance)^2 on the smooth conservative clearances of
the model's capsules (rscasadi.dynamics.collision).  The payload's mass is a parameter of the
dynamics, set at run time.

Problem file and C interface: docs/user-guide/mpc.md (`problems/mpc_arm3.toml` is an example).

Generated (DIR): `mpc_rti.c` (CasADi: mpc_rti(x, reference, X, U, params) -> tau, X_next,
U_next and mpc_hold(x, params) -> X, U; params = (theta_posture, the arm's parameters: controller_arm)),
`rscasadi_mpc.c` and `rscasadi_mpc.h` (the controller, its state in a caller's `mpc_t`), on
arms past straight-line SX `mpc_step_jacobian.c` (the structured step-Jacobian kernel the
controller calls), `librscasadi_mpc.so`, `manifest.json`.  reference is column-major, a column per interval end
t + k h: theta_ref then dtheta_ref (2n), or in task space p_ref, v_ref (6) [and vec(R_ref) (9)].
"""
from __future__ import annotations

import functools

import casadi as ca
import numpy as np

from rscasadi.dynamics.arm import Arm
from rscasadi.dynamics.collision import clearances
from rscasadi.model.limits import limit_arrays as model_limits
from rscasadi.model.parameters import family
from rscasadi.mpc.problem import SOFT, LINE_SEARCH, MPCProblem


def controller_arm(model, parametric: str = "none") -> Arm:
    """The controller's arm: its payload's mass (if it holds one) a parameter of the dynamics;
    "family": every parameter not zero in the model (model.parameters.family), the payload's
    mass among them."""
    if parametric == "family":
        return Arm(model, free=family(model)[0], tie_balanced=True)
    return Arm(model, free=["payload.mass"]) if model.payload is not None else Arm(model)


def n_params(arm: Arm) -> int:
    """Length of the controller's params: the posture (n), then the arm's parameters (none, the
    payload's mass, or a family's)."""
    return arm.n + (arm.n_p if arm.free else 0)


def interval_functions(arm: Arm, h: float, substeps: int, step_jacobian: ca.Function | None = None):
    """F: (x, tau, m) -> (x after h, A = dx/dx0, B = dx/dtau): `substeps` RK4 steps and their
    structured Jacobians chained (A = A_s ... A_1, B = A_s (...) B_1 + ... + B_s); Fx: the state
    alone.  m: the arm's parameters (controller_arm; empty if none).
    One substep (step, Jacobian and the chain's products) is one Function, straight-line SX when
    the step Jacobian is SX (small arms), called `substeps` times: its C is generated once, so
    the controller compiles in a fifth of the time of one straight-line interval, as fast.
    step_jacobian: a Function to use in place of step_functions' (the generated controller's
    structured C kernel, `generate.step_kernel`)."""
    from rscasadi.codegen.generate import step_functions
    n, hs, parametric = arm.n, h / substeps, bool(arm.free)
    step, step_jac = step_functions(arm, parametric=parametric)
    step_jac = step_jac if step_jacobian is None else step_jacobian
    sym = ca.SX if step_jac.is_a("SXFunction") else ca.MX
    if sym is ca.SX:
        step = step.expand()
    z, tau, A, B = sym.sym("x", 4 * n), sym.sym("tau", n), sym.sym("A", 4 * n, 4 * n), sym.sym("B", 4 * n, n)
    m = sym.sym("m", arm.n_p if parametric else 0)
    pm = [m] if parametric else []
    Ai, Bi = step_jac(z, tau, hs, *pm)
    opts = {"cse": True} if sym is ca.SX else {}
    substep = ca.Function("substep", [z, tau, m, A, B], [step(z, tau, hs, *pm), ca.mtimes(Ai, A), ca.mtimes(Ai, B) + Bi], opts)
    substep_x = ca.Function("substep_x", [z, tau, m], [step(z, tau, hs, *pm)], opts)
    x, u, mm = ca.MX.sym("x", 4 * n), ca.MX.sym("tau", n), ca.MX.sym("m", m.shape[0])
    zk, Ak, Bk, z_only = x, ca.MX.eye(4 * n), ca.MX.zeros(4 * n, n), x
    for _ in range(substeps):
        zk, Ak, Bk = substep(zk, u, mm, Ak, Bk)
        z_only = substep_x(z_only, u, mm)
    return ca.Function("interval", [x, u, mm], [zk, Ak, Bk]), ca.Function("interval_x", [x, u, mm], [z_only])


def limit_arrays(arm: Arm) -> dict:
    """The joints' limits (rscasadi.model.limits.limit_arrays: inf where none): tau, psi, dphi,
    theta_lo, theta_hi."""
    return model_limits(arm.model)


def reference_rows(n: int, p: MPCProblem) -> int:
    """Rows of one reference column: 2n (link angles and speeds) or the task space's 6 or 15."""
    return p.reference_rows if p.task_space else 2 * n


def _tracking(arm: Arm, p: MPCProblem, x, ref, posture):
    """The weighted tracking residuals: link angles and speeds, or the frame's position, velocity
    (and rotation) and the posture."""
    n, w = arm.n, p.weights
    theta, dtheta = x[:n], x[2 * n:3 * n]
    if not p.task_space:
        return [np.sqrt(w["theta"]) * (theta - ref[:n]), np.sqrt(w["dtheta"]) * (dtheta - ref[n:])]
    R, pos = arm.frame_placement(p.frame)(theta)
    J = arm.frame_jacobian(p.frame, "local_world_aligned")(theta)
    rows = [np.sqrt(w["position"]) * (pos - ref[:3]), np.sqrt(w["velocity"]) * (ca.mtimes(J[:3, :], dtheta) - ref[3:6])]
    if p.orientation:
        E = ca.mtimes(ca.reshape(ref[6:15], 3, 3).T, R)
        rows.append(np.sqrt(w["orientation"]) * ca.vertcat(E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]) / 2)
    return rows + [np.sqrt(w["posture"]) * (theta - posture)]


def stage_residual(arm: Arm, p: MPCProblem, limits: dict) -> ca.Function:
    """(x_k, reference_k, posture) -> (r, dr/dx): the weighted residual whose half squared norm is
    the stage cost: tracking errors, the psi, dphi and link-angle excess beyond 90 % of their
    limits, and the obstacles' intrusion into their margin."""
    n = arm.n
    x, ref, posture = ca.SX.sym("x", 4 * n), ca.SX.sym("reference", reference_rows(n, p)), ca.SX.sym("posture", n)
    w = p.weights
    parts = _tracking(arm, p, x, ref, posture)
    ranged = np.isfinite(limits["theta_lo"]) & np.isfinite(limits["theta_hi"])
    middle = np.where(ranged, (limits["theta_lo"] + limits["theta_hi"]) / 2, 0.0)
    half = np.where(ranged, (limits["theta_hi"] - limits["theta_lo"]) / 2, np.inf)
    for c, cmax, weight in ((x[n:2 * n] - x[:n], limits["psi"], w["limits"]), (x[3 * n:], limits["dphi"], w["limits"]),
                            (x[:n] - middle, half, w["angle_limits"])):
        finite = np.isfinite(cmax)
        if finite.any() and weight > 0:
            excess = ca.fmax(ca.fabs(c) - SOFT * np.where(finite, cmax, 1.0), 0) * ca.sign(c)
            parts.append(np.sqrt(weight) * finite * excess)
    if p.obstacles:
        parts.append(np.sqrt(w["obstacles"]) * ca.fmax(-clearances(arm.model, p.obstacles, x[:n]), 0))
    r = ca.vertcat(*parts)
    return ca.Function("stage_residual", [x, ref, posture], [r, ca.jacobian(r, x)])


class _Linearisation:
    """The Gauss-Newton QP of the multiple-shooting NLP at (X, U), condensed (Bock & Plitt):
    dx_0 = x_measured - X_0 (initial-value embedding); dx_{k+1} = A_k dx_k + B_k du_k + c_k with the
    gap c_k = F(X_k, U_k) - X_{k+1}; so dx_k = E_k + G_k dU_{<k}, and the QP is in dU alone.  G_k
    holds only the columns of du_0..du_{k-1} (the later ones cannot act on x_k): the products
    that form H and g run over n k columns, not n N."""

    def __init__(self, F, residual, p: MPCProblem, xm, ref, X, U, posture, mass):
        n, N = U.shape[0], p.horizon
        nx, nU = X.shape[0], n * N
        self.H, self.g = p.weights["tau"] * ca.MX.eye(nU), p.weights["tau"] * ca.vec(U)
        E, G = xm - X[:, 0], ca.MX(nx, 0)
        self.E, self.G = [E], [G]
        for k in range(N):
            xp, A, B = F(X[:, k], U[:, k], mass)
            E = ca.mtimes(A, E) + xp - X[:, k + 1]
            G = ca.horzcat(ca.mtimes(A, G), B)                      # nx x n (k + 1), dense
            self.E.append(E)
            self.G.append(G)
            r, Jx = residual(X[:, k + 1] + E, ref[:, k], posture)
            J, rest = ca.mtimes(Jx, G), nU - n * (k + 1)
            self.H += ca.diagcat(ca.mtimes(J.T, J), ca.MX(rest, rest))
            self.g += ca.vertcat(ca.mtimes(J.T, r), ca.MX(rest, 1))

    def step(self, dU):
        """dX = (E_k + G_k dU_{<k})_k."""
        return ca.horzcat(*[E + ca.mtimes(G, dU[:G.shape[1]]) for E, G in zip(self.E, self.G)])


def rollout(Fx, residual, p: MPCProblem, xm, ref, U, posture, mass):
    """The NLP's cost along the plan's states simulated from the measured state, and those states:
    the measure of progress of the line search (a condensed, hence gap-free, merit function)."""
    xs, total = [xm], 0.5 * p.weights["tau"] * ca.sumsqr(U)
    for k in range(p.horizon):
        xs.append(Fx(xs[-1], U[:, k], mass))
        total += 0.5 * ca.sumsqr(residual(xs[-1], ref[:, k], posture)[0])
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
    (CasADi issue #3141), DAQP's generated C allocates in every call, and projected Newton without
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


def rti_function(arm: Arm, p: MPCProblem, step_jacobian: ca.Function | None = None) -> ca.Function:
    """mpc_rti(x, reference, X, U, params) -> (tau, X_next, U_next): `sqp_iterations`
    Gauss-Newton SQP iterations of the multiple-shooting NLP (1: the real-time iteration; more:
    each with a line search on the rollout's cost), then the plan shifted by one sample.
    params: the posture (n) and the payload's mass (if `arm` takes it: `controller_arm`).
    step_jacobian: as `interval_functions`."""
    n, N, nx = arm.n, p.horizon, 4 * arm.n
    F, Fx = interval_functions(arm, p.interval, p.substeps, step_jacobian)
    limits = limit_arrays(arm)
    residual = stage_residual(arm, p, limits)
    xm, ref = ca.MX.sym("x", nx), ca.MX.sym("reference", reference_rows(n, p), N)
    params = ca.MX.sym("params", n_params(arm))
    posture, mass = params[:n], params[n:]
    X0, U0 = ca.MX.sym("X", nx, N + 1), ca.MX.sym("U", n, N)
    X, U, phi0 = X0, U0, None
    tau_max = np.tile(limits["tau"], N)
    for _ in range(p.sqp_iterations):
        lin = _Linearisation(F, residual, p, xm, ref, X, U, posture, mass)
        dU = box_qp(lin.H, lin.g, -tau_max - ca.vec(U), tau_max - ca.vec(U), p.qp_iterations)
        dX = lin.step(dU)
        if p.sqp_iterations == 1:                                         # RTI: the full step
            X, U = X + dX, U + ca.reshape(dU, n, N)
            continue
        # step sizes tried in a fixed set (fixed work in C): the longest whose rollout lowers the
        # cost, else the shortest; the states become that rollout (the gaps close), and its cost
        # is the next iteration's reference
        if phi0 is None:
            phi0 = rollout(Fx, residual, p, xm, ref, U, posture, mass)[0]
        dU = ca.reshape(dU, n, N)
        alpha = ca.MX(LINE_SEARCH[-1])
        phi_new, X_new = rollout(Fx, residual, p, xm, ref, U + alpha * dU, posture, mass)
        for a in reversed(LINE_SEARCH[:-1]):
            phi, Xa = rollout(Fx, residual, p, xm, ref, U + a * dU, posture, mass)
            better = phi < phi0
            alpha, phi_new, X_new = ca.if_else(better, a, alpha), ca.if_else(better, phi, phi_new), ca.if_else(better, Xa, X_new)
        X, U, phi0 = X_new, U + alpha * dU, phi_new
    X = ca.horzcat(xm, X[:, 1:])
    alpha = p.sample_time / p.interval
    return ca.Function("mpc_rti", [xm, ref, X0, U0, params], [U[:, 0], shifted(X, alpha), shifted(U, alpha)],
                       ["x", "reference", "X", "U", "params"], ["tau", "X_next", "U_next"])


def hold_function(arm: Arm, p: MPCProblem) -> ca.Function:
    """mpc_hold(x, params) -> (X, U): the initial plan, the arm held where it is over the horizon."""
    n = arm.n
    x, params = ca.SX.sym("x", 4 * n), ca.SX.sym("params", n_params(arm))
    z = ca.SX.zeros(n)
    pm = [params[n:]] if arm.free else []
    tau = arm.inverse_dynamics(parametric=bool(arm.free))(x[:n], x[n:2 * n], z, z, z, z, *pm)[0]
    return ca.Function("mpc_hold", [x, params], [ca.repmat(x, 1, p.horizon + 1), ca.repmat(tau, 1, p.horizon)],
                       ["x", "params"], ["X", "U"])
