"""Statics of a floating robot on its contacts (docs/user-guide/floating.md, "Standing").

At rest (v = a = 0) on horizontal ground the generalised forces balance:

    h(q) = Q(q, 0, tau) + J(q)^T f,

every row of v: the base's six rows are carried by the contact forces alone, each joint's by its
spring, input and share of the contact forces, each motor's by its spring and input.  Given the
base's pose and the links' angles, `stand` finds the motor angles (the springs deflected by
what they carry), the inputs and the contact forces of least effort (sum of the inputs squared,
scaled by their limits) with every contact force inside its friction cone: for a point contact
f_z >= 0 and |f_xy| <= mu f_z in world axes; for a flat contact the same for its force in its
own axes and, where the model gives its sole (`size = [lx, ly]`), the centre of pressure on it:
|m_x| <= ly/2 f_z, |m_y| <= lx/2 f_z (its twist about z stays free).  The answer is checked: the
contact dynamics at it give a = 0 (`StandingError` otherwise, naming the largest residual row).
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from rscasadi.dynamics import contacts as ct
from rscasadi.errors import Error, InvalidArgument

FORCE_FLOOR = 1e-3          # N: each contact's normal force at least this much (it touches)


class StandingError(Error, RuntimeError):
    """No posture of the asked kind holds the robot still on those contacts."""


@dataclass
class Stance:
    """A standing posture: q (motors deflected), tau (inputs), f (contact forces, as
    contact_dynamics orders them), and the largest acceleration the contact dynamics give there."""
    q: np.ndarray
    tau: np.ndarray
    f: np.ndarray
    residual: float


def stand(robot, theta, base=None, contacts=None, mu: float = 0.7, tol: float = 1e-6) -> Stance:
    """The standing posture of `robot` (a FloatingRobot) with its links at `theta` and its base at
    `base` = [x, y, z, qx, qy, qz, qw] (default: level at the origin), on `contacts` (default: the
    model file's), friction coefficient `mu`; module docstring."""
    cs = ct.contact_set(robot.model, contacts)
    from rscasadi.dynamics.floating import unit_configuration
    theta = np.asarray(theta, float)
    base = np.r_[0, 0, 0, 0, 0, 0, 1.0] if base is None else np.asarray(base, float)
    if theta.shape != (robot.n,) or base.shape != (7,) or not np.all(np.isfinite(np.r_[theta, base])):
        raise InvalidArgument(f"stand: theta must be {robot.n} finite angles and base 7 finite numbers "
                              f"(got shapes {theta.shape}, {base.shape})")
    base = unit_configuration(robot, np.r_[base, theta, theta[robot.model.motors]], "stand: base")[:7]
    if not mu > 0:
        raise InvalidArgument(f"stand: mu = {mu!r}; the friction coefficient must be > 0")
    q0 = np.r_[base, theta, theta[robot.model.motors]]
    robot.check_contacts(cs, q0)
    nc, m, u = sum(c.rows for c in cs), robot.m, robot.u
    opti = ca.Opti()
    phi, tau, f = opti.variable(m), opti.variable(u), opti.variable(nc)
    q = ca.vertcat(ca.DM(base), ca.DM(theta), phi)
    zero = ca.DM.zeros(robot.nv)
    J = ct.jacobian(robot, cs)(q)
    opti.subject_to(robot.nonlinear_effects()(q, zero) == robot.generalized_forces()(q, zero, tau) + J.T @ f)
    row, soles = 0, {frame: (lx, ly) for frame, lx, ly in robot.model.soles}
    for c in cs:                                    # the normal is world z (point) or the frame's z (flat)
        fx, fy, fz = f[row], f[row + 1], f[row + 2]
        opti.subject_to(fz >= FORCE_FLOOR)
        opti.subject_to(fx ** 2 + fy ** 2 <= (mu * fz) ** 2)
        if c.kind == "flat" and c.frame in soles:   # the centre of pressure on the sole
            lx, ly = soles[c.frame]
            opti.subject_to(opti.bounded(-ly / 2 * fz, f[row + 3], ly / 2 * fz))
            opti.subject_to(opti.bounded(-lx / 2 * fz, f[row + 4], lx / 2 * fz))
        row += c.rows
    limits = np.array([robot.model.joints[j].limits.get("tau", 1.0) for j in robot.model.actuated], float)
    opti.minimize(ca.sumsqr(tau / limits) + 1e-9 * ca.sumsqr(f))
    opti.set_initial(phi, theta[robot.model.motors])
    opti.set_initial(f, np.tile(np.r_[0, 0, 1.0, 0, 0, 0], len(cs))[:nc] if all(c.rows == 6 for c in cs)
                     else np.concatenate([[0, 0, 1.0] + [0.0] * (c.rows - 3) for c in cs]))
    opti.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes", "tol": 1e-10, "max_iter": 500})
    try:
        sol = opti.solve()
    except RuntimeError as exc:
        raise StandingError(f"{robot.model.path}: no posture holds the robot still at these link angles on "
                            f"{', '.join(c.frame for c in cs)} with mu = {mu:g} ({exc})") from None
    q_s = np.r_[base, theta, np.atleast_1d(sol.value(phi))]
    tau_s, f_s = np.atleast_1d(sol.value(tau)), np.atleast_1d(sol.value(f))
    a, _ = robot.contact_dynamics(cs)(q_s, np.zeros(robot.nv), tau_s)
    residual = float(np.max(np.abs(np.asarray(a))))
    if residual > tol:
        worst = robot.velocities[int(np.argmax(np.abs(np.asarray(a).ravel())))]
        raise StandingError(f"{robot.model.path}: the posture found does not hold still: the contact dynamics give "
                            f"{residual:.3g} at {worst}")
    return Stance(q_s, tau_s, f_s, residual)
