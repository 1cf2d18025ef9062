"""Tasks stated for a frame: a Cartesian goal in the OCP, reached at rest in a configuration the
solver chooses, checked on the replay; every [goal] field refused by name."""
import numpy as np
import pytest

import rscasadi
from rscasadi import ModelFileError
from rscasadi.model.modelfile import document, to_toml
from rscasadi.ocp import (Problem, SolverOptions, Task, TranscriptionOptions, Verification, load_problem, run,
                          solve)
from rscasadi.ocp.problem import Goal

from conftest import REFERENCE, ROOT


@pytest.fixture(scope="module")
def tool_arm(tmp_path_factory):
    d = tmp_path_factory.mktemp("tool_arm")
    doc = document(rscasadi.load(REFERENCE).model)
    doc["frames"] = {"tool": {"parent": "elbow_pitch", "xyz": [0.3, 0.0, 0.0]}}
    (d / "arm3_tool.toml").write_text(to_toml(doc))
    return d


def goal_problem(d, name="reach.toml", **goal):
    text = ('model = "arm3_tool.toml"\nobjective = "min_time"\ntheta_start = [0.0, 0.3, -0.5]\nduration = 1.0\n'
            '[transcription]\nintervals = 40\n[goal]\n'
            + "".join(f"{k} = {v}\n" for k, v in goal.items()))
    (d / name).write_text(text)
    return d / name


def test_minimum_time_to_a_position_reached_at_rest(tool_arm, tmp_path):
    arm = rscasadi.load(tool_arm / "arm3_tool.toml")
    target = np.array(arm.frame_placement("tool")(np.array([0.8, 0.9, -1.2]))[1]).ravel() + [0.0, 0.03, 0.0]
    path = goal_problem(tool_arm, frame='"tool"', position=str([round(float(v), 6) for v in target]), tolerance="{ position = 1e-4 }")
    sol = run(path, tmp_path / "out", print_level=0, log=lambda m: None)
    report = sol["verification"]
    assert sol.success and report["passed"] and report["goal_position_error"] < 1e-4
    theta_end = sol.theta[:, -1]
    p_end = np.array(arm.frame_placement("tool")(theta_end)[1]).ravel()
    assert np.linalg.norm(p_end - target) < 1e-6                       # the collocation's end, on the model
    assert np.max(np.abs(sol.dtheta[:, -1])) < 1e-6 and np.max(np.abs(sol.dphi[:, -1])) < 1e-6
    lo, hi = (np.array([jt.limits["theta"][i] for jt in arm.model.joints]) for i in (0, 1))
    assert np.all(theta_end >= lo) and np.all(theta_end <= hi)
    assert sol["goal"]["frame"] == "tool" and (tmp_path / "out" / "solution.json").exists()


def test_a_pose_on_a_six_joint_arm(tmp_path):
    """The UR5: position and orientation of tool0, one round of 12 intervals (the collocation
    meets the pose exactly; the replay within millimetres)."""
    arm = rscasadi.load(ROOT / "problems" / "ur5_sea.toml")
    th0 = np.array([0.0, -1.2, 1.2, -1.5, -1.5, 0.0])
    R, p = (np.array(v) for v in arm.frame_placement("tool0")(th0 + [0.4, 0.2, -0.2, 0.3, 0.2, 0.4]))
    problem = Problem(Task(ROOT / "problems" / "ur5_sea.toml", "min_effort", duration=2.0, theta_start=th0,
                           goal=Goal("tool0", p.ravel(), R, position_tol=5e-3, angle_tol=5e-3)),
                      TranscriptionOptions(intervals=12, compiled=False, condense=False), SolverOptions(name="ipopt"),
                      Verification(rounds=0))
    sol = solve(problem, print_level=0, log=lambda m: None)
    assert sol["solver_success"]
    R_end, p_end = (np.array(v) for v in arm.frame_placement("tool0")(sol.theta[:, -1]))
    assert np.linalg.norm(p_end.ravel() - p.ravel()) < 1e-6 and np.allclose(R_end, R, atol=1e-6)
    assert sol["verification"]["goal_position_error"] < 5e-3 and sol["verification"]["goal_angle_error"] < 5e-3


@pytest.mark.parametrize("goal,field,words", [
    ({"position": "[0.3, 0.2, 0.4]"}, "goal.frame", "missing"),
    ({"frame": '"tool"'}, "goal.position", "missing"),
    ({"frame": '"tool"', "position": "[0.3, 0.2]"}, "goal.position", "3 numbers"),
    ({"frame": '"tool"', "position": "[0.3, 0.2, 0.4]", "colour": "1"}, "goal.colour", "unknown key"),
    ({"frame": '"tool"', "position": "[0.3, 0.2, 0.4]", "tolerance": "{ position = -1.0 }"}, "goal.tolerance.position",
     "positive"),
    ({"frame": '"tool"', "position": "[0.3, 0.2, 0.4]", "tolerance": "{ speed = 1.0 }"}, "goal.tolerance", "expected"),
])
def test_a_bad_goal_is_refused_by_name(tool_arm, goal, field, words):
    with pytest.raises(ModelFileError, match=rf"bad_goal.toml: field '{field}'.*{words}"):
        load_problem(goal_problem(tool_arm, "bad_goal.toml", **goal))


def test_goals_the_arm_cannot_meet_are_refused_before_solving(tool_arm):
    base = load_problem(goal_problem(tool_arm, "ok.toml", frame='"tool"', position="[0.3, 0.2, 0.4]"))
    with pytest.raises(ModelFileError, match="field 'goal.frame'.*no frame 'hand'"):
        solve(base.replace(goal=Goal("hand", [0.3, 0.2, 0.4])), print_level=0, log=lambda m: None)
    with pytest.raises(ModelFileError, match="field 'goal'.*6 conditions, more than the 3 joints"):
        solve(base.replace(goal=Goal("tool", [0.3, 0.2, 0.4], np.eye(3))), print_level=0, log=lambda m: None)
    with pytest.raises(ModelFileError, match="field 'goal'.*cannot reach it"):
        solve(base.replace(goal=Goal("tool", [3.0, 0.0, 0.4])), print_level=0, log=lambda m: None)
    with pytest.raises(ModelFileError, match="field 'goal'.*theta_end or a goal, not both"):
        base.replace(theta_end=[0.1, 0.2, 0.3]).check()
