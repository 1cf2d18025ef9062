"""Nonlinear MPC on the complete model, generated to C (`rscasadi mpc PROBLEM.toml --out DIR`).

Multiple shooting on the complete model: a state plan X (4n x N+1, at the ends of N intervals of
length h) and a torque plan U (n x N, held on each interval); each interval is `substeps` steps
of the problem's integrator (RK4, or the L-stable Rosenbrock ROS2 where the spring modes are
too fast for RK4: `with_integrator`), its sensitivities from the structured step Jacobians
(codegen.generate, codegen.rosenbrock).
Gauss-Newton SQP: the QP of each iteration is condensed onto dU (Bock & Plitt; the gaps of the
shooting nodes enter its affine part); its motor-torque box is solved by a fixed number of
primal-dual interior-point iterations (`box_qp`: no data-dependent loops, no allocation). `sqp_iterations = 1` is
the real-time iteration (Diehl et al.: one full step per sample); more iterations take the
longest of a fixed set of step sizes whose simulated rollout lowers the cost (else the shortest),
so the work per sample is bounded. After the iterations the plan is shifted by one sample.

Cost (per interval end k = 1..N): w_theta |theta_k - theta_ref_k|^2 + w_dtheta |dtheta_k -
dtheta_ref_k|^2 + w_tau |tau_k|^2, and a penalty w_limits (|c| - 0.9 c_max)^2 on the SEA
deflection psi and the slow-side speed dphi beyond 90 % of their limits, and w_angle_limits on the
link angles beyond 90 % of their range's half-width about its middle, in joint space beyond the
reference's own distance from it where that is larger, never the range's (Gauss-Newton on the part
active at the linearisation point); the motor torques are hard bounds (every joint must give
its torque limit: mpc_model refuses a model without one).  With angle_limits = "hard" the
plan's link angles theta_k (linear in dU) are rows of the QP within the range itself, each with
an exact L1 penalty on its excess (box_qp), so the QP stays feasible.  In task space the
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
from rscasadi.model.limits import limit_arrays as model_limits
from rscasadi.mpc.problem import SOFT, LINE_SEARCH, MPCProblem, with_integrator
from rscasadi.task.terms import AngleBand, Clearance, FrameTracking, JointTracking, Posture, StateBound


def controller_arm(model, parametric: str = "none") -> Arm:
    """The controller's arm: its payload's mass (if it holds one) a parameter of the dynamics;
    "family": every parameter not zero in the model (model.parameters.family), the payload's
    mass among them."""
    if parametric == "family":
        return Arm.family(model)
    return Arm(model, free=["payload.mass"]) if model.payload is not None else Arm(model)


def n_params(arm: Arm) -> int:
    """Length of the controller's params: the posture (n), then the arm's parameters (none, the
    payload's mass, or a family's)."""
    return arm.n + (arm.n_p if arm.free else 0)


def interval_functions(arm: Arm, h: float, substeps: int, step_jacobian: ca.Function | None = None,
                       integrator: str = "rk4"):
    """F: (x, tau, m) -> (x after h, A = dx/dx0, B = dx/dtau): `substeps` steps of `integrator`
    ("rk4": classical Runge-Kutta, codegen.generate.step_functions; "ros2": the L-stable
    Rosenbrock step for fast spring modes, codegen.rosenbrock) and their structured Jacobians
    chained (A = A_s ... A_1, B = A_s (...) B_1 + ... + B_s); Fx: the state alone.  m: the arm's
    parameters (controller_arm; empty if none).
    One substep (step, Jacobian and the chain's products) is one Function, straight-line SX when
    the step Jacobian is SX (small arms), called `substeps` times: its C is generated once, so
    the controller compiles in a fifth of the time of one straight-line interval, as fast.
    step_jacobian: a Function to use in place of the integrator's step Jacobian (the generated
    controller's structured C kernel of the same integrator, `generate.step_kernel`); when it is
    the chained kernel (three outputs) it also steps and chains, `_chained_interval`."""
    from rscasadi.codegen.generate import rk4_step, step_functions
    from rscasadi.codegen.rosenbrock import ros2_functions
    nx, n, hs, parametric = 2 * arm.nq, arm.u, h / substeps, bool(arm.free)
    if step_jacobian is not None and step_jacobian.n_out() == 3:
        # ROS2's step needs the dynamics' Jacobian (W) as much as the kernel does: the kernel steps alone too
        step = step_jacobian if integrator == "ros2" else rk4_step(arm, parametric)
        return _chained_interval(step, step_jacobian, arm, hs, substeps)
    step, step_jac = (ros2_functions if integrator == "ros2" else step_functions)(arm, parametric=parametric)
    step_jac = step_jacobian if step_jacobian is not None else step_jac
    sym = ca.SX if step_jac.is_a("SXFunction") else ca.MX
    if sym is ca.SX:
        step = step.expand()
    z, tau, A, B = sym.sym("x", nx), sym.sym("tau", n), sym.sym("A", nx, nx), sym.sym("B", nx, n)
    m = sym.sym("m", arm.n_p if parametric else 0)
    pm = [m] if parametric else []
    Ai, Bi = step_jac(z, tau, hs, *pm)
    opts = {"cse": True} if sym is ca.SX else {}
    substep = ca.Function("substep", [z, tau, m, A, B], [step(z, tau, hs, *pm), ca.mtimes(Ai, A), ca.mtimes(Ai, B) + Bi], opts)
    first = ca.Function("first_substep", [z, tau, m], [step(z, tau, hs, *pm), Ai, Bi], opts)   # A_0 = I: no product
    substep_x = ca.Function("substep_x", [z, tau, m], [step(z, tau, hs, *pm)], opts)
    x, u, mm = ca.MX.sym("x", nx), ca.MX.sym("tau", n), ca.MX.sym("m", m.shape[0])
    zk, Ak, Bk = first(x, u, mm)
    z_only = substep_x(x, u, mm)
    for _ in range(substeps - 1):
        zk, Ak, Bk = substep(zk, u, mm, Ak, Bk)
        z_only = substep_x(z_only, u, mm)
    return ca.Function("interval", [x, u, mm], [zk, Ak, Bk]), ca.Function("interval_x", [x, u, mm], [z_only])


def _chained_interval(step, kernel, arm: Arm, hs: float, substeps: int):
    """interval_functions' F and Fx with the chained kernel (codegen.step_kernel, chained=True):
    each substep's call returns the step and carries the interval's A and B through it, so
    neither a separate step nor CasADi's products remain.  Fx steps with `step`: a step Function
    (x, tau, h[, p]) -> x_next, or the kernel itself (its A and B unused: not formed)."""
    n, nx = arm.u, 2 * arm.nq
    x, u, mm = ca.MX.sym("x", nx), ca.MX.sym("tau", n), ca.MX.sym("m", arm.n_p if arm.free else 0)
    pm = [mm] if arm.free else []
    z, A, B = x, ca.MX(ca.DM.eye(nx)), ca.MX(ca.DM.zeros(nx, n))
    z_only = x
    for _ in range(substeps):
        A, B, z = kernel(z, u, hs, *pm, A, B)
        if step is kernel:                     # its A and B not asked for: not formed
            z_only = kernel(z_only, u, hs, *pm, ca.MX(ca.DM.eye(nx)), ca.MX(nx, n))[2]
        else:
            z_only = step(z_only, u, hs, *pm)
    return ca.Function("interval", [x, u, mm], [z, A, B]), ca.Function("interval_x", [x, u, mm], [z_only])


def limit_arrays(arm: Arm) -> dict:
    """The joints' limits (rscasadi.model.limits.limit_arrays: inf where none): tau, psi, dphi,
    theta_lo, theta_hi."""
    return model_limits(arm.model)


def input_limits(arm: Arm) -> np.ndarray:
    """The torque limit of each input (the actuated joints', in tau's order)."""
    return model_limits(arm.model)["tau"][arm.model.actuated]


def reference_rows(n: int, p: MPCProblem) -> int:
    """Rows of one reference column: 2n (link angles and speeds) or the task space's 6 or 15 per frame."""
    return p.reference_rows if p.task_space else 2 * n


def mpc_terms(arm: Arm, p: MPCProblem, limits: dict) -> tuple:
    """The stage cost's terms (rscasadi.task.terms): the tracking of the reference (link angles
    and speeds, or the frame's position, velocity [and rotation] and the posture), the psi, dphi
    and link-angle limits soft beyond SOFT of them (angles: of the range's half-width about its
    middle; in joint space as far out as the reference goes, if farther: AngleBand), the
    obstacles, then the problem's own terms, soft at their weights."""
    n, w = arm.n, p.weights
    if p.task_space:
        terms = [FrameTracking(p.frames, w["position"], w["velocity"], w["orientation"] if p.orientation else None),
                 Posture(n, w["posture"])]
    else:
        terms = [JointTracking(n, w["theta"], w["dtheta"])]
    ranged = np.isfinite(limits["theta_lo"]) & np.isfinite(limits["theta_hi"])
    lo, hi = np.where(ranged, limits["theta_lo"], 0.0), np.where(ranged, limits["theta_hi"], 0.0)
    middle, half = (lo + hi) / 2, np.where(ranged, (hi - lo) / 2, np.inf)
    for quantity, limit, weight in (("psi", limits["psi"], w["limits"]), ("dphi", limits["dphi"], w["limits"])):
        if np.isfinite(limit).any() and weight > 0:
            terms.append(StateBound(quantity, SOFT * limit, weight))
    if np.isfinite(half).any() and w["angle_limits"] > 0:
        if p.task_space:
            terms.append(StateBound("theta", SOFT * half, w["angle_limits"], middle))
        else:                             # the band opens to a reference that goes nearer the edge
            terms.append(AngleBand(n, SOFT * half, half, middle, w["angle_limits"]))
    if p.obstacles:
        terms.append(Clearance(p.obstacles, w["obstacles"]))
    return tuple(terms) + tuple(p.terms)


def stage_residual(arm: Arm, p: MPCProblem, limits: dict) -> ca.Function:
    """(x_k, u, reference_k, posture) -> (r, dr/dx, dr/du): the weighted residual whose half
    squared norm is the stage cost at an interval's end x_k with the interval's torque u: each
    of `mpc_terms`' penalty residuals (a cost's sqrt(weight) r, a constraint's sqrt(weight)
    excess), each given the parameter it names."""
    n = arm.n
    x, u = ca.SX.sym("x", 2 * arm.nq), ca.SX.sym("u", arm.u)
    ref, posture = ca.SX.sym("reference", reference_rows(n, p)), ca.SX.sym("posture", n)
    supplied = {"reference": ref, "posture": posture, None: ca.SX(0, 1)}
    r = ca.vertcat(*[t.penalty_residual(arm, x, u, supplied[t.parameter]) for t in mpc_terms(arm, p, limits)])
    return ca.Function("stage_residual", [x, u, ref, posture], [r, ca.jacobian(r, x), ca.jacobian(r, u)])


def sample_ahead(arm: Arm, p: MPCProblem, step_jacobian: ca.Function | None = None,
                 name: str = "mpc_ahead") -> ca.Function | None:
    """(x, tau, m) -> (r, dr/dx, dr/dtau): the soft slow-side speed limits (`mpc_terms`' dphi
    rows) at the state one sample after x under tau (the problem's integrator over `sample_time`,
    in steps no longer than its substeps), through that step's sensitivities.  That is the state
    the arm is in when the next torque is computed; the intervals' ends never see it (sample <
    interval), and a plan re-made every sample could always brake later: on the shelf motion the
    speed limits overshot by 31 %.  The speeds alone: the torque moves them within a sample,
    while a deflection's or a link angle's excess barely moves in one, so its row would ask for
    a torque step of its excess over that small change (the arm oscillated at rest).  None where
    there is no such row, or where the sample is the interval (its end is the first node)."""
    p = with_integrator(p, arm)
    bounds = [t for t in mpc_terms(arm, p, limit_arrays(arm)) if isinstance(t, StateBound) and t.quantity == "dphi"]
    if not bounds or p.sample_time >= p.interval:
        return None
    h = p.interval / int(p.substeps)
    F, _ = interval_functions(arm, p.sample_time, int(np.ceil(p.sample_time / h - 1e-9)), step_jacobian, p.integrator)
    nx, n = 2 * arm.nq, arm.u
    z, none = ca.SX.sym("z", nx), ca.SX(0, 1)
    rows = ca.vertcat(*[b.penalty_residual(arm, z, ca.SX.zeros(n), none) for b in bounds])
    limit_rows = ca.Function("limit_rows", [z], [rows, ca.jacobian(rows, z)], {"cse": True})
    x, u, m = ca.MX.sym("x", nx), ca.MX.sym("tau", n), ca.MX.sym("m", F.size1_in(2))
    xs, A, B = F(x, u, m)
    r, Jz = limit_rows(xs)
    return ca.Function(name, [x, u, m], [ca.densify(r), ca.densify(ca.mtimes(Jz, A)), ca.densify(ca.mtimes(Jz, B))],
                       ["x", "tau", "m"], ["r", "Jx", "Ju"])


class _Linearisation:
    """The Gauss-Newton QP of the multiple-shooting NLP at (X, U), condensed (Bock & Plitt):
    dx_{k+1} = A_k dx_k + B_k du_k + c_k with the gap c_k = F(X_k, U_k) - X_{k+1}; so
    dx_k = E_k + G_k dU_{<k}, and the QP is in dU alone.  G_k holds only the columns of
    du_0..du_{k-1} (the later ones cannot act on x_k): the products that form H and g run over
    n k columns, not n N.
    With the measured state xm, dx_0 = xm - X_0 (initial-value embedding) and each residual is
    linearised at X_{k+1} + E_k.  With xm None (the split real-time iteration's preparation,
    Diehl), dx_0 stays a parameter: E_k = e_k + Phi_k dx_0 (e_k from the gaps alone,
    Phi_k = A_{k-1} ... A_0), each residual linearised at X_{k+1} + e_k, and the gradient is
    g + M dx_0: what the measurement changes is affine, and the feedback is that product and the
    QP alone."""

    def __init__(self, F, residual, p: MPCProblem, xm, ref, X, U, posture, mass, ahead=None):
        n, N = U.shape[0], p.horizon
        nx, nU = X.shape[0], n * N
        self.H, self.g = p.weights["tau"] * ca.MX.eye(nU), p.weights["tau"] * ca.vec(U)
        E, G = (ca.MX(nx, 1) if xm is None else xm - X[:, 0]), ca.MX(nx, 0)
        Phi, self.M = (ca.MX.eye(nx), ca.MX(nU, nx)) if xm is None else (None, None)
        if ahead is not None:                     # the limits one sample on (`sample_ahead`): tau_0 alone acts
            r, Jx, Ju = ahead(X[:, 0] + E, U[:, 0], mass)
            self.H += ca.diagcat(ca.mtimes(Ju.T, Ju), ca.MX(nU - n, nU - n))
            self.g += ca.vertcat(ca.mtimes(Ju.T, r), ca.MX(nU - n, 1))
            if self.M is not None:
                self.M += ca.vertcat(ca.mtimes(Ju.T, Jx), ca.MX(nU - n, nx))
        self.E, self.G, self.Phi = [E], [G], [Phi]
        for k in range(N):
            xp, A, B = F(X[:, k], U[:, k], mass)
            E = ca.mtimes(A, E) + xp - X[:, k + 1]
            G = ca.horzcat(ca.mtimes(A, G), B)                      # nx x n (k + 1), dense
            Phi = None if Phi is None else ca.mtimes(A, Phi)
            self.E.append(E)
            self.G.append(G)
            self.Phi.append(Phi)
            r, Jx, Ju = residual(X[:, k + 1] + E, U[:, k], ref[:, k], posture)
            J, rest = ca.mtimes(Jx, G) + ca.horzcat(ca.MX(Ju.shape[0], n * k), Ju), nU - n * (k + 1)
            self.H += ca.diagcat(ca.mtimes(J.T, J), ca.MX(rest, rest))
            self.g += ca.vertcat(ca.mtimes(J.T, r), ca.MX(rest, 1))
            if Phi is not None:
                self.M += ca.vertcat(ca.mtimes(J.T, ca.mtimes(Jx, Phi)), ca.MX(rest, nx))

    def step(self, dU):
        """dX = (E_k + G_k dU_{<k})_k."""
        return ca.horzcat(*[E + ca.mtimes(G, dU[:G.shape[1]]) for E, G in zip(self.E, self.G)])

    def maps(self):
        """Prepared (xm None): (Eb, Phi, Gf) with dX (stacked, nx (N + 1)) = Eb + Phi dx_0 + Gf dU."""
        nU = self.H.shape[0]
        return (ca.vertcat(*self.E), ca.vertcat(*self.Phi),
                ca.vertcat(*[ca.horzcat(G, ca.MX(G.shape[0], nU - G.shape[1])) for G in self.G]))

    def angle_rows(self, X, limits: dict):
        """The plan's link angles at the interval ends k = 1..N as rows of the QP: (C, cl, cu) with
        theta_k = X_k + E_k + G_k dU within [theta_lo, theta_hi] (joints with a range; an open
        end at HARD_OPEN rad), C block lower triangular; prepared, also Cx: the bounds at dx_0 are
        cl - Cx dx_0, cu - Cx dx_0.  None without a range."""
        lo, hi = hard_range(limits)
        joints = [j for j in range(len(lo)) if np.isfinite(limits["theta_lo"][j]) or np.isfinite(limits["theta_hi"][j])]
        if not joints:
            return None
        nU, N = self.H.shape[0], len(self.E) - 1
        C = ca.vertcat(*[ca.horzcat(G[joints, :], ca.MX(len(joints), nU - G.shape[1])) for G in self.G[1:]])
        at = ca.vertcat(*[X[joints, k] + self.E[k][joints] for k in range(1, N + 1)])
        rows = C, np.tile(lo[joints], N) - at, np.tile(hi[joints], N) - at
        if self.Phi[0] is None:
            return rows
        return (*rows, ca.vertcat(*[self.Phi[k][joints, :] for k in range(1, N + 1)]))


HARD_OPEN = 1e3      # rad: the missing end of a one-sided range, for the hard link-angle rows
HARD_PRICE = 1e4     # the exact penalty per unit excess of a (unit-norm) row in box_qp's scaled QP
HARD_MERIT = 1e10    # the line search's price per rad beyond a hard range (sqp_iterations > 1)


def hard_range(limits: dict):
    """The link-angle ranges the hard rows hold, an open end at -+HARD_OPEN."""
    return (np.where(np.isfinite(limits["theta_lo"]), limits["theta_lo"], -HARD_OPEN),
            np.where(np.isfinite(limits["theta_hi"]), limits["theta_hi"], HARD_OPEN))


def rollout(Fx, residual, p: MPCProblem, limits: dict, xm, ref, U, posture, mass, ahead=None):
    """The NLP's cost along the plan's states simulated from the measured state, and those states:
    the measure of progress of the line search (a condensed, hence gap-free, merit function)."""
    xs, total = [xm], 0.5 * p.weights["tau"] * ca.sumsqr(U)
    if ahead is not None:
        total += 0.5 * ca.sumsqr(ahead(xm, U[:, 0], mass)[0])
    lo, hi = hard_range(limits) if p.angle_limits == "hard" else (None, None)
    n = len(limits["theta_lo"])                                          # the link angles: x's first n
    for k in range(p.horizon):
        xs.append(Fx(xs[-1], U[:, k], mass))
        total += 0.5 * ca.sumsqr(residual(xs[-1], U[:, k], ref[:, k], posture)[0])
        if lo is not None:
            total += HARD_MERIT * ca.sum1(ca.fmax(xs[-1][:n] - hi, 0) + ca.fmax(lo - xs[-1][:n], 0))
    return total, ca.horzcat(*xs)


def _max_step(v, dv, fraction: float):
    """The longest step <= 1 keeping v + a dv > 0, times the fraction to the boundary."""
    neg = dv < 0
    ratios = neg * (-v / (dv - (1 - neg))) + (1 - neg) * 1e30
    return ca.fmin(1.0, fraction * ca.mmin(ratios))


MU_MIN = 1e-14      # the scaled QP's complementarity at which the interior-point iterate is kept


@functools.lru_cache(maxsize=None)
def _ipm_iteration(m: int, rows: tuple = ()) -> ca.Function:
    """One Mehrotra predictor-corrector iteration (Nocedal & Wright, alg. 16.4) of `box_qp` on the
    (scaled) QP of size m, as straight-line SX.  Every inequality is A_i v >= b_i with a slack
    s_i and a dual z_i; the Newton step solves (Q + A' Z S^-1 A) dv = -r_d - A' S^-1 (r_c + Z r_p)
    (eq. 16.62), reduced onto d: the row penalties t enter diagonally and are eliminated, so one
    Cholesky factor of an m x m matrix serves the predictor and the corrector.
    rows: the sparsity pattern ((row, column) pairs) of C in the rows cl <= C d <= cu, softened
    by t >= 0 at the price rho 1't: the inequalities cu - C d + t >= 0, C d + t - cl >= 0, t >= 0."""
    H, g, lo, hi, d, sl, su, zl, zu = (ca.SX.sym(name, *shape) for name, shape in (
        ("H", (m, m)), ("g", (m, 1)), ("lo", (m, 1)), ("hi", (m, 1)), ("d", (m, 1)),
        ("sl", (m, 1)), ("su", (m, 1)), ("zl", (m, 1)), ("zu", (m, 1))))
    p = (max(r for r, _ in rows) + 1) if rows else 0
    C = ca.SX.sym("C", ca.Sparsity.triplet(p, m, [r for r, _ in rows], [c for _, c in rows]))
    cl, cu, rho, t, s3, s4, z3, z4, zt = (ca.SX.sym(name, *shape) for name, shape in (
        ("cl", (p, 1)), ("cu", (p, 1)), ("rho", (1, 1)), ("t", (p, 1)), ("s3", (p, 1)), ("s4", (p, 1)),
        ("z3", (p, 1)), ("z4", (p, 1)), ("zt", (p, 1))))
    Cd = ca.mtimes(C, d)
    rd = ca.mtimes(H, d) + g - zl + zu + ca.mtimes(C.T, z3 - z4)           # dual residuals
    rt = rho - z3 - z4 - zt
    rp = (d - lo - sl, hi - d - su, cu - Cd + t - s3, Cd + t - cl - s4)     # primal residuals
    pairs = ((sl, zl), (su, zu), (s3, z3), (s4, z4), (t, zt))
    mu = sum(ca.dot(s, z) for s, z in pairs) / (2 * m + 3 * p)
    D = [z / s for s, z in pairs]
    Ktt = D[2] + D[3] + D[4]
    R = ca.chol(H + ca.diag(D[0] + D[1]) + (ca.mtimes(C.T, ca.mtimes(ca.diag((4 * D[2] * D[3] + (D[2] + D[3]) * D[4]) / Ktt), C))
                                            if p else 0))

    def newton(sigma_mu, corrections):                                # eq. (16.62), reduced
        rc = [s * z + c - sigma_mu for (s, z), c in zip(pairs, corrections)]
        w = [(rc[i] + pairs[i][1] * rp[i]) / pairs[i][0] for i in range(4)] + [rc[4] / t]
        rhs_d = -rd - w[0] + w[1] + ca.mtimes(C.T, w[2] - w[3])
        rhs_t = -rt - w[2] - w[3] - w[4]
        dd = ca.solve(R, ca.solve(R.T, rhs_d - ca.mtimes(C.T, (D[3] - D[2]) * rhs_t / Ktt)))
        Cdd = ca.mtimes(C, dd)
        dt = (rhs_t - (D[3] - D[2]) * Cdd) / Ktt
        ds = (dd + rp[0], rp[1] - dd, rp[2] - Cdd + dt, rp[3] + Cdd + dt, dt)
        return dd, dt, ds, [-(rc[i] + pairs[i][1] * ds[i]) / pairs[i][0] for i in range(5)]

    def longest(ds, dz, fraction):
        a = ca.SX(1.0)
        for (s, z), dsi, dzi in zip(pairs, ds, dz):
            if s.shape[0]:
                a = ca.fmin(a, ca.fmin(_max_step(s, dsi, fraction), _max_step(z, dzi, fraction)))
        return a

    zero = [0] * 5
    dd, dt, ds, dz = newton(0, zero)                                  # predictor (affine scaling)
    a = longest(ds, dz, 1)
    mu_aff = sum(ca.dot(s + a * dsi, z + a * dzi) for (s, z), dsi, dzi in zip(pairs, ds, dz)) / (2 * m + 3 * p)
    dd, dt, ds, dz = newton((mu_aff / mu) ** 3 * mu, [dsi * dzi for dsi, dzi in zip(ds, dz)])   # corrector
    a = longest(ds, dz, 0.995)
    state = [d, sl, su, zl, zu] + ([t, s3, s4, z3, z4, zt] if p else [])
    steps = [dd, ds[0], ds[1], dz[0], dz[1]] + ([dt, ds[2], ds[3], dz[2], dz[3], dz[4]] if p else [])
    data = [H, g, lo, hi] + ([C, cl, cu, rho] if p else [])
    new = [v + a * dv for v, dv in zip(state, steps)]
    # converged (or broken down): keep the iterate; later iterations would divide by ~0
    total = sum(ca.sum1(v) for v in new)
    go = ca.logic_and(mu > MU_MIN, total - total == 0)
    return ca.Function("box_qp_iteration", data + state, [ca.if_else(go, v, v0) for v, v0 in zip(new, state)],
                       {"cse": True})


def box_qp(H, g, lo, hi, iterations: int, rows=None, rho: float = 1e4):
    """min 1/2 d' H d + g' d subject to lo <= d <= hi: `iterations` primal-dual interior-point
    iterations with Mehrotra's predictor-corrector (`_ipm_iteration`), slacks for both bounds, the
    QP scaled to O(1) first.  Fixed work and no allocation in C.  On this MPC's cold steps to far
    poses it reaches qpOASES' solution to 3e-9 in 15 iterations (tests/test_mpc.py).
    rows = (C, cl, cu): also cl <= C d <= cu, each row with an exact (L1) penalty on its excess
    (Fletcher's elastic mode): the QP stays feasible when the rows cannot all hold, and where
    they can its solution is the one with the rows hard, as long as rho (per row, each row
    scaled to a unit norm, in the scaled objective's units) exceeds the row's
    multiplier.
    Why not a generated solver: CasADi's qrqp returned bound-violating 'successes' on these QPs
    (CasADi issue #3141), DAQP's generated C allocates in every call, and projected Newton without
    a line search cycles (with one it stalls at this conditioning, ~1e8)."""
    m = g.shape[0]
    c = ca.mmax(ca.fabs(g)) + ca.mmax(ca.diag(H))
    H, g = H / c, g / c
    d = ca.fmin(ca.fmax(ca.MX.zeros(m), lo), hi)
    state = [d] + [ca.MX.ones(m) for _ in range(4)]
    data = [H, g, lo, hi]
    pattern: tuple = ()
    if rows is not None:
        C, cl, cu = rows
        size = ca.fmax(ca.sqrt(ca.sum2(C * C)), 1e-12)                    # each row to a unit norm
        C, cl, cu = ca.mtimes(ca.diag(1 / size), C), cl / size, cu / size
        Cd = ca.mtimes(C, d)
        t = ca.fmax(ca.fmax(Cd - cu, cl - Cd), 0) + 1                     # the rows hold with slack 1
        state += [t, cu - Cd + t, Cd + t - cl] + [rho / 3 * ca.MX.ones(C.shape[0]) for _ in range(3)]   # r_t = 0
        data += [C, cl, cu, rho]
        Cs = C.sparsity()
        pattern = tuple(zip(Cs.get_triplet()[0], Cs.get_triplet()[1]))
    iteration = _ipm_iteration(m, pattern)
    for _ in range(iterations):
        state = iteration(*data, *state)
    return ca.fmin(ca.fmax(state[0], lo), hi)


def shifted(Z, alpha: float):
    """The plan moved forward by alpha intervals (one sample): linear interpolation, last column held."""
    Zn = ca.horzcat(Z[:, 1:], Z[:, -1])
    return (1 - alpha) * Z + alpha * Zn


def rti_function(arm: Arm, p: MPCProblem, step_jacobian: ca.Function | None = None, name: str = "mpc_rti") -> ca.Function:
    """mpc_rti(x, reference, X, U, params) -> (tau, X_next, U_next): `sqp_iterations`
    Gauss-Newton SQP iterations of the multiple-shooting NLP (1: the real-time iteration; more:
    each with a line search on the rollout's cost), then the plan shifted by one sample.
    params: the posture (n) and the payload's mass (if `arm` takes it: `controller_arm`).
    step_jacobian: as `interval_functions`."""
    p = with_integrator(p, arm)
    n, N, nx, nu = arm.n, p.horizon, 2 * arm.nq, arm.u
    F, Fx = interval_functions(arm, p.interval, int(p.substeps), step_jacobian, p.integrator)
    limits = limit_arrays(arm)
    residual = stage_residual(arm, p, limits)
    ahead = sample_ahead(arm, p, step_jacobian)
    xm, ref = ca.MX.sym("x", nx), ca.MX.sym("reference", reference_rows(n, p), N)
    params = ca.MX.sym("params", n_params(arm))
    posture, mass = params[:n], params[n:]
    X0, U0 = ca.MX.sym("X", nx, N + 1), ca.MX.sym("U", nu, N)
    X, U, phi0 = X0, U0, None
    tau_max = np.tile(input_limits(arm), N)
    for _ in range(p.sqp_iterations):
        lin = _Linearisation(F, residual, p, xm, ref, X, U, posture, mass, ahead)
        rows = lin.angle_rows(X, limits) if p.angle_limits == "hard" else None
        dU = box_qp(lin.H, lin.g, -tau_max - ca.vec(U), tau_max - ca.vec(U), p.qp_iterations, rows, HARD_PRICE)
        dX = lin.step(dU)
        if p.sqp_iterations == 1:                                         # RTI: the full step
            X, U = X + dX, U + ca.reshape(dU, nu, N)
            continue
        # step sizes tried in a fixed set (fixed work in C): the longest whose rollout lowers the
        # cost, else the shortest; the states become that rollout (the gaps close), and its cost
        # is the next iteration's reference
        if phi0 is None:
            phi0 = rollout(Fx, residual, p, limits, xm, ref, U, posture, mass, ahead)[0]
        dU = ca.reshape(dU, nu, N)
        alpha = ca.MX(LINE_SEARCH[-1])
        phi_new, X_new = rollout(Fx, residual, p, limits, xm, ref, U + alpha * dU, posture, mass, ahead)
        for a in reversed(LINE_SEARCH[:-1]):
            phi, Xa = rollout(Fx, residual, p, limits, xm, ref, U + a * dU, posture, mass, ahead)
            better = phi < phi0
            alpha, phi_new, X_new = ca.if_else(better, a, alpha), ca.if_else(better, phi, phi_new), ca.if_else(better, Xa, X_new)
        X, U, phi0 = X_new, U + alpha * dU, phi_new
    X = ca.horzcat(xm, X[:, 1:])
    alpha = p.sample_time / p.interval
    return ca.Function(name, [xm, ref, X0, U0, params], [U[:, 0], shifted(X, alpha), shifted(U, alpha)],
                       ["x", "reference", "X", "U", "params"], ["tau", "X_next", "U_next"])


PREPARED = ("H", "g0", "M", "Eb", "Phi", "Gf", "C", "cl0", "cu0", "Cx")


def prepare_function(arm: Arm, p: MPCProblem, step_jacobian: ca.Function | None = None,
                     name: str = "mpc_prepare") -> ca.Function:
    """mpc_prepare(reference, X, U, params) -> the real-time iteration's QP before the
    measurement (`_Linearisation` without xm): H, g0, M, the maps Eb, Phi, Gf of the plan's change and, with hard
    angle limits, the rows C, cl0, cu0, Cx (empty without).  Only for sqp_iterations = 1."""
    p = with_integrator(p, arm)
    n, N, nx = arm.n, p.horizon, 2 * arm.nq
    F, _ = interval_functions(arm, p.interval, int(p.substeps), step_jacobian, p.integrator)
    limits = limit_arrays(arm)
    ref = ca.MX.sym("reference", reference_rows(n, p), N)
    params = ca.MX.sym("params", n_params(arm))
    X, U = ca.MX.sym("X", nx, N + 1), ca.MX.sym("U", arm.u, N)
    prep = _Linearisation(F, stage_residual(arm, p, limits), p, None, ref, X, U, params[:n], params[n:],
                          sample_ahead(arm, p, step_jacobian))
    rows = prep.angle_rows(X, limits) if p.angle_limits == "hard" else None
    rows = rows if rows is not None else (ca.MX(0, arm.u * N), ca.MX(0, 1), ca.MX(0, 1), ca.MX(0, nx))
    return ca.Function(name, [ref, X, U, params], [prep.H, prep.g, prep.M, *prep.maps(), *rows],
                       ["reference", "X", "U", "params"], list(PREPARED))


def feedback_function(arm: Arm, p: MPCProblem, prepare: ca.Function, name: str = "mpc_feedback") -> ca.Function:
    """mpc_feedback(x, X, U, prepared...) -> (tau, X_next, U_next): the QP of `prepare`'s outputs
    at the measured state (g = g0 + M dx_0, the rows' bounds moved), solved by `box_qp`, the plan
    stepped (Eb + Phi dx_0 + Gf dU) and shifted by one sample."""
    n, N, nx = arm.u, p.horizon, 2 * arm.nq
    xm, X0, U0 = ca.MX.sym("x", nx), ca.MX.sym("X", nx, N + 1), ca.MX.sym("U", n, N)
    got = {k: ca.MX.sym(k, prepare.sparsity_out(k)) for k in PREPARED}
    dx0 = xm - X0[:, 0]
    tau_max = np.tile(input_limits(arm), N)
    shift = ca.mtimes(got["Cx"], dx0)
    rows = (got["C"], got["cl0"] - shift, got["cu0"] - shift) if got["C"].shape[0] else None
    dU = box_qp(got["H"], got["g0"] + ca.mtimes(got["M"], dx0), -tau_max - ca.vec(U0), tau_max - ca.vec(U0),
                p.qp_iterations, rows, HARD_PRICE)
    dX = ca.reshape(got["Eb"] + ca.mtimes(got["Phi"], dx0) + ca.mtimes(got["Gf"], dU), nx, N + 1)
    X, U = ca.horzcat(xm, (X0 + dX)[:, 1:]), U0 + ca.reshape(dU, n, N)
    alpha = p.sample_time / p.interval
    return ca.Function(name, [xm, X0, U0, *got.values()], [U[:, 0], shifted(X, alpha), shifted(U, alpha)],
                       ["x", "X", "U", *got], ["tau", "X_next", "U_next"])


def stage_functions(arm: Arm, p: MPCProblem, step_jacobian: ca.Function | None = None, prefix: str = "mpc_"):
    """The QP's pieces one interval at a time, for the Riccati recursion (qp = "riccati", the
    controller's C loops over the intervals): interval (x, tau, m) -> (x_next, A, B), the
    interval's steps and sensitivities (`interval_functions`), and residual (x, u, reference_k,
    posture) -> (r, dr/dx, dr/du) at an interval's end (`stage_residual`), every output dense
    (column-major in C).  The stage QP they give (rscasadi_mpc.c) is `_Linearisation`'s, interval
    by interval: with the gaps b_k = x_next - X_{k+1} and their propagation e_{k+1} = A_k e_k +
    b_k, the residual at X_{k+1} + e_{k+1}, linear in (dx_k, du_k) through dx_{k+1} = A_k dx_k +
    B_k du_k + b_k."""
    p = with_integrator(p, arm)
    n, nx = arm.u, 2 * arm.nq
    F, _ = interval_functions(arm, p.interval, int(p.substeps), step_jacobian, p.integrator)
    x, u, m = ca.MX.sym("x", nx), ca.MX.sym("tau", n), ca.MX.sym("m", F.size1_in(2))
    interval = ca.Function(prefix + "interval", [x, u, m], [ca.densify(v) for v in F(x, u, m)],
                           ["x", "tau", "m"], ["x_next", "A", "B"])
    residual = stage_residual(arm, p, limit_arrays(arm))
    ins = residual.sx_in()
    residual = ca.Function(prefix + "residual", ins, [ca.densify(v) for v in residual(*ins)],
                           ["x", "u", "reference", "posture"], ["r", "Jx", "Ju"], {"cse": True})
    return interval, residual


def hold_function(arm: Arm, p: MPCProblem, name: str = "mpc_hold") -> ca.Function:
    """mpc_hold(x, params) -> (X, U): the initial plan, the arm held where it is over the horizon."""
    n = arm.n
    x, params = ca.SX.sym("x", 2 * arm.nq), ca.SX.sym("params", n_params(arm))
    z, zm = ca.SX.zeros(n), ca.SX.zeros(arm.m)
    pm = [params[n:]] if arm.free else []
    theta, phi, _, _ = arm.split_state(x)
    tau = arm.inverse_dynamics(parametric=bool(arm.free))(theta, phi, z, zm, z, zm, *pm)[0]
    return ca.Function(name, [x, params], [ca.repmat(x, 1, p.horizon + 1), ca.repmat(tau, 1, p.horizon)],
                       ["x", "params"], ["X", "U"])
