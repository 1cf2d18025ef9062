"""One linearly implicit step of the complete model: the two-stage Rosenbrock method ROS2
(Verwer, Spee, Blom and Hundsdorfer, SIAM J. Sci. Comput. 20, 1999), for the MPC's intervals on
arms whose spring modes are too fast for explicit steps.

    W = I - gamma h J,   gamma = 1 + 1/sqrt(2),   J = df/dx at x
    W k1 = f(x)
    W k2 = f(x + h k1) - 2 k1
    x_next = x + 3/2 h k1 + 1/2 h k2

L-stable: a mode however fast (a light flange behind a stiff SEA: real eigenvalues near -5e3
1/s, where RK4 needs steps below 0.5 ms) decays in one step of any length; second order for
any J, so the rigid motion keeps its accuracy.  The state's structure halves the algebra: with
J = [[0, I], [Fq, Fv]] (Fq, Fv the forward dynamics' Jacobian in the coordinates and their speeds),
W k = r is k_v = S^-1 (r_v + gamma h Fq r_q), k_q = r_q + gamma h k_v, one LU of the
nq x nq S = I - gamma h Fv - (gamma h)^2 Fq per step (nq coordinates: 2n on an arm of SEAs).

The step's Jacobian (the MPC's sensitivities A, B) is the chain rule through both stages with W
held fixed: dk1 = W^-1 Jf(x) dx, dk2 = W^-1 (Jf(x + h k1) (dx + h dk1) - 2 dk1), Jf the full
state equation's Jacobian in (x, tau).  Exact for a linear model; on the arm it leaves out W's own
derivative (second derivatives of the dynamics), the inexact-Jacobian real-time iteration's
usual choice: the constraints (the step itself) stay exact.
"""
from __future__ import annotations

import casadi as ca

from rscasadi.codegen.generate import forward_dynamics_jacobian, rhs
from rscasadi.codegen.step_kernel import GAMMA
from rscasadi.dynamics.arm import Arm



def ros2_functions(arm: Arm, prefix: str = "", fd_jacobian: ca.Function | None = None, parametric: bool = False):
    """step: (x, tau, h[, p]) -> x_next, one ROS2 step of the complete model; step_jacobian:
    (x, tau, h[, p]) -> A = dx_next/dx, B = dx_next/dtau with W held fixed (module docstring).
    Straight-line SX where the forward-dynamics Jacobian is SX, an MX graph of it otherwise."""
    nq, nx = arm.nq, 2 * arm.nq
    f = rhs(arm, parametric)
    jac = fd_jacobian or forward_dynamics_jacobian(arm, parametric, prefix + "forward_dynamics_jacobian")
    sym = ca.SX if jac.is_a("SXFunction") else ca.MX
    x, tau, h = sym.sym("x", nx), sym.sym("tau", arm.u), sym.sym("h")
    p = [sym.sym("p", arm.n_p)] if parametric else []
    F1 = ca.densify(jac(*arm.split_state(x), tau, *p))              # d(accelerations)/d(x, tau): nq x (nx + u)
    Fq, Fv, gh = F1[:, :nq], F1[:, nq:nx], GAMMA * h
    S = ca.DM.eye(nq) - gh * Fv - gh ** 2 * Fq

    def solve(r):                                                     # W^-1 r
        kv = ca.solve(S, r[nq:, :] + gh * ca.mtimes(Fq, r[:nq, :]))
        return ca.vertcat(r[:nq, :] + gh * kv, kv)

    k1 = solve(f(x, tau, *p))
    x2 = x + h * k1
    k2 = solve(f(x2, tau, *p) - 2 * k1)
    x_next = x + 1.5 * h * k1 + 0.5 * h * k2
    I = ca.DM.eye(nx + arm.u)

    def along(F, dz):                                                 # d f(z, tau) = [dz's speed rows; F d(z, tau)]
        return ca.vertcat(dz[nq:, :], ca.mtimes(F, ca.vertcat(dz, I[nx:, :])))

    dx = I[:nx, :]                                                    # d x / d(x, tau)
    dk1 = solve(along(F1, dx))
    F2 = ca.densify(jac(*arm.split_state(x2), tau, *p))
    dk2 = solve(along(F2, dx + h * dk1) - 2 * dk1)
    d = dx + 1.5 * h * dk1 + 0.5 * h * dk2
    names = ["x", "tau", "h"] + ["p"] * len(p)
    opts = {"cse": True} if sym is ca.SX else {}
    step = ca.Function(prefix + "step", [x, tau, h] + p, [x_next], names, ["x_next"], opts)
    step_jac = ca.Function(prefix + "step_jacobian", [x, tau, h] + p, [d[:, :nx], d[:, nx:]], names, ["A", "B"],
                           opts)
    return step, step_jac
