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
    """psi with k1 psi + k3 psi^3 = T (static part of the spring law) per motor (T: the motors'
    springs' torques), by `steps` Newton steps; T / k1 exactly for linear springs.  T may be
    numbers or a CasADi expression."""
    motors = arm.model.motors
    k1, k3 = arm.model.column("k1")[motors], arm.model.column("k3")[motors]
    if psi is None and not np.any(k3):
        return T / k1
    psi = T / k1 if psi is None else psi
    for _ in range(steps):
        psi = psi - (k1 * psi + k3 * psi ** 3 - T) / (k1 + 3 * k3 * psi ** 2)
    return psi


def rest(arm: Arm, theta, reduced: bool = False, phi=None) -> tuple:
    """(theta, phi, tau) at rest: the actuated joints at `theta`, each joint without an input
    (spring, free) where its link rests (the equilibrium nearest `theta`, by Newton steps on
    those angles), each SEA's motor where its spring holds its link (a fixed point: unbalanced
    rotors' weight moves with phi), and the torques that hold it all still (`reduced`: the
    DLR/Spong reduced model's; `phi`: the motors held there instead)."""
    n, m, model = arm.n, arm.m, arm.model
    passive = [j for j in range(n) if j not in model.actuated]
    th, ph = ca.SX.sym("theta", n), ca.SX.sym("phi", m)
    inv = arm.reduced_inverse_dynamics() if reduced else arm.inverse_dynamics()
    tau, T = inv(th, ph, ca.DM.zeros(n), ca.DM.zeros(m), ca.DM.zeros(n), ca.DM.zeros(m))
    f = ca.Function("statics", [th, ph], [tau, T, ca.jacobian(T[passive], th[passive]) if passive else ca.DM()])
    theta, held = np.array(theta, float), phi is not None
    phi = np.array(phi, float) if held else theta[model.motors]
    for _ in range(100):
        _, T_now, K = (np.array(v) for v in f(theta, phi))
        T_now = T_now.ravel()
        step = np.linalg.lstsq(K, -T_now[passive], rcond=None)[0] if passive else np.zeros(0)
        theta[passive] += np.clip(step, -0.2, 0.2)
        before = phi
        phi = phi if held else theta[model.motors] + spring_deflection(arm, T_now[model.motors])
        if np.max(np.abs(np.r_[phi - before, step]), initial=0.0) < 1e-14:
            break
    return theta, phi, np.array(f(theta, phi)[0]).ravel()


def rest_state(arm: Arm, theta) -> np.ndarray:
    """At rest at theta (`rest`) with no residual oscillation: (theta, phi, 0, 0)."""
    theta, phi, _ = rest(arm, theta)
    return np.concatenate([theta, phi, np.zeros(arm.n), np.zeros(arm.m)])


def holding_torque(arm: Arm, name: str = "hold") -> ca.Function:
    """(theta, phi) -> tau: the motor torques that hold the motors still at phi with the links at
    theta (the complete model's inverse dynamics at zero speeds and accelerations: the springs'
    torque there, through the gears, and the rotors' weight)."""
    n, m = arm.n, arm.m
    theta, phi = ca.SX.sym("theta", n), ca.SX.sym("phi", m)
    return ca.Function(name, [theta, phi], [arm.inverse_dynamics()(theta, phi, ca.SX.zeros(n), ca.SX.zeros(m),
                                                                   ca.SX.zeros(n), ca.SX.zeros(m))[0]],
                       ["theta", "phi"], ["tau"], {"cse": True})
