"""Problems as Python objects: a Problem built in parts equals the one its TOML file gives, is
checked by the same rules (errors name the field), changes by field name, and its Solution
round-trips through JSON and replays to the same verification."""
import dataclasses

import numpy as np
import pytest

from rscasadi.model.modelfile import ModelFileError
from rscasadi.mpc import MPCProblem, load_mpc_problem
from rscasadi.ocp import (Problem, Solution, SolverOptions, Task, TranscriptionOptions, Verification, load_problem,
                          solve_once, verify)

from conftest import ROOT, problem

PROBLEMS = ROOT / "problems"


def test_a_problem_in_python_equals_its_file():
    built = Problem(Task(PROBLEMS / "arm3.toml", "min_effort", duration=1.5, theta_start=[0.0, 0.3, -0.5],
                         theta_end=[0.8, 0.9, -1.2]),
                    TranscriptionOptions(method="radau", degree=3, intervals=100, dynamics="explicit"),
                    SolverOptions(), Verification()).check()
    read = load_problem(PROBLEMS / "ocp_min_effort.toml")
    assert read.path is not None and built.path is None
    for part in ("transcription", "solver", "verification"):
        assert getattr(built, part) == getattr(read, part)
    a, b = dataclasses.asdict(built.task), dataclasses.asdict(read.task)
    for key in a:
        assert np.array_equal(a[key], b[key]) if isinstance(a[key], np.ndarray) else a[key] == b[key], key


def test_options_left_out_mean_what_the_file_leaves_out():
    """condense defaults to wherever it can be, in Python as in a file: not without compiled C."""
    task = Task(PROBLEMS / "arm3.toml", "min_effort", duration=1.5, theta_start=[0.0, 0.3, -0.5],
                theta_end=[0.8, 0.9, -1.2])
    assert Problem(task, TranscriptionOptions(compiled=False)).check().transcription.condense is False
    assert Problem(task, TranscriptionOptions()).check().transcription.condense is True


@pytest.mark.parametrize("change,field", [
    ({"objective": "fastest"}, "objective"),
    ({"intervals": 1}, "transcription.intervals"),
    ({"degree": 2.5}, "transcription.degree"),
    ({"method": "euler"}, "transcription.method"),
    ({"hessian": "limited-memory"}, "solver.hessian"),          # fatrop needs the exact Hessian
    ({"solver": "snopt"}, "solver.name"),
    ({"compiled": False}, "transcription.condense"),             # the kernel is C
    ({"duration": -1.0}, "duration"),
    ({"limit_tol": float("nan")}, "verification.limit_tol"),
    ({"theta_end": None}, "theta_end"),
    ({"design": {"elbow_pitch.sea.k1": (3000.0, 300.0)}}, "design.elbow_pitch.sea.k1"),
])
def test_the_objects_are_checked_by_the_files_rules(change, field):
    changed = load_problem(PROBLEMS / "ocp_min_effort.toml").replace(**change)
    with pytest.raises(ModelFileError, match=rf"ocp_min_effort.toml: field '{field}'"):
        changed.check()
    with pytest.raises(ModelFileError, match=rf"<Problem>: field '{field}'"):
        changed.replace(path=None).check()


def test_replace_by_name_and_by_part():
    base = load_problem(PROBLEMS / "ocp_min_time.toml")
    changed = base.replace(intervals=40, solver="ipopt", limit_tol=1e-2, theta_end=[0.1, 0.2, 0.3])
    assert changed.transcription.intervals == 40 and changed.solver.name == "ipopt"
    assert changed.verification.limit_tol == 1e-2 and changed.task.theta_end.tolist() == [0.1, 0.2, 0.3]
    assert base.transcription.intervals == 100 and base.solver.name == "fatrop"       # a copy
    assert base.replace(solver=SolverOptions(name="ipopt", hessian="limited-memory")).solver.hessian == "limited-memory"
    with pytest.raises(TypeError, match="no field 'colour'"):
        base.replace(colour="red")


def test_the_removed_barrier_rule_is_refused_by_name(pitch_arm):
    assert load_problem(problem(pitch_arm, "mono.toml", solver={"barrier": "monotone"})).solver.name == "fatrop"
    with pytest.raises(ModelFileError, match=r"field 'solver.barrier'.*adaptive rule was removed"):
        load_problem(problem(pitch_arm, "adaptive.toml", solver={"barrier": "adaptive"}))


def test_a_solution_round_trips_and_replays_alike(pitch_arm, tmp_path):
    p = load_problem(problem(pitch_arm, "sol.toml", transcription={"intervals": 12})).replace(solver="ipopt")
    sol = solve_once(p, print_level=0, log=lambda m: None)
    assert isinstance(sol, Solution) and sol.success
    assert sol.theta.shape == (1, 13) and sol.tau.shape == (1, 13) and sol.t[-1] == pytest.approx(1.0)
    sol.to_json(tmp_path / "solution.json")
    back = Solution.from_json(tmp_path / "solution.json")
    assert np.array_equal(back.theta, sol.theta) and back.status == sol.status
    assert back.verify() == verify(sol)
    back.plot(tmp_path)
    assert (tmp_path / "solution.png").stat().st_size > 10_000


def test_a_solution_is_a_read_only_record_that_says_what_it_claims(pitch_arm):
    """solve() returns a read-only Solution: solved (the solver), verified (the replay), success
    (both); sample() reads the replay on the complete model, which a coarse mesh follows only
    approximately and a refined one closely (an independent simulation, not the collocation)."""
    import copy
    import pickle
    from rscasadi.errors import InvalidArgument, WrongType
    from rscasadi.ocp import solve
    p = load_problem(problem(pitch_arm, "sol.toml", transcription={"intervals": 12})).replace(solver="ipopt")
    sol = solve(p, print_level=0, log=lambda m: None)
    assert sol.solved and sol.verified and sol.success and sol["verification"]["passed"]
    for change in (lambda s: s.__setitem__("success", False), lambda s: s.update(success=False),
                   lambda s: s.pop("success"), lambda s: s.setdefault("new", 1)):
        with pytest.raises(WrongType, match="read-only"):
            change(sol)
    assert sol.replace(status="edited")["status"] == "edited" and sol["status"] != "edited"
    assert pickle.loads(pickle.dumps(sol)) == sol and copy.deepcopy(sol) == sol
    unverified = solve_once(p, print_level=0, log=lambda m: None)
    assert unverified.solved and not unverified.verified and unverified.success == unverified.solved
    t = sol.t
    replayed = sol.sample("theta", t)
    assert replayed.shape == sol.theta.shape and np.max(np.abs(replayed - sol.theta)) < 1e-2
    assert np.max(np.abs(replayed[:, -1] - sol.theta[:, -1])) <= sol["verification"]["final_angle_error"] + 1e-12
    assert np.array_equal(sol.sample("tau", t[:-1] + 1e-9), sol.tau[:, :-1])     # held over each interval
    assert np.allclose(sol.sample("psi", t), sol.sample("phi", t) - replayed)
    with pytest.raises(InvalidArgument, match="quantity 'speed'"):
        sol.sample("speed", t)
    with pytest.raises(InvalidArgument, match="times must lie"):
        sol.sample("theta", [t[-1] + 1.0])


def test_an_mpc_problem_in_python_equals_its_file():
    read = load_mpc_problem(PROBLEMS / "mpc_arm3.toml")
    built = MPCProblem(read.model, read.trajectory, sample_time=read.sample_time, horizon=read.horizon,
                       interval=read.interval, substeps=read.substeps, sqp_iterations=read.sqp_iterations,
                       qp_iterations=read.qp_iterations, weights=dict(read.weights)).check()
    assert dataclasses.replace(built, path=read.path) == read
    with pytest.raises(ModelFileError, match=r"<MPCProblem>: field 'horizon'"):
        dataclasses.replace(built, horizon=0).check()
    with pytest.raises(ModelFileError, match=r"<MPCProblem>: field 'weights.speed'"):
        MPCProblem(read.model, weights={"speed": 1.0}).check()


def test_a_goal_in_python_as_the_file_writes_it():
    """Goal.from_rpy takes the file's roll-pitch-yaw (the constructor a rotation matrix): the same
    rotation as the [goal] table's."""
    import numpy as np
    from rscasadi.model.types import rpy_matrix
    from rscasadi.ocp.problem import Goal
    g = Goal.from_rpy("tool", [0.5, 0.0, 0.3], [0.1, -0.2, 0.3], position_tol=2e-3)
    assert np.array_equal(g.R, rpy_matrix(np.array([0.1, -0.2, 0.3]))) and g.position_tol == 2e-3
    assert Goal.from_rpy("tool", [0.5, 0.0, 0.3]).R is None


@pytest.mark.parametrize("value", ["all", True, "family "])
def test_parametric_is_one_option_of_one_type(value):
    """The problems take model.parameters.PROBLEM_PARAMETRIC ("none", "family"): the strings the
    generated libraries take ("all" too), never a bool; the field is named."""
    task = Task(PROBLEMS / "arm3.toml", "min_effort", duration=1.5, theta_start=[0.0, 0.3, -0.5],
                theta_end=[0.8, 0.9, -1.2])
    with pytest.raises(ModelFileError, match="'transcription.parametric': must be one of none, family"):
        Problem(task, TranscriptionOptions(parametric=value)).check()
    with pytest.raises(ModelFileError, match="'parametric': must be one of none, family"):
        MPCProblem(PROBLEMS / "arm3.toml", trajectory=PROBLEMS / "trajectory_arm3.toml", parametric=value).check()
