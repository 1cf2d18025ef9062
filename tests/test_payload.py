"""A payload held at a frame: in every Function and the parameter vector, against Pinocchio with
the payload as a body of its own; refused by name when wrong; identified alone from a short log
of a payload the identifier is not told."""
import json

import numpy as np
import pytest

import rscasadi
from rscasadi import ModelFileError
from rscasadi.cli import main
from rscasadi.identification.identify import Unknowns
from rscasadi.identification.logs import write_log
from rscasadi.identification.synthetic import record
from rscasadi.model.modelfile import document, parse, to_toml
from rscasadi.model.parameters import body_parameters, names, payload_slice, with_values
from rscasadi.reference.pinocchio_route import PinocchioRoute
from rscasadi.sim.trajectory import load_trajectory

from conftest import REFERENCE, ROOT, dm, random_state

TRUE = {"mass": 1.6, "com": [0.03, -0.01, 0.05], "inertia": [4e-3, 3e-3, 2e-3, 2e-4, 0.0, 0.0]}
GUESS = {"mass": 1.0, "com": [0.0, 0.0, 0.0], "inertia": [1e-3, 1e-3, 1e-3, 0.0, 0.0, 0.0]}


def holding(model_doc, payload, frame="tool", frames=None):
    doc = dict(model_doc)
    doc["frames"] = frames or {"tool": {"parent": "elbow_pitch", "xyz": [0.3, 0.0, 0.0], "rpy": [0.0, 0.3, 0.0]}}
    doc["payload"] = {"frame": frame, **payload}
    return doc


@pytest.fixture(scope="module")
def arm3_doc():
    return document(rscasadi.load(REFERENCE).model)


def test_payload_equals_pinocchio_with_the_payload_as_a_body():
    panda = rscasadi.load(ROOT / "problems" / "panda_sea.toml")
    doc = document(panda.model)
    doc["payload"] = {"frame": "panda_hand_tcp", **TRUE}
    arm = rscasadi.Arm(parse(doc, "panda_payload.toml"))
    route, bare = PinocchioRoute(arm.model), PinocchioRoute(panda.model)
    rng = np.random.default_rng(2)
    for _ in range(3):
        x, tau = random_state(rng, 7), rng.normal(size=7)
        ours = np.concatenate([dm(v) for v in arm.forward_dynamics()(*x, tau)])
        theirs = np.concatenate(route.forward_dynamics(*x, tau))
        assert np.allclose(ours, theirs, atol=1e-9 * np.abs(theirs).max())
        assert not np.allclose(np.concatenate(bare.forward_dynamics(*x, tau)), theirs, atol=1e-3)   # it matters
        M, _ = route.mass_bias(*x)
        assert np.allclose(np.array(arm.mass_matrix()(x[0], x[1])), M, atol=1e-9 * np.abs(M).max())
    c_pin = np.array(__import__("pinocchio").centerOfMass(route.model, route.data, route.G @ np.r_[x[0], x[1]]))
    assert np.allclose(dm(arm.center_of_mass()(x[0], x[1])), c_pin, atol=1e-12)


def test_payload_parameters_sit_after_the_joints_and_before_gravity(arm3_doc):
    arm = rscasadi.Arm(parse(holding(arm3_doc, TRUE), "held.toml"))
    all_names, nominal = arm.parameters()
    held = payload_slice(arm.model)
    assert all_names[held] == [f"payload.{q}" for q in ("mass", "mx", "my", "mz", "Ixx", "Iyy", "Izz", "Ixy", "Ixz", "Iyz")]
    assert all_names[held.stop:] == ["gravity.x", "gravity.y", "gravity.z"] and names(arm.model) == all_names
    assert np.allclose(nominal[held], body_parameters(arm.model.payload.body))
    rng = np.random.default_rng(3)
    x, tau = random_state(rng, 3), rng.normal(size=3)
    p = nominal.copy()
    p[held.start] = 2.5                                              # a heavier payload, same first moment
    heavier = rscasadi.Arm(with_values(arm.model, {"payload.mass": 2.5}))
    got = np.concatenate([dm(v) for v in arm.forward_dynamics(parametric=True)(*x, tau, p)])
    want = np.concatenate([dm(v) for v in heavier.forward_dynamics()(*x, tau)])
    assert np.allclose(got, want, atol=1e-10)
    same = np.concatenate([dm(v) for v in arm.forward_dynamics(parametric=True)(*x, tau, nominal)])
    assert np.allclose(same, np.concatenate([dm(v) for v in arm.forward_dynamics()(*x, tau)]), atol=1e-12)
    u = Unknowns.of(arm.model)                                      # identification keeps the payload
    assert np.all(u.E[held].sum(axis=1) == 1)


@pytest.mark.parametrize("payload,field,words", [
    ({"frame": "nowhere", **TRUE}, "payload.frame", "no frame"),
    ({"frame": "base", **TRUE}, "payload.frame", "fixed base"),
    ({"frame": "tool", "com": [0, 0, 0], "inertia": [1, 1, 1, 0, 0, 0]}, "payload.mass", "missing"),
    ({"frame": "tool", **{**TRUE, "mass": -1.0}}, "payload.mass", "> 0"),
    ({"frame": "tool", **{**TRUE, "inertia": [1.0, 1.0, 3.0, 0, 0, 0]}}, "payload.inertia", "triangle"),
])
def test_a_bad_payload_is_refused_by_name(arm3_doc, tmp_path, payload, field, words):
    doc = holding(arm3_doc, {})
    doc["payload"] = payload
    path = tmp_path / "bad_payload.toml"
    path.write_text(to_toml(doc))
    with pytest.raises(ModelFileError, match=rf"bad_payload.toml: field '{field}'.*{words}"):
        rscasadi.load(path)


def test_payload_round_trips_and_enters_the_ocp(arm3_doc, tmp_path, pitch_arm):
    arm = rscasadi.Arm(parse(holding(arm3_doc, TRUE), "held.toml"))
    path = tmp_path / "held.toml"
    path.write_text(to_toml(document(arm.model)))
    again = rscasadi.load(path)
    a, b = again.model.payload, arm.model.payload
    assert a.frame == b.frame and a.body.mass == b.body.mass
    assert np.allclose(a.body.com, b.body.com, atol=1e-15) and np.allclose(a.body.inertia, b.body.inertia, atol=1e-15)
    from rscasadi.ocp import load_problem, solve_once
    from conftest import problem
    pitch = rscasadi.load(pitch_arm / "pitch.toml")
    doc = document(pitch.model)
    doc["frames"] = {"tool": {"parent": doc["joints"][0]["name"], "xyz": [0.3, 0.0, 0.0]}}
    doc["payload"] = {"frame": "tool", "mass": 0.5, "com": [0.0, 0.0, 0.0], "inertia": [1e-4, 1e-4, 1e-4, 0, 0, 0]}
    (pitch_arm / "pitch_held.toml").write_text(to_toml(doc))
    sols = {m: solve_once(load_problem(problem(pitch_arm, f"effort_{m}.toml", model=m,
                                               transcription={"intervals": 12})).replace(solver="ipopt"),
                          print_level=0, log=lambda s: None)
            for m in ("pitch.toml", "pitch_held.toml")}
    assert all(s.success for s in sols.values())
    assert sols["pitch_held.toml"].objective > 1.2 * sols["pitch.toml"].objective      # holding it costs effort


def test_identify_only_the_payload_from_a_short_log(arm3_doc, tmp_path):
    """The arm holds a payload the identifier is not told (TRUE), its model file a guess (GUESS);
    the paper's 2 s trajectory, recorded with the guess's feedforward and realistic sensors."""
    true = rscasadi.Arm(parse(holding(arm3_doc, TRUE), "true.toml"))
    model = tmp_path / "guess.toml"
    model.write_text(to_toml(holding(arm3_doc, GUESS)))
    guess = rscasadi.load(model)
    traj = load_trajectory(ROOT / "problems" / "trajectory_arm3.toml")
    for name, seed in (("hold.csv", 3), ("held_out.csv", 4)):
        log, _ = record(true, guess, traj, rng=np.random.default_rng(seed))
        write_log(tmp_path / name, log)
    out = tmp_path / "payload"
    assert main(["identify", str(model), str(tmp_path / "hold.csv"), "--only", "payload", "--out", str(out),
                 "--validate", str(tmp_path / "held_out.csv")]) in (0, None)
    rep = json.loads((out / "report.json").read_text())
    est = {p["name"]: p for p in rep["parameters"]}
    truth = dict(zip(names(true.model)[payload_slice(true.model)], body_parameters(true.model.payload.body)))
    for q in ("payload.mass", "payload.mx", "payload.my", "payload.mz"):        # what a 2 s motion determines
        e = est[q]
        assert e["std"] is not None and abs(e["estimate"] - truth[q]) < 4 * e["std"], (q, e, truth[q])
    assert abs(est["payload.mass"]["estimate"] - 1.6) < 0.01 * 1.6
    found = rscasadi.load(out / "model.toml").model.payload.body
    assert np.allclose(found.com, TRUE["com"], atol=3e-3) and found.mass == pytest.approx(1.6, rel=0.01)
    assert max(rep["validation"]["link_torque_relative_rms"]) < 0.02
    assert rep["fit_status"].startswith("converged")


def test_only_payload_needs_a_payload(tmp_path):
    log_path = tmp_path / "log.csv"
    log_path.write_text("t,theta_1,theta_2,theta_3,phi_1,phi_2,phi_3,tau_1,tau_2,tau_3\n"
                        + "".join(f"{k / 1000},0,0,0,0,0,0,0,0,0\n" for k in range(3000)))
    assert main(["identify", str(REFERENCE), str(log_path), "--only", "payload", "--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o").exists()
