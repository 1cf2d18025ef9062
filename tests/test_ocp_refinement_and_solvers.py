"""Optimal control, second round: fatrop against IPOPT, mesh refinement driven by the replay,
implicit dynamics that converges like the explicit form, co-design of actuator parameters."""
import json

import numpy as np
import pytest

from rscasadi.cli import main
from rscasadi.ocp import load_problem, solve, solve_once, verify
from rscasadi.ocp.solving import local_errors
from rscasadi.dynamics.arm import Arm
from rscasadi.model.modelfile import ModelFileError
from rscasadi.model.parameters import with_values

from conftest import REFERENCE, problem, random_state

QUIET = {"print_level": 0, "log": lambda m: None}


@pytest.mark.parametrize("objective,over", [("min_effort", {}), ("min_time", {"max_duration": 5.0})])
def test_fatrop_and_ipopt_find_the_same_optimum(pitch_arm, objective, over):
    sols = {}
    for name in ("ipopt", "fatrop"):
        path = problem(pitch_arm, f"{name}_{objective}.toml", objective=objective, **over,
                       transcription={"intervals": 30}, solver={"name": name})
        sols[name] = solve_once(load_problem(path), **QUIET)
        assert sols[name]["success"] and sols[name]["status"] == "Solve_Succeeded", sols[name]["status"]
    a, b = sols["ipopt"], sols["fatrop"]
    assert abs(a["objective"] - b["objective"]) < 1e-6 * abs(a["objective"])
    assert np.max(np.abs(np.asarray(a["tau"]) - np.asarray(b["tau"]))) < 1e-3 * 0.6


def test_fatrop_is_chosen_from_the_command_line(pitch_arm, capsys):
    out = pitch_arm / "fatrop_cli"
    code = main(["ocp", str(problem(pitch_arm, "cli_f.toml", transcription={"intervals": 60})), "--out", str(out),
                 "--quiet", "--solver", "fatrop"])
    assert code == 0, capsys.readouterr().out
    assert json.loads((out / "solution.json").read_text())["solver"] == "fatrop"


def test_refinement_reaches_the_tolerance_where_one_mesh_does_not(pitch_arm):
    """A coarse mesh misses the tightened rest tolerance; refinement rounds add intervals where the
    local error is, warm-start, and pass; every round is recorded."""
    tight = {"final_angle_tol": 1e-6, "final_speed_tol": 1e-5}
    coarse = load_problem(problem(pitch_arm, "coarse.toml", transcription={"intervals": 12},
                                  verification=tight, refinement={"rounds": 0}))
    one = solve(coarse, **QUIET)
    assert one["solver_success"] and not one["success"] and not one["verification"]["passed"]
    refined = solve(coarse.replace(rounds=5), **QUIET)
    assert refined["success"] and refined["verification"]["passed"]
    rounds = refined["rounds"]
    assert len(rounds) >= 2 and rounds[0]["intervals"] == 12 and not rounds[0]["passed"] and rounds[-1]["passed"]
    assert all(b["intervals"] > a["intervals"] for a, b in zip(rounds, rounds[1:]))
    assert refined["intervals"] < 12 * 2 ** (len(rounds) - 1), "refined everywhere: not local"
    h = np.diff(refined["t"])
    assert h.max() / h.min() > 1.5                                     # a non-uniform mesh
    assert refined["verification"]["final_speed_error"] <= 1e-5
    # the replay that judged it is independent of the mesh bookkeeping: redo it on a finer grid
    again = verify(refined, substeps=50)
    assert again["final_speed_error"] <= 1e-5 and again["final_angle_error"] <= 1e-6
    # every interval of the refined mesh is within the tolerance on its own
    assert np.max(local_errors(coarse.replace(**tight), refined)) < 1.0


def test_rest_to_rest_default_tolerances_are_tight():
    p = load_problem(REFERENCE.parent / "ocp_min_effort.toml")
    assert p.verification.final_angle_tol == 1e-4 and p.verification.final_speed_tol == 1e-3


def test_a_miss_the_replay_places_is_refined_there_and_beside_it_only(pitch_arm):
    """When the replay fails only a check it places in intervals (a limit between two nodes, an
    obstacle's margin), the refinement halves those intervals and their neighbours, not the
    intervals that carry the local error (that mesh was accurate enough: its end state passed)."""
    from rscasadi.ocp.solving import refined_mesh
    p = load_problem(problem(pitch_arm, "located.toml", transcription={"intervals": 10}))
    w = np.full(10, 0.1)
    violation = np.zeros(10)
    violation[4] = 3 * p.verification.limit_tol
    report = {"max_limit_violation": float(violation.max()), "interval_violation": violation.tolist(),
              "min_clearance": 0.1, "interval_clearance": np.full(10, 0.1).tolist()}
    mesh = refined_mesh(p, {"mesh": w}, report)
    assert np.isclose(mesh.sum(), 1.0) and len(mesh) == 13
    assert np.allclose(mesh[:3], 0.1) and np.allclose(mesh[3:9], 0.05) and np.allclose(mesh[9:], 0.1)
    gap = np.full(10, 0.1)
    gap[0] = -10 * p.verification.clearance_tol                       # into the margin in the first interval
    report = {"max_limit_violation": 0.0, "interval_violation": np.zeros(10).tolist(),
              "min_clearance": float(gap.min()), "interval_clearance": gap.tolist()}
    mesh = refined_mesh(p, {"mesh": w}, report)
    assert len(mesh) == 12 and np.allclose(mesh[:4], 0.05) and np.allclose(mesh[4:], 0.1)
    from rscasadi.ocp.solving import failures                       # the URDF's own shapes, measured by coal
    report.update(min_clearance=0.1, interval_clearance=np.full(10, 0.1).tolist(),
                  urdf_min_clearance=float(gap.min()), interval_urdf_clearance=gap.tolist())
    assert list(failures(p, report)) == ["urdf_min_clearance"]
    mesh = refined_mesh(p, {"mesh": w}, report)
    assert len(mesh) == 12 and np.allclose(mesh[:4], 0.05) and np.allclose(mesh[4:], 0.1)


def test_min_effort_reference_problem_passes_after_refinement():
    """Problem (b) at 100 intervals ended with 6e-3 rad/s of SEA ringing; refined, it is at rest."""
    p = load_problem(REFERENCE.parent / "ocp_min_effort.toml").replace(compiled=False, condense=False)
    sol = solve(p, **QUIET)
    assert sol["success"], sol["rounds"]
    assert sol["rounds"][0]["final_speed_error"] > 1e-3 and len(sol["rounds"]) >= 2
    assert sol["verification"]["final_speed_error"] < 1e-3 and sol["verification"]["final_angle_error"] < 1e-4


@pytest.mark.parametrize("name", ["min_time", "tracking"])
def test_other_reference_problems_pass_the_tight_verification(name):
    sol = solve(load_problem(REFERENCE.parent / f"ocp_{name}.toml").replace(compiled=False, condense=False), **QUIET)
    assert sol["success"] and sol["verification"]["passed"], sol["rounds"]


def test_implicit_form_converges_like_the_explicit_one():
    base = load_problem(REFERENCE.parent / "ocp_min_effort.toml").replace(compiled=False, condense=False)
    it = {dyn: solve_once(base.replace(dynamics=dyn), **QUIET) for dyn in ("explicit", "implicit")}
    assert it["implicit"]["success"] and it["explicit"]["success"]
    assert it["implicit"]["iterations"] <= 1.5 * it["explicit"]["iterations"]
    assert abs(it["implicit"]["objective"] - it["explicit"]["objective"]) < 1e-6 * it["explicit"]["objective"]


def test_partially_free_parameters_equal_a_changed_model_file(arm3):
    """Arm(free=names) with values p equals the constant Functions of the model file with those
    values written in (a different route: new numbers, rotors and inertias rebuilt)."""
    names = ["shoulder_pitch.sea.k1", "elbow_pitch.sea.d", "elbow_pitch.link.mass", "shoulder_yaw.link.mz",
             "gravity.z"]
    values = [1500.0, 0.5, 1.7, 0.21, -9.5]
    rng = np.random.default_rng(5)
    for chosen in (names[:2], names):
        free = Arm(arm3.model, free=chosen)
        plain = Arm(with_values(arm3.model, dict(zip(chosen, values))))
        for _ in range(3):
            x, tau = random_state(rng, 3), rng.normal(size=3)
            a = np.vstack([np.array(v) for v in free.forward_dynamics(parametric=True)(*x, tau, values[:len(chosen)])])
            b = np.vstack([np.array(v) for v in plain.forward_dynamics()(*x, tau)])
            assert np.max(np.abs(a - b)) < 1e-10 * max(1.0, np.max(np.abs(b)))


def test_codesign_improves_on_the_nominal_arm_and_is_what_it_says(pitch_arm):
    """Minimum time with the spring stiffness free: no slower than the nominal arm; and the same
    problem with the spring *fixed* at the chosen value in the model file gives the same time."""
    path = problem(pitch_arm, "design.toml", objective="min_time", max_duration=5.0,
                   transcription={"intervals": 40}, design={"shoulder_pitch.sea.k1": [200.0, 5000.0]})
    sol = solve(load_problem(path), **QUIET)
    assert sol["success"], sol["rounds"]
    k = sol["design"]["shoulder_pitch.sea.k1"]
    assert 200.0 - 1e-6 <= k <= 5000.0 + 1e-6
    assert sol["t"][-1] <= sol["nominal"]["duration"] * (1 + 1e-6)
    # independent check: write k into a model file and solve the plain problem on the same mesh
    import tomllib
    from rscasadi.model.modelfile import to_toml
    with open(pitch_arm / "pitch.toml", "rb") as fh:
        d = tomllib.load(fh)
    d["joints"][0]["sea"]["k1"] = k
    (pitch_arm / "pitch_k.toml").write_text(to_toml(d))
    fixed = load_problem(problem(pitch_arm, "fixed_k.toml", model="pitch_k.toml", objective="min_time",
                                 max_duration=5.0, transcription={"intervals": sol["intervals"]}))
    ref = solve_once(fixed, w=sol["mesh"], warm=sol, **QUIET)
    assert ref["success"] and abs(ref["t"][-1] - sol["t"][-1]) < 1e-5 * sol["t"][-1]


def test_gear_ratio_codesign_keeps_the_motor_speed_limit_and_is_what_it_says(pitch_arm):
    """Minimum time with the gear ratio free: the motor's speed limit mu dphi stays (the slow
    side's dphi limit scales by mu_nominal / mu); the same problem on a model file with the chosen
    ratio *and* that scaled limit written in gives the same time."""
    import tomllib
    from rscasadi.model.modelfile import to_toml
    path = problem(pitch_arm, "gear.toml", objective="min_time", max_duration=5.0,
                   transcription={"intervals": 40}, design={"shoulder_pitch.gear_ratio": [30.0, 300.0]})
    sol = solve(load_problem(path), **QUIET)
    assert sol["success"], sol["rounds"]
    mu = sol["design"]["shoulder_pitch.gear_ratio"]
    assert 30.0 - 1e-6 <= mu <= 300.0 + 1e-6 and abs(mu - 100.0) > 1.0, "the ratio moved"
    assert sol["t"][-1] <= sol["nominal"]["duration"] * (1 + 1e-6)
    with open(pitch_arm / "pitch.toml", "rb") as fh:
        d = tomllib.load(fh)
    jt = d["joints"][0]
    dphi = jt["limits"]["dphi"] * jt["gear_ratio"] / mu
    speeds = np.abs(np.asarray(sol["dphi"][0]))
    assert speeds.max() <= dphi * (1 + 1e-6), "the scaled slow-side speed limit holds"
    jt["gear_ratio"], jt["limits"]["dphi"] = mu, dphi
    (pitch_arm / "pitch_mu.toml").write_text(to_toml(d))
    fixed = load_problem(problem(pitch_arm, "fixed_mu.toml", model="pitch_mu.toml", objective="min_time",
                                 max_duration=5.0, transcription={"intervals": sol["intervals"]}))
    ref = solve_once(fixed, w=sol["mesh"], warm=sol, **QUIET)
    assert ref["success"] and abs(ref["t"][-1] - sol["t"][-1]) < 1e-5 * sol["t"][-1]


@pytest.mark.parametrize("design,field", [
    ({"shoulder_pitch.sea.k1": [5.0, 1.0]}, "design.shoulder_pitch.sea.k1"),
    ({"shoulder_pitch.sea.k1": "stiff"}, "design.shoulder_pitch.sea.k1"),
])
def test_bad_design_table_names_the_field(pitch_arm, design, field):
    with pytest.raises(ModelFileError, match=rf"field '{field}'"):
        load_problem(problem(pitch_arm, "bad_design.toml", design=design))


@pytest.mark.parametrize("over,field", [
    ({"design": {"shoulder_pitch.gear_ratio": [0.0, 200.0]}}, "design.shoulder_pitch.gear_ratio"),
    ({"design": {"shoulder_pitch.gear_ratio": [-50.0, 200.0]}}, "design.shoulder_pitch.gear_ratio"),
])
def test_nonpositive_gear_ratio_bounds_are_refused_by_field(pitch_arm, over, field):
    p = load_problem(problem(pitch_arm, "bad_gear.toml", **over))
    with pytest.raises(ModelFileError, match=rf"bad_gear\.toml: field '{field}': a gear ratio stays positive"):
        solve_once(p, **QUIET)


def test_swept_nonpositive_gear_ratio_is_refused(pitch_arm):
    p = load_problem(problem(pitch_arm, "sweep_gear.toml")).replace(
                            parameters={"shoulder_pitch.gear_ratio": 0.0})
    with pytest.raises(ModelFileError, match=r"sweep_gear\.toml: parameter 'shoulder_pitch\.gear_ratio' = 0"):
        solve_once(p, **QUIET)


def test_unknown_design_parameter_is_named(pitch_arm):
    p = load_problem(problem(pitch_arm, "unknown_design.toml", design={"shoulder_pitch.sea.k9": [1.0, 2.0]}))
    with pytest.raises(ModelFileError, match=r"unknown_design\.toml.*'shoulder_pitch\.sea\.k9'"):
        solve_once(p, **QUIET)


def test_bad_solver_name_is_named(pitch_arm):
    with pytest.raises(ModelFileError, match=r"field 'solver\.name'"):
        load_problem(problem(pitch_arm, "bad_solver.toml", solver={"name": "snopt"}))


def test_codesign_writes_the_designed_arm_beside_its_solution(pitch_arm, tmp_path):
    """`rscasadi ocp` on a gear co-design: solution.json names designed_model.toml, a complete
    model file with the chosen ratio and the speed limit scaled as the test computes it; the
    plain problem on that file reproduces the optimum."""
    import json
    import tomllib
    import rscasadi
    from rscasadi.ocp import run
    path = problem(pitch_arm, "gear_out.toml", objective="min_time", max_duration=5.0,
                   transcription={"intervals": 40}, design={"shoulder_pitch.gear_ratio": [30.0, 300.0]})
    sol = run(path, tmp_path / "out", print_level=0, log=lambda m: None)
    assert sol["success"] and json.loads((tmp_path / "out" / "solution.json").read_text())["designed_model"] \
        == "designed_model.toml"
    designed = rscasadi.load(tmp_path / "out" / "designed_model.toml").model.joints[0]
    with open(pitch_arm / "pitch.toml", "rb") as fh:
        nominal = tomllib.load(fh)["joints"][0]
    mu = sol["design"]["shoulder_pitch.gear_ratio"]
    assert abs(designed.gear_ratio - mu) < 1e-9 * mu
    assert abs(designed.limits["dphi"] - nominal["limits"]["dphi"] * nominal["gear_ratio"] / mu) < 1e-9
    fixed = load_problem(problem(tmp_path / "out", "plain.toml", model="designed_model.toml", objective="min_time",
                                 max_duration=5.0, transcription={"intervals": sol["intervals"]}))
    ref = solve_once(fixed, w=sol["mesh"], warm=sol, **QUIET)
    assert ref["success"] and abs(ref["t"][-1] - sol["t"][-1]) < 1e-5 * sol["t"][-1]


def test_a_limit_margin_keeps_the_motion_between_the_nodes_inside(tmp_path):
    """The reference arm's minimum-time motion rides its speed limits: on 30 intervals the replay
    passes a limit between the collocation points (by 4.8e-3 of it, more than limit_tol); with
    limit_margin = 0.01 held in reserve at the points it stays inside, for about 1 % more time."""
    sols = {}
    for margin in (0.0, 0.01):
        path = tmp_path / f"margin_{margin}.toml"
        path.write_text(f"""model = "{REFERENCE}"
objective = "min_time"
theta_start = [0.0, 0.3, -0.5]
theta_end = [0.8, 0.9, -1.2]
duration = 1.0
max_duration = 5.0
[transcription]
intervals = 30
compiled = false
condense = false
limit_margin = {margin}
""")
        p = load_problem(path)
        sol = solve_once(p, **QUIET)
        assert sol["success"], sol["status"]
        sols[margin] = (sol, verify(sol))
    (plain, plain_replay), (kept, kept_replay) = sols[0.0], sols[0.01]
    assert plain_replay["max_limit_violation"] > 1e-3
    assert kept_replay["max_limit_violation"] <= 1e-6
    assert 1.0 <= kept["t"][-1] / plain["t"][-1] < 1.02
