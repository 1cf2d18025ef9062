"""Tasks stated for a frame: a Cartesian goal in the OCP, reached at rest in a configuration the
solver chooses, checked on the replay; every [goal] field refused by name."""
import re

import numpy as np
import pytest

import rscasadi
from rscasadi import ModelFileError
from rscasadi.model.modelfile import document, to_toml
from rscasadi.ocp import (Problem, SolverOptions, Task, TranscriptionOptions, Verification, load_problem, run,
                          solve)
from rscasadi.ocp.problem import Goal
from rscasadi.ocp.solution import solution_arm
from rscasadi.sim.simulation import simulate_held

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


def test_no_goal_row_meets_its_bound_at_the_goal_with_a_zero_gradient():
    """At rest at a pose goal, every end row that meets a bound has a gradient: an active row
    without one (trace(R_goal^T R) <= 3 is met at the goal with a zero gradient) leaves its
    multiplier unbounded, and the interior point follows it away (Baxter's obstacle task: the
    trace row's multiplier at 906 after 20 iterations, five restorations, 122 iterations
    instead of 53)."""
    import casadi as ca
    from rscasadi.dynamics.arm import Arm
    from rscasadi.dynamics.statics import rest_state
    from rscasadi.ocp.transcription import Transcription
    arm = rscasadi.load(ROOT / "problems" / "ur5_sea.toml")
    th0 = np.array([0.0, -1.2, 1.2, -1.5, -1.5, 0.0])
    th_goal = th0 + [0.4, 0.2, -0.2, 0.3, 0.2, 0.4]
    R, p = (np.array(v) for v in arm.frame_placement("tool0")(th_goal))
    problem = Problem(Task(ROOT / "problems" / "ur5_sea.toml", "min_time", duration=1.0, theta_start=th0,
                           goal=Goal("tool0", p.ravel(), R)), TranscriptionOptions(intervals=4, compiled=False, condense=False))
    tr = Transcription(problem, Arm(arm.model), N=4)
    end = tr._boundary_piece(end=True)
    x = ca.SX.sym("x", tr.nx)
    goal = ca.DM(np.r_[p.ravel(), R.ravel(order="F")])
    rows = end(x, goal, ca.DM.zeros(tr.n_pfix), 1.0)[0]
    at = np.r_[rest_state(arm, th_goal), 0.5]                          # at rest at the goal, T = 0.5 s
    value = np.array(ca.Function("r", [x], [rows])(at)).ravel()
    gradient = np.array(ca.Function("J", [x], [ca.jacobian(rows, x)])(at))
    lo, hi = tr._end_bounds()
    meets = (np.isfinite(lo) & (np.abs(value - lo) < 1e-9)) | (np.isfinite(hi) & (np.abs(value - hi) < 1e-9))
    assert meets.sum() >= 4 * arm.n                                    # the rest and pose rows at least
    assert np.all(np.linalg.norm(gradient[meets], axis=1) > 1e-6), np.nonzero(meets & (np.linalg.norm(gradient, axis=1) <= 1e-6))


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


# ----------------------------------------------------------------------------- obstacles

@pytest.fixture(scope="module")
def capsule_arm(tmp_path_factory):
    d = tmp_path_factory.mktemp("capsules")
    doc = document(rscasadi.load(REFERENCE).model)
    doc["frames"] = {"tool": {"parent": "elbow_pitch", "xyz": [0.3, 0.0, 0.0]}}
    doc["collision"] = {"margin": 0.01, "tip": "tool", "links": {"shoulder_pitch": 0.04, "elbow_pitch": 0.03}}
    (d / "arm3_capsules.toml").write_text(to_toml(doc))
    return d / "arm3_capsules.toml"


def test_minimum_time_around_an_obstacle_keeps_its_margin(capsule_arm, tmp_path):
    """A sphere where the tool would pass halfway on the straight line between the poses: the
    replay, sampled between the nodes, keeps the margin (exact distances of the capsules)."""
    from rscasadi.dynamics.collision import exact_clearance
    from rscasadi.ocp.problem import Obstacle
    arm = rscasadi.load(capsule_arm)
    th0, th1 = np.array([0.0, 0.3, -0.5]), np.array([0.8, 0.9, -1.2])
    obstacle = Obstacle("sphere", np.array(arm.frame_placement("tool")((th0 + th1) / 2)[1]).ravel(), 0.05)
    gap = exact_clearance(arm.model, [obstacle])
    assert float(gap((th0 + th1) / 2)) < -0.05                          # the straight line runs into it
    # the motion rides the speed limits (a margin); fatrop's line search fails here (its fallback
    # to IPOPT: tests/test_ocp.py)
    sol = solve(Problem(Task(capsule_arm, "min_time", duration=1.0, theta_start=th0, theta_end=th1,
                             obstacles=(obstacle,)), TranscriptionOptions(intervals=40, limit_margin=0.01),
                        SolverOptions(name="ipopt")), print_level=0, log=lambda m: None)
    assert sol.success and sol["verification"]["passed"]
    assert 0.0 <= sol["verification"]["min_clearance"] < 0.01          # it passes close, outside the margin
    assert all(float(gap(th)) >= -1e-9 for th in sol.theta.T)         # at the nodes too, exactly


def test_the_guess_around_an_obstacle_moves_from_rest_to_rest(capsule_arm):
    """The first guess around an obstacle follows the clear path from the start pose to the end
    pose at rest at both ends, as the start and end rows ask: no speed at the first and last
    nodes, the fastest between them."""
    from rscasadi.ocp.problem import Obstacle
    from rscasadi.ocp.solving import _around_obstacles
    arm = rscasadi.load(capsule_arm)
    th0, th1 = np.array([0.0, 0.3, -0.5]), np.array([0.8, 0.9, -1.2])
    obstacle = Obstacle("sphere", np.array(arm.frame_placement("tool")((th0 + th1) / 2)[1]).ravel(), 0.05)
    task = Problem(Task(capsule_arm, "min_time", duration=1.0, theta_start=th0, theta_end=th1, obstacles=(obstacle,)),
                   TranscriptionOptions(intervals=40))
    t = np.linspace(0.0, 1.0, 41)
    Xs, _, U = _around_obstacles(task, arm, t, (t[:-1] + t[1:]) / 2)
    n = arm.n
    assert np.allclose(Xs[:n, 0], th0) and np.allclose(Xs[:n, -1], th1)
    speed = np.abs(Xs[2 * n:]).max(axis=0)
    assert speed.max() > 0.5 and speed[0] < 0.01 * speed.max() and speed[-1] < 0.01 * speed.max()
    assert speed.argmax() not in (0, len(t) - 1) and U.shape == (n, 40) and np.all(np.isfinite(U))


def test_the_box_distance_is_conservative_and_close():
    """The optimiser's smooth distance to a box never exceeds the exact one outside the box and
    is <= 0 inside (so a positive clearance for the optimiser is a true one), and is within a
    millimetre of the exact one outside."""
    from rscasadi.dynamics import collision as C
    from rscasadi.ocp.problem import Obstacle
    box = Obstacle("box", [0.5, 0.0, -0.01], size=[1.0, 1.0, 0.02])
    rng = np.random.default_rng(1)
    import casadi as ca
    p = ca.SX.sym("p", 3)
    smooth = ca.Function("s", [p], [C._sphere_distance(p, 0.0, box)])
    exact = ca.Function("e", [p], [C._exact_distance(p, box)])
    for point in rng.uniform([-0.5, -1.0, -0.3], [1.5, 1.0, 0.4], (200, 3)):
        s, e = float(smooth(point)), float(exact(point))
        assert s <= max(e, 0.0) + 1e-12
        if e > 0.002:
            assert e - s < 1e-3


@pytest.mark.parametrize("collision,field,words", [
    ({"links": {"nowhere": 0.05}, "tip": "tool"}, "collision.links.nowhere", "no frame"),
    ({"links": {"base": 0.05}}, "collision.links.base", "fixed base"),
    ({"links": {"elbow_pitch": -0.05}, "tip": "tool"}, "collision.links.elbow_pitch", "> 0"),
    ({"links": {"elbow_pitch": 0.05}}, "collision.tip", "needs the frame"),
    ({"links": {"shoulder_pitch": 0.05}, "margin": -1.0}, "collision.margin", ">= 0"),
])
def test_bad_collision_geometry_is_refused_by_name(tmp_path, collision, field, words):
    doc = document(rscasadi.load(REFERENCE).model)
    doc["frames"] = {"tool": {"parent": "elbow_pitch", "xyz": [0.3, 0.0, 0.0]}}
    doc["collision"] = collision
    (tmp_path / "bad_collision.toml").write_text(to_toml(doc))
    with pytest.raises(ModelFileError, match=rf"bad_collision.toml: field '{field}'.*{words}"):
        rscasadi.load(tmp_path / "bad_collision.toml")


@pytest.mark.parametrize("obstacles,field,words", [
    ('[[obstacles]]\ncone = { center = [0, 0, 0] }\n', "obstacles[0]", "sphere = "),
    ('[[obstacles]]\nsphere = { center = [0, 0, 0] }\n', "obstacles[0].sphere", "the keys"),
    ('[[obstacles]]\nsphere = { center = [0, 0], radius = 0.1 }\n', "obstacles[0].sphere.center", "3 numbers"),
    ('[[obstacles]]\nbox = { center = [0, 0, 0], size = [1, -1, 1] }\n', "obstacles[0].box.size[1]", "positive"),
])
def test_bad_obstacles_are_refused_by_name(tool_arm, obstacles, field, words):
    path = tool_arm / "bad_obstacles.toml"
    path.write_text('model = "arm3_tool.toml"\nobjective = "min_time"\ntheta_start = [0.0, 0.3, -0.5]\n'
                    'theta_end = [0.8, 0.9, -1.2]\nduration = 1.0\n' + obstacles)
    with pytest.raises(ModelFileError, match=rf"bad_obstacles.toml: field .{re.escape(field)}.*{words}"):
        load_problem(path)


def test_obstacles_need_the_arms_capsules(tool_arm):
    from rscasadi.ocp.problem import Obstacle
    problem = Problem(Task(tool_arm / "arm3_tool.toml", "min_time", duration=1.0, theta_start=[0.0, 0.3, -0.5],
                           theta_end=[0.8, 0.9, -1.2], obstacles=(Obstacle("sphere", [0.3, 0.2, 0.4], 0.05),)))
    with pytest.raises(ModelFileError, match="field 'obstacles'.*no \\[collision\\] table"):
        solve(problem, print_level=0, log=lambda m: None)


# ----------------------------------------------------------------------------- payload in the task

def test_carrying_a_payload_costs_effort_and_is_verified_with_it(tool_arm, tmp_path):
    """The same minimum-effort task with 1.5 kg at the tool (the problem sets it, the model has
    none): more effort, and the replay (which must use the payload) verifies it."""
    base = ('model = "arm3_tool.toml"\nobjective = "min_effort"\ntheta_start = [0.0, 0.3, -0.5]\n'
            'theta_end = [0.8, 0.9, -1.2]\nduration = 1.5\n[transcription]\nintervals = 40\n')
    (tool_arm / "bare.toml").write_text(base)
    (tool_arm / "laden.toml").write_text(base.replace("duration = 1.5\n", 'duration = 1.5\npayload = { frame = "tool", '
                                                      'mass = 1.5, com = [0.0, 0.0, 0.02], inertia = [1e-3, 1e-3, '
                                                      '1e-3, 0.0, 0.0, 0.0] }\n'))
    bare, laden = (run(tool_arm / f"{k}.toml", tmp_path / k, print_level=0, log=lambda m: None) for k in ("bare", "laden"))
    assert bare.success and laden.success
    assert laden.objective > 1.2 * bare.objective
    from rscasadi.ocp import Solution, verify
    again = Solution.from_json(tmp_path / "laden" / "solution.json")
    assert again["payload"]["mass"] == 1.5 and verify(again)["final_angle_error"] < 1e-4
    unladen = dict(again, payload=None)                                # the same torques without it miss
    assert verify(unladen)["final_angle_error"] > 1e-3


@pytest.mark.parametrize("payload,field", [('{ mass = 1.0 }', "payload"),
                                           ('{ frame = "base", mass = 1.0, com = [0, 0, 0], inertia = [1, 1, 1, 0, 0, 0] }',
                                            "payload.frame"),
                                           ('{ colour = 1 }', "payload")])
def test_a_bad_task_payload_is_refused_by_name(tool_arm, payload, field):
    path = tool_arm / "bad_payload_task.toml"
    path.write_text('model = "arm3_tool.toml"\nobjective = "min_time"\ntheta_start = [0.0, 0.3, -0.5]\n'
                    f'theta_end = [0.8, 0.9, -1.2]\nduration = 1.0\npayload = {payload}\n')
    with pytest.raises(ModelFileError, match=rf"bad_payload_task.toml: field '{re.escape(field)}'"):
        solve(load_problem(path), print_level=0, log=lambda m: None)


# ----------------------------------------------------------------------------- a path for the tool

def test_the_tool_follows_a_path_at_its_speed(tmp_path):
    """A polyline through three points at a mean 0.2 m/s, rest to rest: the replay keeps the tool
    within the path's tolerance at every sample (between the nodes too), fatrop and IPOPT alike."""
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    th0 = np.array([0.0, 0.3, -0.5])
    p0 = np.array(arm.frame_placement("tool")(th0)[1]).ravel()
    points = [[float(v) for v in q] for q in (p0, p0 + [-0.1, 0.1, 0.0], p0 + [-0.15, 0.1, 0.1])]
    path = tmp_path / "path.toml"
    path.write_text(f'model = "{(ROOT / "problems" / "arm3_tool.toml").as_posix()}"\nobjective = "min_effort"\n'
                    f"theta_start = {th0.tolist()}\n[path]\nframe = \"tool\"\npoints = {points}\nspeed = 0.2\n"
                    "tolerance = 1e-3\n[transcription]\nintervals = 30\n")
    problem = load_problem(path)
    assert problem.task.duration == pytest.approx(problem.task.path.length / 0.2)
    results = {}
    for solver in ("fatrop", "ipopt"):
        sol = solve(problem.replace(solver=solver), print_level=0, log=lambda m: None)
        assert sol.success and sol["verification"]["path_error"] <= 1e-3, sol["verification"]
        results[solver] = sol["verification"]["path_error"]
    assert results["fatrop"] == pytest.approx(results["ipopt"], rel=1e-6)
    end = np.array(arm.frame_placement("tool")(sol.theta[:, -1])[1]).ravel()
    assert np.linalg.norm(end - points[-1]) < 1e-6 and np.max(np.abs(sol.dtheta[:, -1])) < 1e-6


def _path_problem(tmp_path, objective, geometry, extra=""):
    th0 = [0.0, 0.3, -0.5]
    timing = "duration = 1.0\n" if objective == "min_time" else ""
    speed = "speed = 0.2\n" if objective == "min_effort" else ""
    path = tmp_path / f"{objective}.toml"
    path.write_text(f'model = "{(ROOT / "problems" / "arm3_tool.toml").as_posix()}"\nobjective = "{objective}"\n'
                    f"{timing}theta_start = {th0}\n[path]\nframe = \"tool\"\n{geometry}{speed}tolerance = 1e-3\n{extra}"
                    "[transcription]\nintervals = 40\n")
    return load_problem(path)


def _limits_used(arm, sol) -> float:
    """The largest |tau|, |psi|, |dphi| along the solution relative to its limit."""
    lim = {k: np.array([jt.limits[k] for jt in arm.model.joints]) for k in ("tau", "psi", "dphi")}
    used = [np.abs(sol.tau) / lim["tau"][:, None], np.abs(sol.phi - sol.theta) / lim["psi"][:, None],
            np.abs(sol.dphi) / lim["dphi"][:, None]]
    return max(float(u.max()) for u in used)


def test_minimum_time_along_a_polyline(tmp_path):
    """The path fixed, its timing free: the replay stays within the tolerance of the polyline
    (its distance measured here by dense sampling), the tool ends at the last point at rest, a
    limit binds (the time is minimal), and the timed path at 0.2 m/s takes longer."""
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    p0 = np.array(arm.frame_placement("tool")(np.array([0.0, 0.3, -0.5]))[1]).ravel()
    corners = np.array([p0, p0 + [-0.1, 0.1, 0.0], p0 + [-0.15, 0.1, 0.1]])
    problem = _path_problem(tmp_path, "min_time", f"points = {corners.tolist()}\n")
    sol = solve(problem, print_level=0, log=lambda m: None)
    assert sol.success and sol["verification"]["path_error"] <= 1e-3, sol["verification"]
    dense = np.vstack([a + np.linspace(0, 1, 2000)[:, None] * (b - a) for a, b in zip(corners[:-1], corners[1:])])
    replay = simulate_held(solution_arm(sol), np.concatenate([sol.theta[:, 0], sol.phi[:, 0],
                                        sol.dtheta[:, 0], sol.dphi[:, 0]]), sol.t, sol.tau, 10, 1e-10)
    tool = np.array(arm.frame_placement("tool").map(replay["theta"].shape[1])(replay["theta"])[1]).T
    assert np.max(np.min(np.linalg.norm(tool[:, None] - dense[None], axis=2), axis=1)) < 1e-3 + 1e-4
    assert np.linalg.norm(tool[-1] - corners[-1]) < 1e-4 and np.max(np.abs(sol.dtheta[:, -1])) < 1e-6
    assert _limits_used(arm, sol) > 0.99
    assert sol.t[-1] < problem.task.path.length / 0.2 / 2


@pytest.mark.parametrize("objective", ["min_effort", "min_time"])
def test_once_round_a_circle(tmp_path, objective):
    """A circle of 8 cm in the horizontal plane from where the tool starts: the replay's tool stays
    within the tolerance of the circle (distance from the centre's axis and the plane) and goes
    round it once (its angle about the centre unwrapped)."""
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    p0 = np.array(arm.frame_placement("tool")(np.array([0.0, 0.3, -0.5]))[1]).ravel()
    centre = p0 + [-0.08, 0.0, 0.0]
    problem = _path_problem(tmp_path, objective, f"circle = {{ center = {centre.tolist()}, radius = 0.08, "
                                                 "normal = [0.0, 0.0, 1.0] }\n")
    sol = solve(problem, print_level=0, log=lambda m: None)
    assert sol.success and sol["verification"]["path_error"] <= 1e-3, sol["verification"]
    replay = simulate_held(solution_arm(sol), np.concatenate([sol.theta[:, 0], sol.phi[:, 0],
                                        sol.dtheta[:, 0], sol.dphi[:, 0]]), sol.t, sol.tau, 10, 1e-10)
    d = np.array(arm.frame_placement("tool").map(replay["theta"].shape[1])(replay["theta"])[1]).T - centre
    assert np.max(np.hypot(np.hypot(d[:, 0], d[:, 1]) - 0.08, d[:, 2])) < 1e-3 + 1e-4
    turned = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    assert abs(turned[-1] - turned[0]) == pytest.approx(2 * np.pi, abs=0.02)
    if objective == "min_time":
        assert _limits_used(arm, sol) > 0.99 and sol.t[-1] < 2 * np.pi * 0.08 / 0.2


POLYLINE = "points = [[0.6, 0.0, 0.4], [0.5, 0.1, 0.4]]\n"


@pytest.mark.parametrize("objective,top,inside,field,words", [
    ("min_effort", "theta_end = [0.8, 0.9, -1.2]\n", POLYLINE + "speed = 0.2\n", "path", "no theta_end"),
    ("min_effort", "duration = 1.0\n", POLYLINE + "speed = 0.2\n", "duration", "leave it out"),
    ("min_effort", "", POLYLINE, "path.speed", "missing"),
    ("min_time", "duration = 1.0\n", POLYLINE + "speed = 0.2\n", "path.speed", "no speed"),
    ("min_time", "", POLYLINE, "duration", "the guess of min_time"),
    ("min_effort", "", POLYLINE + "circle = { center = [0.5, 0.0, 0.4], radius = 0.1, normal = [0, 0, 1] }\n",
     "path", "one of them"),
    ("min_effort", "", "circle = { center = [0.5, 0.0, 0.4], normal = [0, 0, 1] }\nspeed = 0.2\n",
     "path.circle", "center, radius, normal"),
    ("min_effort", "", "circle = { center = [0.5, 0.0, 0.4], radius = 0.1, normal = [0, 0, 0] }\nspeed = 0.2\n",
     "path.circle.normal", "not be"),
    ("tracking", 'trajectory = "trajectory_arm3.toml"\n', POLYLINE + "speed = 0.2\n", "path", "min_effort"),
])
def test_a_bad_path_is_refused_by_name(tmp_path, objective, top, inside, field, words):
    path = tmp_path / "bad_path.toml"
    path.write_text(f'model = "{(ROOT / "problems" / "arm3_tool.toml").as_posix()}"\nobjective = "{objective}"\n'
                    f'theta_start = [0.0, 0.3, -0.5]\n{top}[path]\nframe = "tool"\n{inside}')
    with pytest.raises(ModelFileError, match=rf"bad_path.toml: field '{re.escape(field)}'.*{words}"):
        load_problem(path)


def test_a_start_off_the_path_is_refused(tmp_path):
    from rscasadi.ocp.problem import ToolPath
    path = ToolPath("tool", [[0.5, 0.2, 0.4], [0.45, 0.2, 0.45]], speed=0.2)
    problem = Problem(Task(ROOT / "problems" / "arm3_tool.toml", "min_effort", duration=path.duration,
                           theta_start=[0.0, 0.3, -0.5], path=path))
    with pytest.raises(ModelFileError, match=r"field 'path.points\[0\]': theta_start puts 'tool'"):
        solve(problem, print_level=0, log=lambda m: None)


def test_a_problem_may_give_the_arm_its_collision_geometry(tool_arm, capsule_arm):
    """The same obstacle task with the capsules given by the problem instead of the model file:
    the same capsules, and the same NLP, so the same solution to the last digit (a short
    interpreted solve each); without any, refused; a bad one refused naming the problem file."""
    from rscasadi.model.collision import capsules, with_collision
    from rscasadi.ocp.problem import Obstacle
    arm = rscasadi.load(capsule_arm)
    th0, th1 = np.array([0.0, 0.3, -0.5]), np.array([0.8, 0.9, -1.2])
    obstacle = Obstacle("sphere", np.array(arm.frame_placement("tool")((th0 + th1) / 2)[1]).ravel(), 0.05)
    shape = {"margin": 0.01, "tip": "tool", "links": {"shoulder_pitch": 0.04, "elbow_pitch": 0.03}}
    tool = rscasadi.load(tool_arm / "arm3_tool.toml").model
    plain = lambda caps: [(c.link, c.body, c.a.tolist(), c.b.tolist(), c.radius) for c in caps]   # noqa: E731
    assert plain(capsules(with_collision(tool, shape, "<Problem>"))) == plain(capsules(arm.model))
    task = dict(objective="min_time", duration=1.0, theta_start=th0, theta_end=th1, obstacles=(obstacle,))
    short = dict(transcription=TranscriptionOptions(intervals=10, compiled=False, condense=False),
                 solver=SolverOptions(name="ipopt"), verification=Verification(rounds=0))
    given = solve(Problem(Task(tool_arm / "arm3_tool.toml", collision=shape, **task), **short),
                  print_level=0, log=lambda m: None)
    own = solve(Problem(Task(capsule_arm, **task), **short), print_level=0, log=lambda m: None)
    assert given["solver_success"] and given["collision"] == shape and given["iterations"] == own["iterations"]
    assert np.max(np.abs(given.theta - own.theta)) < 1e-12
    assert given["verification"]["min_clearance"] == pytest.approx(own["verification"]["min_clearance"], abs=1e-12)
    from rscasadi.ocp import verify
    assert verify(given)["min_clearance"] == pytest.approx(given["verification"]["min_clearance"])
    with pytest.raises(ModelFileError, match=r"<Problem>: field 'collision.links.nowhere'"):
        solve(Problem(Task(tool_arm / "arm3_tool.toml", collision={"links": {"nowhere": 0.1}}, **task)),
              print_level=0, log=lambda m: None)


# ----------------------------------------------------------------------------- the shipped problems

SHIPPED = sorted((ROOT / "problems").glob("ocp_*.toml")) + sorted((ROOT / "problems").glob("mpc_*.toml"))


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_every_shipped_problem_states_its_task_and_fits_its_arm(path):
    """Each example opens with its task in words (a comment of at least two lines) and is read,
    checked and fitted to its model without error; a task for a frame names a frame of the arm."""
    from rscasadi.mpc.problem import load_mpc_problem, mpc_model
    from rscasadi.ocp.problem import check_against_model
    from rscasadi.model.modelfile import read
    head = []
    for line in path.read_text().splitlines():
        if not line.startswith("#"):
            break
        head.append(line.lstrip("# ").strip())
    assert len(head) >= 2 and len(" ".join(head)) > 80, f"{path.name}: no statement of its task"
    if path.name.startswith("mpc_"):
        mpc_model(load_mpc_problem(path))
    else:
        problem = load_problem(path)
        check_against_model(problem, read(problem.task.model))


def test_every_shipped_optimal_control_problem_is_in_the_main_job():
    from rscasadi.studies.reproduce import OCP_PROBLEMS
    shipped = {p.stem.removeprefix("ocp_") for p in SHIPPED if p.stem.startswith("ocp_")}
    assert shipped == set(OCP_PROBLEMS) | {"panda_shelf"}


def test_the_panda_shelf_task_at_a_coarse_mesh():
    """The shipped 7-joint task (2 kg, a pose goal, a ball and the table) on 16 intervals, as
    shipped otherwise (fatrop on the condensed, compiled NLP): solved; the collocation's end at
    the pose; the replay clear of both obstacles and within millimetres of the goal (the main
    job refines it until the replay passes)."""
    problem = load_problem(ROOT / "problems" / "ocp_panda_shelf.toml").replace(intervals=16, rounds=0)
    sol = solve(problem, print_level=0, log=lambda m: None)
    report = sol["verification"]
    assert sol["solver_success"] and 0.3 < sol.t[-1] < 1.5
    arm = solution_arm(sol)
    R, p = (np.array(v) for v in arm.frame_placement("panda_hand_tcp")(sol.theta[:, -1]))
    assert np.linalg.norm(p.ravel() - [0.45, 0.35, 0.45]) < 1e-6 and np.allclose(R[:, 2], [0, 0, -1], atol=1e-6)
    assert report["min_clearance"] > 0 and report["goal_position_error"] < 5e-3
    assert report["urdf_min_clearance"] >= report["min_clearance"] - 1e-4     # the fingers' own boxes, by coal
