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


def light_flange(tmp_path, factor=1e-3):
    """The reference arm with its last link `factor` times as heavy (its modes: 1.9 kHz and
    127 Hz, critically damped, beside the 17 Hz ones)."""
    import tomllib
    with open(REFERENCE, "rb") as fh:
        doc = tomllib.load(fh)
    flange = doc["joints"][2]["link"]
    flange["mass"] *= factor
    flange["inertia"] = [v * factor for v in flange["inertia"]]
    (tmp_path / "light.toml").write_text(to_toml(doc))
    return tmp_path / "light.toml"


def test_auto_substeps_are_the_fewest_that_hold_every_mode_or_refused_naming_it(tmp_path):
    """substeps = "auto": along the Panda problem's trajectory RK4's fewest are the file's own 3,
    stretched up the 4 the 72 Hz mode needs (integrator = "auto" keeps RK4 there); on the reference
    arm with a flange a thousand times lighter no RK4 substeps up to the limit hold its spring
    mode: integrator = "rk4" is refused, naming the field, the mode and the joint, before any C
    is generated; "auto" takes the L-stable ROS2 in steps of at most 10 ms."""
    import dataclasses
    from rscasadi.model.modelfile import ModelFileError
    from rscasadi.mpc.problem import MPCProblem, load_mpc_problem, mpc_model, with_integrator
    p = dataclasses.replace(load_mpc_problem(ROOT / "problems" / "mpc_panda.toml"), substeps="auto")
    arm = rscasadi.Arm(mpc_model(p))
    assert (with_integrator(p, arm).integrator, with_integrator(p, arm).substeps) == ("rk4", 3)
    up = dataclasses.replace(p, trajectory=None, theta_start=np.zeros(7))
    assert with_integrator(up, arm).substeps == rk4_substeps(linear_modes(arm, np.zeros(7)), 0.02) == 4
    light = MPCProblem(light_flange(tmp_path), trajectory=ROOT / "problems" / "trajectory_arm3.toml", interval=0.02)
    arm = rscasadi.Arm(mpc_model(light))
    with pytest.raises(ModelFileError, match=r"field 'substeps': auto: even 20 RK4 steps .* Hz spring mode of elbow_pitch"
                                             r".*integrator = \"ros2\""):
        with_integrator(dataclasses.replace(light, integrator="rk4"), arm)
    settled = with_integrator(light, arm)
    assert (settled.integrator, settled.substeps) == ("ros2", 2)
    assert with_integrator(dataclasses.replace(light, substeps=3), arm).integrator == "ros2"


def test_the_rosenbrock_step_is_stable_where_rk4_is_not_and_its_jacobian_is_the_chain_rule(tmp_path):
    """ROS2 (codegen.rosenbrock) on the reference arm with a flange a thousand times lighter
    (real eigenvalues near -1.2e4 1/s): from a deflected, moving state, 10 ms steps follow RK4 at
    10 us within 2 mrad over 0.2 s, where RK4 at 1 ms diverges; on the Panda its step Jacobian
    equals CasADi's AD of the same step with W's point held fixed (a dense 4n solve, not the
    structured one) to 1e-7."""
    import casadi as ca
    from rscasadi.codegen.generate import forward_dynamics_jacobian, rhs, rk4
    from rscasadi.codegen.rosenbrock import GAMMA, ros2_functions
    arm = rscasadi.load(light_flange(tmp_path))
    n, f = arm.n, rhs(arm)
    step, _ = ros2_functions(arm)
    xs, us, hs = ca.SX.sym("x", 4 * n), ca.SX.sym("u", n), ca.SX.sym("h")
    explicit = ca.Function("rk4", [xs, us, hs], [rk4(lambda z: f(z, us), xs, hs)[0]])
    theta = np.array([0.2, 0.5, -0.7])
    x0, tau = np.concatenate([theta, theta + [0.002, -0.003, 0.004], [0.3, -0.2, 0.5], [0.1, 0.2, -0.3]]), np.zeros(n)

    def run(F, h, T=0.2):
        x = x0.copy()
        for _ in range(int(round(T / h))):
            x = np.array(F(x, tau, h)).ravel()
            if not np.all(np.isfinite(x)) or np.max(np.abs(x)) > 1e6:
                return None
        return x
    fine, coarse = run(explicit, 1e-5), run(step, 0.01)
    assert np.max(np.abs(coarse[:2 * n] - fine[:2 * n])) < 2e-3, coarse[:2 * n] - fine[:2 * n]
    assert run(explicit, 1e-3) is None
    panda = rscasadi.load(ROOT / "problems" / "panda_sea.toml")
    n, f, jac = panda.n, rhs(panda), forward_dynamics_jacobian(panda)
    step, step_jacobian = ros2_functions(panda)
    x, xw, u, uw, h = (ca.SX.sym(k, m) for k, m in (("x", 4 * n), ("xw", 4 * n), ("u", n), ("uw", n), ("h", 1)))
    F = ca.densify(jac(*ca.vertsplit(xw, n), uw))
    W = ca.DM.eye(4 * n) - GAMMA * h * ca.vertcat(ca.horzcat(ca.DM.zeros(2 * n, 2 * n), ca.DM.eye(2 * n)), F[:, :4 * n])
    k1 = ca.solve(W, f(x, u))
    k2 = ca.solve(W, f(x + h * k1, u) - 2 * k1)
    x_next = x + 1.5 * h * k1 + 0.5 * h * k2
    ad = ca.Function("ad", [x, xw, u, uw, h], [x_next, ca.jacobian(x_next, x), ca.jacobian(x_next, u)])
    rng = np.random.default_rng(3)
    q = rng.normal(0, 0.5, n)
    xv, uv = np.concatenate([q, q + rng.normal(0, 0.01, n), rng.normal(0, 0.5, 2 * n)]), rng.normal(0, 0.2, n)
    want = [np.array(v) for v in ad(xv, xv, uv, uv, 0.01)]
    got = [np.array(step(xv, uv, 0.01))] + [np.array(v) for v in step_jacobian(xv, uv, 0.01)]
    for g, w in zip(got, want):
        assert np.max(np.abs(g - w)) < 1e-7 * max(1.0, np.max(np.abs(w))), np.max(np.abs(g - w))


def test_the_default_mpc_runs_an_arm_whose_flange_is_a_thousand_times_lighter(tmp_path):
    """The reference arm with a flange a thousand times lighter, the MPC at 20 ms intervals with
    nothing tuned: generated with ROS2 (said), every step finite, tracking the paper's trajectory
    closer than feedforward + PD on a plant with a 20 % heavier flange (integrated finely)."""
    from rscasadi.mpc.generate import generate_mpc
    from rscasadi.mpc.problem import MPCProblem
    from rscasadi.mpc.study import closed_loop
    from rscasadi.sim.loop import rk4_plant
    p = MPCProblem(light_flange(tmp_path), trajectory=ROOT / "problems" / "trajectory_arm3.toml", interval=0.02,
                   horizon=10)
    said: list = []
    generate_mpc(p, tmp_path / "mpc", opt="-O1", log=said.append)
    assert any(line.startswith("integrator ros2, 2 steps of 10 ms") for line in said), said
    res = closed_loop(p, tmp_path / "mpc", duration=0.5, log=lambda m: None,
                      simulator=lambda plant, dt: rk4_plant(plant, dt, 40))
    mpc, pd = res["MPC (C)"], res["feedforward + PD"]
    assert np.isfinite(mpc["max_error"]) and mpc["max_error"] < pd["max_error"] / 2, (mpc["max_error"], pd["max_error"])
    assert mpc["max_limit_violation"] == 0.0


def test_the_rosenbrock_mpc_of_a_seven_joint_arm_runs_its_structured_kernel(tmp_path):
    """The Panda with a wrist fifty times lighter (a spring mode more RK4 substeps than 4 would
    need): integrator = "auto" takes ROS2, and the generated controller steps with ROS2's
    structured kernel (mpc_step_jacobian.c among its sources, codegen.step_kernel) in place of
    the dense graph of codegen.rosenbrock.  Its torques equal the CasADi Functions' built on that
    graph (no shared C) over five steps; a NaN, infinite or absurd measurement is refused (code 6)
    with finite torques within the limits, and the next good sample is stepped; in closed loop on
    the plant integrated finely (RK4 at 0.1 ms) it tracks the Panda's trajectory twice as close as
    feedforward + PD (3.5x on 2026-11-29), no limit passed."""
    import dataclasses
    import json
    from rscasadi.model.modelfile import document
    from rscasadi.mpc import CompiledMPC, closed_loop, hold_function
    from rscasadi.mpc.formulation import controller_arm, feedback_function, input_limits, prepare_function
    from rscasadi.mpc.generate import generate_mpc
    from rscasadi.mpc.problem import load_mpc_problem, mpc_model, with_integrator
    from rscasadi.sim.loop import rk4_plant
    doc = document(rscasadi.load(ROOT / "problems" / "panda_sea.toml").model)
    wrist = doc["joints"][6]["link"]
    wrist["mass"] *= 0.02
    wrist["inertia"] = [v * 0.02 for v in wrist["inertia"]]
    (tmp_path / "light.toml").write_text(to_toml(doc))
    p = dataclasses.replace(load_mpc_problem(ROOT / "problems" / "mpc_panda.toml"), model=tmp_path / "light.toml",
                            trajectory=ROOT / "problems" / "trajectory_panda.toml", substeps="auto", integrator="auto")
    said: list = []
    generate_mpc(p, tmp_path / "mpc", opt="-O1", log=said.append)
    assert any(line.startswith("integrator ros2") for line in said), said
    assert "mpc_step_jacobian.c" in json.loads((tmp_path / "mpc" / "manifest.json").read_text())["sources"]
    arm = controller_arm(mpc_model(p))
    settled = with_integrator(p, arm)
    prepare = prepare_function(arm, settled)
    feedback, hold = feedback_function(arm, settled, prepare), hold_function(arm, settled)
    c, rng = CompiledMPC(tmp_path / "mpc"), np.random.default_rng(5)
    x = rest_state(arm, [0.0, -0.3, 0.0, -2.0, 0.0, 1.7, 0.8])
    c.init(x)
    posture = x[:7].copy()
    X, U = (np.array(v) for v in hold(x, posture))
    for _ in range(5):
        ref = np.vstack([x[:7, None] + rng.normal(0, 0.02, (7, settled.horizon)), rng.normal(0, 0.1, (7, settled.horizon))])
        tau_c, _, flag = c.step(x, ref)
        tau_py, X, U = (np.array(v) for v in feedback(x, X, U, *prepare(ref, X, U, posture)))
        assert flag == 0 and np.max(np.abs(tau_c - tau_py.ravel())) < 1e-8, np.max(np.abs(tau_c - tau_py.ravel()))
        x = x + rng.normal(0, 1e-4, x.shape)
    limit = input_limits(arm)
    for k, bad in enumerate((np.nan, np.inf, -1e12)):          # a bad measurement: refused, torques safe
        xb = x.copy()
        xb[(5 * k + 3) % x.size] = bad
        tau_c, _, flag = c.step(xb, ref)
        assert flag == 6 and np.all(np.isfinite(tau_c)) and np.all(np.abs(tau_c) <= limit + 1e-12), (bad, flag)
    tau_c, _, flag = c.step(x, ref)                              # and the next good sample is stepped
    assert flag == 0 and np.all(np.isfinite(tau_c)) and np.all(np.abs(tau_c) <= limit + 1e-12)
    res = closed_loop(p, tmp_path / "mpc", duration=0.3, log=lambda m: None,
                      simulator=lambda plant, dt: rk4_plant(plant, dt, 10))
    mpc, pd = res["MPC (C)"], res["feedforward + PD"]
    assert np.isfinite(mpc["max_error"]) and mpc["max_error"] < pd["max_error"] / 2, (mpc["max_error"], pd["max_error"])
    assert mpc["max_limit_violation"] == 0.0
