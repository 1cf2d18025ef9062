"""Energy: conserved without losses and torque; otherwise dE/dt equals the power of the forces."""
import dataclasses

import casadi as ca
import numpy as np

from rscasadi import Arm

from conftest import random_state


def lossless(arm):
    joints = tuple(dataclasses.replace(jt, d=0.0, b=0.0, c=0.0) for jt in arm.model.joints)
    return Arm(dataclasses.replace(arm.model, joints=joints))


def test_energy_conserved_over_two_seconds(arm3):
    arm, n = lossless(arm3), arm3.n
    x = ca.SX.sym("x", 4 * n)
    parts = ca.vertsplit(x, n)
    ddq = ca.vertcat(*arm.forward_dynamics()(*parts, ca.DM.zeros(n)))
    ode = {"x": x, "ode": ca.vertcat(parts[2], parts[3], ddq)}
    sim = ca.integrator("sim", "cvodes", ode, 0.0, np.linspace(0.0, 2.0, 21)[1:],
                        {"abstol": 1e-13, "reltol": 1e-13, "max_num_steps": 200000})
    rng = np.random.default_rng(11)
    x0 = np.concatenate(random_state(rng, n, scale=1.0))
    X = np.array(sim(x0=x0)["xf"])
    E = arm.energy()
    E0 = float(E(*np.split(x0, 4)))
    Et = np.array([float(E(*np.split(X[:, i], 4))) for i in range(X.shape[1])])
    assert abs(E0) > 1.0
    assert np.ptp(X[:3], axis=1).max() > 0.1, "the arm must actually move"
    assert np.max(np.abs(Et - E0)) / abs(E0) < 1e-8


def test_power_balance_on_random_arms(random_arms):
    """dE/dt = sum(-d dpsi^2 - T_B2 dphi - mu tau dphi) along the complete model, any arm."""
    rng = np.random.default_rng(12)
    for arm in random_arms:
        n = arm.n
        th, ph, dth, dph, tau = (ca.SX.sym(s, n) for s in ("th", "ph", "dth", "dph", "tau"))
        ddth, ddph = arm.forward_dynamics()(th, ph, dth, dph, tau)
        E = arm.energy()(th, ph, dth, dph)
        dE = ca.jtimes(E, ca.vertcat(th, ph, dth, dph), ca.vertcat(dth, dph, ddth, ddph))
        d, mu = ca.DM(arm.model.column("d")), ca.DM(arm.model.column("gear_ratio"))
        power = ca.sum1(-d * (dph - dth) ** 2 - arm.gear_loss(dph) * dph - mu * tau * dph)
        f = ca.Function("f", [th, ph, dth, dph, tau], [dE, power])
        for _ in range(3):
            x = random_state(rng, n)
            lhs, rhs = (float(v) for v in f(*x, rng.normal(size=n)))
            assert abs(lhs - rhs) <= 1e-9 * max(abs(rhs), 1.0)
