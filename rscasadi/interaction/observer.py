"""The generalised-momentum residual observer (De Luca and Mattone, 2003; Haddadin, De Luca
and Albu-Schaeffer, 2017) on the complete rotor-separated model, q = (theta, phi):

    p = M(q) dq,     dp/dt = M ddq + dM dq = tau_ext - G(q, dq, 0, tau) + dM dq,
    r(t) = K ( p(t) - p(0) - int_0^t ( dM dq - G(q, dq, 0, tau) + r ) ds ),

so that dr/dt = K (tau_ext - r): r follows the external generalised forces through a first-order
filter of bandwidth K, from positions and speeds alone (no acceleration).  G is the complete
model's residual, zero for the free arm:

    G = [ T_id(q, dq, ddq) - T_SEA(psi, dpsi) ;  mu (tau - tau_id(q, dq, ddq)) ]

(link rows: the SEA torque the links' motion needs less the springs' torque; rotor rows: the
applied motor torque less the one the motion needs, times the gear ratio: the generalised
forces of the rotor coordinates), and M = dG/dddq, the mass matrix of `Arm.mass_matrix`.
The link rows hold neither the motor torque nor the gear's friction: with an SEA the links'
estimate rests on the springs' torque, which the two encoders measure, not on a motor-current
model and a harmonic drive's friction, which a rigid arm's estimate carries.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from rscasadi.dynamics.arm import Arm
from rscasadi.model.limits import measurement_bounds, torque_bounds
from rscasadi.native.controller import BAD_MEASUREMENT, COLLISION, NOT_FINITE, NOT_INITIALISED, within
from rscasadi.errors import InvalidArgument

BAD_TORQUE = 7               # the observer's name for the guard's BAD_REFERENCE: tau_applied refused


def observer_terms(arm: Arm, name: str = "observer_terms") -> ca.Function:
    """(theta, phi, dtheta, dphi, tau) -> (p, beta): the generalised momentum p = M dq (2n) and
    beta = dM dq - G(q, dq, 0, tau) (2n), the known part of dp/dt."""
    n = arm.n
    th, ph, dth, dph, tau = (ca.SX.sym(s, n) for s in ("theta", "phi", "dtheta", "dphi", "tau"))
    dd = ca.SX.sym("ddq", 2 * n)
    tau_id, T_id = arm.inverse_dynamics()(th, ph, dth, dph, dd[:n], dd[n:])
    mu = ca.DM(arm.model.column("gear_ratio"))
    G = ca.vertcat(T_id - arm.sea_torque(th, ph, dth, dph), mu * (tau - tau_id))
    M = ca.jacobian(G, dd)
    q, dq = ca.vertcat(th, ph), ca.vertcat(dth, dph)
    v = ca.SX.sym("v", 2 * n)
    Mdot_dq = ca.substitute(ca.jtimes(ca.mtimes(M, v), q, dq), v, dq)
    G0 = ca.substitute(G, dd, ca.DM.zeros(2 * n))
    return ca.Function(name, [th, ph, dth, dph, tau], [ca.mtimes(M, dq), Mdot_dq - G0],
                       ["theta", "phi", "dtheta", "dphi", "tau"], ["p", "beta"], {"cse": True})


class MomentumObserver:
    """The residual observer in discrete time at the sample time `dt` with gain `gain` (1/s, a
    number or one per coordinate), the generated C's twin: `init(x)` at the first sample, then
    `step(x, tau)` each sample with the measured state and the torque applied over the sample
    before; it returns r (2n): the external torques on the links (first n, N m) and on the
    rotors (last n).  With a `threshold` (N m), `collision` tells after each step whether a
    link's |r| exceeds it (the delay: docs/user-guide/interaction.md).  The C's failure policy:
    `code` is the last call's return code (0, COLLISION, or what was refused: then the state is
    kept and the last r returned); nothing raises for bad data."""

    def __init__(self, arm: Arm, gain, dt: float, threshold: float = np.inf):
        self.n, self.dt, self.threshold, self.collision = arm.n, float(dt), float(threshold), False
        self.K = np.broadcast_to(np.asarray(gain, float), (2 * arm.n)).copy()
        if not np.all(self.K > 0) or not dt > 0 or self.K.max() * dt >= 1.0:
            raise InvalidArgument(f"observer: gain {gain!r} 1/s and dt {dt!r} s need K > 0 and K dt < 1")
        self.terms = observer_terms(arm)
        self.x_box, self.tau_max = measurement_bounds(arm.model), torque_bounds(arm.model)
        self.r, self.ready, self.code = np.zeros(2 * arm.n), False, NOT_INITIALISED

    def _terms(self, x, tau):
        n = self.n
        p, beta = self.terms(x[:n], x[n:2 * n], x[2 * n:3 * n], x[3 * n:], tau)
        return np.array(p).ravel(), np.array(beta).ravel()

    def init(self, x) -> int:
        """At the first sample: the measured state.  0, or BAD_MEASUREMENT (then uninitialised)."""
        self.ready = within(x, *self.x_box)
        if self.ready:
            self.p0, self.beta = self._terms(np.asarray(x, float).ravel(), np.zeros(self.n))[0], None
            self.integral, self.r = np.zeros(2 * self.n), np.zeros(2 * self.n)
        self.code = 0 if self.ready else BAD_MEASUREMENT
        return self.code

    def step(self, x, tau) -> np.ndarray:
        """One sample: beta by the trapezoidal rule (the rectangle rule's error stays in the
        integral as a bias: 2 % on a push against 0.1 % here; the first sample, with no torque
        before it, by the rectangle rule), r held over the sample."""
        if not self.ready:
            self.code = NOT_INITIALISED
            return np.zeros(2 * self.n)
        if not within(x, *self.x_box):
            self.code = BAD_MEASUREMENT
        elif not within(tau, -self.tau_max, self.tau_max):
            self.code = BAD_TORQUE
        else:
            p, beta = self._terms(np.asarray(x, float).ravel(), np.asarray(tau, float).ravel())
            integral = self.integral + self.dt * (0.5 * (beta + (beta if self.beta is None else self.beta)) + self.r)
            r = self.K * (p - self.p0 - integral)
            if not np.all(np.isfinite(r)):
                self.code = NOT_FINITE
                return self.r.copy()
            self.integral, self.beta, self.r = integral, beta, r
            self.collision = bool(np.abs(self.r[:self.n]).max() > self.threshold)
            self.code = COLLISION if self.collision else 0
        return self.r.copy()


def tool_wrench(arm: Arm, frame: str, theta, r_links, force_only: bool | None = None) -> np.ndarray:
    """The wrench at `frame` [force; moment] (world axes) that best explains the links' external
    torques r_links (least squares through J^T, J local_world_aligned); the force alone (3) on
    arms of fewer than 6 joints (`force_only`), where a moment is not observable besides it."""
    J = np.array(arm.frame_jacobian(frame, "local_world_aligned")(theta))
    force_only = arm.n < 6 if force_only is None else force_only
    A = J[:3].T if force_only else J.T
    return np.linalg.lstsq(A, np.asarray(r_links, float), rcond=None)[0]
