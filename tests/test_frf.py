"""Frequency responses (rscasadi frf): the model's linearised response against a second
derivation (the two-mass joint written by hand), its anti-resonance and resonance against the
textbook formulas, and the H1 estimate from a simulated log against the model's."""
import json

import numpy as np
import pytest

import rscasadi
from conftest import ROOT, to_toml
from rscasadi.cli import main
from rscasadi.identification.frf import log_frf, model_frf, peaks, rigid
from rscasadi.identification.logs import Log, LogError, write_log
from rscasadi.model.modelfile import document


def one_joint(tmp_path, d=0.0, b=0.0):
    """arm3's first joint alone (a vertical axis: no gravity torque), its link made heavy."""
    doc = document(rscasadi.load(ROOT / "problems" / "arm3.toml").model)
    jt = doc["joints"][0]
    jt["link"]["inertia"] = [0.3, 0.3, 0.3, 0.0, 0.0, 0.0]
    jt["sea"]["d"], jt["gear_loss"]["b"], jt["gear_loss"]["c"] = d, b, 0.0
    doc["joints"] = [jt]
    path = tmp_path / f"one_{d}_{b}.toml"
    path.write_text(to_toml(doc))
    return rscasadi.load(path)


def by_hand(arm, f):
    """tau -> phi of the two-mass joint: [J_M s^2 + K + b s, -K; -K, J_L s^2 + K] [phi; theta]
    = [-mu tau; 0], K = k1 + d s, J_M = Izz(S) + mu^2 Izz(F), J_L the link's Izz about the axis."""
    jt = arm.model.joints[0]
    J_L = jt.link.inertia[2, 2] + jt.link.mass * (jt.link.com[0] ** 2 + jt.link.com[1] ** 2)
    J_M = jt.slow_rotor.inertia[2, 2] + jt.gear_ratio ** 2 * jt.fast_rotor.inertia[2, 2]
    s = 2j * np.pi * np.asarray(f)
    K = jt.k1 + jt.d * s
    return -jt.gear_ratio * (J_L * s ** 2 + K) / ((J_M * s ** 2 + K + jt.b * s) * (J_L * s ** 2 + K) - K ** 2), J_L, J_M


def test_the_model_response_is_the_two_mass_joint(tmp_path):
    """Damped: equal to the hand-written two-mass response to 1e-10; undamped: its anti-resonance
    at sqrt(k1 / J_L) and resonance at sqrt(k1 (1/J_L + 1/J_M)) within the grid's 0.2 %; the rigid
    joint has neither."""
    f = np.geomspace(1.0, 100.0, 4000)
    damped = one_joint(tmp_path, d=1.5, b=2.0)
    G, _, _ = by_hand(damped, f)
    assert np.max(np.abs(model_frf(damped, [0.0], 0, f) - G) / np.abs(G)) < 1e-10
    arm = one_joint(tmp_path)
    _, J_L, J_M = by_hand(arm, f)
    k1 = arm.model.joints[0].k1
    found = peaks(f, model_frf(arm, [0.0], 0, f), model_frf(rigid(arm), [0.0], 0, f))
    assert found["antiresonance_hz"] == pytest.approx(np.sqrt(k1 / J_L) / (2 * np.pi), rel=2e-3)
    assert found["resonance_hz"] == pytest.approx(np.sqrt(k1 * (1 / J_L + 1 / J_M)) / (2 * np.pi), rel=2e-3)
    stiff = model_frf(rigid(arm), [0.0], 0, f)
    assert peaks(f, stiff, stiff) == {"antiresonance_hz": None, "resonance_hz": None}


def test_a_logged_response_matches_the_model_and_the_command_draws_both(tmp_path, capsys):
    """20 s of white motor torque (held each 1 ms sample) on the damped joint, simulated (RK4,
    4 substeps): the H1 estimate within 1 dB and 10 degrees of the model where coherent (95 % of
    the bins; leakage widens the sharp anti-resonance), its anti-resonance and resonance within
    three of its 0.1 Hz bins of the model's; `rscasadi frf` draws both and names the peaks; a link-side log is
    refused naming tau_1."""
    from rscasadi.sim.loop import rk4_plant
    arm = one_joint(tmp_path, d=0.3, b=0.5)
    dt, N = 1e-3, 20000
    tau = np.random.default_rng(3).normal(0, 0.05, N)
    step, x = rk4_plant(arm, dt), np.zeros(4)
    xs = [x]
    for u in tau[:-1]:
        x = step(x, np.array([u]), 0.0)[0]
        xs.append(x)
    X = np.array(xs).T
    log = Log("sim", np.arange(N) * dt, X[:1], X[1:2], tau[None, :])
    f, G, coh = log_frf(log, 0)
    good = (coh > 0.9) & (f > 2) & (f < 40)
    assert good.sum() > 100
    M = model_frf(arm, [0.0], 0, f[good])
    ratio = G[good] / M
    dB, deg = np.abs(20 * np.log10(np.abs(ratio))), np.abs(np.degrees(np.angle(ratio)))
    assert np.percentile(dB, 95) < 1.0 and dB.max() < 3.0          # Welch's leakage at the sharp anti-resonance
    assert np.percentile(deg, 95) < 10.0                           # the torque held over a sample: 7 deg at 40 Hz
    write_log(tmp_path / "log.csv", log)
    assert main(["frf", str(arm.model.path), str(tmp_path / "log.csv"), "--out", str(tmp_path / "frf"),
                 "--resolution", "0.1"]) in (0, None)
    said = capsys.readouterr().out
    assert "complete anti-resonance" in said and (tmp_path / "frf" / "frf.png").stat().st_size > 10000
    result = json.loads((tmp_path / "frf" / "frf.json").read_text())
    assert abs(result["log"]["resonance_hz"] - result["complete"]["resonance_hz"]) <= 0.3     # three 0.1 Hz bins
    assert abs(result["log"]["antiresonance_hz"] - result["complete"]["antiresonance_hz"]) <= 0.3
    write_log(tmp_path / "link.csv", Log("link", log.t, log.theta, T=log.theta * 1e3))
    assert main(["frf", str(arm.model.path), str(tmp_path / "link.csv"), "--out", str(tmp_path / "no")]) == 2
    assert "column 'tau_1'" in capsys.readouterr().err and not (tmp_path / "no").exists()
    with pytest.raises(LogError, match="tau_1"):
        log_frf(Log("link", log.t, log.theta, T=log.theta), 0)


def test_the_coulomb_terms_are_left_out_of_the_linear_response():
    """arm3 held against gravity (its springs loaded, so c1 |T| is not zero at rest) with every
    Coulomb-like term (c, c1, Stribeck, link_c): the same response as without them, to 1e-12;
    a viscous term (b) does change it (the comparison can tell)."""
    import dataclasses
    from rscasadi.dynamics.arm import Arm
    arm = rscasadi.load(ROOT / "problems" / "arm3.toml")
    f, pose = np.geomspace(1.0, 100.0, 200), [0.2, 0.6, -0.9]
    change = lambda **kw: Arm(dataclasses.replace(arm.model, joints=tuple(dataclasses.replace(jt, **kw)  # noqa: E731
                                                                           for jt in arm.model.joints)))
    plain = model_frf(change(c=0.0), pose, 1, f)
    sticky = model_frf(change(c=0.5, c1=0.05, stribeck=0.3, v_stribeck=0.1, link_c=0.2), pose, 1, f)
    assert np.max(np.abs(sticky - plain) / np.abs(plain)) < 1e-12
    assert np.max(np.abs(model_frf(change(c=0.0, b=5.0), pose, 1, f) - plain) / np.abs(plain)) > 1e-3


def _closed_loop_log(arm, seconds=20.0, dt=1e-3, noise=2e-4):
    """The joint held at rest by a motor-position PD acting on a noisy encoder, nothing else
    exciting it: the logged torque is the controller's answer to the sensor noise."""
    from rscasadi.sim.loop import rk4_plant
    rng, step, x = np.random.default_rng(5), rk4_plant(arm, dt), np.zeros(4)
    mu = arm.model.joints[0].gear_ratio
    kp, kd = 4.0 / mu, 0.05 / mu
    N, last = int(seconds / dt), 0.0
    taus, phis, thetas = [], [], []
    for _ in range(N):
        measured = x[1] + rng.normal(0, noise)
        tau = (kp * measured + kd * (measured - last) / dt)            # the fast rotor turns by -mu: + holds it
        last = measured
        taus.append(tau)
        phis.append(measured)
        thetas.append(x[0])
        x = step(x, np.array([tau]), 0.0)[0]
    t = np.arange(N) * dt
    return Log("closed", t, np.array([thetas]), np.array([phis]), np.array([taus]))


def test_a_log_that_cannot_show_the_resonance_says_so(tmp_path, capsys):
    """Three logs that cannot show the joint's resonance, each told why, with null peaks: a
    closed loop whose torque answers sensor noise (its tau -> phi is not passive: the estimate is
    minus the controller's inverse, though coherent), and the README's `excite` -> `simulate`
    pipeline (excited below 2 Hz only: no coherent bin near 7-11 Hz); and a pose with NaN is
    refused by name before any work."""
    arm = one_joint(tmp_path, d=0.3, b=0.5)
    lg = _closed_loop_log(arm)
    f, G, coh = log_frf(lg, 0)
    assert np.mean(coh[(f > 1) & (f < 100)] > 0.9) > 0.5               # coherent: coherence cannot tell
    write_log(tmp_path / "closed.csv", lg)
    assert main(["frf", str(arm.model.path), str(tmp_path / "closed.csv"), "--out", str(tmp_path / "frf")]) in (0, None)
    said = capsys.readouterr().out
    result = json.loads((tmp_path / "frf" / "frf.json").read_text())
    assert result["log"]["resonance_hz"] is None and result["log"]["antiresonance_hz"] is None
    assert "closed-loop log" in result["log"]["not_shown"]["resonance"] and "closed-loop log" in said
    traj = tmp_path / "excite"
    assert main(["excite", str(ROOT / "problems" / "arm3.toml"), "--out", str(traj), "--period", "10",
                 "--harmonics", "5"]) in (0, None)
    assert main(["simulate", str(ROOT / "problems" / "arm3.toml"), str(traj / "trajectory.toml"), "--out",
                 str(tmp_path / "log.csv"), "--perturb", "1"]) in (0, None)
    capsys.readouterr()
    assert main(["frf", str(ROOT / "problems" / "arm3.toml"), str(tmp_path / "log.csv"), "--joint", "2",
                 "--out", str(tmp_path / "frf2")]) in (0, None)
    said = capsys.readouterr().out
    result = json.loads((tmp_path / "frf2" / "frf.json").read_text())
    assert result["complete"]["resonance_hz"] is not None
    assert result["log"]["resonance_hz"] is None and "too little excitation" in result["log"]["not_shown"]["resonance"]
    assert "the log cannot show the resonance" in said
    assert main(["frf", str(ROOT / "problems" / "arm3.toml"), "--pose", "0", "nan", "0", "--out",
                 str(tmp_path / "nan")]) == 2
    assert "angle 2 (shoulder_pitch) is nan" in capsys.readouterr().err and not (tmp_path / "nan").exists()
