"""The joints' limits read one way everywhere (rscasadi.model.limits): a limit the model does not
give is no limit, one violation figure (joint angles included) for every replay and closed loop,
and the MPC keeps the link angles in their ranges."""
import re

import numpy as np
import pytest

import rscasadi
from conftest import ROOT
from rscasadi.model.limits import limit_arrays, max_violation, violation

ARM3 = (ROOT / "problems" / "arm3.toml").read_text()


def arm3_with(tmp_path, yaw_limits: str, name="arm.toml"):
    """The reference arm with the shoulder yaw's limits table replaced."""
    text = re.sub(r"limits = \{[^}]*\}", "limits = {" + yaw_limits + "}", ARM3, count=1)
    path = tmp_path / name
    path.write_text(text)
    return path


def test_the_violation_figure_by_hand(tmp_path):
    """Each kind of limit's excess, relative to the limit (the range for angles), the largest per
    sample; a joint without a limit adds nothing; none at all: 0."""
    model = rscasadi.load(arm3_with(tmp_path, "dphi = 2.0, psi = 0.1, theta = [-0.5, 1.5]")).model
    theta = np.array([[1.7, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])       # joint 1 0.2 above its range
    phi = theta + np.array([[0.0, 0.12, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])   # 0.02 beyond psi 0.1
    dphi = np.array([[0.0, 0.0, -2.6], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])        # 0.6 beyond dphi 2
    lim = limit_arrays(model)
    v = violation(model, theta, phi, dphi)
    assert np.allclose(v, [0.2 / 2.0, 0.02 / 0.1, 0.6 / 2.0])
    assert max_violation(model, theta, phi, dphi) == pytest.approx(0.3)
    assert np.isinf(lim["tau"][0]) and lim["tau"][1] == 0.6                   # no tau on joint 1: none
    bare = rscasadi.load(arm3_with(tmp_path, "", "bare.toml")).model
    assert limit_arrays(bare)["theta_lo"][0] == -np.inf
    assert max_violation(bare, theta[:, :1] * 0, theta[:, :1] * 0, theta[:, :1] * 0) == 0.0


def test_the_ocp_and_the_mpc_studies_share_the_figure():
    """The OCP's replay and the closed loop's figure (every MPC study's) call the one definition."""
    import importlib
    import inspect
    study, solution, loop = (importlib.import_module(f"rscasadi.{m}") for m in ("mpc.study", "ocp.solution", "sim.loop"))
    assert "violation(arm.model" in inspect.getsource(solution.verify)
    assert "violation(arm.model" in inspect.getsource(loop.limit_violation)
    for fn in (study.reach_pose, study.closed_loop, study.task_closed_loop):
        assert "limit_violation(" in inspect.getsource(fn)


@pytest.fixture(scope="module")
def narrow_yaw(tmp_path_factory):
    """The reference arm with the shoulder yaw's range narrowed to +-0.3 rad, and its MPC with the
    link-angle penalty on and off, and with hard limits (no penalty); 5 intervals of 10 ms, the
    substeps the arm's modes ask for (a short horizon: the tests compile three)."""
    from rscasadi.mpc import generate_mpc
    d = tmp_path_factory.mktemp("narrow_yaw")
    model = arm3_with(d, "tau = 0.6, dphi = 4.0, psi = 0.15, theta = [-0.3, 0.3]")
    out = {}
    for name, weight, kind in (("on", None, "soft"), ("off", 0.0, "soft"), ("hard", 0.0, "hard")):
        extra = "" if weight is None else f"angle_limits = {weight}\n"
        problem = d / f"mpc_{name}.toml"
        problem.write_text(f'model = "{model.name}"\nhorizon = 5\ninterval = 0.01\nsubsteps = "auto"\n'
                           f'angle_limits = "{kind}"\n[weights]\n{extra}')
        out[name] = (problem, d / f"mpc_{name}")
        generate_mpc(problem, out[name][1], opt="-O1", log=lambda m: None)
    return out


def test_the_mpc_keeps_the_link_angles_in_their_range(narrow_yaw):
    """Asked for 0.6 rad on a joint whose range ends at 0.3: the MPC stops the link within 1 % of
    the range past its end (a soft limit, weight angle_limits); with the penalty off it follows
    the target out of the range, and the violation figure says so."""
    from rscasadi.mpc.study import reach_pose
    target = [0.6, 0.0, 0.0]
    kept = reach_pose(narrow_yaw["on"][0], narrow_yaw["on"][1], target, seconds=1.5)
    free = reach_pose(narrow_yaw["off"][0], narrow_yaw["off"][1], target, seconds=1.5)
    assert kept["max_limit_violation"] < 0.01, kept["max_limit_violation"]
    assert free["final_angle_error"] < 0.01 and free["max_limit_violation"] > 0.4


def test_hard_angle_limits_hold_the_range_to_its_end(narrow_yaw):
    """With `angle_limits = "hard"` (and no penalty) the link goes to the end of its range and no
    further (the plant between the plan's interval ends: within 0.1 % of the range), on a step
    beyond it and on a fast swing back across it; a target inside the range is reached."""
    from rscasadi.mpc.study import reach_pose
    problem, out = narrow_yaw["hard"]
    beyond = reach_pose(problem, out, [0.6, 0.0, 0.0], seconds=1.5)
    assert beyond["max_limit_violation"] < 1e-3
    assert 0.3 - 1e-3 < 0.6 - beyond["final_angle_error"] and beyond["final_angle_error"] < 0.3 + 1e-3
    back = reach_pose(problem, out, [-0.45, 0.0, 0.0], seconds=1.5, start=[0.2, 0.0, 0.0])
    assert back["max_limit_violation"] < 1e-3
    inside = reach_pose(problem, out, [0.2, 0.3, -0.2], seconds=1.5)
    assert inside["final_angle_error"] < 1e-3


def test_the_mpc_refuses_a_joint_without_a_torque_limit(tmp_path):
    """No torque limit is no limit, and an MPC must not command any torque: refused before any
    work, naming the joint and the field."""
    from rscasadi.model.types import ModelFileError
    from rscasadi.mpc import generate_mpc
    arm3_with(tmp_path, "dphi = 4.0, psi = 0.15")
    problem = tmp_path / "p.toml"
    problem.write_text('model = "arm.toml"\n')
    with pytest.raises(ModelFileError, match="joint 'shoulder_yaw': limits.tau missing"):
        generate_mpc(problem, tmp_path / "out", opt="-O1", log=lambda m: None)
    assert not (tmp_path / "out").exists()


def test_the_guard_boxes_follow_the_limits(narrow_yaw):
    """The controller's measurement box: the range widened by 0.5 rad (phi by 1 rad), speeds to
    5x the speed limit; written into the C and the manifest."""
    import json
    guard = json.loads((narrow_yaw["on"][1] / "manifest.json").read_text())["guard"]
    assert guard["x_lo"][0] == pytest.approx(-0.8) and guard["x_hi"][3] == pytest.approx(1.3)
    assert guard["x_hi"][6] == pytest.approx(20.0) and guard["tau_max"] == [0.6, 0.6, 0.4]
    assert "X_LO[MPC_NX] = {-0.8," in (narrow_yaw["on"][1] / "rscasadi_mpc.c").read_text()
