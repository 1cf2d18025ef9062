"""The arm's linear modes about a rest pose, and what an explicit integrator does to them.

Linearised at rest at theta (the motors holding it), the complete model's state x = (theta, phi,
dtheta, dphi) moves as dx/dt = A x near it; each eigenvalue lambda of A is a mode: the
rigid-body ones near zero (or real and positive where gravity tips the arm over), the spring
modes a lightly damped pair at the springs' frequencies. A one-step method multiplies a mode
by R(lambda h) per step, where the exact flow multiplies it by exp(lambda h); RK4's
R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24 grows where |R| > 1 (about |z| > 2.8 on the imaginary
axis): a spring mode that the arm damps, the integrator then amplifies.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from rscasadi.dynamics.arm import Arm
from rscasadi.dynamics.statics import rest_state


@dataclass(frozen=True)
class Mode:
    """One eigenvalue of the linearised arm: `eigenvalue` (1/s), its `hz` and `damping_ratio`,
    and the `joint` whose spring deflection (phi - theta; a joint without a motor: its angle)
    dominates its shape."""
    eigenvalue: complex
    hz: float
    damping_ratio: float
    joint: str


def linear_modes(arm: Arm, theta) -> list[Mode]:
    """The modes of the complete model at rest at `theta`, fastest first (one of each complex pair)."""
    n, nq, motors = arm.n, arm.nq, arm.model.motors
    x0 = rest_state(arm, np.asarray(theta, float))
    z, zm = np.zeros(n), np.zeros(arm.m)
    tau = np.array(arm.inverse_dynamics()(x0[:n], x0[n:nq], z, zm, z, zm)[0]).ravel()
    xs = ca.SX.sym("x", 2 * nq)
    f = ca.vertcat(xs[nq:], *arm.forward_dynamics()(*arm.split_state(xs), tau))
    A = np.array(ca.Function("A", [xs], [ca.jacobian(f, xs)])(x0))
    lam, V = np.linalg.eig(A)
    names = [jt.name for jt in arm.model.joints]
    modes = []
    for i in np.argsort(-np.abs(lam)):
        if lam[i].imag < 0:
            continue
        deflection = np.abs(V[:n, i])                           # a joint's own motion, an SEA's deflection
        deflection[motors] = np.abs(V[n:nq, i] - V[motors, i])
        w = abs(lam[i])
        modes.append(Mode(complex(lam[i]), w / (2 * np.pi), -lam[i].real / w if w > 0 else 1.0,
                          names[int(np.argmax(deflection))]))
    return modes


def rk4_growth(z) -> np.ndarray:
    """|R(z)| of one RK4 step."""
    z = np.asarray(z, complex)
    return np.abs(1 + z + z ** 2 / 2 + z ** 3 / 6 + z ** 4 / 24)


def rk4_spurious(modes: list[Mode], h: float) -> list[Mode]:
    """The modes RK4 with steps of h amplifies beyond what the arm does (|R| > max(1, |exp|))."""
    return [m for m in modes
            if rk4_growth(m.eigenvalue * h) > max(1.0, abs(np.exp(m.eigenvalue * h))) * (1 + 1e-9)]


def rk4_substeps(modes: list[Mode], interval: float, most: int = 50) -> int | None:
    """The fewest RK4 substeps of an interval that amplify no mode spuriously (None: more than `most`)."""
    for s in range(1, most + 1):
        if not rk4_spurious(modes, interval / s):
            return s
    return None
