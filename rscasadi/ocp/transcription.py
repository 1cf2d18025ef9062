"""Direct collocation, stage by stage, so that a structure-exploiting solver (fatrop) sees the
optimal-control structure and a general one (IPOPT) is none the worse.

Collocation is written as the implicit Runge-Kutta method it is (Butcher tableau A, b, c of
the collocation points: Radau IIA, Gauss-Legendre, or Lobatto IIIA for Hermite-Simpson), with
the *accelerations* at the points as the unknowns.  For q'' = a the positions and speeds at the
points are then linear in them,

    v_j = v_k + h sum_l A_jl a_l,   q_j = q_k + h c_j v_k + h^2 sum_l (A A)_jl a_l,

so an interval carries nq m unknowns and nq m dynamics equations instead of 2 nq m of each: the
same polynomial solution as collocating the states, half the stage size (fatrop's Riccati
recursion costs about the cube of it).

Stage k = 0..N-1 has the state x_k = (theta, phi, dtheta, dphi, [T], [design]) (theta: every
joint's link, phi: the SEAs' motors, nq = n + m coordinates) and the "control" u_k = (tau_k: the
actuated joints', the accelerations at its m points, scaled).  Constraints in stage order:

    x_{k+1} - F(x_k, u_k) = 0           gap closing: the interval's end point (T, design carried)
    c_k(x_k, u_k) (=, <=) 0             dynamics at the points (explicit: a_j = FD(q_j, v_j, tau);
                                        implicit: the inverse-dynamics residual), limits at the
                                        interior points and the SEA deflection (and a geared
                                        joint's motor speed) at x_k, (stage 0) the start
    c_N(x_N)                            the end at rest (rest-to-rest problems), deflection, motor speed

A designed or swept gear ratio keeps the motor: its speed limit mu dphi is the model file's, so
dphi's limit is a row (mu / mu_file) dphi within limits.dphi instead of a bound.  The NLP is
built as stage, start and end pieces, whose own derivatives assembly.py places.

Rest is the static equilibrium, stated as constraints (the actuated joints' theta given, speeds
zero, each SEA's spring torque = its gravity torque, each joint without an input balanced where
it hangs), so it holds for any designed or swept spring.  The mesh is the vector
of interval fractions w (sum 1, h_k = T w_k), an NLP parameter: refining a mesh with the same N
reuses the compiled NLP.  NLP parameters P = (theta_start, theta_end, duration, effort_weight,
objective scale, w, [theta_ref], [fixed model parameters]).
"""
from __future__ import annotations

import hashlib

import casadi as ca
import numpy as np

from rscasadi.dynamics.arm import Arm
from rscasadi.model.parameters import gear_ratios
from rscasadi.ocp.assembly import Calls, Piece, chain_rule_derivatives, constraints_and_objective
from rscasadi.ocp.condensing import Condensed, cached_kernel, condense
from rscasadi.ocp.problem import Goal, Problem
from rscasadi.task.objects import Limits
from rscasadi.task.terms import Clearance, objective_terms
from rscasadi.model.collision import capsule_pairs


# the stage pieces (fn, derivatives or None) by the stage's serialisation (the few most recent)
_DERIVATIVES: dict[str, tuple] = {}
_KEPT = 4


class Transcription:
    """The problem transcribed by direct collocation on N intervals: the NLP as start, stage and
    end pieces, its variables' layout, bounds and parameters, and its unpacking."""
    def __init__(self, problem: Problem, arm: Arm, N: int | None = None):
        self.p, self.model = problem, arm.model
        self.n, self.N = arm.n, N or problem.transcription.intervals
        # coordinates (theta: every joint, phi: the SEAs' motors), motors and torque inputs
        self.nq, self.motors, self.n_tau = arm.nq, list(arm.model.motors), arm.u
        self.actuated, self.passive = list(arm.model.actuated), [j for j in range(arm.n) if j not in arm.model.actuated]
        # each joint's slow side, whose speed `dphi` limits: an SEA's motor coordinate, a geared
        # joint's link (its rotors turn with it); as indices into the speeds v = (dtheta, dphi)
        self.slow = [(self.n + i, j) for i, j in enumerate(self.motors)] + \
            [(j, j) for j, k in enumerate(arm.model.kinds) if k.rotors == "link"]
        self.design, self.fixed = list(problem.task.design), list(problem.task.parameters)
        free = self.design + self.fixed
        self.arm = Arm(arm.model, free=free, tie_balanced=problem.transcription.parametric == "family") if free else arm
        # SEAs whose gear ratio is designed or swept (indices into the motors): their motor speed
        # limit mu dphi is the model's, so dphi's limit becomes a constraint row instead of a bound
        self.geared = [i for i, j in enumerate(self.motors) if f"{arm.model.joints[j].name}.gear_ratio" in free]
        n, nq = self.n, self.nq
        c = np.array([0.0, 0.5, 1.0]) if problem.transcription.method == "hermite-simpson" else \
            np.array(ca.collocation_points(problem.transcription.degree, problem.transcription.method))
        self.A, self.b = butcher(c)
        self.fractions, self.m = c, len(c)
        self.interior = [j for j in range(self.m) if 0.0 < c[j] < 1.0]
        self.nT = 1 if problem.task.objective == "min_time" else 0
        self.nz = self.nT + len(self.design)                                 # carried constants
        self.tool_path = problem.task.path                  # its frame's position pinned at every node
        # min_time along a path: the path's arc length s is a state, its rate a control (>= 0)
        self.ns = 1 if self.tool_path is not None and self.nT else 0
        self.nx = 2 * nq + self.nz + self.ns
        self.nu_lifted = self.n_tau + self.ns + nq * self.m
        # condensed: the accelerations are solved for inside the NLP's functions (condensing.py)
        self.condensed = problem.transcription.condense
        self.nu = self.n_tau + self.ns if self.condensed else self.nu_lifted
        self.n_start = 2 * nq + self.ns                                      # the start's rows
        # condensed, the collocation equations are solved exactly, so both forms give the same
        # NLP; the inverse dynamics' derivatives are the cheaper (Hessian 17 807 SX instructions
        # with the projections, 26 332 through the forward dynamics; n = 3)
        self.dynamics = "implicit" if self.condensed else problem.transcription.dynamics
        self.tracking = problem.task.objective == "tracking"
        self.goals = problem.task.goals if self.tool_path is None else (Goal(self.tool_path.frame, self.tool_path.end),)
        # what the arm must do, as terms (rscasadi.task.terms): the objective's costs (with the
        # power of effort_weight each weight takes), the problem's own, and the constraints
        self.costs = objective_terms(problem.task.objective, n) + [(t, 0) for t in problem.task.terms if not t.constraint]
        kept_apart = problem.task.obstacles or capsule_pairs(arm.model)       # from obstacles, and from each other
        self.constraints = ([Clearance(problem.task.obstacles)] if kept_apart else []) + \
            [t for t in problem.task.terms if t.constraint]
        self.row_bounds = [t.bounds(self.arm) for t in self.constraints]
        self.constraint_calls = [t.of_angles(self.arm) for t in self.constraints]     # None: inlined
        self.limits = Limits.of(arm.model).narrowed(problem.transcription.limit_margin)   # the NLP's reserve
        self.acc_scale = self._acceleration_scale()
        # a family's NLP takes the acceleration scale as parameters too (it is the arm's): p_fixed
        # = (the fixed parameters, then the scale)
        self.family = problem.transcription.parametric == "family"
        self.n_pfix = len(self.fixed) + (len(self.acc_scale) if self.family else 0)
        self.calls = None                    # a Calls recorder while the stage's derivatives are built
        self.kernel = None                   # the condensing kernel (condensing.Condensed), if condensed
        self.stage = self._stage_function()

    # -- the pieces of one stage ------------------------------------------------------------
    def _call(self, name, *args, pf=None):
        f = getattr(self.arm, name)(parametric=pf is not None)
        args = [*args, *([] if pf is None else [pf])]
        return f(*args) if self.calls is None else self.calls(f, args)

    def _called(self, f: ca.Function, args: list):
        """f at args, recorded as a call while the stage's derivatives are built."""
        return f(*args) if self.calls is None else self.calls(f, args)[0]

    def _f(self, x, u, pf):
        q = self.arm.split_state(x)
        return ca.vertcat(q[2], q[3], *self._call("forward_dynamics", *q, u, pf=pf))

    def _residual(self, x, a, u, pf):
        """Implicit dynamics: M ddq + c - Q = 0 (docs/user-guide/model.md section 3) from the
        inverse dynamics (tau_id, T_id), one row per coordinate, each a generalised force (N m):
        an SEA's link T_id - T and its motor mu (u - tau_id); a geared joint's mu (u - tau_id); a
        direct joint's u - tau_id; a joint without an input T_id (its spring and loss are in it)."""
        n, q = self.n, self.arm.split_state(x)
        tau_id, T_id = self._call("inverse_dynamics", *q, a[:n], a[n:], pf=pf)
        phys = self.arm.physics if pf is None else self.arm._physics_of(pf)
        mu, model = phys.columns["gear_ratio"], self.model
        if self.n_tau == len(self.motors) == n:                          # every joint an SEA
            return ca.vertcat(T_id - self.arm.sea_torque(*q, phys=phys), mu * (u - tau_id))
        T_sea = self.arm.sea_torque(*q, phys=phys)
        at, motor_of = model.input_of, model.motor_of
        drive = lambda j: (mu[j] if model.kinds[j].rotors else 1) * (u[at[j]] - tau_id[at[j]])   # noqa: E731
        rows = [T_id[j] - T_sea[motor_of[j]] if j in motor_of else drive(j) if j in at else T_id[j] for j in range(n)]
        return ca.vertcat(*rows, *[drive(j) for j in self.motors])

    def rest_residual(self, x, theta, pf):
        """At rest at theta in the static equilibrium: the actuated joints at theta, speeds 0, each
        SEA's T_K(psi) = its gravity torque, each joint without an input balanced (T_id = 0: where
        it hangs); theta None: at rest wherever the arm is."""
        n, q = self.n, self.arm.split_state(x[:2 * self.nq])
        z, zm = ca.DM.zeros(n), ca.DM.zeros(len(self.motors))
        T_g = self._call("inverse_dynamics", q[0], q[1], z, zm, z, zm, pf=pf)[1]
        phys = self.arm.physics if pf is None else self.arm._physics_of(pf)
        held = self.arm.sea_torque(q[0], q[1], z, zm, phys=phys) - _take(T_g, self.motors)
        rows = [q[2], q[3], held, _take(T_g, self.passive)]
        return ca.vertcat(*([] if theta is None else [_take(q[0] - theta, self.actuated)]), *rows)

    def goal_rows(self, theta, goal):
        """Each goal's frame at its pose: p - p_goal (3); with a rotation, the skew part of
        R_goal^T R (3) and its trace (>= 1: within 90 degrees, away from the half-turns).
        goal: the NLP parameter [p_goal; vec(R_goal)] of each goal in turn."""
        rows = []
        for i, g in enumerate(self.goals):
            R, p = self.arm.frame_placement(g.frame)(theta)
            rows.append(p - goal[12 * i:12 * i + 3])
            if g.R is not None:
                E = ca.reshape(goal[12 * i + 3:12 * i + 12], 3, 3).T @ R
                rows += [ca.vertcat(E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]) / 2, ca.trace(E)]
        return rows

    def _end_bounds(self):
        """Bounds of the end piece's rows: at rest (and at theta_end, or at the goal), then the
        SEA deflection and the geared joints' motor speeds."""
        psi_max, dphi_max = self._limit("psi")[self.motors], self._limit("dphi")[self.motors][self.geared]
        if self.tracking:
            rest_lo = rest_hi = np.zeros(0)
        elif not self.goals:
            rest_lo = rest_hi = np.zeros(2 * self.nq)
        else:
            # the trace's upper end open: trace(E) <= 3 holds for every rotation, with equality
            # exactly at the goal, where its gradient is zero; as a bound it is an active row
            # without a gradient, whose multiplier the interior point follows away
            rest = 2 * self.nq - len(self.actuated)          # speeds and balances; no theta rows
            rest_lo = np.r_[np.zeros(rest), *[np.r_[0.0, 0.0, 0.0, [0.0, 0.0, 0.0, 1.0] if g.R is not None else []]
                                               for g in self.goals]]
            rest_hi = np.r_[np.zeros(rest), *[np.r_[0.0, 0.0, 0.0, [0.0, 0.0, 0.0, np.inf] if g.R is not None else []]
                                               for g in self.goals]]
        ends = [b for t, b in zip(self.constraints, self.row_bounds) if t.at_end]
        s = np.zeros(self.ns)                                              # at the path's end: s_N = L
        return (np.concatenate([rest_lo, s, -psi_max, -dphi_max, *[lo for lo, _ in ends]]),
                np.concatenate([rest_hi, s, psi_max, dphi_max, *[hi for _, hi in ends]]))

    def _pf(self, design, p_fixed):
        """The free parameters' values, in the order of Arm(free=design + fixed); None if none."""
        parts = ([design] if self.design else []) + ([p_fixed[:len(self.fixed)]] if self.fixed else [])
        return ca.vertcat(*parts) if parts else None

    def _speed_scale(self, pf):
        """mu / mu_nominal per motor (1 where the gear ratio is the model's)."""
        if not self.geared:
            return ca.DM.ones(len(self.motors))
        mu = gear_ratios(self.model, self.design + self.fixed, pf) / ca.DM(self.model.column("gear_ratio"))
        return _take(mu, self.motors)

    def _geared_speeds(self, dphi, pf):
        """Rows of the geared joints' speed limits: their mu dphi / mu_nominal (none if none)."""
        return (self._speed_scale(pf) * dphi)[self.geared] if self.geared else ca.SX(0, 1)   # x[[]] of 1x1 is 1x1

    def _slow_speeds(self, v, pf):
        """Every slow side's speed (self.slow): the motors' mu dphi / mu_nominal, the geared
        joints' dtheta."""
        motors = self._speed_scale(pf) * v[self.n:]
        return ca.vertcat(motors, *[v[i] for i, _ in self.slow[len(self.motors):]])

    def _acceleration_scale(self):
        """The accelerations are variables a = s * a_scaled, s per coordinate about the largest
        acceleration the torque and deflection limits can cause, so that every variable is O(1)
        (unscaled, the implicit form took 149 iterations where the explicit one took 18)."""
        theta = self.p.task.theta_start if self.p.task.theta_start is not None else np.zeros(self.n)
        M = np.array(Arm(self.model).mass_matrix()(theta, theta[self.motors]))
        jts, kinds = self.model.joints, self.model.kinds
        drive = np.array([jt.limits.get("tau", 1.0) for jt in jts]) * np.where(
            [bool(k.rotors) for k in kinds], self.model.column("gear_ratio"), 1.0)
        k_psi = np.array([jt.k1 * jt.limits.get("psi", 0.1) for jt in jts])
        # on a link: its SEA's spring, its geared or direct drive, or (no input) its spring's
        # torque over 0.1 rad (at least 1 N m)
        link = np.where([k.motor for k in kinds], k_psi, np.where(
            [k.actuated for k in kinds], drive, np.maximum(0.1 * self.model.column("cb_k"), 1.0)))
        force = np.concatenate([link, (drive + k_psi)[self.motors]])
        acc = np.abs(np.linalg.solve(M, np.diag(force))).max(axis=1)
        return np.maximum(acc, 1e-3)

    def _stage_function(self) -> ca.Function:
        """(x_k, u_k, w_k, P) -> (x_{k+1} target, path constraints): SX, mapped over N."""
        x, u, w = ca.SX.sym("x", self.nx), ca.SX.sym("u", self.nu_lifted), ca.SX.sym("w")
        dur, pfix = ca.SX.sym("duration"), ca.SX.sym("p_fixed", self.n_pfix)
        return ca.Function("stage", [x, u, w, dur, pfix], self._stage(x, u, w, dur, pfix),
                           ["x", "u", "w", "duration", "p_fixed"], ["x_next", "path"])

    def _stage(self, x, u, w, dur, pfix):
        """The stage's expressions (its model calls recorded if self.calls is a recorder)."""
        n, nq, m, A, b, c = self.n, self.nq, self.m, self.A, self.b, self.fractions
        q, v, z, arc = x[:nq], x[nq:2 * nq], x[2 * nq:2 * nq + self.nz], x[2 * nq + self.nz:]
        h = (z[0] if self.nT else dur) * w
        pf = self._pf(z[self.nT:self.nz] if self.design else None, pfix)
        s = pfix[len(self.fixed):] if self.family else ca.DM(self.acc_scale)
        tau, a0 = u[:self.n_tau], self.n_tau + self.ns
        acc = [s * u[a0 + nq * j: a0 + nq * (j + 1)] for j in range(m)]      # ddtheta, ddphi
        AA = A @ A
        V = [v + h * sum(A[j, l] * acc[l] for l in range(m)) for j in range(m)]
        Q = [q + h * c[j] * v + h ** 2 * sum(AA[j, l] * acc[l] for l in range(m)) for j in range(m)]
        dynamics = []
        for j in range(m):
            xj = ca.vertcat(Q[j], V[j])
            if self.dynamics == "implicit":
                dynamics.append(self._residual(xj, acc[j], tau, pf))
            else:
                dynamics.append((acc[j] - self._f(xj, tau, pf)[nq:]) / s)
        x_end = ca.vertcat(q + h * v + h ** 2 * sum((b @ A)[l] * acc[l] for l in range(m)),
                           v + h * sum(b[l] * acc[l] for l in range(m)))
        psi = lambda q: q[n:] - _take(q, self.motors)                                # noqa: E731
        limits = [psi(q), self._geared_speeds(v[n:], pf)]                      # psi (geared dphi) at x_k
        for j in self.interior:                                                 # theta, psi, dphi inside
            limits += [Q[j][:n], psi(Q[j]), self._slow_speeds(V[j], pf)]
        for term, angles in zip(self.constraints, self.constraint_calls):      # the task's rows at x_k [and inside]
            points = [ca.vertcat(q, v)] + ([ca.vertcat(Q[j], V[j]) for j in self.interior] if term.inside else [])
            limits += [term.expression(self.arm, xj, tau, ca.SX(0, 1)) if angles is None else self._called(angles, [xj[:n]])
                       for xj in points]
        arc_end = arc + h * u[self.n_tau:self.n_tau + self.ns]                 # s_{k+1} = s_k + h ds_k
        return [ca.vertcat(x_end, z, arc_end), ca.vertcat(*dynamics, *limits)]

    # -- the NLP ----------------------------------------------------------------------------
    def parameter_layout(self):
        n, N = self.n, self.N
        sizes = [("theta_start", n), ("theta_end", n), ("duration", 1), ("effort_weight", 1), ("scale", 1),
                 ("w", N), ("theta_ref", n * N if self.tracking else 0), ("p_fixed", self.n_pfix),
                 ("goal", 12 * len(self.goals)),
                 ("path_target", 3 * N if self.tool_path and not self.ns else 0)]
        out, i = {}, 0
        for key, size in sizes:
            out[key] = slice(i, i + size)
            i += size
        return out, i

    def _stage_piece(self):
        """Stage k's constraint rows (gap closing, then path) and objective share, of its
        variables z = (x_k, u_k, x_{k+1}): (fn, its key, derivatives()) with derivatives() their
        derivatives by the chain rule through the stage's model calls
        (assembly.chain_rule_derivatives: 2.4x fewer instructions than AD), built when asked."""
        n, nq, nx, nu = self.n, self.nq, self.nx, self.nu_lifted
        z = ca.SX.sym("z", 2 * nx + nu)
        x, u, x1 = z[:nx], z[nx:nx + nu], z[nx + nu:]
        w, dur, pfix = ca.SX.sym("w"), ca.SX.sym("duration"), ca.SX.sym("p_fixed", self.n_pfix)
        ew, scale, ref = ca.SX.sym("effort_weight"), ca.SX.sym("scale"), ca.SX.sym("theta_ref", n)
        target = ca.SX.sym("path_target", 3)                 # where the path's frame is at x_k's time
        timed = self.tool_path is not None and not self.ns
        args = [w, dur, pfix, ew, scale] + ([ref] if self.tracking else []) + ([target] if timed else [])

        h = (x[2 * nq] if self.nT else dur) * w
        supplied = {"reference": ref, None: ca.SX(0, 1)}

        def pieces(stage):
            x_next, path = stage(x, u, w, dur, pfix)
            # each cost term at the interval's end with the interval's torques, integrated
            f = sum(h * _power(ew, power) * term.stage_weight
                    * ca.sumsqr(term.expression(self.arm, x1[:2 * nq], u[:self.n_tau], supplied[term.parameter]))
                    for term, power in self.costs)
            # fatrop's stage k may constrain x_k and u_k only: the path holds at x_k (the first
            # stage's rows are left free: theta_start is on the path), and the end's is the goal
            # (the timing free: at the path's point of its own arc length s_k)
            on = self.tool_path.position_symbolic(x[nx - 1]) if self.ns else target
            on_path = [self.arm.frame_placement(self.tool_path.frame)(x[:n])[1] - on] if self.tool_path else []
            return ca.vertcat(x1 - x_next, path, *on_path), scale * f

        fn = ca.Function("stage_piece", [z, *args], list(pieces(self.stage)),
                         ["z", "w", "duration", "p_fixed", "effort_weight", "scale"] + (["theta_ref"] if self.tracking else [])
                         + (["path_target"] if timed else []), ["rows", "f"])
        key = hashlib.sha256((fn.serialize() + repr(self.condensed)).encode()).hexdigest()
        if key not in _DERIVATIVES:
            while len(_DERIVATIVES) >= _KEPT:
                _DERIVATIVES.pop(next(iter(_DERIVATIVES)))
            _DERIVATIVES[key] = (fn, None)
        fn = _DERIVATIVES[key][0]            # the same Function object: compiled pieces are found by it

        def derivatives():
            # they depend on the stage alone, not on the mesh: a refinement round (or another
            # solve of the same stage) reuses them (7 joints: 8.6 s each time otherwise)
            if _DERIVATIVES.get(key, (None, None))[1] is None:
                self.calls = Calls()
                try:
                    rows, f = pieces(self._stage)
                    found = chain_rule_derivatives(fn, z, args, rows, f, self.calls, split=self.condensed)
                finally:
                    self.calls = None
                _DERIVATIVES[key] = (fn, found)
            return _DERIVATIVES[key][1]
        return fn, key, derivatives

    def _boundary_piece(self, end: bool) -> ca.Function:
        """The start (at rest at theta_start; T is the min-time objective) or the end (at rest at
        theta_end, or at rest with the goal frame at its pose, unless tracking; the SEA
        deflection within its limit) of x_0 or x_N.  `theta`: theta_start, theta_end or the goal."""
        n, nq = self.n, self.nq
        goal_end = end and bool(self.goals)
        x, theta = ca.SX.sym("x", self.nx), ca.SX.sym("theta", 12 * len(self.goals) if goal_end else n)
        pfix, scale = ca.SX.sym("p_fixed", self.n_pfix), ca.SX.sym("scale")
        pf = self._pf(x[2 * nq + self.nT:] if self.design else None, pfix)
        if end:
            rest = [] if self.tracking else [self.rest_residual(x, None if goal_end else theta, pf)]
            rest += self.goal_rows(x[:n], theta) if goal_end else []
            rest += [x[self.nx - 1] - self.tool_path.length] if self.ns else []
            rows = rest + [x[n:nq] - _take(x, self.motors), self._geared_speeds(x[nq + n:2 * nq], pf)]
            rows += [t.expression(self.arm, x[:2 * nq], ca.SX.zeros(self.n_tau), ca.SX(0, 1))
                     for t in self.constraints if t.at_end]
            f = ca.SX(0)
        else:
            rows = [self.rest_residual(x, theta, pf)] + ([x[self.nx - 1]] if self.ns else [])     # s_0 = 0
            f = scale * x[2 * nq] if self.p.task.objective == "min_time" else ca.SX(0)
        return ca.Function("end_piece" if end else "start_piece", [x, theta, pfix, scale], [ca.vertcat(*rows), f],
                           ["z", "theta", "p_fixed", "scale"], ["rows", "f"])

    def _n_path(self):
        """A stage's path rows (without the dynamics rows when condensed), and the path's frame's 3."""
        return self.stage.size1_out(1) - (self.nq * self.m if self.condensed else 0) + (3 if self.tool_path else 0)

    def _condensed(self, key, derivatives, log) -> Condensed:
        """The stage piece with its accelerations eliminated (condensing.py): kept z = (x_k, tau_k,
        x_{k+1}), solved rows = the dynamics at the points (the first path rows).  Found by the
        stage's key (this process's, or the cache's) without building its derivatives."""
        nx, nul, na = self.nx, self.nu_lifted, self.nq * self.m
        nu = self.n_tau + self.ns                                             # tau, [ds]
        keep = np.r_[np.arange(nx + nu), nx + nul + np.arange(nx)]

        def build():
            d1, f1, d2, split = derivatives()
            return condense(d1, f1, d2, split, keep, nx + nu + np.arange(na), nx + np.arange(na), log=log)
        return cached_kernel(key, build, log)

    def nlp(self, log=print):
        """The NLP dict and its constant bounds on g; variables and constraints in stage order.
        self.pieces: the same NLP as a sum of stage, start and end pieces (assembly.py)."""
        n, N, nx = self.n, self.N, self.nx
        layout, n_par = self.parameter_layout()
        P = ca.MX.sym("P", n_par)
        par = {k: P[s] for k, s in layout.items()}
        stride = nx + self.nu
        w = ca.MX.sym("w", N * stride + nx)                                 # stage by stage
        r = nx + self._n_path()                                             # a stage's rows
        end_lo, end_hi = self._end_bounds()
        n_end = len(end_lo)
        n0 = self.n_start
        stage_rows = np.vstack([np.arange(r)] + [r + n0 + (k - 1) * r + np.arange(r) for k in range(1, N)])
        n_g = r + n0 + (N - 1) * r + n_end
        at = lambda key, step=0: (layout[key].start, layout[key].stop - layout[key].start if step == 0 else step, step)
        stage_args = [ca.reshape(par["w"], 1, N), par["duration"], par["p_fixed"], par["effort_weight"], par["scale"]]
        stage_places = [at("w", 1), at("duration"), at("p_fixed"), at("effort_weight"), at("scale")]
        if self.tracking:
            stage_args.append(ca.reshape(par["theta_ref"], n, N))
            stage_places.append(at("theta_ref", n))
        if self.tool_path and not self.ns:
            stage_args.append(ca.reshape(par["path_target"], 3, N))
            stage_places.append(at("path_target", 3))
        stage, key, built = self._stage_piece()
        symbols = None
        if self.condensed:
            self.kernel = self._condensed(key, built, log)
            stage, derivatives = self.kernel.fn, self.kernel.derivatives
            stage_args.append(ca.DM(np.arange(N)).T)                        # the interval, for the kernel's cache
            stage_places.append((0, 1, -1))
            symbols = {role: self.kernel.prefix + "ext_" + name for role, name in
                       (("value", "rows"), ("first", "first"), ("objective", "objective"), ("second", "second"))}
        else:
            derivatives = built()
        target = "goal" if self.goals else "theta_end"
        self.pieces = [
            Piece(stage, np.arange(N)[:, None] * stride + np.arange(stride + nx), stage_rows, stage_args, derivatives,
                  self.kernel.library if self.kernel else None, symbols, stage_places),
            Piece(self._boundary_piece(False), np.arange(nx)[None, :], r + np.arange(n0)[None, :],
                  [par["theta_start"], par["p_fixed"], par["scale"]], arg_places=[at("theta_start"), at("p_fixed"), at("scale")]),
            Piece(self._boundary_piece(True), N * stride + np.arange(nx)[None, :], n_g - n_end + np.arange(n_end)[None, :],
                  [par[target], par["p_fixed"], par["scale"]], arg_places=[at(target), at("p_fixed"), at("scale")])]
        g, f = constraints_and_objective(self.pieces, w, n_g)
        stage_lo, stage_hi = self._path_bounds()
        first_lo, first_hi = stage_lo.copy(), stage_hi.copy()
        if self.tool_path:                                  # the start is theta_start: on the path already
            first_lo[-3:], first_hi[-3:] = -np.inf, np.inf
        lbg = np.concatenate([first_lo, np.zeros(n0), np.tile(stage_lo, N - 1), end_lo])
        ubg = np.concatenate([first_hi, np.zeros(n0), np.tile(stage_hi, N - 1), end_hi])
        return {"x": w, "f": f, "g": g, "p": P}, lbg, ubg

    def _limit(self, key):
        """A psi or dphi limit per joint (inf: none), less the transcription's limit_margin."""
        return getattr(self.limits, key)

    def _range(self):
        """The link-angle ranges (lo, hi), each narrowed by limit_margin of its width at both ends."""
        return self.limits.theta_lo, self.limits.theta_hi

    def _path_bounds(self):
        """Bounds of one stage's path rows: gap rows and dynamics = 0, then the limits."""
        lo_th, hi_th = self._range()
        psi, dphi = self._limit("psi")[self.motors], self._limit("dphi")
        slow = dphi[[j for _, j in self.slow]]
        eq = np.zeros(self.nx + (0 if self.condensed else self.nq * self.m))
        lo = [eq, -psi, -dphi[self.motors][self.geared]] + [np.r_[lo_th, -psi, -slow]] * len(self.interior)
        hi = [eq, psi, dphi[self.motors][self.geared]] + [np.r_[hi_th, psi, slow]] * len(self.interior)
        for term, (t_lo, t_hi) in zip(self.constraints, self.row_bounds):   # at x_k [and inside]
            times = 1 + (len(self.interior) if term.inside else 0)
            lo, hi = lo + [np.tile(t_lo, times)], hi + [np.tile(t_hi, times)]
        if self.tool_path:           # near the path at x_k: a box of half the tolerance (an equality
            b = 0.5 * self.tool_path.tolerance / np.sqrt(3)           # would over-determine a 3-joint arm)
            lo, hi = lo + [np.full(3, -b)], hi + [np.full(3, b)]
        return np.concatenate(lo), np.concatenate(hi)

    def structure(self) -> dict:
        """fatrop's manual structure: per stage nx, nu and the number of non-gap constraints."""
        N = self.N
        n_path = self._n_path()
        ng = [n_path + self.n_start] + [n_path] * (N - 1)
        ng.append(len(self._end_bounds()[0]))
        return {"structure_detection": "manual", "N": N, "nx": [self.nx] * (N + 1),
                "nu": [self.nu] * N + [0], "ng": ng}

    def bounds(self, max_duration: float):
        """Simple bounds: theta and dphi limits on every state point, tau limits, T and design boxes."""
        n, nq, N, jts = self.n, self.nq, self.N, self.model.joints
        lo_q, hi_q = np.full(2 * nq, -np.inf), np.full(2 * nq, np.inf)
        lo_q[:n], hi_q[:n] = self._range()
        dphi = self._limit("dphi")
        designed = {self.n + i for i in self.geared}                      # a row (_geared_speeds)
        for i, j in self.slow:
            if "dphi" in jts[j].limits and i not in designed:
                lo_q[nq + i], hi_q[nq + i] = -dphi[j], dphi[j]
        lo_z = ([1e-3] if self.nT else []) + [b[0] for b in self.p.task.design.values()] + [0.0] * self.ns
        hi_z = (([max_duration] if self.nT else []) + [b[1] for b in self.p.task.design.values()]
                + ([self.tool_path.length] if self.ns else []))           # 0 <= s <= L
        tau_max = np.array([jts[j].limits.get("tau", np.inf) for j in self.actuated])
        nt = self.n_tau
        lo_u = np.concatenate([-tau_max, np.zeros(self.ns), np.full(self.nu - nt - self.ns, -np.inf)])   # ds >= 0
        hi_u = np.concatenate([tau_max, np.full(self.nu - nt, np.inf)])
        lo_x, hi_x = np.concatenate([lo_q, lo_z]), np.concatenate([hi_q, hi_z])
        lb = np.concatenate([np.tile(np.concatenate([lo_x, lo_u]), N), lo_x])
        ub = np.concatenate([np.tile(np.concatenate([hi_x, hi_u]), N), hi_x])
        if self.p.transcription.limit_margin:       # the start and the end may lie in the reserve
            for at in (slice(0, n), slice(len(lb) - len(lo_x), len(lb) - len(lo_x) + n)):
                lb[at] = [jt.limits.get("theta", (-np.inf, np.inf))[0] for jt in jts]
                ub[at] = [jt.limits.get("theta", (-np.inf, np.inf))[1] for jt in jts]
        return lb, ub

    def parameters(self, theta_start, theta_end, duration, effort_weight, w, theta_ref=None, p_fixed=(), scale=1.0):
        """The NLP's parameter vector (the goal's pose and the path's targets, if any, from the problem)."""
        layout, n_par = self.parameter_layout()
        P = np.zeros(n_par)
        goal = np.concatenate([np.r_[g.position, (g.R if g.R is not None else np.eye(3)).ravel("F")]
                               for g in self.goals]) if self.goals else None
        for key, value in (("theta_start", theta_start), ("theta_end", theta_end), ("duration", duration),
                           ("effort_weight", effort_weight), ("scale", scale), ("w", w),
                           ("theta_ref", theta_ref), ("goal", goal),
                           ("p_fixed", np.r_[p_fixed, self.acc_scale] if self.family else p_fixed),
                           ("path_target", None if self.tool_path is None or self.ns else
                            self.tool_path(duration * np.r_[0.0, np.cumsum(w)[:-1]]).T)):
            if value is not None and layout[key].stop > layout[key].start:
                P[layout[key]] = np.ravel(value, order="F")
        return P

    # -- guesses and solutions --------------------------------------------------------------
    def pack(self, Xs, U, T, design, acc, arc=None, t=None):
        """Stage-ordered vector from Xs (2 nq, N+1), U (u, N), T, design, acc (nq, m, N) unscaled,
        and (min_time along a path) the arc lengths s (N+1) at the node times t."""
        N = self.N
        z = np.concatenate([[T] if self.nT else [], design])
        X = np.vstack([Xs, np.repeat(np.reshape(z, (-1, 1)), N + 1, axis=1)] + ([np.reshape(arc, (1, -1))] if self.ns else []))
        ds = [np.maximum(np.diff(arc), 0.0)[None, :] / np.diff(t)[None, :]] if self.ns else []
        scaled = (np.asarray(acc) / self.acc_scale[:, None, None]).reshape(self.nq * self.m, N, order="F")
        body = [X[:, :N], U] + ds + ([] if self.condensed else [scaled])      # condensed: solved for inside
        return np.concatenate([np.vstack(body).ravel("F"), X[:, N]])

    def unpack(self, w) -> dict:
        nq, N = self.nq, self.N
        w = np.asarray(w, float).ravel()
        body = w[:N * (self.nx + self.nu)].reshape(self.nx + self.nu, N, order="F")
        X = np.hstack([body[:self.nx], w[N * (self.nx + self.nu):, None]])
        z = X[2 * nq:2 * nq + self.nz, 0]
        a0 = self.nx + self.n_tau + self.ns
        acc = None if self.condensed else body[a0:].reshape(nq, self.m, N, order="F") * self.acc_scale[:, None, None]
        return {"Xs": X[:2 * nq], "U": body[self.nx:self.nx + self.n_tau], "acc": acc,
                "T": float(z[0]) if self.nT else None, "design": z[self.nT:],
                "arc": X[self.nx - 1] if self.ns else None}


def _take(v, index: list):
    """v's entries at `index` (a column; CasADi gives a 1 x 1 v's [] back whole)."""
    return v[index] if index else ca.DM(0, 1)


def _power(ew, power: int):
    """effort_weight to the power a cost term's weight takes (1/ew kept finite at ew = 0)."""
    return 1 if power == 0 else ew ** power if power > 0 else ca.fmax(ew, 1e-12) ** power


def butcher(c):
    """The collocation method on points c as a Runge-Kutta tableau: A_jl = int_0^c_j L_l,
    b_l = int_0^1 L_l, L_l the Lagrange polynomials on c."""
    from numpy.polynomial import polynomial as P
    m = len(c)
    A, b = np.zeros((m, m)), np.zeros(m)
    for l in range(m):
        others = [c[i] for i in range(m) if i != l]
        L = P.polyint(P.polyfromroots(others) / np.prod([c[l] - o for o in others]))
        b[l] = P.polyval(1.0, L) - P.polyval(0.0, L)
        A[:, l] = P.polyval(np.asarray(c), L) - P.polyval(0.0, L)
    return A, b
