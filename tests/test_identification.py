"""Identification, tested honestly: the regressor against the inverse dynamics on random arms,
the base parameters out of sample, the log checks, the excitation under the limits, and the
whole workflow on synthetic logs of a *different* arm than the model file describes."""
import json

import numpy as np
import pytest

import rscasadi
from rscasadi.cli import main
from rscasadi.sim.trajectory import load_trajectory
from rscasadi.identification import identify as ident_mod
from rscasadi.studies.identification_demo import recovered_table
from rscasadi.identification.logs import LogError, Log, header, read_log, write_log
from rscasadi.identification.regressor import base_parameters, random_samples, regressor, stacked
from rscasadi.model.parameters import n_linear

from conftest import REFERENCE, ROOT, dm


def _rel(a, b):
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)


# ----------------------------------------------------------------------------- regressor

def test_regressor_reproduces_inverse_dynamics_on_random_arms(arm3, random_arms, balanced_arms):
    rng = np.random.default_rng(41)
    cases = [(a, False) for a in [arm3] + random_arms] + [(a, True) for a in balanced_arms[:4]]
    for arm, reduced in cases:
        inv = arm.reduced_inverse_dynamics() if reduced else arm.inverse_dynamics()
        p = arm.parameters()[1][:n_linear(arm.model)]
        R = regressor(arm, reduced=reduced)
        for _ in range(3):
            s = [v[:, 0] for v in random_samples(arm, 1, rng)]
            Y, y0 = R(*s)
            assert np.max(np.abs(dm(y0))) == 0.0                       # nothing known: y0 = 0
            want = np.concatenate([dm(v) for v in inv(*s)])
            assert _rel(np.array(Y) @ p, want) < 1e-10, arm


def test_known_parameters_move_into_y0(arm3):
    names, nominal = arm3.parameters()
    known = [n for n in names if ".link." in n]
    R = regressor(arm3, known=known)
    s = [v[:, 0] for v in random_samples(arm3, 1, np.random.default_rng(2))]
    Y, y0 = R(*s)
    free = [i for i in range(n_linear(arm3.model)) if names[i] not in known]
    want = np.concatenate([dm(v) for v in arm3.inverse_dynamics()(*s)])
    assert np.array(Y).shape[1] == len(free) and np.max(np.abs(dm(y0))) > 0
    assert _rel(np.array(Y) @ nominal[free] + dm(y0), want) < 1e-10


def test_base_parameters_hold_out_of_sample(arm3, random_arms):
    """beta = P p reproduces every row of *new* samples, for any p, and the rank does not
    depend on the samples."""
    rng = np.random.default_rng(43)
    for arm in [arm3] + random_arms[:3]:
        base = base_parameters(arm, rng=np.random.default_rng(1))
        assert base.rank == base_parameters(arm, rng=np.random.default_rng(2)).rank
        W = stacked(arm, random_samples(arm, 30, rng))
        for _ in range(3):
            p = rng.normal(size=W.shape[1])
            assert _rel(W[:, base.independent] @ (base.P @ p), W @ p) < 1e-8


def test_base_parameters_of_the_reference_arm_make_physical_sense(arm3):
    base = base_parameters(arm3)
    # a link turning about the vertical base axis with its centre of mass on it: its mass does nothing
    assert "shoulder_yaw.link.mass" in base.unidentifiable
    text = "\n".join(base.explain())
    # the base joint's rotors act only through B_1 = Izz_S + mu^2 Izz_F (here divided by mu^2)
    assert "shoulder_yaw.fast_rotor.Izz + 0.0001 shoulder_yaw.slow_rotor.Izz" in text
    for name in ("elbow_pitch.sea.k1", "shoulder_pitch.sea.d", "elbow_pitch.gear_loss.c"):
        assert any(line.endswith(f"= {name}") for line in base.explain()), name


# ----------------------------------------------------------------------------- logs

def _log(n=3, N=200):
    t = np.arange(N) * 1e-3
    return Log("x", t, np.zeros((n, N)), np.zeros((n, N)), np.zeros((n, N)))


def _cell(row: str, k: int, value: str) -> str:
    cells = row.split(",")
    cells[k] = value
    return ",".join(cells)


@pytest.mark.parametrize("mutate, words", [
    (lambda rows: rows.__setitem__(0, rows[0].replace("phi_2", "phi2")), "missing column 'phi_2'"),
    (lambda rows: rows.__setitem__(0, rows[0] + ",extra"), "unexpected column 'extra'"),
    (lambda rows: rows.__setitem__(5, _cell(rows[5], 4, "nan")), "column 'phi_1'"),
    (lambda rows: rows.__setitem__(5, _cell(rows[5], 4, "nan")), "NaN"),
    (lambda rows: rows.__setitem__(7, "0.1," + rows[7].split(",", 1)[1]), "column 't'"),
    (lambda rows: rows.__setitem__(9, _cell(rows[9], 1, "abc")), "column 'theta_1'"),
    (lambda rows: rows.__setitem__(9, "0.0075," + rows[9].split(",", 1)[1]), "not uniform"),
    (lambda rows: rows.__setitem__(slice(30, None), []), "only"),
    (lambda rows: rows.__setitem__(3, rows[3] + ",1.0"), "line 4"),
    (lambda rows: rows.__setitem__(0, rows[0].replace("phi_", "T_")), "'tau_1' (motor torque) needs 'phi_1..phi_3'"),
    (lambda rows: rows.__setitem__(0, rows[0].replace("tau_", "current_")), "unexpected column 'current_1' (a motor current is i_j)"),
    (lambda rows: rows.__setitem__(0, rows[0].replace("phi_", "i_")), "both motor torques (tau_j) and motor currents (i_j)"),
    (lambda rows: rows.__setitem__(0, rows[0].replace("tau_", "i_").replace("phi_", "T_")), "'i_1' (motor current) needs 'phi_1..phi_3'"),
    (lambda rows: rows.__setitem__(0, rows[0].replace("tau_3", "T_3")), "missing column 'tau_3'"),
    (lambda rows: rows.__setitem__(0, rows[0].replace("phi_2", "theta_1")), "column 'theta_1' appears twice"),
    (lambda rows: rows.__setitem__(0, rows[0].replace("tau_", "dphi_")), "no torque column"),
])
def test_bad_logs_are_refused_naming_file_and_column(tmp_path, mutate, words):
    path = tmp_path / "run.csv"
    write_log(path, _log())
    rows = path.read_text().splitlines()
    mutate(rows)
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(LogError) as err:
        read_log(path, 3)
    assert "run.csv" in str(err.value) and words in str(err.value)


def test_motor_currents_become_motor_torques_with_the_torque_constants(tmp_path):
    """A log of motor currents i_j: with the model file's torque_constant per joint, the motor
    torques are kt_j i_j (what a log of tau_j gives, to the digit); a model without a torque
    constant for some joints is refused naming them, by `identify` and `simulate` before any work;
    `simulate` logs the currents of a model that has them."""
    import dataclasses
    from conftest import to_toml
    from rscasadi.identification.identify import run
    from rscasadi.identification.logs import motor_torques
    from rscasadi.model.modelfile import document
    lg, kt = _log(), np.array([0.05, 0.08, 0.11])
    lg.tau = np.random.default_rng(4).normal(0, 0.3, lg.tau.shape)
    write_log(tmp_path / "tau.csv", lg)
    write_log(tmp_path / "i.csv", dataclasses.replace(lg, tau=None, i=lg.tau / kt[:, None]))
    assert (tmp_path / "i.csv").read_text().splitlines()[0].split(",")[7:10] == ["i_1", "i_2", "i_3"]
    doc = document(rscasadi.load(ROOT / "problems" / "arm3.toml").model)
    for jt, k in zip(doc["joints"], kt):
        jt["torque_constant"] = float(k)
    (tmp_path / "kt.toml").write_text(to_toml(doc))
    arm = rscasadi.load(tmp_path / "kt.toml")
    assert [jt.torque_constant for jt in arm.model.joints] == kt.tolist()
    assert document(arm.model)["joints"][2]["torque_constant"] == kt[2]
    got, want = motor_torques(read_log(tmp_path / "i.csv", 3), arm.model), read_log(tmp_path / "tau.csv", 3)
    assert np.array_equal(got.i, want.tau / kt[:, None]) and np.max(np.abs(got.tau - want.tau)) < 1e-12 * np.max(np.abs(want.tau))
    del doc["joints"][1]["torque_constant"], doc["joints"][2]["torque_constant"]
    (tmp_path / "some.toml").write_text(to_toml(doc))
    with pytest.raises(LogError, match=r"i.csv.*torque_constant.*shoulder_pitch, elbow_pitch"):
        run(tmp_path / "some.toml", [tmp_path / "i.csv"], tmp_path / "out", log=lambda m: None)
    assert not (tmp_path / "out").exists()
    traj = ROOT / "problems" / "trajectory_arm3.toml"                 # simulate logs currents likewise
    assert main(["simulate", str(tmp_path / "some.toml"), str(traj), "--out", str(tmp_path / "sim.csv"),
                 "--columns", "theta,phi,i"]) == 2 and not (tmp_path / "sim.csv").exists()
    assert main(["simulate", str(tmp_path / "kt.toml"), str(traj), "--out", str(tmp_path / "sim.csv"), "--rate", "250",
                 "--columns", "theta,phi,i", "--noise", "0"]) in (0, None)
    sim = read_log(tmp_path / "sim.csv", 3)
    assert sim.tau is None and sim.i is not None and np.all(np.abs(sim.i * kt[:, None]) <= 0.6 + 1e-9)


def test_torque_constants_from_currents_with_and_without_a_torque_sensor(excitation, tmp_path):
    """Motors whose torque constants are 10 % off the model file's, in turn up and down (true kt
    0.055, 0.072, 0.121 against 0.05, 0.08, 0.11), logging currents.  With a joint torque sensor
    (theta, phi, i, T) every kt is identified: within 1 % and 3 of its standard deviations, the
    springs within 0.2 %.  From currents alone (theta, phi, i) kt is known only up to a scale
    every parameter shares: the ratios come out within 1 % with their mean held at the file's
    (said), every other parameter carries that scale (k1 low by the mean's 3.3 %), and the held-out
    motor torques are predicted within 3 % (with kt held at the file's, joint 2's error was 16 %)."""
    import dataclasses
    from conftest import to_toml
    from rscasadi.dynamics.arm import Arm
    from rscasadi.identification.identify import run
    from rscasadi.identification.synthetic import perturbed_arm, record
    from rscasadi.model.modelfile import document
    from rscasadi.sim.trajectory import load_trajectory
    doc = document(rscasadi.load(REFERENCE).model)
    kt_file, kt_true = np.array([0.05, 0.08, 0.11]), np.array([0.055, 0.072, 0.121])
    for jt, k in zip(doc["joints"], kt_file):
        jt["torque_constant"] = float(k)
    (tmp_path / "kt.toml").write_text(to_toml(doc))
    nominal = rscasadi.load(tmp_path / "kt.toml")
    true = perturbed_arm(nominal, np.random.default_rng(2026))
    true = Arm(dataclasses.replace(true.model, joints=tuple(dataclasses.replace(jt, torque_constant=float(k))
                                                             for jt, k in zip(true.model.joints, kt_true))))
    for name, traj in (("ident", excitation / "trajectory.toml"), ("valid", ROOT / "problems" / "trajectory_arm3.toml")):
        lg, _ = record(true, nominal, load_trajectory(traj), rng=np.random.default_rng(len(name)),
                       columns=("theta", "phi", "i", "T"))
        write_log(tmp_path / f"{name}_T.csv", lg)
        write_log(tmp_path / f"{name}.csv", dataclasses.replace(lg, T=None))
    k1_true = np.array([jt.k1 for jt in true.model.joints])
    said: list = []
    rep, _ = run(tmp_path / "kt.toml", [tmp_path / "ident_T.csv"], tmp_path / "with_T", log=said.append)
    got = [rep["parameters"][f"{jt.name}.torque_constant"] for jt in nominal.model.joints]
    for g, k in zip(got, kt_true):
        assert abs(g["estimate"] - k) < min(0.01 * k, 3 * g["std"]), (g, k)
    k1 = np.array([rep["parameters"][f"{jt.name}.sea.k1"]["estimate"] for jt in nominal.model.joints])
    assert np.all(np.abs(k1 / k1_true - 1) < 2e-3), k1 / k1_true
    assert not any("ratios" in line for line in said)
    said.clear()
    rep, _ = run(tmp_path / "kt.toml", [tmp_path / "ident.csv"], tmp_path / "currents", validate=tmp_path / "valid.csv",
                 log=said.append)
    got = np.array([rep["parameters"][f"{jt.name}.torque_constant"]["estimate"] for jt in nominal.model.joints])
    assert any("torque constants: their ratios" in line for line in said), said
    assert abs(np.mean(got / kt_file) - 1) < 1e-9                             # the scale: the file's
    assert np.all(np.abs((got / got[0]) / (kt_true / kt_true[0]) - 1) < 0.01), got
    scale = np.mean(kt_true / kt_file)                                         # 1.033: what every parameter carries
    k1 = np.array([rep["parameters"][f"{jt.name}.sea.k1"]["estimate"] for jt in nominal.model.joints])
    assert np.all(np.abs(k1 * scale / k1_true - 1) < 0.01), k1 * scale / k1_true
    held_out = [rep["validation"]["prediction"][f"tau_{j}"]["relative"] for j in (1, 2, 3)]
    assert max(held_out) < 0.03, held_out


def test_log_round_trip_with_torque_sensor(tmp_path):
    lg = _log()
    lg.T = np.ones((3, 200))
    write_log(tmp_path / "a.csv", lg)
    back = read_log(tmp_path / "a.csv", 3)
    assert back.T is not None and np.allclose(back.T, 1.0) and np.allclose(back.t, lg.t)
    assert (tmp_path / "a.csv").read_text().splitlines()[0] == ",".join(header(3, True))


# ----------------------------------------------------------------------------- the workflow

def test_excitation_is_at_rest_within_limits_and_better_than_a_hand_picked_motion(excitation, arm3):
    summary = json.loads((excitation / "excitation.json").read_text())
    traj = load_trajectory(excitation / "trajectory.toml")
    q = traj(np.array([0.0, traj.period]))
    assert np.max(np.abs(q[1])) < 1e-12 and np.max(np.abs(q[2])) < 1e-12 and np.max(np.abs(q[3])) < 1e-12
    assert np.allclose(q[0][:, 0], q[0][:, 1])                         # periodic
    assert max(summary["limit_use"].values()) <= 1.0
    # the limits are checked again here on the written feedforward, independently of the summary
    ff = np.loadtxt(excitation / "feedforward.csv", delimiter=",", skiprows=1)
    tau = ff[:, 1:4]
    assert np.all(np.abs(tau) <= np.array([jt.limits["tau"] for jt in arm3.model.joints]))
    theta = ff[:, 4:7]
    lo = np.array([jt.limits["theta"][0] for jt in arm3.model.joints])
    hi = np.array([jt.limits["theta"][1] for jt in arm3.model.joints])
    assert np.all(theta >= lo) and np.all(theta <= hi)
    assert np.max(np.abs(ff[:, 7:10] - theta)) <= 0.15                  # deflection limit
    assert summary["condition_number"] * 100 < summary["condition_number_hand_picked"]
    # checked, not just stopped: converged or stalled, every joint sweeps a tenth of its range, kappa bounded
    assert summary["status"] in ("Solve_Succeeded", "Solved_To_Acceptable_Level", "Stalled")
    assert np.all(np.ptp(theta, axis=0) >= 0.1 * (hi - lo)) and summary["condition_number"] < 1e4


def test_identified_model_file_round_trips(identified, arm3):
    model = rscasadi.load(identified / "model.toml")
    assert [jt.name for jt in model.model.joints] == [jt.name for jt in arm3.model.joints]
    for a, b in zip(model.model.joints, arm3.model.joints):
        assert np.allclose(a.R, b.R, atol=1e-12) and np.allclose(a.origin_xyz, b.origin_xyz) \
            and a.gear_ratio == b.gear_ratio and a.eps == b.eps
    report = json.loads((identified / "report.json").read_text())
    names = arm3.parameters()[0]
    assert all({"nominal", "estimate", "std"} <= set(v) for v in report["parameters"].values())
    assert "shoulder_yaw.sea.k1" in report["parameters"] and "residual_rms" in report
    # the designed excitation rings the springs: the cut-off passes twice the highest mode (27.5 Hz)
    assert 50 < report["cutoff_hz"] < 60 and "highest SEA mode the log excites" in report["cutoff_why"]
    assert (identified / "validation.png").exists() and (identified / "fit.png").exists()
    assert len(names) > len(report["parameters"])                        # balanced rotors stay balanced
    assert report["physical_fit"].startswith("converged")


def test_prediction_of_held_out_torques(identified, synthetic, arm3):
    """Within 2 % RMS of each motor torque's RMS, beyond the sensor noise that no model can
    predict (the true arm's own error on the same filtered log)."""
    true, logs = synthetic
    report = json.loads((identified / "report.json").read_text())
    val = read_log(logs["validation"], 3)
    u = ident_mod.Unknowns.of(arm3.model)
    rows = ident_mod.rows(arm3, ident_mod.prepare(val, report["cutoff_hz"]), u)
    floor = ident_mod.predict(rows, u.from_p(true.parameters()[1][:n_linear(arm3.model)]))
    nominal = ident_mod.predict(rows, u.from_p(arm3.parameters()[1][:n_linear(arm3.model)]))
    for ch, got in report["validation"]["prediction"].items():
        assert got["relative"] ** 2 <= floor[ch]["relative"] ** 2 + 0.02 ** 2, (ch, got, floor[ch])
        assert got["relative"] < 0.2 * nominal[ch]["relative"], ch             # and far better than the file


def test_actuator_parameters_recovered_within_their_standard_deviation(synthetic, arm3):
    true, logs = synthetic
    ident = ident_mod.identify(arm3, [read_log(logs["identification"], 3)])
    table = recovered_table(ident, arm3, true)
    checked = [r for r in table if r["z"] is not None]
    assert len(checked) >= 17                                            # k1, k3, d, b, c, B of every joint
    for r in checked:
        assert abs(r["z"]) < 4.0, r
    for r in checked:                                                    # and useful: much closer than the file
        if r["std"] < 0.1 * abs(r["true"] - r["nominal"]):
            assert abs(r["estimate"] - r["true"]) < 0.25 * abs(r["true"] - r["nominal"]), r


def test_reduced_model_ablation_runs(synthetic, tmp_path):
    _, logs = synthetic
    out = tmp_path / "reduced"
    assert main(["identify", str(REFERENCE), str(logs["identification"]), "--out", str(out), "--reduced"]) == 0
    assert rscasadi.load(out / "model.toml").n == 3


def test_identify_refuses_a_log_of_another_arm(synthetic, tmp_path, capsys):
    _, logs = synthetic
    code = main(["identify", str(ROOT / "problems" / "panda_sea.toml"), str(logs["identification"]),
                 "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert code == 2 and "identification.csv" in err and "theta_4" in err and not (tmp_path / "x").exists()


def test_identify_explain_prints_the_base_parameters(synthetic, tmp_path, capsys):
    _, logs = synthetic
    assert main(["identify", str(REFERENCE), str(logs["identification"]), "--out", str(tmp_path / "e"),
                 "--explain"]) == 0
    out = capsys.readouterr().out
    assert "beta_1 = " in out and "base parameters of" in out
    assert "shoulder_yaw.fast_rotor.Izz + 0.0001 shoulder_yaw.slow_rotor.Izz" in out


def test_logs_that_cannot_identify_are_refused(synthetic, arm3):
    """Too short to filter, or a motion that leaves parameter combinations undetermined."""
    _, logs = synthetic
    lg = read_log(logs["identification"], 3)
    short = Log("short.csv", lg.t[:800], lg.theta[:, :800], lg.phi[:, :800], lg.tau[:, :800])
    with pytest.raises(LogError, match="short.csv.*too short"):
        ident_mod.identify(arm3, [short])
    N = 3000                                            # the arm held still: no dynamics to fit
    still = Log("still.csv", lg.t[:N], np.repeat(lg.theta[:, :1], N, 1), np.repeat(lg.phi[:, :1], N, 1),
                np.repeat(lg.tau[:, :1], N, 1))
    with pytest.raises(LogError, match="still.csv.*determines only"):
        ident_mod.identify(arm3, [still])


def test_a_degenerate_excitation_is_refused_naming_the_cause(arm3, tmp_path, capsys):
    """The fresh machine's failure: a design where a joint hardly moves, or whose condition number
    is too large, is refused: by the check, by `design`, and by `excite` with one line and exit 2."""
    from rscasadi.sim.trajectory import Trajectory
    from rscasadi.identification import excitation as ex
    t = np.linspace(0.0, 4.0, 401)
    rng = np.random.default_rng(3)
    a, b = ex._rest_projection(rng.normal(0, 0.1, (3, 3)), rng.normal(0, 0.1, (3, 3)))
    a[0], b[0] = a[0] * 1e-4, b[0] * 1e-4                              # joint 1 still
    still = Trajectory(model_path=REFERENCE, period=4.0, duration=4.0, kind="fourier", offset=np.zeros(3), a=a, b=b)
    problems = ex.check_design(arm3, still, t, ex.condition_number(arm3, still))
    assert any("shoulder_yaw" in p and "sweeps" in p for p in problems), problems
    assert any("condition number" in p for p in problems), problems
    with pytest.raises(ex.ExcitationError, match="start 1: .*condition number .* above 1"):
        ex.design(arm3, period=4.0, harmonics=3, starts=1, max_condition=1.0, log=lambda m: None)


def test_the_limits_jacobian_assembled_by_the_chain_rule_equals_casadis_ad():
    """The design's limit constraints take their Jacobian from each sample's Jacobian times the
    Fourier basis (custom_jacobian); CasADi's own AD of the mapped samples is the reference."""
    import casadi as ca
    from rscasadi.identification import excitation as ex
    arm = rscasadi.load(ROOT / "problems" / "panda_sea.toml")
    n, K, M = arm.n, 3, 12
    (_, g_limits), _ = ex._design_parts(arm)
    B = ex._basis(6.0, K, np.linspace(0, 6.0, M, endpoint=False))
    x = ca.MX.sym("x", 2 * n * K + n)
    ours = ca.Function("ours", [x], [ca.jacobian(ex._limit_function(g_limits, B, n, K)(x), x)])
    a, b, q0 = ca.MX.sym("a", n, K), ca.MX.sym("b", n, K), ca.MX.sym("q0", n)
    tau, psi, dphi = g_limits.map(M)(*ex._series(a, b, q0, B))
    w = ca.vertcat(ca.vec(a), ca.vec(b), q0)
    ad = ca.Function("ad", [w], [ca.jacobian(ca.vertcat(ca.vec(tau.T), ca.vec(psi.T), ca.vec(dphi.T)), w)])
    v = np.random.default_rng(4).normal(0, 0.2, 2 * n * K + n)
    J, J_ad = np.array(ours(v)), np.array(ad(v))
    assert J.shape == (3 * n * M, 2 * n * K + n) and np.max(np.abs(J - J_ad)) < 1e-12 * np.max(np.abs(J_ad))


def test_excitation_on_seven_joints_fixes_what_it_cannot_excite(tmp_path, capsys):
    """The Panda (7 joints, 90 base parameters) at short settings: the wrist's cubic spring term,
    which the wrist's small deflections cannot show, is fixed at the file's value with a note
    (printed and in excitation.json), and the design of the other 89 passes at rest within the
    limits; `identify` on a log of it reports that parameter as uncertain.  Asked for a
    condition number no design reaches, `excite` refuses in one whole line: every start's cause,
    the direction that holds it up, and what to change."""
    panda = ROOT / "problems" / "panda_sea.toml"
    short = ["--harmonics", "3", "--samples", "20", "--starts", "1", "--period", "6"]
    assert main(["excite", str(panda), "--out", str(tmp_path / "refused"), *short, "--max-condition", "10"]) == 2
    out = capsys.readouterr()
    assert "excitation: start 1/1: IPOPT" in out.out
    assert "start 1: condition number" in out.err and "least determined: " in out.err
    assert out.err.rstrip().endswith("held near the model file's values)") and "What to change" in out.err
    assert len(out.err.strip().splitlines()) == 1 and not (tmp_path / "refused").exists()
    design = tmp_path / "design"
    assert main(["excite", str(panda), "--out", str(design), *short]) == 0
    assert "panda_joint7.sea.k3 cannot be excited within the limits; fixed at the file's value" in capsys.readouterr().out
    summary = json.loads((design / "excitation.json").read_text())
    assert summary["condition_number"] < 1e5 and summary["hessian"] == "limited-memory"
    assert list(summary["fixed"]) == ["panda_joint7.sea.k3"] and summary["base_parameters"] == 89
    traj = load_trajectory(design / "trajectory.toml")
    q = traj(np.array([0.0, traj.period]))
    assert np.max(np.abs(np.vstack(q[1:4]))) < 1e-12                   # at rest at both ends
    arm = rscasadi.load(panda)
    ff = np.loadtxt(design / "feedforward.csv", delimiter=",", skiprows=1)
    assert np.all(np.abs(ff[:, 1:8]) <= np.array([jt.limits["tau"] for jt in arm.model.joints]))
    assert main(["simulate", str(panda), str(design / "trajectory.toml"), "--out", str(tmp_path / "log.csv"),
                 "--rate", "500"]) == 0
    assert main(["identify", str(panda), str(tmp_path / "log.csv"), "--out", str(tmp_path / "identified")]) == 0
    report = json.loads((tmp_path / "identified" / "report.json").read_text())
    assert "panda_joint7.sea.k3" in report["uncertain"]                 # {name: std / |estimate|}


def test_excitation_at_default_settings_on_an_arm_it_never_saw(tmp_path, capsys):
    """Unitree's Z1 (tests/data/z1_description, as shipped: products of inertia written to 1e-8
    beside moments of 1e-3, two ranges ending at 0) with an SEA table whose wrist spring has a
    cubic term: `excite` at its default settings designs a checked trajectory (it stopped at
    IPOPT's iteration 0 with Invalid_Number_Detected on every start), the cubic term fixed with
    a note."""
    z1 = ROOT / "tests" / "data" / "z1_sea.toml"
    assert main(["excite", str(z1), "--out", str(tmp_path / "z1")]) == 0
    out = capsys.readouterr().out
    assert "Invalid_Number" not in out and "joint6.sea.k3 cannot be excited" in out
    summary = json.loads((tmp_path / "z1" / "excitation.json").read_text())
    assert summary["condition_number"] < 1e5 and "joint6.sea.k3" in summary["fixed"]
    assert all(e["status"] != "Invalid_Number_Detected" for e in summary["starts"])


def test_the_design_sizes_round_off_as_its_kind():
    """A product of inertia a URDF writes as 6e-8 (or 1e-20) beside a moment of 1e-3 is sized by
    the design at a tenth of that moment; identify's prior keeps the file's own magnitude."""
    from rscasadi.identification.identify import Unknowns, prior_scale
    from rscasadi.identification.excitation import SIZE_FLOOR
    arm = rscasadi.load(ROOT / "tests" / "data" / "z1_sea.toml")
    unknowns = Unknowns.of(arm.model, load_losses=False)
    th = unknowns.from_p(arm.parameters()[1][:n_linear(arm.model)])
    k = unknowns.names.index("joint2.link.Ixy")
    moments = [i for i, name in enumerate(unknowns.names) if name.startswith("joint2.link.I")]
    th[k] = 1e-20
    design, prior = prior_scale(unknowns, th, floor=SIZE_FLOOR), prior_scale(unknowns, th)
    assert design[k] == pytest.approx(SIZE_FLOOR * max(abs(th[i]) for i in moments)) and prior[k] <= 1e-12


def test_excitation_design_holds_on_other_blas_kernels(tmp_path):
    """A fresh machine's BLAS took other kernels and the design landed on a trajectory where
    joint 1 never moved (condition number 7e11).  Here numpy's OpenBLAS is forced onto another
    kernel family: the design converges and passes its checks there too."""
    import subprocess
    import sys
    import os
    env = dict(os.environ, OPENBLAS_CORETYPE="Prescott")
    out = tmp_path / "val"
    res = subprocess.run([sys.executable, "-m", "rscasadi.cli", "excite", str(REFERENCE), "--out", str(out),
                          "--period", "8", "--harmonics", "4"], capture_output=True, text=True, env=env, timeout=900)
    assert res.returncode == 0, res.stderr
    summary = json.loads((out / "excitation.json").read_text())
    assert summary["status"] in ("Solve_Succeeded", "Stalled") and summary["condition_number"] < 1e4, summary
    assert all(not s["refused"] for s in summary["starts"]), summary["starts"]


def test_held_out_log_that_does_not_move_a_joint_is_refused_by_name(synthetic, tmp_path, capsys):
    _, logs = synthetic
    lg = read_log(logs["validation"], 3)
    lg.theta[0], lg.phi[0] = lg.theta[0, :1], lg.phi[0, :1]            # joint 1 held still
    write_log(tmp_path / "still_joint.csv", lg)
    code = main(["identify", str(REFERENCE), str(logs["identification"]), "--out", str(tmp_path / "o"),
                 "--validate", str(tmp_path / "still_joint.csv")])
    captured = capsys.readouterr()
    assert code == 2 and "still_joint.csv" in captured.err and "phi_1" in captured.err
    assert "shoulder_yaw" in captured.err and "identifying" not in captured.out and "nan" not in captured.out
    assert not (tmp_path / "o").exists()


def test_a_weak_log_is_warned_about_and_its_uncertainty_is_honest(synthetic, arm3, identified, tmp_path):
    """Two bumps of 0.2-0.3 rad in 3 s (condition number about 600): the shoulder yaw's k1 comes
    out of the least squares at about 190 N m/rad against a true 1430, 60 noise standard
    deviations off; the reported std (noise or segment bootstrap, plus the move between two
    cut-offs) puts every k1 within 3 of it, the log is called weak and the yaw's k1 uncertain.
    On the designed excitation no such warning, and the springs stay known to 5 %."""
    import json
    from rscasadi.identification.identify import identify, report
    from rscasadi.identification.logs import read_log, write_log
    from rscasadi.identification.synthetic import record
    from rscasadi.sim.trajectory import load_trajectory
    true, _ = synthetic
    bumps = tmp_path / "bumps.toml"
    bumps.write_text(f'model = "{REFERENCE}"\nperiod = 1.5\nduration = 3.0\nstart = [0.0, 0.4, -0.6]\n'
                     'amplitude = [0.3, 0.2, -0.25]\n')
    lg, _ = record(true, arm3, load_trajectory(bumps), rng=np.random.default_rng(2026))
    write_log(tmp_path / "weak.csv", lg)
    ident = identify(arm3, [read_log(tmp_path / "weak.csv", 3)])
    truth = dict(zip(*true.parameters()))
    u, z_noise = ident.unknowns, []
    for jt in arm3.model.joints:
        c = np.eye(len(u.names))[u.names.index(f"{jt.name}.sea.k1")]
        d = ident.ls.base.functional(c)
        error = d @ ident.ls.beta - truth[f"{jt.name}.sea.k1"]
        assert abs(error) < 3 * ident.ls.std_of(c), (jt.name, error, ident.ls.std_of(c))
        z_noise.append(abs(error) / np.sqrt(d @ ident.ls.cov_noise @ d))
    assert max(z_noise) > 20                                  # the noise alone was overconfident
    rep = report(ident, arm3, None, ["weak.csv"])
    assert any("weak log" in w for w in rep["warnings"]) and "shoulder_yaw.sea.k1" in rep["uncertain"]
    good = json.loads((identified / "report.json").read_text())
    assert not any("weak log" in w for w in good["warnings"])
    for jt in arm3.model.joints:
        k1 = good["parameters"][f"{jt.name}.sea.k1"]
        assert k1["std"] < 0.05 * k1["estimate"], (jt.name, k1)


def test_simulate_writes_a_log_identify_reads(tmp_path, capsys):
    """rscasadi simulate: a log in the documented format from a model and a trajectory file, of a
    perturbed arm of the family whose model file it writes too; bad paths refused by name."""
    from rscasadi.identification.logs import read_log
    traj = ROOT / "problems" / "trajectory_arm3.toml"
    assert main(["simulate", str(REFERENCE), str(traj), "--out", str(tmp_path / "log.csv"), "--rate", "500",
                 "--perturb", "4", "--true-model", str(tmp_path / "true.toml")]) in (0, None)
    lg = read_log(tmp_path / "log.csv", 3)
    assert lg.t.size == 1001 and np.all(np.isfinite(lg.tau)) and np.ptp(lg.theta[0]) > 0.9
    true, nominal = rscasadi.load(tmp_path / "true.toml"), rscasadi.load(REFERENCE)
    assert true.model.joints[0].k1 != nominal.model.joints[0].k1 and true.model.joints[0].k3 > 0
    assert "wrote" in capsys.readouterr().out
    assert main(["simulate", str(REFERENCE), str(traj), "--out", str(tmp_path)]) == 2
    assert "is a directory" in capsys.readouterr().err
    assert main(["simulate", str(ROOT / "problems" / "panda_sea.toml"), str(traj), "--out", str(tmp_path / "x.csv")]) == 2
    assert "3 joints" in capsys.readouterr().err and not (tmp_path / "x.csv").exists()


def test_identification_on_logs_mujoco_recorded(excitation, tmp_path):
    """A perturbed arm of the family (linear springs, no Coulomb loss: what MJCF holds) exported to
    MuJoCo records the excitation and the paper's trajectory (`rscasadi simulate --simulator
    mujoco`: MuJoCo's physics, not rscasadi's); `rscasadi identify` on the nominal model predicts
    the held-out motor torques within 1 % RMS beyond what the exported arm itself predicts on the
    same filtered log (the sensors' noise and quantisation), far better than the model file, and
    recovers every spring's k1 within 1 % of the exported arm's (measured 2026-11-26: 0.05-0.08 %)."""
    pytest.importorskip("mujoco")
    logs = {}
    for name, traj in (("identification", excitation / "trajectory.toml"),
                       ("validation", ROOT / "problems" / "trajectory_arm3.toml")):
        logs[name] = tmp_path / f"{name}.csv"
        assert main(["simulate", str(REFERENCE), str(traj), "--out", str(logs[name]), "--perturb", "4",
                     "--simulator", "mujoco", "--true-model", str(tmp_path / "true.toml")]) in (0, None)
    true = rscasadi.load(tmp_path / "true.toml")
    assert all(jt.k3 == 0 and jt.c == 0 for jt in true.model.joints)
    assert main(["identify", str(REFERENCE), str(logs["identification"]), "--out", str(tmp_path / "ident"),
                 "--validate", str(logs["validation"])]) == 0
    report = json.loads((tmp_path / "ident" / "report.json").read_text())
    arm3 = rscasadi.load(REFERENCE)
    u = ident_mod.Unknowns.of(arm3.model)
    rows = ident_mod.rows(arm3, ident_mod.prepare(read_log(logs["validation"], 3), report["cutoff_hz"]), u)
    floor = ident_mod.predict(rows, u.from_p(true.parameters()[1][:n_linear(arm3.model)]))
    nominal = ident_mod.predict(rows, u.from_p(arm3.parameters()[1][:n_linear(arm3.model)]))
    for ch, got in report["validation"]["prediction"].items():
        assert got["relative"] ** 2 <= floor[ch]["relative"] ** 2 + 0.01 ** 2, (ch, got, floor[ch])
        assert got["relative"] < 0.2 * nominal[ch]["relative"], ch
    found = rscasadi.load(tmp_path / "ident" / "model.toml")
    for mine, theirs in zip(found.model.joints, true.model.joints):
        assert abs(mine.k1 - theirs.k1) < 0.01 * theirs.k1, (mine.name, mine.k1, theirs.k1)


def test_synthetic_sensors_read_with_an_offset_and_a_latency():
    """record's torque sensor with offsets and a 2 ms latency reads what the plain one read 2 ms
    before, plus the offset, to the digit (the same draws of noise)."""
    from rscasadi.identification.synthetic import record
    arm = rscasadi.load(REFERENCE)
    traj = load_trajectory(ROOT / "problems" / "trajectory_arm3.toml")
    kw = {"rate": 500.0, "columns": ("theta", "T")}
    plain, _ = record(arm, arm, traj, rng=np.random.default_rng(3), **kw)
    real, _ = record(arm, arm, traj, rng=np.random.default_rng(3), offsets={"T": [0.1, -0.2, 0.3]},
                     delays={"T": 0.004}, **kw)
    assert np.array_equal(real.theta, plain.theta)
    assert np.max(np.abs(real.T[:, 2:] - plain.T[:, :-2] - np.array([[0.1], [-0.2], [0.3]]))) < 1e-12
