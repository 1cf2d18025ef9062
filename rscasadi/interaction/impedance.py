"""Impedance control of the complete FS-SEA model through its springs, on motor positions, in
Cartesian or joint space: the passive flexible-joint design of Albu-Schaeffer, Ott and Hirzinger
(IJRR 26(1), 2007) and Ott et al. (IEEE TRO 24(2), 2008), with the complete model's statics.

The commanded spring V_K (Cartesian: 1/2 e^T K e at the frame, e = [p - p_d; e_R]; joint space:
1/2 (q - q_d)^T K (q - q_d)) asks the SEAs for the link torque

    T(q) = g(q) - dV_K/dq = g(q) - J(q)^T K e(q)                     (g: the complete model's)

On motor positions phi alone: q_bar(phi) solves phi = q_bar + psi(T(q_bar)), the link angles at
which springs deflected to carry T balance the motors at phi (Newton from the measured theta).
The motors then ask the springs for

    u = T(q_bar) - D(q_bar) dphi,     D = J^T D_x J + N^T D_n N,     D_x = 2 zeta sqrt(K Lambda)

(Lambda = (J M_tt^-1 J^T)^-1 the frame's inertia, N = I - M_tt^-1 J^T Lambda J the dynamically
consistent null space, damped on arms with more joints than task rows), with torque feedback
u_m = T_s + rho (u - T_s) (T_s the measured spring torque; rho > 1 makes the rotors feel lighter),
and tau = -(Q_s + u_m) / mu (the model's convention: -mu tau on the rotor rows; Q_s their other
static terms).  At rest u = T_s gives theta = q_bar, so the links' statics T_s = g - J^T f give
f = K e: the stiffness at the frame is the commanded one, the springs' compliance included.  With
rho = 1, H = E(x) - V_g(q_bar) + V_K(q_bar) - V_s(phi - q_bar) (E the complete model's energy)
has dH/dt = dtheta^T J^T f_ext - dphi^T D dphi - losses: the loop is passive (H bounded below
where the springs dominate gravity's stiffness; isotropic rotational stiffness is an exact
potential, 3 - tr(R_d^T R), anisotropic a first-order one)."""
from __future__ import annotations

import casadi as ca
import numpy as np

from rscasadi.dynamics.arm import Arm
from rscasadi.dynamics.statics import holding_torque, spring_deflection
from rscasadi.model.limits import limit_arrays, measurement_bounds
from rscasadi.native.controller import (BAD_MEASUREMENT, BAD_REFERENCE, DAMPING_RATIO_BOUND, NOT_FINITE,
                                        NOT_INITIALISED, STIFFNESS_BOUND, TOO_STIFF, clamp, task_reference_bounds,
                                        within)
from rscasadi.errors import InvalidArgument


def _vee(S):
    return ca.vertcat(S[2, 1], S[0, 2], S[1, 0])


def _cartesian(arm: Arm, frame: str):
    """(q, pose_desired (12), K (6)) -> (dV_K/dq, J): the commanded spring at `frame`; the rows
    of rotation only on arms of 6 joints or more."""
    q, pose, K = ca.SX.sym("q", arm.n), ca.SX.sym("pose_desired", 12), ca.SX.sym("stiffness", 6)
    R, p = arm.frame_placement(frame)(q)
    J = arm.frame_jacobian(frame, "local_world_aligned")(q)
    R_d, e = ca.reshape(pose[3:], 3, 3), p - pose[:3]
    if arm.n >= 6:                              # e_R = vee(R R_d^T - R_d R^T) / 2, world axes
        e = ca.vertcat(e, ca.mtimes(R_d, _vee(ca.mtimes(R_d.T, R) - ca.mtimes(R.T, R_d))) / 2)
    else:
        J = J[:3, :]
    return ca.Function("spring", [q, pose, K], [ca.mtimes(J.T, K[:J.shape[0]] * e), J])


def _joint(arm: Arm):
    """(q, q_desired (n), K (n)) -> (dV_K/dq, I)."""
    q, q_d, K = ca.SX.sym("q", arm.n), ca.SX.sym("q_desired", arm.n), ca.SX.sym("stiffness", arm.n)
    return ca.Function("spring", [q, q_d, K], [K * (q - q_d), ca.DM.eye(arm.n)])


def impedance_law(arm: Arm, frame: str | None, design: str = "motor", torque_feedback=None, motor_damping=None,
                  null_damping: float = 2.0, newton_steps: int = 2, reduced: bool = False,
                  motor_bandwidth_hz: float = 10.0, name: str = "impedance") -> ca.Function:
    """(theta, phi, dtheta, dphi, reference, stiffness, damping_ratio) -> (tau, u, q_bar, margin):
    the motor torques (not yet limited), the spring torques asked, the static link angles the
    potential is evaluated at, and the realisability margin (> 0: the commanded stiffness is
    softer than the springs allow the passive design; the smallest pivot of I - K^1/2 J C_s J^T
    K^1/2, C_s the springs' compliance).
    frame: Cartesian at that frame (reference = p (3), R (9, column-major); stiffness and
    damping_ratio 6), or None for joint space (reference q_d, stiffness, damping_ratio: n each).
    design "motor": q_bar(phi), damping on dphi, passive (the module's text); design "link": q_bar
    = theta, damping on dtheta, the spring torque held by a torque loop (rho = 1 + B w^2 / k1,
    D_m = 2 0.6 B w, w = 2 pi motor_bandwidth_hz): stiffer than the springs, not shown passive.
    torque_feedback rho and motor_damping D_m override those; null_damping: D_n = c diag(M_tt)
    (1/s) where joints outnumber task rows; reduced: designed on the DLR/Spong reduced model."""
    if design not in ("motor", "link"):
        raise InvalidArgument(f"impedance design {design!r}: choose 'motor' (passive) or 'link'")
    n = arm.n
    spring = _cartesian(arm, frame) if frame is not None else _joint(arm)
    m = n if frame is None else (6 if n >= 6 else 3)                          # task rows
    th, ph, dth, dph = (ca.SX.sym(s, n) for s in ("theta", "phi", "dtheta", "dphi"))
    ref, K, zeta = (ca.SX.sym(s, spring.size1_in(i)) for i, s in ((1, "reference"), (2, "stiffness"), (2, "damping_ratio")))
    zero = ca.DM.zeros(n)
    inverse = arm.reduced_inverse_dynamics() if reduced else arm.inverse_dynamics()
    mass = arm.mass_matrix(reduced=reduced)
    B = np.diag(np.array(mass(np.zeros(n), np.zeros(n))))[n:]
    k1, w = arm.model.column("k1"), 2 * np.pi * motor_bandwidth_hz
    link = design == "link"
    rho = (1 + B * w ** 2 / k1 if link else 1.0) if torque_feedback is None else torque_feedback
    D_m = (2 * 0.6 * B * w if link else 0.0) if motor_damping is None else motor_damping

    q = ca.SX.sym("q", n)
    T = inverse(q, q, zero, zero, zero, zero)[1] - spring(q, ref, K)[0]        # T(q) = g - dV_K/dq
    q_bar = th if link else _static_link_angles(arm, q, T, th, ph, ref, K, newton_steps)
    J = spring(q_bar, ref, K)[1][:m, :]
    D = _damping(J, mass(q_bar, q_bar)[:n, :n], K[:m], zeta[:m], null_damping)
    u = ca.substitute(T, q, q_bar) - ca.mtimes(D, dth if link else dph)
    T_s = arm.sea_torque(th, ph, zero, zero)                                   # measured, elastic part
    u_m = T_s + rho * (u - T_s) - D_m * dph
    mu = arm.model.column("gear_ratio")
    tau_hold = inverse(q_bar, ph, zero, zero, zero, zero)[0]                   # -(Q_s + spring(phi - q_bar)) / mu
    tau = tau_hold + (arm.sea_torque(q_bar, ph, zero, zero) - u_m) / mu        # = -(Q_s + u_m) / mu
    margin = _margin(J, K[:m], k1)
    names = ["pose_desired" if frame is not None else "q_desired", "stiffness", "damping_ratio"]
    return ca.Function(name, [th, ph, dth, dph, ref, K, zeta], [tau, u, q_bar, margin],
                       ["theta", "phi", "dtheta", "dphi"] + names, ["tau", "u", "q_bar", "margin"], {"cse": True})


def _static_link_angles(arm: Arm, q, T, theta, phi, ref, K, steps: int):
    """q_bar with phi = q_bar + psi(T(q_bar)): `steps` Newton steps from the measured theta."""
    F = q + spring_deflection(arm, T, steps=4) - phi
    newton = ca.Function("newton", [q, phi, ref, K], [q - ca.solve(ca.jacobian(F, q), F)])
    q_bar = theta
    for _ in range(steps):
        q_bar = newton(q_bar, phi, ref, K)
    return q_bar


def _damping(J, M, K, zeta, null_damping: float):
    """D = J^T D_x J + N^T D_n N: D_x = 2 zeta sqrt(K Lambda_ii), Lambda = (J M^-1 J^T)^-1; the
    dynamically consistent null space N = I - M^-1 J^T Lambda J damped by D_n = c diag(M)."""
    n = M.shape[0]
    MiJt = ca.solve(M, J.T)
    Lam = ca.inv(ca.mtimes(J, MiJt))
    D = ca.mtimes([J.T, ca.diag(2 * zeta * ca.sqrt(K * ca.diag(Lam))), J])
    if J.shape[0] < n:
        N = ca.DM.eye(n) - ca.mtimes([MiJt, Lam, J])
        D += null_damping * ca.mtimes([N.T, ca.diag(ca.diag(M)), N])
    return D


def _margin(J, K, k1):
    """The smallest LDL^T pivot of I - K^1/2 J C_s J^T K^1/2, C_s = diag(1 / k1): > 0 while the
    commanded compliance K^-1 exceeds the springs' J C_s J^T."""
    sqrtK = ca.diag(ca.sqrt(K))
    S = ca.DM.eye(J.shape[0]) - ca.mtimes([sqrtK, J, ca.diag(1 / k1), J.T, sqrtK])
    return ca.mmin(ca.ldl(S)[0])


def impedance_boxes(model, frame: str | None) -> dict:
    """The impedance controller's guard: the measured state's box, the reference's (link angles;
    Cartesian: p (3) then R (9)), the stiffness's and the damping ratio's."""
    n, nk = model.n, (6 if frame is not None else model.n)
    x_lo, x_hi = measurement_bounds(model)
    if frame is None:
        ref_lo, ref_hi = x_lo[:n], x_hi[:n]
    else:                                  # task_reference_bounds' velocity rows are no reference here
        ref_lo, ref_hi = (np.delete(b, range(3, 6)) for b in task_reference_bounds(15))
    return {"x_lo": x_lo, "x_hi": x_hi, "ref_lo": ref_lo, "ref_hi": ref_hi, "k_lo": np.zeros(nk),
            "k_hi": np.full(nk, STIFFNESS_BOUND), "z_lo": np.zeros(nk), "z_hi": np.full(nk, DAMPING_RATIO_BOUND)}


class ImpedanceController:
    """The impedance controller in discrete time, the generated C's twin: `init(x)` once, then
    `step(x, reference, stiffness, damping_ratio)` -> the motor torques within the limits.  frame
    given: Cartesian, reference p (3) and R (9, column-major), stiffness translational N/m (3) and
    rotational N m/rad (3, used on arms of 6 joints or more), damping_ratio 6; frame None: joint
    space, reference q_d, stiffness N m/rad and damping_ratio, n each.  Keywords as
    `impedance_law`.  The C's failure policy: `code` is the last call's return code
    (native.controller's names; 0: good) and a refused step returns the holding torque of the
    last good state; nothing raises for bad data."""

    def __init__(self, arm: Arm, frame: str | None, **design):
        self.n, self.passive = arm.n, design.get("design", "motor") == "motor"
        self.law = impedance_law(arm, frame, **design)
        self.hold = holding_torque(arm)
        self.limit = limit_arrays(arm.model)["tau"]
        self.box = impedance_boxes(arm.model, frame)
        self.x_good: np.ndarray | None = None
        self.code = NOT_INITIALISED

    def init(self, x) -> int:
        """0, or BAD_MEASUREMENT for a state outside its box (then uninitialised)."""
        ok = within(x, self.box["x_lo"], self.box["x_hi"])
        self.x_good = np.asarray(x, float).ravel().copy() if ok else None
        self.code = 0 if ok else BAD_MEASUREMENT
        return self.code

    def _refuse(self, code: int) -> np.ndarray:
        self.code = code
        n = self.n
        return clamp(np.array(self.hold(self.x_good[:n], self.x_good[n:2 * n])).ravel(), self.limit)

    def step(self, x, reference, stiffness, damping_ratio) -> np.ndarray:
        """The motor torques (code 0), or the holding torque of the last good state with the code
        of what was refused (TOO_STIFF: the passive design asked for a stiffness beyond the
        springs', its margin <= 0)."""
        if self.x_good is None:
            self.code = NOT_INITIALISED
            return np.zeros(self.n)
        b = self.box
        if not within(x, b["x_lo"], b["x_hi"]):
            return self._refuse(BAD_MEASUREMENT)
        n, x = self.n, np.asarray(x, float).ravel()
        self.x_good = x.copy()
        if not (within(reference, b["ref_lo"], b["ref_hi"]) and within(stiffness, b["k_lo"], b["k_hi"])
                and within(damping_ratio, b["z_lo"], b["z_hi"])):
            return self._refuse(BAD_REFERENCE)
        tau, _, _, margin = self.law(x[:n], x[n:2 * n], x[2 * n:3 * n], x[3 * n:], reference, stiffness, damping_ratio)
        tau = np.array(tau).ravel()
        if not np.all(np.isfinite(tau)):
            return self._refuse(NOT_FINITE)
        if self.passive and not float(margin) > 0:
            return self._refuse(TOO_STIFF)
        self.code = 0
        return clamp(tau, self.limit)
