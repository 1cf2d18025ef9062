"""The generalised-momentum observer on the complete model: the arm is pushed at its tool in a
simulation with the external wrench in the dynamics (forward_dynamics(external=...)), the
observer sees only the states (exact, or quantised encoders with speeds by differences) and the
applied torque, and must find the push: its link torques J^T f, the wrench itself, the moment
it starts."""
import casadi as ca
import numpy as np
import pytest

import rscasadi
from rscasadi.codegen import rk4
from rscasadi.dynamics.statics import rest_state
from rscasadi.interaction import MomentumObserver, observer_terms, tool_wrench
from rscasadi.sim.loop import Encoders

from conftest import ROOT

DT, PUSH = 1e-3, (0.1, 0.6)                      # s


def pushed(arm, frame, wrench, theta0, quantised=False, gain=300.0, seconds=0.8):
    """The arm at rest at theta0, its motors holding the rest torque, pushed by `wrench` at
    `frame` during PUSH; returns per sample t, the observer's r, the true link torques J^T f,
    the configuration."""
    n = arm.n
    fd = arm.forward_dynamics(external=[frame])
    xs, us, fs = ca.SX.sym("x", 4 * n), ca.SX.sym("u", n), ca.SX.sym("f", 6)
    z = xs
    for _ in range(4):
        z = rk4(lambda v: ca.vertcat(v[2 * n:], *fd(*ca.vertsplit(v, n), us, fs)), z, DT / 4)[0]
    advance = ca.Function("advance", [xs, us, fs], [z])
    jac = arm.frame_jacobian(frame, "local_world_aligned")
    x = rest_state(arm, theta0)
    zero = np.zeros(n)
    tau = np.array(arm.inverse_dynamics()(x[:n], x[n:2 * n], zero, zero, zero, zero)[0]).ravel()
    encoders = Encoders(arm, DT)
    obs, out = MomentumObserver(arm, gain, DT), {"t": [], "r": [], "true": [], "theta": []}
    obs.init(x)
    for k in range(int(round(seconds / DT))):
        t = (k + 1) * DT
        f = np.asarray(wrench, float) if PUSH[0] <= k * DT < PUSH[1] else np.zeros(6)
        x = np.array(advance(x, tau, f)).ravel()
        meas = encoders(x) if quantised else x
        out["r"].append(obs.step(meas, tau))
        out["true"].append(np.array(jac(x[:n])).T @ f)
        out["t"].append(t)
        out["theta"].append(meas[:n])
    return {k: np.array(v) for k, v in out.items()}


def test_the_momentum_is_the_mass_matrix_times_the_speeds(arm3):
    rng = np.random.default_rng(4)
    terms = observer_terms(arm3)
    for _ in range(3):
        th, ph, dth, dph, tau = (rng.normal(size=3) for _ in range(5))
        p = np.array(terms(th, ph, dth, dph, tau)[0]).ravel()
        assert np.allclose(p, np.array(arm3.mass_matrix()(th, ph)) @ np.r_[dth, dph], atol=1e-12)


def test_the_observer_finds_a_push_at_the_tool():
    """Exact states, K = 300 1/s: nothing before the push; during it the link torques within
    1.5 % of J^T f once 5/K has passed, the rotor rows near zero (the push is on the links), the
    force through J^T within 1.5 %; after it, back to zero."""
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    F = np.array([3.0, -4.0, -10.0, 0.0, 0.0, 0.0])
    run = pushed(arm, "tool", F, [0.0, 0.3, -0.5])
    t, r, true = run["t"], run["r"], run["true"]
    before, during = t < PUSH[0], (t > PUSH[0] + 5 / 300.0) & (t < PUSH[1])
    assert np.abs(r[before]).max() < 1e-6
    err = np.linalg.norm(r[during, :3] - true[during], axis=1) / np.linalg.norm(true[during], axis=1)
    assert err.max() < 0.015
    assert np.abs(r[during, 3:]).max() < 0.02 * np.abs(true[during]).max()
    k = np.searchsorted(t, 0.5)
    assert np.linalg.norm(tool_wrench(arm, "tool", run["theta"][k], r[k, :3]) - F[:3]) < 0.015 * np.linalg.norm(F)
    assert np.abs(r[t > PUSH[1] + 5 / 300.0, :3]).max() < 0.02 * np.abs(true[during]).max()


def test_a_push_is_flagged_within_ten_milliseconds_through_quantised_encoders():
    """Encoders quantised as the identification logs' (speeds by backward differences), K = 50
    1/s: a threshold of 1 N m on any link flags nothing before the push and the push within
    10 ms; the link torques averaged over the push's second half within 5 % of J^T f."""
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    run = pushed(arm, "tool", [3.0, -4.0, -10.0, 0.0, 0.0, 0.0], [0.0, 0.3, -0.5], quantised=True, gain=50.0)
    t, r, true = run["t"], run["r"], run["true"]
    flagged = np.abs(r[:, :3]).max(axis=1) > 1.0
    assert not flagged[t <= PUSH[0]].any()
    assert t[np.argmax(flagged)] - PUSH[0] <= 0.010
    late = (t > 0.35) & (t < PUSH[1])
    mean_r, mean_true = r[late, :3].mean(axis=0), true[late].mean(axis=0)
    assert np.linalg.norm(mean_r - mean_true) < 0.05 * np.linalg.norm(mean_true)


@pytest.mark.parametrize("wrench", [[5.0, 0.0, -8.0, 0.3, -0.2, 0.1]])
def test_the_panda_wrench_is_found_force_and_moment(wrench):
    """Seven joints: the full wrench (force and moment) at the hand from the links' r by least
    squares through J^T, within 2 % at K = 300 1/s with exact states."""
    arm = rscasadi.load(ROOT / "problems" / "panda_sea.toml")
    th0 = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.7, 0.8])
    run = pushed(arm, "panda_hand_tcp", wrench, th0, seconds=0.4)
    k = np.searchsorted(run["t"], 0.35)
    est = tool_wrench(arm, "panda_hand_tcp", run["theta"][k], run["r"][k, :7])
    assert np.linalg.norm(est - wrench) < 0.02 * np.linalg.norm(wrench), (est, wrench)


def test_the_observer_refuses_a_gain_it_cannot_sample(arm3):
    with pytest.raises(ValueError, match="K dt < 1"):
        MomentumObserver(arm3, 2000.0, DT)


@pytest.fixture(scope="module")
def observer_dir(tmp_path_factory):
    from rscasadi.cli import main
    out = tmp_path_factory.mktemp("observer") / "arm3_tool"
    assert main(["controller", "observer", str(ROOT / "problems" / "arm3_tool.toml"), "--gain", "50", "--threshold", "1",
                 "--out", str(out), "--opt=-O1"]) in (0, None)
    return out


def test_the_generated_observer_equals_the_python_one_and_survives_a_nan(observer_dir):
    """The C observer (its state in the caller's observer_t) against MomentumObserver on the
    quantised push: equal to 1e-9 N m at every sample, the collision flags (threshold 1 N m)
    equal; two observers of one library kept apart; a NaN measurement returns
    OBSERVER_BAD_MEASUREMENT (6) and keeps the state, so the next good sample is unchanged; the
    Python twin does the same without raising."""
    from rscasadi.interaction import CompiledObserver
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    rng = np.random.default_rng(2)
    x0 = rest_state(arm, [0.0, 0.3, -0.5])
    xs = x0 + np.cumsum(rng.normal(0, 3e-4, (200, 12)), axis=0)
    taus = rng.normal(0, 0.05, (200, 3))
    py, c, other = MomentumObserver(arm, 50.0, DT, 1.0), CompiledObserver(observer_dir), CompiledObserver(observer_dir)
    py.init(x0)
    assert c.init(x0) == 0 and other.init(xs[50]) == 0
    flags = []
    for k, (x, tau) in enumerate(zip(xs, taus)):
        r_py = py.step(x, tau)
        r_c, flag = c.step(x, tau)
        other.step(xs[::-1][k], tau)                   # another arm's observer in between
        assert flag == py.collision and np.max(np.abs(r_c - r_py)) < 1e-9, k
        flags.append(flag)
        if k == 100:
            bad = x.copy()
            bad[5] = np.nan
            r_bad, flag = c.step(bad, tau)
            assert flag == 6 and np.array_equal(r_bad, r_c)
            assert np.array_equal(py.step(bad, tau), r_py) and py.code == 6
    assert 0 < sum(flags) < len(flags)                 # both answers were given


def test_a_bad_observer_gain_is_refused_by_name(tmp_path, capsys):
    from rscasadi.cli import main
    assert main(["controller", "observer", str(ROOT / "problems" / "arm3_tool.toml"), "--gain", "2000",
                 "--out", str(tmp_path / "obs")]) == 2
    assert "--gain" in capsys.readouterr().err and not (tmp_path / "obs").exists()


# ----------------------------------------------------------------------------- contacts in simulation

def _lossless_arm():
    """The tool arm with no SEA damping and no gear losses: its energy is conserved."""
    from rscasadi.model.parameters import with_values
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    zero = {f"{jt.name}.{k}": 0.0 for jt in arm.model.joints for k in ("sea.d", "gear_loss.b", "gear_loss.c")}
    return rscasadi.Arm(with_values(arm.model, zero))


def _fall(arm, contact, seconds=0.6):
    """The arm released at rest, motors off, its tool falling onto `contact`: per sample the
    energy (the arm's and the contact spring's, k delta^2 / 2) and the depth."""
    from rscasadi.sim.contact import World, plant_with_contacts
    th0 = np.array([0.0, 0.3, -0.5])
    plant = plant_with_contacts(arm, World(contacts=(contact,)), DT, 8)
    energy, place = arm.energy(), arm.frame_placement("tool")
    surface = contact.point[2] if contact.point is not None else contact.center[2] + contact.size[2] / 2
    x, out = rest_state(arm, th0), {"energy": [], "depth": []}
    for k in range(int(round(seconds / DT))):
        x = np.array(plant(x, np.zeros(3), k * DT)[0]).ravel()
        depth = max(0.0, surface - float(place(x[:3])[1][2]))
        out["energy"].append(float(energy(x[:3], x[3:6], x[6:9], x[9:12])) + 0.5 * contact.k * depth ** 2)
        out["depth"].append(depth)
    return {k: np.array(v) for k, v in out.items()}


@pytest.mark.parametrize("shape", ["plane", "box"])
def test_an_elastic_contact_conserves_energy(shape):
    """A lossless arm falls 1 cm onto a frictionless, undamped plane or box (k = 2e4 N/m) and
    bounces: the contact's wrench enters the complete model so that the arm's energy plus the
    contact spring's is conserved (to the RK4 error), through several impacts."""
    from rscasadi.sim.contact import Contact
    arm = _lossless_arm()
    p0 = np.array(arm.frame_placement("tool")(np.array([0.0, 0.3, -0.5]))[1]).ravel()
    contact = (Contact("tool", k=2e4, point=p0 - [0, 0, 0.01], normal=[0, 0, 1]) if shape == "plane" else
               Contact("tool", k=2e4, center=p0 - [0, 0, 0.51], size=[3.0, 3.0, 1.0]))
    run = _fall(arm, contact)
    assert run["depth"].max() > 2e-3                                      # it did hit
    assert np.ptp(run["energy"]) < 1e-5                                   # J, of ~0.05 J exchanged


def test_damping_and_friction_only_take_energy():
    from rscasadi.sim.contact import Contact
    arm = _lossless_arm()
    p0 = np.array(arm.frame_placement("tool")(np.array([0.0, 0.3, -0.5]))[1]).ravel()
    run = _fall(arm, Contact("tool", k=2e4, c=50.0, mu=0.5, point=p0 - [0, 0, 0.01], normal=[0, 0, 1]))
    assert run["depth"].max() > 1e-3
    assert np.all(np.diff(run["energy"]) < 1e-7) and run["energy"][-1] < run["energy"][0] - 1e-3


def test_a_push_acts_only_in_its_window():
    """A scripted push: the motion equals the unpushed one before t1, the observer sees its
    J^T f inside the window (the push is the only external force)."""
    from rscasadi.sim.contact import Push, World, plant_with_contacts
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    x0 = rest_state(arm, [0.0, 0.3, -0.5])
    zero = np.zeros(3)
    tau = np.array(arm.inverse_dynamics()(x0[:3], x0[3:6], zero, zero, zero, zero)[0]).ravel()
    pushed_plant = plant_with_contacts(arm, World(pushes=(Push("tool", [0, 0, -8.0, 0, 0, 0], 0.05, 0.3),)), DT, 4)
    free_plant = plant_with_contacts(arm, World(pushes=(Push("tool", [0, 0, 0, 0, 0, 0], 0.05, 0.3),)), DT, 4)
    obs = MomentumObserver(arm, 300.0, DT)
    obs.init(x0)
    x, y = x0.copy(), x0.copy()
    for k in range(250):
        x = np.array(pushed_plant(x, tau, k * DT)[0]).ravel()
        y = np.array(free_plant(y, tau, k * DT)[0]).ravel()
        r = obs.step(x, tau)
        if (k + 1) * DT < 0.05 - 1e-9:                  # (the step ending at t1 feels it in its last stage)
            assert np.array_equal(x, y)
    J = np.array(arm.frame_jacobian("tool", "local_world_aligned")(x[:3]))
    assert np.linalg.norm(r[:3] - J[:3].T @ [0, 0, -8.0]) < 0.02 * np.linalg.norm(J[:3].T @ [0, 0, -8.0])


@pytest.mark.parametrize("kwargs,words", [
    ({"k": 1e4}, "a plane .point, normal. or a box"),
    ({"k": 1e4, "point": [0, 0, 0], "normal": [0, 0, 0]}, "normal, not all zero"),
    ({"k": -1.0, "point": [0, 0, 0], "normal": [0, 0, 1]}, "k > 0"),
    ({"k": 1e4, "center": [0, 0, 0], "size": [1, 0, 1]}, "size of three positive"),
])
def test_a_bad_contact_is_refused(kwargs, words):
    from rscasadi.sim.contact import Contact
    with pytest.raises(ValueError, match=words):
        Contact("tool", **kwargs)


def test_the_observer_c_example_flags_the_push_and_is_valgrind_clean(observer_dir, tmp_path):
    """examples/observer.c on the generated model (with the push in its dynamics) and observer:
    -Werror, the push flagged within 10 ms and estimated within 5 % through quantised encoders,
    no error or leak under valgrind, bad arguments refused."""
    import re
    import shutil
    import subprocess
    from conftest import build_example
    from rscasadi.cli import main
    arm_dir = tmp_path / "arm3_tool"
    assert main(["codegen", str(ROOT / "problems" / "arm3_tool.toml"), "--frames", "tool", "--external", "tool",
                 "--out", str(arm_dir), "--opt=-O1"]) in (0, None)
    exe = build_example("observer", tmp_path / "observer", {arm_dir: "rscasadi_arm", observer_dir: "rscasadi_observer"})
    run = subprocess.run([str(exe)], capture_output=True, text=True, check=True)
    flagged, error = (float(v) for v in re.search(r"flagged at ([0-9.]+) s .* within ([0-9.]+) %", run.stdout).groups())
    assert 0.2 < flagged <= 0.21 and error < 5.0
    if shutil.which("valgrind") is not None:
        check = subprocess.run(["valgrind", "--error-exitcode=9", "--leak-check=full", str(exe)], capture_output=True,
                               text=True)
        assert check.returncode == 0, check.stderr
    bad = subprocess.run([str(exe), "1", "two", "3"], capture_output=True, text=True)
    assert bad.returncode == 2 and "argument 2" in bad.stderr and bad.stdout == ""


@pytest.fixture(scope="module")
def panda_tool(tmp_path_factory):
    """A 7-joint arm for the C examples: the Panda with a `tool` frame at its hand's TCP, its
    library with the tool's kinematics and the push in its dynamics."""
    from rscasadi.cli import main
    d = tmp_path_factory.mktemp("panda_tool")
    text = (ROOT / "problems" / "panda_sea.toml").read_text()
    text = text.replace('urdf = "urdf/panda.urdf"', f'urdf = "{ROOT / "problems" / "urdf" / "panda.urdf"}"')
    (d / "panda.toml").write_text(text + '\n[frames]\ntool = { parent = "panda_hand_tcp" }\n')
    assert main(["codegen", str(d / "panda.toml"), "--frames", "tool", "--external", "tool",
                 "--out", str(d / "arm"), "--opt=-O1"]) in (0, None)
    return d


def test_the_observer_c_example_takes_a_7_joint_arm(panda_tool, tmp_path):
    """The same source built on a 7-joint arm: n, springs and gear ratios from the generated
    header. With ideal encoders the push is flagged within 15 ms and estimated within 5 %; with
    the default ones (their speed noise times the Panda's inertias) it is flagged too."""
    import re
    import subprocess
    from conftest import build_example
    from rscasadi.cli import main
    obs_dir = tmp_path / "observer"
    assert main(["controller", "observer", str(panda_tool / "panda.toml"), "--gain", "50", "--threshold", "1",
                 "--out", str(obs_dir), "--opt=-O1"]) in (0, None)
    libs = {panda_tool / "arm": "rscasadi_arm", obs_dir: "rscasadi_observer"}
    for defines, late, within in (((), 0.21, None), (("LINK_BITS=40", "MOTOR_BITS=40"), 0.215, 5.0)):
        exe = build_example("observer", tmp_path / f"observer{len(defines)}", libs, defines)
        run = subprocess.run([str(exe)], capture_output=True, text=True, check=True)
        rows = [line.split() for line in run.stdout.splitlines() if not line.startswith("#")]
        assert len(rows) == 80 and all(len(r) == 1 + 2 * 7 + 1 for r in rows)
        flagged, error = (float(v) for v in re.search(r"flagged at ([0-9.]+) s .* within ([0-9.]+) %", run.stdout).groups())
        assert 0.2 < flagged <= late, run.stdout[-200:]
        assert within is None or error < within, error


def test_the_impedance_c_example_takes_a_7_joint_arm(panda_tool, tmp_path):
    """The same source on the Panda: pushed by 15 N at K = 1000 N/m its tool moves F / K within
    2 %, 7 torques a row."""
    import re
    import subprocess
    from conftest import build_example
    from rscasadi.cli import main
    imp_dir = tmp_path / "impedance"
    assert main(["controller", "impedance", str(panda_tool / "panda.toml"), "--frame", "tool",
                 "--out", str(imp_dir), "--opt=-O1"]) in (0, None)
    exe = build_example("impedance", tmp_path / "impedance7", {panda_tool / "arm": "rscasadi_arm",
                                                              imp_dir: "rscasadi_impedance"})
    run = subprocess.run([str(exe)], capture_output=True, text=True, check=True)
    assert all(len(line.split()) == 4 + 7 for line in run.stdout.splitlines() if not line.startswith("#"))
    moved, expected = (float(v) for v in re.search(r"= (-?[0-9.]+) m along z \(F / K = (-?[0-9.]+) m\)",
                                                   run.stdout).groups())
    assert abs(moved / expected - 1) < 0.02


# ----------------------------------------------------------------------------- impedance control

ARM3_THETA = [0.0, 0.3, -0.5]
PANDA_THETA = [0.0, -0.3, 0.0, -2.0, 0.0, 1.7, 0.8]


@pytest.mark.parametrize("stiffness,design", [(300.0, "motor"), (1000.0, "motor"), (2000.0, "link")])
def test_the_realised_stiffness_is_the_commanded_one(stiffness, design):
    """(a) A 15 N push at the tool, quantised encoders, 1 kHz: the steady displacement is F / K
    within 5 % (the springs in between do not soften it), no deflection limit broken.  2000 N/m
    is stiffer than the springs at the tool here (1855 N/m along z): the link design."""
    from rscasadi.interaction.study import push
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    run = push(arm, "tool", ARM3_THETA, stiffness, seconds=2.0, design=design)
    assert abs(run["error_percent"]) < 5.0 and run["psi_of_limit"] < 1.0, run


def test_the_passive_design_refuses_a_stiffness_beyond_the_springs():
    """Along z at ARM3_THETA the springs alone give 1855 N/m at the tool (J C_s J^T): 1800 is
    accepted, 1900 refused by name."""
    from rscasadi.interaction import ImpedanceController
    from rscasadi.interaction.study import pose_of
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    ctrl, x = ImpedanceController(arm, "tool"), rest_state(arm, ARM3_THETA)
    J = np.array(arm.frame_jacobian("tool", "local_world_aligned")(ARM3_THETA))[:3]
    limit = 1 / np.linalg.eigvalsh(J @ np.diag(1 / arm.model.column("k1")) @ J.T).max()
    assert 1850 < limit < 1860
    assert ctrl.init(x) == 0
    ctrl.step(x, pose_of(arm, "tool", ARM3_THETA), [0.97 * limit] * 3 + [0] * 3, [0.7] * 6)
    assert ctrl.code == 0
    ctrl.step(x, pose_of(arm, "tool", ARM3_THETA), [1.03 * limit] * 3 + [0] * 3, [0.7] * 6)
    assert ctrl.code == 4                                          # TOO_STIFF


def test_the_panda_realises_the_commanded_stiffness_and_settles():
    """(a) on seven joints, the passive design with rotational stiffness 50 N m/rad and the null
    space damped: 15 N at K = 1000 N/m moves the hand F / K within 5 %, and it is at rest."""
    from rscasadi.interaction.study import push
    arm = rscasadi.load(ROOT / "problems" / "panda_sea.toml")
    run = push(arm, "panda_hand_tcp", PANDA_THETA, 1000.0, seconds=1.6)
    t, along = run["trace"]
    assert abs(run["error_percent"]) < 5.0 and run["psi_of_limit"] < 1.0, run
    assert np.ptp(along[t > 1.4]) < 0.01 * run["expected"]


def test_the_motor_position_design_is_passive():
    """Continuous time (the law inside the RK4 step, no limits, no quantisation), the arm's SEA
    and gear damping on: from a disturbed state H = E(x) - V_g(q_bar) + 1/2 e^T K e - V_s(phi -
    q_bar) never rises (E from Arm.energy, V_g = E at rest with phi = theta), and falls."""
    from rscasadi.interaction.impedance import impedance_law
    from rscasadi.interaction.study import pose_of
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    law, energy, place = impedance_law(arm, "tool", newton_steps=4), arm.energy(), arm.frame_placement("tool")
    ref, K = pose_of(arm, "tool", ARM3_THETA), np.array([600.0, 600.0, 600.0, 0, 0, 0])
    fd, k1 = arm.forward_dynamics(), arm.model.column("k1")
    xs = ca.SX.sym("x", 12)
    tau = law(xs[:3], xs[3:6], xs[6:9], xs[9:], ref, K, [0.7] * 6)[0]
    f = ca.Function("f", [xs], [ca.vertcat(xs[6:], *fd(xs[:3], xs[3:6], xs[6:9], xs[9:], tau))])
    step = ca.Function("step", [xs], [rk4(lambda v: f(v), xs, 2e-4)[0]])

    def H(x):
        q_bar = np.array(law(x[:3], x[3:6], x[6:9], x[9:], ref, K, [0.7] * 6)[2]).ravel()
        e = np.array(place(q_bar)[1]).ravel() - ref[:3]
        psi = x[3:6] - q_bar
        return (float(energy(x[:3], x[3:6], x[6:9], x[9:])) - float(energy(q_bar, q_bar, np.zeros(3), np.zeros(3)))
                + 0.5 * e @ (K[:3] * e) - 0.5 * np.sum(k1 * psi ** 2))
    x = rest_state(arm, ARM3_THETA) + np.r_[0.05, -0.04, 0.03, 0.0, 0.02, 0.0, 0.5, -0.3, 0.2, 0.0, 0.0, 0.0]
    values = []
    for _ in range(2500):
        values.append(H(x))
        x = np.array(step(x)).ravel()
    values = np.array(values)
    assert np.diff(values).max() < 1e-7 * values[0] and values[-1] < 0.05 * values[0], (values[0], values[-1])


def test_the_joint_space_impedance_holds_each_joint_at_its_stiffness():
    """The joint-space variant: a 15 N push at the tool moves the joints by K_q^-1 J^T f within
    5 % (K_q 300, 200, 100 N m/rad, softer than the springs)."""
    from rscasadi.interaction import ImpedanceController
    from rscasadi.sim.loop import Encoders
    from rscasadi.sim.contact import Push, World, plant_with_contacts
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    Kq, F = np.array([300.0, 200.0, 100.0]), np.array([0.0, -10.0, -15.0, 0, 0, 0])
    ctrl = ImpedanceController(arm, None)
    plant = plant_with_contacts(arm, World(pushes=(Push("tool", F, 0.2, 9.0),)), DT, 8)
    x, enc = rest_state(arm, ARM3_THETA), Encoders(arm, DT)
    assert ctrl.init(enc(x)) == 0
    for k in range(1500):
        x = np.array(plant(x, ctrl.step(enc(x), ARM3_THETA, Kq, [0.7] * 3), k * DT)[0]).ravel()
    J = np.array(arm.frame_jacobian("tool", "local_world_aligned")(x[:3]))
    expected = (J.T @ F) / Kq
    assert np.linalg.norm(x[:3] - ARM3_THETA - expected) < 0.05 * np.linalg.norm(expected), (x[:3] - ARM3_THETA, expected)


def test_pressing_into_a_stiff_wall_settles_at_k_times_the_commanded_depth():
    """(b) The target moved in 0.5 s to 5 mm inside a wall of 1e5 N/m under the tool (K = 1000
    N/m): the tool touches, stays in contact, and the force settles at K d k_w / (K + k_w)
    (4.95 N) within 5 %, without chattering."""
    from rscasadi.interaction.study import wall
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    run = wall(arm, "tool", ARM3_THETA, 1000.0, 1e5, seconds=1.5)
    assert abs(run["error_percent"]) < 5.0 and run["lost_contact_ms"] == 0 and run["chatter_percent"] < 5.0, run


@pytest.mark.parametrize("space", ["cartesian", "joint"])
def test_the_generated_impedance_controller_equals_the_python_one(tmp_path, space):
    """rscasadi controller impedance (--frame tool, or --joint-space): the C (its memory the
    caller's impedance_t) equals ImpedanceController to 1e-12 at random states and references,
    within the torque limits; a stiffness beyond the springs returns IMPEDANCE_TOO_STIFF (4) with
    the holding torque at the measured state (the complete model's inverse dynamics at rest there),
    and so does the Python twin."""
    from rscasadi.cli import main
    from rscasadi.interaction import CompiledImpedance, ImpedanceController
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    where = ["--frame", "tool"] if space == "cartesian" else ["--joint-space"]
    assert main(["controller", "impedance", str(ROOT / "problems" / "arm3_tool.toml"), *where,
                 "--out", str(tmp_path / "imp"), "--opt=-O1"]) in (0, None)
    c, py = CompiledImpedance(tmp_path / "imp"), ImpedanceController(arm, "tool" if space == "cartesian" else None)
    rng = np.random.default_rng(9)
    x0 = rest_state(arm, ARM3_THETA)
    assert c.init(x0) == 0 and py.init(x0) == 0
    nk = 6 if space == "cartesian" else 3
    for _ in range(20):
        x = x0 + rng.normal(0, [0.05] * 6 + [0.5] * 6)
        ref = np.r_[rng.uniform(0.3, 0.6, 3), np.eye(3).ravel()] if space == "cartesian" else x0[:3] + rng.normal(0, 0.1, 3)
        K, zeta = rng.uniform(100, 500, nk), rng.uniform(0.3, 1.0, nk)
        tau_c, flag = c.step(x, ref, K, zeta)
        assert flag == 0 and np.max(np.abs(tau_c - py.step(x, ref, K, zeta))) < 1e-12
    too_stiff = [5000.0] * nk
    tau_c, flag = c.step(x0, ref, too_stiff, zeta)
    z = np.zeros(3)
    hold = np.array(arm.inverse_dynamics()(x0[:3], x0[3:6], z, z, z, z)[0]).ravel()
    assert flag == 4 and np.max(np.abs(tau_c - hold)) < 1e-12 and c.seconds() > 0
    assert np.max(np.abs(py.step(x0, ref, too_stiff, zeta) - hold)) < 1e-12 and py.code == 4


def test_an_impedance_controller_for_an_unknown_frame_is_refused(tmp_path, capsys):
    from rscasadi.cli import main
    assert main(["controller", "impedance", str(ROOT / "problems" / "arm3_tool.toml"), "--frame", "nowhere",
                 "--out", str(tmp_path / "imp")]) == 2
    assert "--frame" in capsys.readouterr().err and not (tmp_path / "imp").exists()


def test_the_impedance_c_example_realises_the_stiffness_and_is_valgrind_clean(tmp_path):
    """examples/impedance.c on the generated model and controller: -Werror; pushed by 15 N at
    K = 1000 N/m the tool moves F / K within 1 %; valgrind clean; bad arguments refused."""
    import re
    import shutil
    import subprocess
    from conftest import build_example
    from rscasadi.cli import main
    arm_dir, imp_dir = tmp_path / "arm3_tool", tmp_path / "impedance"
    assert main(["codegen", str(ROOT / "problems" / "arm3_tool.toml"), "--frames", "tool", "--external", "tool",
                 "--out", str(arm_dir), "--opt=-O1"]) in (0, None)
    assert main(["controller", "impedance", str(ROOT / "problems" / "arm3_tool.toml"), "--frame", "tool",
                 "--out", str(imp_dir), "--opt=-O1"]) in (0, None)
    exe = build_example("impedance", tmp_path / "impedance_example",
                        {arm_dir: "rscasadi_arm", imp_dir: "rscasadi_impedance"})
    run = subprocess.run([str(exe)], capture_output=True, text=True, check=True)
    moved, expected = (float(v) for v in re.search(r"= (-?[0-9.]+) m along z \(F / K = (-?[0-9.]+) m\)",
                                                   run.stdout).groups())
    assert abs(moved / expected - 1) < 0.01
    if shutil.which("valgrind") is not None:
        check = subprocess.run(["valgrind", "--error-exitcode=9", "--leak-check=full", str(exe), "1000", "-15", "0.5"],
                               capture_output=True, text=True)
        assert check.returncode == 0, check.stderr
    bad = subprocess.run([str(exe), "-5"], capture_output=True, text=True)
    assert bad.returncode == 2 and "argument 1" in bad.stderr and bad.stdout == ""


@pytest.mark.parametrize("model,frame,trajectory,gain,threshold", [
    ("arm3_tool", "tool", "trajectory_arm3.toml", 50.0, 1.0),
    ("panda_sea", "panda_hand_tcp", "trajectory_panda.toml", 100.0, 5.0)])
def test_a_collision_during_a_motion_is_flagged_and_measured(model, frame, trajectory, gain, threshold):
    """(c) A feedforward motion + motor PD (quantised encoders) into a wall (1e4 N/m) across the
    frame's path that nobody told the controller of: the observer (fed the torque of the sample
    before) stays below the threshold during the free motion, flags the collision within 10 ms,
    and its link torques average within 5 % of J^T f from the contact."""
    from rscasadi.interaction.study import collision_feedforward
    from rscasadi.sim.trajectory import load_trajectory
    arm = rscasadi.load(ROOT / "problems" / f"{model}.toml")
    r = collision_feedforward(arm, frame, load_trajectory(ROOT / "problems" / trajectory), gain=gain,
                              threshold=threshold, seconds=0.8)
    assert 0.3 < r["contact_s"] < 0.5 and r["free_max_Nm"] < threshold, r
    assert 0 <= r["delay_ms"] <= 10 and r["error_percent"] < 5, r



def test_the_interaction_study_writes_its_evidence(tmp_path):
    """rscasadi controller impedance --study --short on the tool arm: (a) F / K within 5 % (the
    passive design at 300 N/m, the link one beyond the springs at 2000), (b) the wall's force
    within 5 % without losing contact, (c) a collision during an impedance and a feedforward motion
    flagged within 10 ms, no flag before it,
    the torques within 5 %, (d) the reduced model's design side by side, the C's time per step;
    study.md, study.json and study.png written; a missing --theta refused by name."""
    import json
    from rscasadi.cli import main
    model = str(ROOT / "problems" / "arm3_tool.toml")
    assert main(["controller", "impedance", model, "--frame", "tool", "--study", "--short", "--opt=-O1",
                 "--out", str(tmp_path / "nothing")]) == 2 and not (tmp_path / "nothing").exists()
    assert main(["controller", "impedance", model, "--frame", "tool", "--study", "--short", "--opt=-O1",
                 "--theta", "0,0.3,-0.5", "--trajectory", str(ROOT / "problems" / "trajectory_arm3.toml"),
                 "--out", str(tmp_path / "study")]) == 0
    r = json.loads((tmp_path / "study" / "study.json").read_text())
    assert [p["design"] for p in r["push"]] == ["motor", "link"]
    assert all(abs(p["error_percent"]) < 5 and p["psi_of_limit"] < 1 for p in r["push"])
    assert all(abs(w["error_percent"]) < 5 and w["lost_contact_ms"] == 0 for w in r["wall"])
    assert set(r["collision"]) == {"impedance motion", "feedforward motion"}
    for c in r["collision"].values():
        assert 0 <= c["delay_ms"] <= 10 and c["free_max_Nm"] < c["threshold_Nm"] and c["error_percent"] < 5
    assert set(r["reduced"]) == {"complete", "reduced", "classical_series_stiffness_percent"}
    assert r["reduced"]["classical_series_stiffness_percent"] < -20             # what the compensation buys
    assert r["timing"]["impedance_step"]["median_us"] > 0
    assert {"study.md", "study.json", "study.png"} <= {p.name for p in (tmp_path / "study").iterdir()}


def test_a_flag_before_the_contact_is_a_false_alarm_not_a_negative_delay():
    """A flag at 0.2 s and again from 0.55 s with the contact at 0.5 s: flagged 50 ms after the
    contact, a false alarm at 0.2 s (was reported as 'flagged after -300 ms')."""
    from rscasadi.interaction.study import _first_flags
    t = np.arange(0, 1, 0.05)
    flagged = (np.abs(t - 0.2) < 1e-9) | (t >= 0.55 - 1e-9)
    flag, false_alarm = _first_flags(t, flagged, 0.5)
    assert flag == pytest.approx(0.55) and false_alarm == pytest.approx(0.2)
    assert np.isnan(_first_flags(t, t < 0.1, 0.5)[0])
