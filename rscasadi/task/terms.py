"""What the arm must do on a stage, as terms (Crocoddyl's cost and constraint models, rockit's
`add_objective` / `subject_to`).

A term is a CasADi expression of a stage's state x = (theta, phi, dtheta, dphi) (2 nq: every
joint's link, then the SEAs' motors; `arm.split_state`), its motor torques u = tau (one per
actuated joint) and its parameters p (`n_p` numbers the problem supplies on each stage:
the reference, the posture; none for a term a user writes, whose numbers are its own):

- a **cost** gives a residual r(x, u, p): the OCP adds the integral of weight |r|^2 over the
  motion (r at each interval's end, with the interval's torque), the MPC adds weight / 2 |r_k|^2
  at each interval end k = 1..N of its horizon (Gauss-Newton: it needs r and its Jacobians);
- a **constraint** gives rows c(x, u) within [lower, upper]: hard in the OCP (at every node and,
  if `inside`, at the collocation points between; at the last node with u = 0 if `at_end`),
  soft in the MPC (a penalty weight / 2 |excess|^2, `excess` the rows' distance outside
  their bounds).

Each term also measures itself on the replay (`replay_metric`): a constraint its largest
violation over the replayed samples, which the verification compares with its `tolerance`.

A term a user adds (docs/user-guide/problems.md, "Terms"): subclass `Term`, set `name`,
`constraint` and, for a constraint, `bounds`; write `expression`.  `Task(terms=[...])` and
`MPCProblem(terms=[...])` take it; nothing else changes.
"""
from __future__ import annotations

from typing import Callable

import casadi as ca
import numpy as np

from rscasadi.dynamics.collision import clearance_function, clearances, exact_clearance
from rscasadi.errors import InvalidArgument

PENALTY = 1e8       # a constraint's penalty weight in the MPC, unless the term gives its own


class Term:
    """One thing the arm must do on a stage (see the module's text).  Subclasses set the class
    attributes and write `expression`; a constraint writes `bounds` too."""
    name: str = "term"
    constraint: bool = False          # a cost (residual) if False
    weight: float | None = None       # a cost's weight (None: 1); a constraint's penalty weight in
                                      # the MPC (None: PENALTY, the obstacles' default)
    inside: bool = True               # OCP: a constraint also at the collocation points
    at_end: bool = True               # OCP: a constraint also at the last node (u = 0 there)
    tolerance: float = 1e-3           # a constraint's largest violation on the replay
    n_p: int = 0                      # parameters the problem supplies per stage (built-in terms)
    parameter: str | None = None      # which: "reference" (the reference column), "posture"

    def expression(self, arm, x, u, p):
        """The residual (a cost) or the rows (a constraint) at (x, u, p): a column."""
        raise NotImplementedError(f"{type(self).__name__}.expression")

    def of_angles(self, arm) -> ca.Function | None:
        """The expression as a Function of the link angles alone (theta -> the column), for a
        term that reads nothing else: the OCP then differentiates it once and evaluates it at
        each point as a call (ocp.assembly.Calls); None: inlined at each point."""
        return None

    def bounds(self, arm) -> tuple[np.ndarray, np.ndarray]:
        """A constraint's (lower, upper) per row (-inf, inf: open)."""
        raise NotImplementedError(f"{type(self).__name__}.bounds")

    def check(self, arm) -> "Term":
        """The term fits the arm: a column of the right size from (x, u, p) of `arm`, finite
        bounds in order; an InvalidArgument names the term."""
        n = arm.n
        x, u, p = ca.SX.sym("x", 2 * arm.nq), ca.SX.sym("u", arm.u), ca.SX.sym("p", self.n_p)
        try:
            r = ca.SX(self.expression(arm, x, u, p))
        except Exception as exc:                            # noqa: BLE001  (the user's code, named)
            raise InvalidArgument(f"term {self.name!r}: its expression failed on a {n}-joint arm: {exc}") from exc
        if r.shape[1] != 1:
            raise InvalidArgument(f"term {self.name!r}: expected a column, got a {r.shape[0]}x{r.shape[1]} expression")
        if self.constraint:
            lo, hi = (np.asarray(b, float).ravel() for b in self.bounds(arm))
            if lo.shape != (r.shape[0],) or hi.shape != (r.shape[0],) or np.any(lo > hi) or np.any(np.isnan(lo + hi)):
                raise InvalidArgument(f"term {self.name!r}: bounds must be {r.shape[0]} pairs with lower <= upper")
        if self.weight is not None and not (isinstance(self.weight, (int, float)) and np.isfinite(self.weight)
                                            and self.weight >= 0):
            raise InvalidArgument(f"term {self.name!r}: weight must be a number >= 0, got {self.weight!r}")
        return self

    # -- derived: one definition for every user of a term -----------------------------------
    @property
    def stage_weight(self) -> float:
        """The weight in use: `weight`, else 1 for a cost and PENALTY for a constraint."""
        return self.weight if self.weight is not None else PENALTY if self.constraint else 1.0

    def function(self, arm) -> ca.Function:
        """(x, u, p) -> the expression, as a Function named after the term."""
        x, u, p = ca.SX.sym("x", 2 * arm.nq), ca.SX.sym("u", arm.u), ca.SX.sym("p", self.n_p)
        return ca.Function(f"term_{_c_name(self.name)}", [x, u, p], [self.expression(arm, x, u, p)],
                           ["x", "u", "p"], ["r"])

    def excess(self, arm, x, u, p):
        """A constraint's rows' distance outside their bounds, signed (0 inside): the MPC's
        penalty residual and the replay's measure."""
        c = self.expression(arm, x, u, p)
        lo, hi = self.bounds(arm)
        rows = [j for j in range(c.shape[0]) if np.isfinite(lo[j]) or np.isfinite(hi[j])]
        lo, hi = np.asarray(lo, float)[rows], np.asarray(hi, float)[rows]
        c = c[rows]
        return (ca.fmax(c - np.where(np.isfinite(hi), hi, 0.0), 0) * np.isfinite(hi)
                + ca.fmin(c - np.where(np.isfinite(lo), lo, 0.0), 0) * np.isfinite(lo))

    def penalty_residual(self, arm, x, u, p):
        """The MPC's residual of the term: sqrt(weight) r (a cost) or sqrt(weight) excess."""
        part = self.excess(arm, x, u, p) if self.constraint else self.expression(arm, x, u, p)
        return np.sqrt(self.stage_weight) * part

    def replay_metric(self, arm, X, U) -> float:
        """On replayed samples X (2 nq x K) with the torques U (u x K): a constraint's largest
        violation (its rows' largest distance outside their bounds; 0 inside), a cost's mean
        value of weight |r|^2."""
        x, u = ca.SX.sym("x", 2 * arm.nq), ca.SX.sym("u", arm.u)
        p = ca.SX.zeros(self.n_p)
        out = self.excess(arm, x, u, p) if self.constraint else self.stage_weight * ca.sumsqr(self.expression(arm, x, u, p))
        f = ca.Function("metric", [x, u], [ca.fabs(out) if self.constraint else out])
        values = np.array(f.map(X.shape[1])(X, U))
        return float(values.max(initial=0.0)) if self.constraint else float(values.mean())


def _c_name(name: str) -> str:
    out = "".join(ch if ch.isalnum() else "_" for ch in name)
    return out if out[:1].isalpha() else "t_" + out


def check_terms(arm, terms, where: str, parameters: bool = False) -> tuple:
    """Each term checked on `arm`, names unique; a user's term may not ask the problem for
    parameters (parameters=False).  Errors name `where` and the term."""
    names = set()
    for term in terms:
        if not isinstance(term, Term):
            raise InvalidArgument(f"{where}: field 'terms': expected rscasadi.task.terms.Term objects, got {term!r}")
        if term.name in names:
            raise InvalidArgument(f"{where}: field 'terms': two terms are named {term.name!r}")
        names.add(term.name)
        if term.n_p and not parameters:
            raise InvalidArgument(f"{where}: term {term.name!r}: n_p = {term.n_p}: a term added to a problem "
                                  "carries its numbers itself (the problems supply parameters to their own terms only)")
        try:
            term.check(arm)
        except InvalidArgument as exc:
            raise InvalidArgument(f"{where}: {exc}") from None
    return tuple(terms)


# -- the built-in terms ---------------------------------------------------------------------
class Effort(Term):
    """The motor torques: r = tau."""
    name = "effort"

    def __init__(self, weight: float = 1.0):
        self.weight = weight

    def expression(self, arm, x, u, p):
        return u


class JointTracking(Term):
    """The link angles (and speeds) against the reference p = (theta_ref[, dtheta_ref]):
    r = (sqrt(w_theta) (theta - theta_ref)[, sqrt(w_dtheta) (dtheta - dtheta_ref)])."""
    name = "joint_tracking"
    parameter = "reference"

    def __init__(self, n: int, w_theta: float = 1.0, w_dtheta: float | None = None):
        self.w_theta, self.w_dtheta = w_theta, w_dtheta
        self.n_p = n * (1 if w_dtheta is None else 2)

    def expression(self, arm, x, u, p):
        n = arm.n
        theta, _, dtheta, _ = arm.split_state(x)
        rows = [np.sqrt(self.w_theta) * (theta - p[:n])]
        if self.w_dtheta is not None:
            rows.append(np.sqrt(self.w_dtheta) * (dtheta - p[n:2 * n]))
        return ca.vertcat(*rows)


def orientation_error(R_ref, R):
    """skew(R_ref^T R) as a vector: sin of the angle times the axis, 0 at R = R_ref."""
    E = ca.mtimes(R_ref.T, R)
    return ca.vertcat(E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]) / 2


class FrameTracking(Term):
    """Frames' positions and velocities against p = (p_ref, v_ref[, vec(R_ref)]) (world), a block
    per frame in `frames`' order: r = (sqrt(w_position) (p - p_ref), sqrt(w_velocity) (J dtheta -
    v_ref)[, sqrt(w_orientation) skew(R_ref^T R)]) per frame (two hands meeting, say)."""
    name = "frame_tracking"
    parameter = "reference"

    def __init__(self, frames, w_position: float, w_velocity: float, w_orientation: float | None = None):
        self.frames = (frames,) if isinstance(frames, str) else tuple(frames)
        self.w = (w_position, w_velocity, w_orientation)
        self.block = 6 if w_orientation is None else 15
        self.n_p = self.block * len(self.frames)

    def expression(self, arm, x, u, p):
        theta, _, dtheta, _ = arm.split_state(x)
        rows = []
        for i, frame in enumerate(self.frames):
            q = p[i * self.block:(i + 1) * self.block]
            R, pos = arm.frame_placement(frame)(theta)
            J = arm.frame_jacobian(frame, "local_world_aligned")(theta)
            rows += [np.sqrt(self.w[0]) * (pos - q[:3]), np.sqrt(self.w[1]) * (ca.mtimes(J[:3, :], dtheta) - q[3:6])]
            if self.w[2] is not None:
                rows.append(np.sqrt(self.w[2]) * orientation_error(ca.reshape(q[6:15], 3, 3), R))
        return ca.vertcat(*rows)


POSTURE_DAMPING = 0.3      # s: the posture's speed rows, tau_d dtheta


class Posture(Term):
    """The link angles against a posture p (n), damped: r = (theta - theta_posture, tau_d
    dtheta) with tau_d = POSTURE_DAMPING (a redundant arm's null space).  Undamped, nothing
    priced the null space's speed: at the end of the Panda's shelf motion the joints swung back
    toward the posture at 2-3 rad/s, at their speed limits, and the hand never settled."""
    name = "posture"
    parameter = "posture"

    def __init__(self, n: int, weight: float = 1.0):
        self.n_p, self.weight = n, weight

    def expression(self, arm, x, u, p):
        theta, _, dtheta, _ = arm.split_state(x)
        return ca.vertcat(theta - p, POSTURE_DAMPING * dtheta)


class StateBound(Term):
    """A limit of the model as a constraint: `quantity` psi (phi - theta), dphi or theta (its
    offset from `middle`) within -+`limit` per joint (rows only where it is finite; psi of the
    SEAs, dphi of every joint's slow side: an SEA's motor, a geared joint's link)."""
    constraint = True

    def __init__(self, quantity: str, limit, weight: float = 1.0, middle=None):
        if quantity not in ("psi", "dphi", "theta"):
            raise InvalidArgument(f"StateBound: quantity must be psi, dphi or theta, got {quantity!r}")
        self.name, self.quantity, self.weight = f"{quantity}_limit", quantity, weight
        self.limit = np.asarray(limit, float)
        self.middle = np.zeros_like(self.limit) if middle is None else np.asarray(middle, float)

    def expression(self, arm, x, u, p):
        theta, phi, dtheta, dphi = arm.split_state(x)
        motors = arm.model.motors
        slow = ca.vertcat(*[dphi[arm.model.motor_of[j]] if j in arm.model.motor_of else dtheta[j] for j in range(arm.n)])
        psi = ca.vertcat(*[phi[arm.model.motor_of[j]] - theta[j] if j in arm.model.motor_of else 0 * theta[j]
                           for j in range(arm.n)]) if len(motors) != arm.n else phi - theta
        c = {"psi": psi, "dphi": slow if len(motors) != arm.n else dphi, "theta": theta - self.middle}[self.quantity]
        return c[[j for j in range(arm.n) if np.isfinite(self.limit[j])]]

    def bounds(self, arm):
        finite = self.limit[np.isfinite(self.limit)]
        return -finite, finite


class AngleBand(Term):
    """The link angles' soft band in joint space, opening to the reference: per joint with a range
    (`half` its half-width about `middle`, finite), the excess of |theta - middle| beyond
    b = min(max(soft, |theta_ref - middle|), half), signed, as a cost residual; p the reference
    column (theta_ref, dtheta_ref).  A reference that uses its range to the edge is followed
    there (the band never closes in on the plan), and no farther (b <= half); one inside `soft`
    leaves the band where it was."""
    name = "theta_limit"
    parameter = "reference"

    def __init__(self, n: int, soft, half, middle, weight: float = 1.0):
        self.rows = [j for j in range(n) if np.isfinite(half[j])]
        self.soft, self.half = np.asarray(soft, float)[self.rows], np.asarray(half, float)[self.rows]
        self.middle, self.weight, self.n_p = np.asarray(middle, float)[self.rows], weight, 2 * n

    def expression(self, arm, x, u, p):
        c = x[self.rows] - self.middle                         # theta: x's first n
        band = ca.fmin(ca.fmax(self.soft, ca.fabs(p[self.rows] - self.middle)), self.half)
        return ca.sign(c) * ca.fmax(ca.fabs(c) - band, 0)


class Clearance(Term):
    """The arm's capsules clear of the obstacles: the smooth conservative clearances
    (rscasadi.dynamics.collision.clearances) >= 0; on the replay, the exact clearance."""
    name = "clearance"
    constraint = True

    def __init__(self, obstacles, weight: float | None = None, tolerance: float = 1e-4):
        self.obstacles, self.weight, self.tolerance = tuple(obstacles), weight, tolerance

    def expression(self, arm, x, u, p):
        return clearances(arm.model, self.obstacles, x[:arm.n])          # theta: x's first n

    def of_angles(self, arm) -> ca.Function:
        # inlined at a stage's three points, the Panda's clearances to two obstacles were 7 of
        # the condensing kernel's 10 MB of C
        return clearance_function(arm.model, self.obstacles)

    def bounds(self, arm):
        rows = clearance_function(arm.model, self.obstacles).size1_out(0)
        return np.zeros(rows), np.full(rows, np.inf)

    def replay_metric(self, arm, X, U) -> float:
        """The largest intrusion into the margin, by the exact clearance (m; 0 when clear)."""
        gap = np.array(exact_clearance(arm.model, self.obstacles).map(X.shape[1])(X[:arm.n])).ravel()
        return float(max(-gap.min(), 0.0))


# the objectives a problem file names, as cost terms, each with the power of the problem's
# effort_weight (an NLP parameter, so a sweep over it reuses the compiled NLP) its weight takes
OBJECTIVES: dict[str, Callable[[int], list]] = {
    "min_time": lambda n: [(Effort(), 1)],                                # and the duration itself
    "min_effort": lambda n: [(Effort(), 0)],
    "tracking": lambda n: [(JointTracking(n), -1), (Effort(), 0)]}


def objective_terms(objective: str, n: int) -> list:
    """The cost terms of a problem file's `objective` on an n-joint arm: (term, power of
    effort_weight in its weight) pairs.  min_time adds the duration, which the transcription
    carries as a variable; tracking's term takes the reference angles."""
    return OBJECTIVES[objective](n)
