"""Statics of the SEA arm: the spring deflection that carries a torque, the rest state, and the
motor torque that holds the motors still (every generated controller's safe output)."""
from __future__ import annotations

import casadi as ca
import numpy as np

from rscasadi.dynamics.arm import Arm


def spring_torque(model, theta, phi, dtheta, dphi) -> np.ndarray:
    """T = k1 psi + k3 psi^3 + d dpsi of the model file's springs on numbers: arrays (n,) or
    (n, samples), psi = phi - theta (the law Arm.sea_torque writes symbolically)."""
    col = lambda a: model.column(a).reshape((-1,) + (1,) * (np.ndim(theta) - 1))   # noqa: E731
    psi, dpsi = np.asarray(phi) - theta, np.asarray(dphi) - dtheta
    return col("k1") * psi + col("k3") * psi ** 3 + col("d") * dpsi


def spring_deflection(arm: Arm, T, psi=None, steps: int = 30):
    """psi with k1 psi + k3 psi^3 = T (static part of the spring law), by `steps` Newton steps;
    T / k1 exactly for linear springs.  T may be numbers or a CasADi expression."""
    k1, k3 = arm.model.column("k1"), arm.model.column("k3")
    if psi is None and not np.any(k3):
        return T / k1
    psi = T / k1 if psi is None else psi
    for _ in range(steps):
        psi = psi - (k1 * psi + k3 * psi ** 3 - T) / (k1 + 3 * k3 * psi ** 2)
    return psi


def rest_state(arm: Arm, theta) -> np.ndarray:
    """At rest at theta with the SEAs holding the links statically (no residual oscillation)."""
    z, theta = np.zeros(arm.n), np.asarray(theta, float)
    T = np.array(arm.inverse_dynamics()(theta, theta, z, z, z, z)[1]).ravel()
    return np.concatenate([theta, theta + spring_deflection(arm, T), z, z])


def holding_torque(arm: Arm, name: str = "hold") -> ca.Function:
    """(theta, phi) -> tau: the motor torques that hold the motors still at phi with the links at
    theta (the complete model's inverse dynamics at zero speeds and accelerations: the springs'
    torque there, through the gears, and the rotors' weight)."""
    n = arm.n
    theta, phi, z = ca.SX.sym("theta", n), ca.SX.sym("phi", n), ca.SX.zeros(n)
    return ca.Function(name, [theta, phi], [arm.inverse_dynamics()(theta, phi, z, z, z, z)[0]],
                       ["theta", "phi"], ["tau"], {"cse": True})
