"""The arm's linear modes (rscasadi.dynamics.modes) against a two-mass spring written by hand, and
what they predict about RK4 against the nonlinear model integrated finely."""
import numpy as np
import pytest

import rscasadi
from rscasadi.dynamics.modes import linear_modes, rk4_growth, rk4_spurious, rk4_substeps
from rscasadi.dynamics.statics import rest_state
from rscasadi.model.modelfile import to_toml

from conftest import REFERENCE, ROOT


def test_one_joint_is_the_two_mass_spring_written_by_hand(tmp_path):
    """The shoulder yaw alone (no gravity about a vertical axis): link inertia I = Izz of the link
    (its centre on the axis), rotor B = Izz(S) + mu^2 Izz(F), spring k1 and d between them, the
    gear loss b on the rotor: the eigenvalues of that 4 x 4 system, to 1e-9."""
    import tomllib
    with open(REFERENCE, "rb") as fh:
        doc = tomllib.load(fh)
    doc["joints"] = [doc["joints"][0]]
    (tmp_path / "yaw.toml").write_text(to_toml(doc))
    arm = rscasadi.load(tmp_path / "yaw.toml")
    jt = doc["joints"][0]
    I, B = jt["link"]["inertia"][2], jt["slow_rotor"]["inertia"][2] + jt["gear_ratio"] ** 2 * jt["fast_rotor"]["inertia"][2]
    k, d, b = jt["sea"]["k1"], jt["sea"]["d"], jt["gear_loss"]["b"]
    A = np.array([[0, 0, 1, 0], [0, 0, 0, 1], [-k / I, k / I, -d / I, d / I], [k / B, -k / B, d / B, -(d + b) / B]])
    spring = max(np.linalg.eigvals(A), key=abs)
    mode = linear_modes(arm, [0.3])[0]
    assert abs(mode.eigenvalue - complex(spring.real, abs(spring.imag))) < 1e-9 * abs(spring)
    assert mode.joint == "shoulder_yaw" and mode.hz == pytest.approx(abs(spring) / (2 * np.pi))


def test_rk4_growth_is_the_method_s_own():
    """|R(z)| of one RK4 step equals one explicit RK4 step of dy/dt = lambda y, at any z."""
    for z in (-2.0, 2.5j, -0.7 + 2.9j, 0.3):
        k1 = z
        k2 = z * (1 + k1 / 2)
        k3 = z * (1 + k2 / 2)
        k4 = z * (1 + k3)
        assert rk4_growth(z) == pytest.approx(abs(1 + (k1 + 2 * k2 + 2 * k3 + k4) / 6), rel=1e-12)


def test_the_mode_rk4_amplifies_is_the_one_the_nonlinear_model_shows():
    """The Panda stretched up (theta = 0): at 20 ms intervals RK4 with 3 substeps amplifies the
    72 Hz spring mode of joint 3, with 4 it does not. Integrated on the nonlinear model from a
    1 mrad deflection of that spring, 3 substeps take its deflection to several times the
    start and far from a 40-substep run, 4 follow the 40-substep run."""
    from rscasadi.mpc.generate import integrator_notes
    from rscasadi.mpc.problem import load_mpc_problem, mpc_model
    from rscasadi.sim.loop import rk4_plant
    p = load_mpc_problem(ROOT / "problems" / "mpc_panda.toml")
    arm = rscasadi.Arm(mpc_model(p))
    n, theta = arm.n, np.zeros(7)
    modes = linear_modes(arm, theta)
    assert [m.joint for m in rk4_spurious(modes, 0.02 / 3)] == ["panda_joint3"] and rk4_substeps(modes, 0.02) == 4
    note, = integrator_notes(arm, p, [theta])
    assert "panda_joint3" in note and "substeps = 4 or more" in note
    x0 = rest_state(arm, theta)
    z = np.zeros(n)
    tau = np.array(arm.inverse_dynamics()(x0[:n], x0[n:2 * n], z, z, z, z)[0]).ravel()
    x0[n + 2] += 1e-3
    runs = {}
    for substeps in (3, 4, 40):
        plant, x, deflection = rk4_plant(arm, 0.02, substeps), x0.copy(), []
        for _ in range(15):
            x, _ = plant(x, tau, 0.0)
            deflection.append(x[n + 2] - x[2])
        runs[substeps] = np.array(deflection)
    assert np.max(np.abs(runs[3])) > 3e-3 and np.max(np.abs(runs[3] - runs[40])) > 3e-3
    assert np.max(np.abs(runs[4] - runs[40])) < 2e-4
    assert not integrator_notes(arm, p)              # along its own trajectory the problem's 3 substeps hold


def test_auto_substeps_are_the_fewest_that_hold_every_mode_or_refused_naming_it(tmp_path):
    """substeps = "auto" (the MPC's default): along the Panda problem's trajectory the file's own 3,
    stretched up the 4 the 72 Hz mode needs; on the reference arm with a flange a thousand times
    lighter no substeps up to the limit hold its spring mode: refused, naming the field, the mode
    and the joint, before any C is generated."""
    import dataclasses
    import tomllib
    from rscasadi.model.modelfile import ModelFileError
    from rscasadi.mpc.problem import MPCProblem, load_mpc_problem, mpc_model, with_substeps
    p = dataclasses.replace(load_mpc_problem(ROOT / "problems" / "mpc_panda.toml"), substeps="auto")
    arm = rscasadi.Arm(mpc_model(p))
    assert with_substeps(p, arm).substeps == 3
    up = dataclasses.replace(p, trajectory=None, theta_start=np.zeros(7))
    assert with_substeps(up, arm).substeps == rk4_substeps(linear_modes(arm, np.zeros(7)), 0.02) == 4
    with open(REFERENCE, "rb") as fh:
        doc = tomllib.load(fh)
    flange = doc["joints"][2]["link"]
    flange["mass"] *= 1e-3
    flange["inertia"] = [v * 1e-3 for v in flange["inertia"]]
    (tmp_path / "light.toml").write_text(to_toml(doc))
    light = MPCProblem(tmp_path / "light.toml", trajectory=ROOT / "problems" / "trajectory_arm3.toml", interval=0.02)
    with pytest.raises(ModelFileError, match=r"field 'substeps': auto: even 20 RK4 steps .* Hz spring mode of elbow_pitch"):
        with_substeps(light, rscasadi.Arm(mpc_model(light)))
