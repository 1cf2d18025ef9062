"""Simulation, the feedforward pipeline, the paper's cascade and the `paper` command."""
import json

import numpy as np
import pytest

import rscasadi
from rscasadi.model.modelfile import ModelFileError
from rscasadi.studies.paper import run
from rscasadi.sim.simulation import cascade_simulate, feedforward, simulate
from rscasadi.sim.trajectory import load_trajectory

from conftest import ROOT

TRAJECTORY = ROOT / "problems" / "trajectory_arm3.toml"


@pytest.fixture(scope="module")
def traj():
    return load_trajectory(TRAJECTORY)


def test_trajectory_starts_at_rest_and_moves(traj):
    q, dq, ddq, d3, _ = traj(np.linspace(0, traj.period, 401))
    assert np.allclose(dq[:, 0], 0) and np.allclose(ddq[:, 0], 0) and np.allclose(d3[:, 0], 0)
    assert np.all(np.ptp(q, axis=1) >= 0.5) and traj.period <= 2.0
    assert np.allclose(q[:, -1], q[:, 0]), "one full period returns to the start"


def test_rk4_and_cvodes_agree(arm3, traj):
    t = np.linspace(0, 0.2, 201)
    ff = feedforward(arm3, traj, t)
    a = simulate(arm3, ff["x0"], t, ff["tau"], method="cvodes", tol=1e-11)
    b = simulate(arm3, ff["x0"], t, ff["tau"], method="rk4", substeps=4)
    assert np.max(np.abs(a["x"] - b["x"])) < 1e-8
    assert np.allclose(a["psi"], a["phi"] - a["theta"]) and a["energy"].shape == (201,)


def test_feedforward_tracks_and_separates_the_models(arm3, traj):
    """The complete model's feedforward reproduces the expected motion on the complete model;
    the DLR feedforward does measurably worse; the start is a static equilibrium."""
    t = np.linspace(0, 0.4, 401)
    err = {}
    for reduced in (False, True):
        ff = feedforward(arm3, traj, t, reduced=reduced)
        sim = simulate(arm3, ff["x0"], t, ff["tau"], tol=1e-11)
        err[reduced] = np.max(np.abs(sim["theta"] - ff["theta_d"]))
        if not reduced:
            x0 = np.split(ff["x0"], 4)
            acc = np.concatenate([np.array(v).ravel() for v in arm3.forward_dynamics()(*x0, ff["tau"][:, 0])])
            assert np.max(np.abs(acc)) < 1e-6, "at rest in a spring-consistent static equilibrium"
    assert err[False] < 2e-6
    assert err[True] > 20 * err[False]


def test_feedforward_converges_as_the_step_shrinks(arm3, traj):
    errs = []
    for h in (4e-3, 2e-3, 1e-3):
        t = np.arange(0, 0.4 + h / 2, h)
        ff = feedforward(arm3, traj, t)
        errs.append(np.max(np.abs(simulate(arm3, ff["x0"], t, ff["tau"], tol=1e-11)["theta"] - ff["theta_d"])))
    assert errs[0] > errs[1] > errs[2]


def test_cascade_converges_to_the_exact_simulation(arm3, traj):
    t = np.linspace(0, 0.12, 31)
    ff = feedforward(arm3, traj, t)
    exact = simulate(arm3, ff["x0"], t, ff["tau"], tol=1e-12)
    errs = [np.max(np.abs(cascade_simulate(arm3, ff["x0"], t, ff["tau"], h)["x"] - exact["x"]))
            for h in (2e-3, 1e-3, 5e-4)]
    assert errs[0] / errs[1] > 3 and errs[1] / errs[2] > 3
    assert errs[2] < 1e-6
    with pytest.raises(ValueError, match="whole number of steps"):
        cascade_simulate(arm3, ff["x0"], t, ff["tau"], 3e-3)


def test_paper_command_writes_replayable_results(tmp_path, arm3):
    out = tmp_path / "paper"
    results = run(TRAJECTORY, out, duration=0.25, sweeps=False, log=lambda m: None)
    tracking = json.loads((out / "tracking.json").read_text())
    assert tracking["model"].endswith("arm3.toml")
    assert set(tracking["methods"]) == {"rotor_separated", "dlr"}
    assert all(len(tracking["methods"][m][k]) == 3 for m in tracking["methods"] for k in ("max_error", "rms_error"))
    ff = json.loads((out / "feedforward.json").read_text())
    assert ff["tau_interpolation"] == "linear" and set(ff["initial_state"]) == {"theta", "phi", "dtheta", "dphi"}
    assert len(ff["t"]) == 251 and len(ff["theta_d"]) == 3 and len(ff["tau"]["dlr"][0]) == 251
    for stem in ["fig05_expected_trajectories"] + [f"fig{k:02d}_joint{(k - 6) % 3 + 1}_{'trajectory' if k < 9 else 'error'}"
                                                   for k in range(6, 12)]:
        assert (out / f"{stem}.png").exists() and (out / f"{stem}.pdf").exists(), stem
    # anyone can replay the torques on their own plant and check the table
    x0 = np.concatenate([ff["initial_state"][k] for k in ("theta", "phi", "dtheta", "dphi")])
    for m in ("rotor_separated", "dlr"):
        sim = simulate(arm3, x0, np.array(ff["t"]), np.array(ff["tau"][m]), tol=1e-10)
        e = np.max(np.abs(sim["theta"] - np.array(ff["theta_d"])), axis=1)
        assert np.allclose(e, tracking["methods"][m]["max_error"], rtol=1e-3, atol=1e-9)
    assert results["dlr"]["max_error"][1] > 10 * results["rotor_separated"]["max_error"][1]


@pytest.mark.parametrize("text,field", [
    ('model = "arm3.toml"\nperiod = 2.0\nduration = 2.0\nstart = [0.0]\n', "amplitude"),
    ('model = "arm3.toml"\nperiod = -2.0\nduration = 2.0\nstart = [0.0]\namplitude = [1.0]\n', "period"),
    ('model = "arm3.toml"\nperiod = 2.0\nduration = 2.0\nstart = [0.0]\namplitude = [1.0, 2.0]\n', "amplitude"),
    ('model = "arm3.toml"\nperiod = 2.0\nduration = 2.0\nstart = [0.0]\namplitude = [1.0]\nspeed = 1\n', "speed"),
])
def test_bad_trajectory_file_names_the_field(tmp_path, text, field):
    f = tmp_path / "traj.toml"
    f.write_text(text)
    with pytest.raises(ModelFileError, match=rf"traj\.toml: field '{field}'"):
        load_trajectory(f)


def test_failed_paper_run_leaves_nothing(tmp_path):
    f = tmp_path / "traj.toml"
    f.write_text('model = "missing.toml"\nperiod = 2.0\nduration = 2.0\nstart = [0.0]\namplitude = [1.0]\n')
    with pytest.raises(ModelFileError):
        run(f, tmp_path / "out", duration=0.1, sweeps=False, log=lambda m: None)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["traj.toml"]


def test_tilted_variant_file_is_the_sweeps_point(arm3):
    from rscasadi.studies.paper import _variant
    tilted = rscasadi.load(ROOT / "problems" / "arm3_tilted.toml")
    q = np.array([0.2, -0.4, 0.9])
    M_file = np.array(tilted.mass_matrix()(q, q))
    M_sweep = np.array(_variant(arm3, "t", tilt=0.4).mass_matrix()(q, q))
    assert np.allclose(M_file, M_sweep, rtol=0, atol=1e-15)
    assert abs(M_file[0, 5]) > 1e-5 and np.isclose(M_file[1, 5], -1.03e-3 * np.cos(0.4))


def test_the_compiled_replay_equals_the_interpreted_one_on_seven_joints(monkeypatch):
    """From COMPILED_FROM_JOINTS joints on, CVODES integrates the arm family's compiled dynamics
    with the model's numbers as an input: the same motion as CasADi's virtual machine on the
    constant arm's SX (a different build of the equations), a payload included, and one library
    for the arm with a payload of either mass."""
    from rscasadi.dynamics.arm import Arm
    from rscasadi.dynamics.statics import holding_torque, rest_state
    from rscasadi.model.modelfile import read
    from rscasadi.sim import simulation
    from rscasadi.task.objects import holding_payload
    model = read(ROOT / "problems" / "panda_sea.toml")
    part = {"frame": "panda_hand_tcp", "com": [0.0, 0.0, 0.04], "inertia": [3e-3, 3e-3, 2e-3, 0.0, 0.0, 0.0]}
    monkeypatch.setattr(simulation, "_ODES", {})
    ends = []
    for m in (holding_payload(model, {**part, "mass": 1.0}), holding_payload(model, {**part, "mass": 2.0})):
        arm = Arm(m)
        x0 = rest_state(arm, np.array([0.3, -0.5, 0.2, -2.0, 0.1, 1.6, 0.7]))
        tau = np.array(holding_torque(arm)(x0[:7], x0[7:14])).ravel() + np.linspace(-2.0, 2.0, 7)
        p = np.concatenate([tau, [0.05]])
        compiled = np.array(simulation.held_interval(arm, 1e-11)(x0, p)).ravel()
        monkeypatch.setattr(simulation, "COMPILED_FROM_JOINTS", 100)
        interpreted = np.array(simulation.held_interval(arm, 1e-11)(x0, p)).ravel()
        monkeypatch.setattr(simulation, "COMPILED_FROM_JOINTS", 6)
        assert np.max(np.abs(compiled - interpreted)) < 1e-8 * max(1.0, np.max(np.abs(interpreted - x0)))
        ends.append(compiled)
    assert np.max(np.abs(ends[0] - ends[1])) > 1e-3, "the payload's numbers reach the compiled dynamics"
    assert len({rhs.name() for rhs, _ in simulation._ODES.values()}) == 1, "either payload: one library"
