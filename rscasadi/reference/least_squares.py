"""Independent least-squares fits of an arm's logs, as a reference for `rscasadi identify`
(optional: `pip install pin`).

They share no code with rscasadi's identification: the link rows are Pinocchio's joint-torque
regressor of the URDF's links (`computeJointTorqueRegressor`: the ten inertial parameters per
link; a rotor's mass, fixed on its parent link, is part of that link's), filtering and
differentiation are scipy's and numpy's, and the solve is numpy's minimum-norm least squares,
with no physical constraint.  What a team would write without rscasadi:

- link side (theta, T logged): T = Y_pin(theta, dtheta, ddtheta) pi [+ per joint an offset, a
  viscous and a Coulomb link loss and a spring on theta (counterbalance)];
- motor side (theta, phi, tau logged): Y_pin pi [+ the same link terms] = k1 psi + k3 psi^3 +
  d dpsi (link rows) and k1 psi + k3 psi^3 + d dpsi + J ddphi + b dphi + c tanh(dphi / eps) =
  -mu tau (motor rows: the rotors as an armature J, no gyroscopic coupling).

Each returns the held-out relative RMS error per joint of the torque it predicts, both logs
filtered at the same cut-off (Butterworth order 4, zero phase), 0.25 s dropped at each end, one
row per 1 / (2 fc) s, motor rows within 10 eps of a reversal left out (as rscasadi's are).
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin
import scipy.signal

from rscasadi.reference.pinocchio_route import configuration, urdf_model

EDGE_S = 0.25
REVERSAL = 10.0


def _filtered(log, fc):
    """The log's angles, their speeds and accelerations and its torques, filtered at fc, at the
    kept samples."""
    sos = scipy.signal.butter(4, fc, fs=1 / log.dt, output="sos")
    lp = lambda x: None if x is None else scipy.signal.sosfiltfilt(sos, x, axis=1)      # noqa: E731
    d = lambda x: None if x is None else np.gradient(x, log.dt, axis=1)               # noqa: E731
    th, ph = lp(log.theta), lp(log.phi)
    dth, dph = d(th), d(ph)
    edge = int(EDGE_S / log.dt)
    keep = np.arange(edge, log.t.size - edge, max(1, int(0.5 / (fc * log.dt))))
    at = lambda x: None if x is None else x[:, keep]                                  # noqa: E731
    return {"th": at(th), "dth": at(dth), "ddth": at(d(dth)), "ph": at(ph), "dph": at(dph), "ddph": at(d(dph)),
            "T": at(lp(log.T)), "tau": at(lp(log.tau))}


def _link_terms(s, i, n, eps) -> np.ndarray:
    """Per joint: offset, viscous, Coulomb, spring on theta (n, 4n)."""
    out = np.zeros((n, 4 * n))
    for j in range(n):
        out[j, 4 * j:4 * j + 4] = 1.0, s["dth"][j, i], np.tanh(s["dth"][j, i] / eps[j]), s["th"][j, i]
    return out


class _Fit:
    def __init__(self, arm, link_terms: bool):
        self.pm = urdf_model(arm.model)
        self.pd = self.pm.createData()
        self.n, self.link_terms = arm.n, link_terms
        self.mu, self.eps = arm.model.column("gear_ratio"), arm.model.column("eps")

    def Y(self, s, i):
        Y = pin.computeJointTorqueRegressor(self.pm, self.pd, configuration(self.pm, s["th"][:, i]), s["dth"][:, i],
                                            s["ddth"][:, i])
        return np.hstack([Y, _link_terms(s, i, self.n, self.eps)]) if self.link_terms else Y


def link_side_fit(arm, ident_log, valid_log, fc: float, link_terms: bool = False) -> np.ndarray:
    """Held-out relative RMS error of T per joint (logs with theta and T)."""
    fit = _Fit(arm, link_terms)

    def rows(log):
        s = _filtered(log, fc)
        return np.vstack([fit.Y(s, i) for i in range(s["th"].shape[1])]), s["T"].T.ravel()

    A, y = rows(ident_log)
    x = np.linalg.lstsq(A, y, rcond=1e-10)[0]
    A, y = rows(valid_log)
    pred, y = (A @ x).reshape(-1, arm.n).T, y.reshape(-1, arm.n).T
    return np.sqrt(np.mean((pred - y) ** 2, axis=1) / np.mean(y ** 2, axis=1))


def motor_side_fit(arm, ident_log, valid_log, fc: float, link_terms: bool = False) -> np.ndarray:
    """Held-out relative RMS error of the motor torque tau per joint (logs with theta, phi, tau)."""
    fit, n = _Fit(arm, link_terms), arm.n

    def rows(log):
        s = _filtered(log, fc)
        blocks, ys, joint = [], [], []
        for i in range(s["th"].shape[1]):
            Y = fit.Y(s, i)
            psi, dpsi = s["ph"][:, i] - s["th"][:, i], s["dph"][:, i] - s["dth"][:, i]
            spring, motor = np.zeros((n, 6 * n)), np.zeros((n, 6 * n))        # per joint: k1, k3, d, J, b, c
            for j in range(n):
                spring[j, 6 * j:6 * j + 3] = psi[j], psi[j] ** 3, dpsi[j]
                motor[j, 6 * j:6 * j + 6] = (psi[j], psi[j] ** 3, dpsi[j], s["ddph"][j, i], s["dph"][j, i],
                                             np.tanh(s["dph"][j, i] / fit.eps[j]))
            blocks += [np.hstack([Y, -spring]), np.hstack([np.zeros_like(Y), motor])]
            ys += [np.zeros(n), -fit.mu * s["tau"][:, i]]
            moving = np.abs(s["dph"][:, i]) > REVERSAL * fit.eps
            joint += [np.full(n, -1), np.where(moving, np.arange(n), -2)]
        return np.vstack(blocks), np.concatenate(ys), np.concatenate(joint)

    A, y, joint = rows(ident_log)
    use = joint != -2
    x = np.linalg.lstsq(A[use], y[use], rcond=1e-10)[0]
    A, y, joint = rows(valid_log)
    pred = A @ x
    return np.array([np.sqrt(np.mean((pred[joint == j] - y[joint == j]) ** 2) / np.mean(y[joint == j] ** 2))
                     for j in range(n)])
