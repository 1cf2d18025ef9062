"""Optimal control: problem files, transcriptions, honest verification, the `ocp` command."""
import json

import numpy as np
import pytest

from rscasadi.cli import main
from rscasadi.model.modelfile import ModelFileError
from rscasadi.ocp import load_problem, rest_state, solve, verify

from conftest import problem, to_toml


@pytest.mark.parametrize("over,field", [
    ({"objective": "fastest"}, "objective"),
    ({"duration": -1.0}, "duration"),
    ({"theta_end": "far"}, "theta_end"),
    ({"colour": 1}, "colour"),
    ({"transcription": {"method": "euler"}}, "transcription.method"),
    ({"transcription": {"degree": 0}}, "transcription.degree"),
    ({"transcription": {"dynamics": "magic"}}, "transcription.dynamics"),
    ({"transcription": {"knots": 3}}, "transcription.knots"),
    ({"transcription": {"limit_margin": 0.5}}, "transcription.limit_margin"),
    ({"transcription": {"limit_margin": -0.01}}, "transcription.limit_margin"),
])
def test_bad_problem_file_names_the_field(pitch_arm, over, field):
    path = problem(pitch_arm, "bad.toml", **over)
    with pytest.raises(ModelFileError, match=rf"bad\.toml: field '{field}'"):
        load_problem(path)


def test_min_effort_solves_and_passes_the_independent_replay(pitch_arm):
    sol = solve(load_problem(problem(pitch_arm, transcription={"intervals": 60})), print_level=0, log=lambda m: None)
    assert sol["success"] and sol["status"] == "Solve_Succeeded"
    report = verify(sol)
    assert report["final_angle_error"] < 1e-3 and report["final_speed_error"] < 1e-2
    assert report["max_limit_violation"] <= 1e-3
    t, tau = np.asarray(sol["t"]), np.asarray(sol["tau"])
    assert np.isclose(sol["objective"], np.sum(np.diff(t) * tau[0, :-1] ** 2), rtol=1e-9)


@pytest.mark.parametrize("method,dynamics", [("legendre", "explicit"), ("hermite-simpson", "explicit"),
                                             ("radau", "implicit")])
def test_transcriptions_agree(pitch_arm, method, dynamics):
    ref = solve(load_problem(problem(pitch_arm, "r.toml", transcription={"intervals": 60})), print_level=0,
                log=lambda m: None)
    tr = {"method": method, "dynamics": dynamics, "intervals": 120 if method == "hermite-simpson" else 60}
    sol = solve(load_problem(problem(pitch_arm, "o.toml", transcription=tr)), print_level=0, log=lambda m: None)
    assert sol["success"]
    assert abs(sol["objective"] - ref["objective"]) < 0.03 * ref["objective"]


def test_min_time_respects_the_torque_limit(pitch_arm):
    sol = solve(load_problem(problem(pitch_arm, objective="min_time", max_duration=5.0,
                                     transcription={"intervals": 50})), print_level=0, log=lambda m: None)
    assert sol["success"]
    tau = np.asarray(sol["tau"])
    assert np.max(np.abs(tau)) <= 0.6 + 1e-6
    assert np.max(np.abs(tau)) > 0.55, "a minimum-time solution uses the torque limit"
    assert sol["t"][-1] < 1.0
    report = verify(sol)                  # bang-bang torques replayed exactly, switch by switch
    assert report["final_angle_error"] < 1e-5 and report["max_collocation_deviation"] < 1e-5


def test_infeasible_limits_fail_loudly(pitch_arm, capsys):
    path = problem(pitch_arm, "inf.toml", objective="min_time", max_duration=0.05, transcription={"intervals": 20})
    out = pitch_arm / "inf_out"
    code = main(["ocp", str(path), "--out", str(out), "--quiet"])
    text = capsys.readouterr().out
    assert code == 1 and "FAILED" in text
    sol = json.loads((out / "solution.json").read_text())
    assert sol["success"] is False and sol["status"] != "Solve_Succeeded"


def test_a_pose_the_arm_cannot_rest_in_is_named_before_the_solve(pitch_arm):
    """A rest-to-rest task whose end (or start) needs more motor torque to hold than the joint has
    (here its limit between the holding torques at 0.9 and 0.2 rad): refused
    before anything is built, naming the file, the field, the joint and both torques."""
    import tomllib
    from rscasadi.dynamics.arm import Arm
    from rscasadi.dynamics.statics import holding_torque
    from rscasadi.model.modelfile import read
    arm = Arm(read(pitch_arm / "pitch.toml"))
    hold = lambda th: abs(float(holding_torque(arm)(*np.split(rest_state(arm, [th])[:2], 2))))   # noqa: E731
    assert hold(0.9) < hold(0.2)
    with open(pitch_arm / "pitch.toml", "rb") as fh:
        doc = tomllib.load(fh)
    doc["joints"][0]["limits"]["tau"] = (hold(0.2) + hold(0.9)) / 2
    (pitch_arm / "weak.toml").write_text(to_toml(doc))
    name = doc["joints"][0]["name"]
    path = problem(pitch_arm, "weak_end.toml", model="weak.toml", theta_start=[0.9], theta_end=[0.2])
    with pytest.raises(ModelFileError, match=rf"weak_end.toml: field 'theta_end': the arm cannot rest there: joint "
                                             rf"'{name}' needs {hold(0.2):.3g} N m at its motor to hold it"):
        solve(load_problem(path), log=lambda m: None)
    path = problem(pitch_arm, "weak_start.toml", model="weak.toml")
    with pytest.raises(ModelFileError, match=r"weak_start.toml: field 'theta_start': the arm cannot rest there"):
        solve(load_problem(path), log=lambda m: None)


def test_ocp_command_writes_solution_and_plots(pitch_arm, capsys):
    out = pitch_arm / "out"
    code = main(["ocp", str(problem(pitch_arm, "cli.toml", transcription={"intervals": 60})), "--out", str(out), "--quiet"])
    assert code == 0, capsys.readouterr().out
    sol = json.loads((out / "solution.json").read_text())
    assert set(sol) >= {"model", "status", "success", "solve_time_s", "iterations", "objective", "t", "theta",
                        "phi", "dtheta", "dphi", "tau", "tau_interpolation"}
    assert sol["tau_interpolation"] == "constant" and sol["verification"]["passed"]
    assert len(sol["theta"]) == 1 and len(sol["theta"][0]) == len(sol["t"]) == 61
    assert (out / "solution.png").exists()
    # warm start from it: converges in fewer iterations
    code = main(["ocp", str(problem(pitch_arm, "cli.toml", transcription={"intervals": 60})), "--out", str(out),
                 "--warm", str(out / "solution.json"), "--quiet"])
    warm = json.loads((out / "solution.json").read_text())
    assert code == 0 and warm["iterations"] < sol["iterations"]


def test_bad_problem_file_exit_code(tmp_path, capsys):
    f = tmp_path / "x.toml"
    f.write_text('model = "m.toml"\nobjective = "min_effort"\n')
    assert main(["ocp", str(f), "--out", str(tmp_path / "o")]) == 2
    assert "field 'duration'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_compiled_nlp_equals_vm_and_is_cached(pitch_arm, tmp_path, monkeypatch):
    import rscasadi.ocp.condensing as condensing
    monkeypatch.setenv("RSCASADI_CACHE", str(tmp_path / "cache"))     # empty: the first solve compiles;
    monkeypatch.setattr(condensing, "_KERNELS", {})                     # the kernels it loads stay with it
    path = problem(pitch_arm, "c.toml", transcription={"intervals": 30, "compiled": True})
    first, again = [], []
    a = solve(load_problem(path), print_level=0, log=first.append)
    b = solve(load_problem(path), print_level=0, log=again.append)
    vm = solve(load_problem(problem(pitch_arm, "v.toml", transcription={"intervals": 30})), print_level=0,
               log=lambda m: None)
    assert a["success"] and b["success"] and vm["success"]
    assert abs(a["objective"] - vm["objective"]) < 1e-8 * vm["objective"]
    # the first solve compiles (the condensing kernel, the end pieces); the second finds them all
    assert any(m.startswith("compiled the condensing kernel") for m in first)
    assert not any(m.startswith("compiling") for m in again), again


def test_large_nlp_c_compiles_at_o0_unless_told(monkeypatch):
    """An OCP's compiled functions: -O1 up to a megabyte of C, -O0 above (gcc's -O1 passes grow
    faster than the code), RSCASADI_NLP_OPT over both; the cache keys say "auto" until the size
    decides, so a level chosen by size and one chosen by the user never share a library."""
    from rscasadi.native.build import LARGE_C, nlp_opt
    monkeypatch.delenv("RSCASADI_NLP_OPT", raising=False)
    assert (nlp_opt(), nlp_opt(LARGE_C), nlp_opt(LARGE_C + 1)) == ("auto", "-O1", "-O0")
    monkeypatch.setenv("RSCASADI_NLP_OPT", "-O2")
    assert (nlp_opt(), nlp_opt(10), nlp_opt(10 * LARGE_C)) == ("-O2",) * 3


def test_a_failed_fatrop_solve_falls_back_to_ipopt_and_says_so(pitch_arm):
    path = problem(pitch_arm, "fallback.toml", transcription={"intervals": 20, "compiled": True})
    logs = []
    sol = solve(load_problem(path), print_level=0, log=logs.append, options={"max_iter": 1})   # fatrop's only
    # kept to the end, through the refinement rounds that follow (IPOPT's): it had been lost there
    assert sol["fallback_from"] == {"solver": "fatrop", "round": 0, "iterations": 2,
                                    "status": "Maximum_Iterations_Exceeded (fatrop return flag 1)"}
    assert sol["solver"] == "ipopt" and sol["status"] == "Solve_Succeeded" and sol["success"]
    assert len(sol["rounds"]) > 1 and {r["solver"] for r in sol["rounds"]} == {"ipopt"}
    assert any("solving again with IPOPT" in m for m in logs)


def test_tracking_ocp_follows_the_trajectory_between_nodes(pitch_arm):
    (pitch_arm / "traj.toml").write_text('model = "pitch.toml"\nperiod = 1.0\nduration = 1.0\n'
                                         'start = [0.3]\namplitude = [0.6]\n')
    # effort weight 1e-8 on one joint: fatrop (the default) cannot reach tol 1e-8 (its dual
    # infeasibility floors near 1.5e-8) and stops at an acceptable point, which counts as IPOPT's
    # acceptable level does; the replay is the judge
    path = problem(pitch_arm, "track.toml", objective="tracking", trajectory="traj.toml", effort_weight=1e-8,
                   transcription={"intervals": 100})
    sol = solve(load_problem(path), print_level=0, log=lambda m: None)
    report = verify(sol)
    assert sol["solver"] == "fatrop" and "fallback_from" not in sol
    assert sol["status"].startswith("Solved_To_Acceptable_Level"), sol["status"]
    assert sol["success"] and sol["trajectory"].endswith("traj.toml")
    assert report["tracking_error"] < 1e-4                  # on the fine replay grid, not only at nodes


def test_a_new_process_finds_the_kernel_without_building_its_derivatives(pitch_arm, monkeypatch):
    """The condensing kernel is indexed by the stage's key in the cache: a process that has never
    built it (this one, forgetting) solves without the symbolic derivatives, to the same iterates."""
    import rscasadi.ocp.condensing as condensing
    import rscasadi.ocp.transcription as transcription
    path = problem(pitch_arm, "kernel_index.toml", transcription={"intervals": 20, "compiled": True})
    a = solve(load_problem(path), print_level=0, log=lambda m: None)
    monkeypatch.setattr(condensing, "_KERNELS", {})
    monkeypatch.setattr(transcription, "_DERIVATIVES", {})

    def refuse(*args, **kwargs):
        raise AssertionError("the stage's derivatives were built again")
    monkeypatch.setattr(transcription, "chain_rule_derivatives", refuse)
    b = solve(load_problem(path), print_level=0, log=lambda m: None)
    assert a["success"] and b["success"] and b["iterations"] == a["iterations"]
    assert abs(b["objective"] - a["objective"]) <= 1e-12 * abs(a["objective"])


def test_a_second_run_of_the_same_problem_starts_from_its_verified_solution(pitch_arm, capsys):
    """A coarse problem the replay sends through refinement rounds: run again (the cache holds its
    verified solution), it starts on the refined mesh from that solution and passes in one round,
    to the same objective; a changed problem, or --cold, starts from its own guess."""
    path = problem(pitch_arm, "reuse.toml", transcription={"intervals": 6},
                   verification={"final_angle_tol": 1e-5, "final_speed_tol": 3e-4})
    out = pitch_arm / "reuse"
    assert main(["ocp", str(path), "--out", str(out), "--quiet", "--cold"]) == 0     # kept, though cold
    first = json.loads((out / "solution.json").read_text())
    assert len(first["rounds"]) >= 2 and "starting from the verified solution" not in capsys.readouterr().out
    assert main(["ocp", str(path), "--out", str(out), "--quiet"]) == 0
    again = json.loads((out / "solution.json").read_text())
    said = capsys.readouterr().out
    assert "starting from the verified solution of the same problem" in said
    assert len(again["rounds"]) == 1 and again["success"] and len(again["t"]) == len(first["t"])
    assert again["objective"] == pytest.approx(first["objective"], rel=1e-6)
    assert main(["ocp", str(path), "--out", str(out), "--quiet", "--cold"]) == 0
    cold = json.loads((out / "solution.json").read_text())
    assert "starting from" not in capsys.readouterr().out and len(cold["rounds"]) == len(first["rounds"])
    other = problem(pitch_arm, "reuse2.toml", transcription={"intervals": 6}, theta_end=[0.8],
                    verification={"final_angle_tol": 1e-5, "final_speed_tol": 3e-4})
    assert main(["ocp", str(other), "--out", str(pitch_arm / "other"), "--quiet"]) == 0
    assert "starting from" not in capsys.readouterr().out
