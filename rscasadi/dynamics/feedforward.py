"""The paper's feedforward as two Functions with an explicit state, for a controller in C.

One sample of the cascade (paper eqs. 26 and 22, the spring law between them):

- eq. (26) gives the SEA torque T that the desired link motion requires; it needs the rotor
  accelerations ddphi = ddtheta + ddpsi (through the coupling S), predicted by linear
  extrapolation and corrected once (PECE);
- the deflection psi = phi - theta must produce T through k1 psi + k3 psi^3 + d dpsi = T,
  integrated by the trapezoidal rule (implicit: d/k1 is about a millisecond), by Newton;
- eq. (22) then gives the motor torque tau.

    feedforward_init(theta_d, dtheta_d, ddtheta_d) -> tau, state      (at rest: static deflection)
    feedforward_step(state, theta_d, dtheta_d, ddtheta_d, h) -> tau, state_next

theta_d and its derivatives are those of the *new* sample; state = (psi, dpsi, ddpsi,
ddpsi_previous), 4n.  Newton runs a fixed number of iterations, so the C has no loops with
data-dependent ends and allocates nothing.
"""
from __future__ import annotations

import casadi as ca

STATIC_NEWTON = 30      # static deflection k1 psi + k3 psi^3 = T, from psi = T / k1
TRAPEZOID_NEWTON = 4    # the trapezoidal spring law per correction
CORRECTIONS = 2         # evaluate-correct passes of eq. (26) per sample


def _spring(arm, parametric):
    """The actuator columns (k1, k3, d, ...): the model file's numbers, or expressions of a new
    parameter vector p (returned too)."""
    if not parametric:
        return None, arm.physics.columns
    p = ca.SX.sym("p", arm.n_p)
    return p, arm._physics_of(p).columns


def feedforward_functions(arm, reduced: bool = False, parametric: bool = False) -> tuple[ca.Function, ca.Function]:
    """(init, step): the paper's feedforward cascade as CasADi Functions, one sample per call of
    `step` (the spring law integrated by the trapezoidal rule); `init` gives the first sample's
    torque and state from theta, dtheta, ddtheta at rest."""
    n = arm.n
    inv = (arm.reduced_inverse_dynamics if reduced else arm.inverse_dynamics)(parametric=parametric)
    p, c = _spring(arm, parametric)
    extra = [p] if parametric else []
    k1, k3, d = c["k1"], c["k3"], c["d"]
    th, dth, ddth = (ca.SX.sym(s, n) for s in ("theta_d", "dtheta_d", "ddtheta_d"))

    def T_required(psi, dpsi, ddpsi):                                      # eq. (26)
        return inv(th, th + psi, dth, dth + dpsi, ddth, ddth + ddpsi, *extra)[1]

    def tau_of(psi, dpsi, ddpsi):                                          # eq. (22)
        return inv(th, th + psi, dth, dth + dpsi, ddth, ddth + ddpsi, *extra)[0]

    def static(T, psi):
        for _ in range(STATIC_NEWTON):
            psi = psi - (k1 * psi + k3 * psi ** 3 - T) / (k1 + 3 * k3 * psi ** 2)
        return psi

    zero = ca.SX.zeros(n)
    psi0 = static(T_required(zero, zero, zero), T_required(zero, zero, zero) / k1)
    psi0 = static(T_required(psi0, zero, zero), psi0)
    init = ca.Function("feedforward_init", [th, dth, ddth] + extra,
                       ca.cse([tau_of(psi0, zero, zero), ca.vertcat(psi0, zero, zero, zero)]),
                       ["theta_d", "dtheta_d", "ddtheta_d"] + ["p"] * len(extra), ["tau", "state"])

    state, h = ca.SX.sym("state", 4 * n), ca.SX.sym("h")
    psi_k, dpsi_k, ddpsi_k, ddpsi_prev = ca.vertsplit(state, n)
    ddpsi = 2 * ddpsi_k - ddpsi_prev                                       # predictor
    dpsi = dpsi_k + h * ddpsi_k
    psi = psi_k + h * dpsi_k
    for _ in range(CORRECTIONS):                                           # evaluate, correct
        T = T_required(psi, dpsi, ddpsi)
        for _ in range(TRAPEZOID_NEWTON):                                  # trapezoid + spring law
            g = 2 * d / h * (psi - psi_k) - d * dpsi_k + k1 * psi + k3 * psi ** 3 - T
            psi = psi - g / (2 * d / h + k1 + 3 * k3 * psi ** 2)
        dpsi = 2 / h * (psi - psi_k) - dpsi_k
        ddpsi = (dpsi - dpsi_k) / h
    step = ca.Function("feedforward_step", [state, th, dth, ddth, h] + extra,
                       ca.cse([tau_of(psi, dpsi, ddpsi), ca.vertcat(psi, dpsi, ddpsi, ddpsi_k)]),
                       ["state", "theta_d", "dtheta_d", "ddtheta_d", "h"] + ["p"] * len(extra),
                       ["tau", "state_next"])
    return init, step
