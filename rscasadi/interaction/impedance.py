"""Cartesian impedance control of the complete FS-SEA model: the links are given the spring and
damper of a commanded stiffness at a frame, through the SEAs' torque.

Link-side law: the SEA torque the links should feel,

    T_d = g(theta) - J(theta)^T [ K_t (p - p_d) + D_t v ;  K_r e_R + D_r omega ],

(g: the links' gravity torques of the complete model at rest; J, v, omega at the frame, world
axes; e_R the rotation error R_d vee(R_d^T R - R^T R_d) / 2, used on arms of 6 joints or more),
is realised by the motors through the springs: the motor angle that gives it, phi_d = theta +
psi(T_d) (the spring law inverted), is held by a motor-side PD around the complete model's
holding torque at (theta, phi_d),

    tau = tau_hold(theta, phi_d) + (K_m (phi - phi_d) + D_m dphi) / mu

(in the model's convention mu tau enters the rotor rows as -mu tau).  At rest the springs then
carry exactly T_d, and the links' statics T_SEA = g - J^T f give f = K (p - p_d): the stiffness
seen at the frame is the commanded one, whatever the springs' (the link encoders measure theta;
a design on motor positions alone sees the springs in series).  Damping: D = 2 zeta sqrt(K
Lambda_ii), Lambda the frame's inertia seen from the links, (J M_tt^-1 J^T)^-1.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from rscasadi.dynamics.arm import Arm


def _vee(S):
    return ca.vertcat(S[2, 1], S[0, 2], S[1, 0])


def impedance_law(arm: Arm, frame: str, motor_bandwidth_hz: float = 10.0, motor_damping: float = 0.6) -> ca.Function:
    """(theta, phi, dtheta, dphi, pose_desired [p; vec(R)] (12), stiffness (6), damping_ratio (6))
    -> (tau, T_d): the motor torques (not yet limited) and the SEA torques the links should feel.
    The motor PD per joint: K_m = B w^2, D_m = 2 zeta B w (B the rotor row's inertia at theta = 0,
    w = 2 pi motor_bandwidth_hz, zeta = motor_damping)."""
    n = arm.n
    th, ph, dth, dph = (ca.SX.sym(s, n) for s in ("theta", "phi", "dtheta", "dphi"))
    pose, K, zeta = ca.SX.sym("pose_desired", 12), ca.SX.sym("stiffness", 6), ca.SX.sym("damping_ratio", 6)
    zero = ca.DM.zeros(n)
    R, p = arm.frame_placement(frame)(th)
    J = arm.frame_jacobian(frame, "local_world_aligned")(th)
    rotation = n >= 6
    Jt = J if rotation else J[:3, :]
    twist = ca.mtimes(Jt, dth)
    M = arm.mass_matrix()(th, th)
    Lam = ca.inv(ca.mtimes(Jt, ca.solve(M[:n, :n], Jt.T)))
    k = K if rotation else K[:3]
    D = 2 * (zeta if rotation else zeta[:3]) * ca.sqrt(k * ca.diag(Lam))
    R_d = ca.reshape(pose[3:], 3, 3)
    error = p - pose[:3]
    if rotation:
        error = ca.vertcat(error, ca.mtimes(R_d, _vee(ca.mtimes(R_d.T, R) - ca.mtimes(R.T, R_d)) / 2))
    g = arm.inverse_dynamics()(th, th, zero, zero, zero, zero)[1]
    T_d = g - ca.mtimes(Jt.T, k * error + D * twist)
    psi_d = _spring_inverse(arm, T_d)
    phi_d = th + psi_d
    tau_hold = arm.inverse_dynamics()(th, phi_d, zero, zero, zero, zero)[0]
    mu = arm.model.column("gear_ratio")
    B = np.diag(np.array(arm.mass_matrix()(np.zeros(n), np.zeros(n))))[n:]
    w = 2 * np.pi * motor_bandwidth_hz
    Km, Dm = B * w ** 2, 2 * motor_damping * B * w
    tau = tau_hold + (Km * (ph - phi_d) + Dm * dph) / mu
    return ca.Function("impedance", [th, ph, dth, dph, pose, K, zeta], [tau, T_d],
                       ["theta", "phi", "dtheta", "dphi", "pose_desired", "stiffness", "damping_ratio"], ["tau", "T_d"],
                       {"cse": True})


def _spring_inverse(arm: Arm, T):
    """The deflection psi with k1 psi + k3 psi^3 = T (three Newton steps from T / k1; exact when
    k3 = 0)."""
    k1 = ca.DM([jt.k1 for jt in arm.model.joints])
    k3 = ca.DM([jt.k3 for jt in arm.model.joints])
    psi = T / k1
    if float(ca.mmax(ca.fabs(k3))) > 0:
        for _ in range(3):
            psi = psi - (k1 * psi + k3 * psi ** 3 - T) / (k1 + 3 * k3 * psi ** 2)
    return psi


class ImpedanceController:
    """The Cartesian impedance controller at `frame`, in discrete time: `step(x, pose_desired,
    stiffness, damping_ratio)` -> the motor torques within the limits.  pose_desired: p (3) and
    R (9, column-major); stiffness: translational N/m (3), rotational N m/rad (3, used on arms of
    6 joints or more); damping_ratio: 6."""

    def __init__(self, arm: Arm, frame: str, **motor):
        self.n = arm.n
        self.law = impedance_law(arm, frame, **motor)
        self.limit = np.array([jt.limits.get("tau", np.inf) for jt in arm.model.joints])

    def step(self, x, pose_desired, stiffness, damping_ratio) -> np.ndarray:
        n, x = self.n, np.asarray(x, float)
        tau = np.array(self.law(x[:n], x[n:2 * n], x[2 * n:3 * n], x[3 * n:], pose_desired, stiffness,
                                damping_ratio)[0]).ravel()
        return np.clip(tau, -self.limit, self.limit)
