"""A real robot's description on the first day: a whole-robot URDF (Baxter: torso, head, two
7-joint arms, grippers; as shipped by the example-robot-data package) as a sub-chain with only
the actuator table, CAD-truncated right angles, point-mass tool links, and rotations that no
roll-pitch-yaw writes back exactly."""
import copy

import numpy as np
import pytest

import rscasadi
from conftest import ROOT, dm, random_state, to_toml
from rscasadi import ModelFileError
from rscasadi.reference.pinocchio_route import PinocchioRoute

BAXTER = ROOT / "tests" / "data" / "baxter_description" / "urdf" / "baxter.urdf"
LEFT = ["left_s0", "left_s1", "left_e0", "left_e1", "left_w0", "left_w1", "left_w2"]


def actuator(name: str, big: bool) -> dict:
    rotor = lambda m, i: {"mass": m, "com": [0.0, 0.0, 0.0], "inertia": [i, i, 1.6 * i, 0.0, 0.0, 0.0]}  # noqa: E731
    return {"name": name, "gear_ratio": 100.0, "sea": {"k1": 3000.0 if big else 800.0, "d": 3.0 if big else 0.8},
            "gear_loss": {"b": 1.0}, "limits": {"tau": 0.5 if big else 0.15, "dphi": 2.0, "psi": 0.1},
            "slow_rotor": rotor(0.3, 2e-4), "fast_rotor": rotor(0.2, 1.5e-5)}


def sidecar(**over) -> dict:
    """The only thing a user writes for Baxter's left arm: the actuator table and the tip."""
    return {"name": "baxter-left-sea", "urdf": str(BAXTER), "tip": "left_gripper",
            "joints": [actuator(j, k < 4) for k, j in enumerate(LEFT)], **over}


def write(tmp_path, doc, name="baxter.toml"):
    path = tmp_path / name
    path.write_text(to_toml(doc))
    return path


def test_the_left_arm_of_a_whole_robot_from_the_actuator_table_alone(tmp_path):
    """No locking by hand: the head, the right arm and the fingers are held at lock_others (0);
    the chain equals Pinocchio's own parse of the whole URDF, those joints removed by its
    buildReducedModel, to 1e-9 (the right angles snapped here differ from its 1.57079632679 by
    5e-12)."""
    arm = rscasadi.load(write(tmp_path, sidecar()))
    assert [jt.name for jt in arm.model.joints] == LEFT
    held = arm.model.extra["locked"]
    assert {"head_pan", "right_s0", "right_w2", "l_gripper_l_finger_joint"} <= set(held) and set(held.values()) == {0.0}
    route, rng, fd = PinocchioRoute.from_urdf(arm.model), np.random.default_rng(3), arm.forward_dynamics()
    for _ in range(3):
        x, tau = random_state(rng, 7, 2.0), rng.normal(size=7)
        ours = np.concatenate([dm(v) for v in fd(*x, tau)])
        theirs = np.concatenate(route.forward_dynamics(*x, tau))
        assert np.max(np.abs(ours - theirs)) < 1e-9 * np.max(np.abs(theirs))


def test_truncated_right_angles_fold_as_exact_ones(tmp_path, monkeypatch):
    """Baxter writes pi/2 as 1.57079632679 (33 times) and 1.57079633: snapped, its forward dynamics
    has as few instructions as the same URDF written with exact right angles; unsnapped it has
    two thirds more (the test can tell)."""
    import rscasadi.model.urdf as urdf
    text = BAXTER.read_text()
    exact = text.replace("1.57079632679", repr(np.pi / 2)).replace("1.57079633", repr(np.pi / 2))
    exact = exact.replace("3.14159265359", repr(np.pi))
    (tmp_path / "exact.urdf").write_text(exact)
    counts = {name: rscasadi.load(write(tmp_path, sidecar(urdf=str(u)), f"{name}.toml")).forward_dynamics().n_instructions()
              for name, u in (("cad", BAXTER), ("exact", tmp_path / "exact.urdf"))}
    assert counts["cad"] == counts["exact"], counts
    monkeypatch.setattr(urdf, "SNAP", 0.0)
    unsnapped = rscasadi.load(write(tmp_path, sidecar(), "raw.toml")).forward_dynamics().n_instructions()
    assert unsnapped > 1.3 * counts["exact"], (unsnapped, counts)


def test_every_written_model_reads_back_the_same_rotations(tmp_path):
    """A joint placed at a gimbal-locked rotation (no roll-pitch-yaw gives it back to 1e-12) and a
    frame likewise: the link-list form writes them as origin_R and R, and reading that back gives
    the same rotations; a matrix that is no rotation is refused by name."""
    import tomllib
    from rscasadi.model.modelfile import document, parse
    from rscasadi.model.types import rpy_matrix, rpy_of
    R = rpy_matrix([2.2, np.pi / 2 + 3e-10, 2.3])
    assert rpy_of(R) is None                                  # what made identify fail to write model.toml
    with open(ROOT / "problems" / "arm3.toml", "rb") as fh:
        doc = tomllib.load(fh)
    del doc["joints"][1]["origin_rpy"]
    doc["joints"][1]["origin_R"] = R.tolist()
    doc["frames"] = {"tool": {"parent": "elbow_pitch", "xyz": [0.3, 0.0, 0.0], "R": R.tolist()}}
    model = parse(copy.deepcopy(doc))
    written = document(model)
    assert "origin_R" in written["joints"][1] and "R" in written["frames"]["tool"]
    again = parse(copy.deepcopy(written))
    assert all(np.max(np.abs(a.R - b.R)) == 0.0 for a, b in zip(model.joints, again.joints))
    assert np.max(np.abs(again.frame("tool").R - model.frame("tool").R)) < 1e-15
    doc["joints"][1]["origin_R"] = (2 * R).tolist()
    with pytest.raises(ModelFileError, match="origin_R.*not a rotation matrix"):
        parse(copy.deepcopy(doc))


def test_missing_joints_are_named_all_at_once(tmp_path):
    """Two joints of the arm left out of the table: one message names both; with no tip, the
    fingers below the last joint are named too, with the way out (tip)."""
    doc = sidecar()
    doc["joints"] = [jt for jt in doc["joints"] if jt["name"] not in ("left_e1", "left_w1")]
    with pytest.raises(ModelFileError, match="'left_e1', 'left_w1'"):
        rscasadi.load(write(tmp_path, doc))
    doc = sidecar()
    del doc["tip"]
    with pytest.raises(ModelFileError, match="'l_gripper_l_finger_joint', 'l_gripper_r_finger_joint'.*tip") as err:
        rscasadi.load(write(tmp_path, doc))
    assert "right_s0" not in str(err.value)                  # the other arm is no concern of this one
    doc = sidecar(locked={"l_gripper_l_finger_joint": 0.01, "l_gripper_r_finger_joint": -0.01})
    del doc["tip"]
    held = rscasadi.load(write(tmp_path, doc)).model.extra["locked"]
    assert held["l_gripper_l_finger_joint"] == 0.01 and held["head_pan"] == 0.0


def test_a_point_mass_tool_link_is_a_frame_and_a_negative_inertia_is_not(tmp_path):
    """Baxter's left_gripper: 0.1 g with zero inertia (a tool point): accepted, its mass merged
    and its frame kept; a link with a negative principal moment is still refused by name."""
    arm = rscasadi.load(write(tmp_path, sidecar()))
    assert "left_gripper" in arm.frames()
    bad = BAXTER.read_text().replace('<mass value="0.0001"/>\n      <inertia ixx="0"', '<mass value="0.0001"/>\n      <inertia ixx="-1e-6"', 1)
    assert bad != BAXTER.read_text()
    (tmp_path / "bad.urdf").write_text(bad)
    with pytest.raises(ModelFileError, match="not positive semidefinite"):
        rscasadi.load(write(tmp_path, sidecar(urdf=str(tmp_path / "bad.urdf")), "bad.toml"))


def test_info_and_view_take_the_whole_robot(tmp_path, capsys):
    """The commands a new user runs first: info prints the 7 joints; view draws the arm, names
    the meshes it cannot read (they are not shipped here) and ends without a traceback."""
    from rscasadi.cli import main
    model = write(tmp_path, sidecar())
    assert main(["info", str(model)]) == 0
    assert "left_w2" in capsys.readouterr().out
    assert main(["view", str(model), "--out", str(tmp_path / "view.html")]) in (0, None)
    out = capsys.readouterr().out
    assert "skipped mesh" in out and (tmp_path / "view.html").stat().st_size > 10000
    from rscasadi.view.scene import scene_of                 # a link with a mesh skipped keeps its capsules drawn
    scene = scene_of(model)
    assert 7 in scene.visuals and 7 in scene.incomplete and scene.draws_capsules(7)


def test_a_new_users_first_day_on_a_whole_robot_end_to_end(tmp_path, capsys):
    """Baxter's left arm from the actuator table, a margin and a held part with a radius, through
    info --collision, codegen, a tool-goal OCP around a ball verified on the complete model, view (the page),
    excite, simulate and identify, without a traceback. The OCP's clearance is measured on the capsules
    the solver used (the hand's cylinders, the fingers' boxes, the part's sphere), and re-checked
    here on the URDF's true shapes placed by Pinocchio (coal's cylinders and boxes) and the part's
    sphere: never less clear than reported, and outside the margin at every node."""
    import json

    import pinocchio as pin
    from rscasadi.cli import main
    from rscasadi.model.collision import capsules
    from rscasadi.reference.pinocchio_route import configuration, urdf_model
    doc = sidecar(collision={"margin": 0.02})
    for k, jt in enumerate(doc["joints"]):          # strong enough to hold the arm; springs well damped
        jt["limits"]["tau"] = 1.0 if k < 4 else 0.15
        jt["sea"]["d"] = 40.0 if k < 4 else 10.0
    model = write(tmp_path, doc)
    assert main(["info", str(model), "--collision"]) in (0, None)
    out = capsys.readouterr().out
    assert "l_gripper_r_finger_tip" in out and "left_gripper_base_link" in out
    assert main(["codegen", str(model), "--out", str(tmp_path / "c"), "--opt=-O1", "--frames", "left_gripper"]) in (0, None)
    assert "#define ARM_NQ 7" in (tmp_path / "c" / "rscasadi_arm.h").read_text()
    part = {"frame": "left_gripper", "mass": 0.5, "com": [0.0, 0.0, 0.04], "inertia": [5e-4, 5e-4, 5e-4, 0.0, 0.0, 0.0],
            "radius": 0.04}
    ball = {"center": [0.47, 1.03, -0.06], "radius": 0.08}
    start = [0.0, -0.5, 0.0, 1.0, 0.0, 0.6, 0.0]
    (tmp_path / "ocp.toml").write_text(f"""model = "{model}"
objective = "min_effort"
theta_start = {start}
duration = 1.0
payload = {{ frame = "left_gripper", mass = 0.5, com = [0.0, 0.0, 0.04], inertia = [5e-4, 5e-4, 5e-4, 0, 0, 0], radius = 0.04 }}
[goal]
frame = "left_gripper"
position = [0.230, 1.145, -0.107]
tolerance = {{ position = 1e-3 }}
[[obstacles]]
sphere = {{ center = {ball["center"]}, radius = {ball["radius"]} }}
[transcription]
intervals = 12
dynamics = "implicit"
limit_margin = 0.02
[refinement]
rounds = 2
""")
    main(["ocp", str(tmp_path / "ocp.toml"), "--out", str(tmp_path / "ocp"), "--quiet"])
    sol = json.loads((tmp_path / "ocp" / "solution.json").read_text())
    assert sol["success"], (sol["status"], sol["rounds"])              # verified on the complete model
    reported = sol["verification"]["min_clearance"]
    assert reported >= -1e-4                           # the replay between the nodes keeps the margin
    # the true shapes, independently: Pinocchio's parse of the URDF's collision geometry
    arm = rscasadi.load(model)
    pm = urdf_model(arm.model)
    pdata = pm.createData()
    import re
    stripped = tmp_path / "stripped.urdf"          # its meshes are not shipped here: only the base has them
    stripped.write_text(re.sub(r"<collision>(?:(?!</collision>).)*<mesh(?:(?!</collision>).)*</collision>", "",
                               BAXTER.read_text(), flags=re.S))
    geom = pin.buildGeomFromUrdf(pm, str(stripped), pin.GeometryType.COLLISION)
    gdata = geom.createData()
    c, R_ball, margin = np.array(ball["center"]), ball["radius"], 0.02
    moving = {name for name in arm.frames() if arm.model.frame(name).body > 0}
    theta = np.array(sol["theta"])
    for th in theta.T:
        pin.updateGeometryPlacements(pm, pdata, geom, gdata, configuration(pm, th))
        pin.updateFramePlacements(pm, pdata)
        gaps = []
        for i, obj in enumerate(geom.geometryObjects):
            if pm.frames[obj.parentFrame].name not in moving:
                continue
            M, g = gdata.oMg[i], obj.geometry
            q = M.rotation.T @ (c - M.translation)                     # the ball's centre in the shape's frame
            if type(g).__name__ == "Box":
                nearest = np.clip(q, -np.asarray(g.halfSide), np.asarray(g.halfSide))
            else:                                                      # a cylinder about z
                radial = np.linalg.norm(q[:2])
                scale = min(1.0, g.radius / radial) if radial > 0 else 0.0
                nearest = np.array([q[0] * scale, q[1] * scale, np.clip(q[2], -g.halfLength, g.halfLength)])
            gaps.append(np.linalg.norm(q - nearest) - R_ball)
        F = pdata.oMf[pm.getFrameId("left_gripper")]
        gaps.append(np.linalg.norm(F.translation + F.rotation @ part["com"] - c) - part["radius"] - R_ball)
        assert min(gaps) - margin >= reported - 1e-9 and min(gaps) >= margin - 1e-6, (min(gaps), reported)
    from rscasadi.ocp.solution import solution_arm
    assert any(c.link.startswith("payload") for c in capsules(solution_arm(sol).model))
    assert main(["view", str(tmp_path / "ocp" / "solution.json"), "--out", str(tmp_path / "view.html")]) in (0, None)
    assert "<title>ocp/solution.json" in (tmp_path / "view.html").read_text()   # its GIF: test_view, this arm
    excite = tmp_path / "excite"                       # short settings; its condition (~1e6) accepted
    assert main(["excite", str(model), "--out", str(excite), "--harmonics", "3", "--samples", "20", "--starts", "1",
                 "--period", "6", "--max-condition", "1e8"]) in (0, None)
    assert main(["simulate", str(model), str(excite / "trajectory.toml"), "--out", str(tmp_path / "log.csv"),
                 "--rate", "200", "--perturb", "3"]) in (0, None)
    assert main(["identify", str(model), str(tmp_path / "log.csv"), "--out", str(tmp_path / "ident")]) in (0, None)
    assert rscasadi.load(tmp_path / "ident" / "model.toml").n == 7


def test_the_mpc_runs_a_whole_robots_arm_with_its_default_settings(tmp_path):
    """`rscasadi mpc` on Baxter's left arm from its whole-robot URDF (the actuator table alone) with
    a problem file that names only the model, the motion and the horizon (10 intervals of 10 ms:
    the Riccati QP, the integrator and substeps from the arm's spring modes): on the plant with a
    20 % heavier last link, through quantised encoders, every step finite and within the limits,
    and at least 10x closer than feedforward + motor PD."""
    import json

    from rscasadi.cli import main
    from rscasadi.mpc import closed_loop
    doc = sidecar()
    for k, jt in enumerate(doc["joints"]):
        jt["limits"]["tau"] = 1.0 if k < 4 else 0.3
    write(tmp_path, doc, "baxter_sea.toml")
    (tmp_path / "motion.toml").write_text('model = "baxter_sea.toml"\nperiod = 2.0\nduration = 2.0\n'
                                          'start = [0.0, -0.55, 0.0, 0.75, 0.0, 1.26, 0.0]\n'
                                          'amplitude = [0.4, 0.2, 0.0, 0.3, 0.0, -0.3, 0.0]\n')
    problem = tmp_path / "mpc.toml"
    problem.write_text('model = "baxter_sea.toml"\ntrajectory = "motion.toml"\nhorizon = 10\ninterval = 0.01\n')
    assert main(["mpc", str(problem), "--out", str(tmp_path / "c"), "--opt=-O1"]) in (0, None)
    manifest = json.loads((tmp_path / "c" / "manifest.json").read_text())
    assert manifest["qp"] == "riccati", manifest["qp"]
    res = closed_loop(problem, tmp_path / "c", duration=0.3, log=lambda m: None)
    mpc, pd = res["MPC (C)"], res["feedforward + PD"]
    assert mpc["max_limit_violation"] == 0.0 and np.isfinite(mpc["max_error"])
    assert mpc["max_error"] < pd["max_error"] / 10, (mpc["max_error"], pd["max_error"])
