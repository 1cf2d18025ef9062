"""Robots that are trees: the recursions over a parent array, checked against Pinocchio with the
rotors as bodies of their own (a tree of 3n joints built depth first, sharing no code with the
recursions), on random trees and on three public whole robots read from their URDFs: Baxter's two
arms and head (three branches on the torso), the Unitree G1's upper body (a waist carrying two
arms) and the PR2 (a prismatic torso lift carrying two arms and the head)."""
import copy
import tomllib

import casadi as ca
import numpy as np
import pinocchio as pin
import pytest

import rscasadi
from rscasadi import ModelFileError
from rscasadi.model.modelfile import document, parse
from rscasadi.reference.pinocchio_route import PinocchioRoute, urdf_model

from conftest import (ROOT, check_against_pinocchio, dm, mujoco_against_model, random_state, random_tree_doc, to_toml,
                      write_arm)

BAXTER = ROOT / "tests" / "data" / "baxter_description" / "urdf" / "baxter.urdf"
G1 = ROOT / "tests" / "data" / "g1_description" / "urdf" / "g1_29dof_rev_1_0.urdf"
PR2 = ROOT / "tests" / "data" / "pr2_description" / "urdf" / "pr2.urdf"
PR2_ARM = ("shoulder_pan", "shoulder_lift", "upper_arm_roll", "elbow_flex", "forearm_roll", "wrist_flex", "wrist_roll")
ARM7 = ("s0", "s1", "e0", "e1", "w0", "w1", "w2")
G1_ARM = ("shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow", "wrist_roll", "wrist_pitch", "wrist_yaw")
ROBOTS = {
    "baxter": (BAXTER, ["left_gripper", "right_gripper", "head"],
               ["head_pan"] + [f"{s}_{j}" for s in ("left", "right") for j in ARM7]),
    "g1": (G1, ["left_rubber_hand", "right_rubber_hand"],
           ["waist_yaw_joint", "waist_roll_joint", "waist_pitch_joint"]
           + [f"{s}_{j}_joint" for s in ("left", "right") for j in G1_ARM]),
    "pr2": (PR2, ["l_gripper_tool_frame", "r_gripper_tool_frame", "head_plate_frame"],
            ["torso_lift_joint", "head_pan_joint", "head_tilt_joint"]
            + [f"{s}_{j}_joint" for s in "lr" for j in PR2_ARM]),
}
OTHER_KINDS = {"torso_lift_joint": {"kind": "direct", "limits": {"tau": 10000.0}}}   # a prismatic lift


def actuator(name: str, rng) -> dict:
    """An SEA with unbalanced rotors (centre off the axis, products of inertia)."""
    def rotor(m, i):
        return {"mass": m, "com": list(rng.uniform(-2e-3, 2e-3, 3)), "inertia": [i, 1.1 * i, 1.6 * i, 1e-2 * i, 0.0, 0.0]}
    return {"name": name, "gear_ratio": float(rng.uniform(30, 120)), "sea": {"k1": 1500.0, "d": 1.0},
            "gear_loss": {"b": 0.5}, "slow_rotor": rotor(0.2, 1e-4), "fast_rotor": rotor(0.1, 1e-5)}


def whole_robot(tmp_path, name):
    urdf, tips, joints = ROBOTS[name]
    rng = np.random.default_rng(len(joints))
    doc = {"name": f"{name}-tree", "urdf": str(urdf), "tips": tips,
           "joints": [{"name": j, **OTHER_KINDS[j]} if j in OTHER_KINDS else actuator(j, rng) for j in joints]}
    return rscasadi.load(write_arm(tmp_path, doc, f"{name}.toml"))


def random_tree(tmp_path, seed, n, balanced=False):
    return rscasadi.load(write_arm(tmp_path, random_tree_doc(np.random.default_rng(seed), n, balanced), f"tree{seed}.toml"))


def rel(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)


@pytest.mark.parametrize("seed,n", [(1, 5), (2, 8), (3, 12)])
def test_random_trees_equal_pinocchio_with_rotors_as_bodies(tmp_path, seed, n):
    """Random trees (several joints on the base and on one link, axes at any angle, unbalanced
    rotors, random gravity): every quantity equal to Pinocchio's to 1e-9 or better."""
    arm = random_tree(tmp_path, seed, n)
    parent = arm.model.parent
    assert not arm.model.is_chain and len(set(parent)) < n
    check_against_pinocchio(arm, PinocchioRoute(arm.model), np.random.default_rng(seed))


@pytest.mark.parametrize("name", ROBOTS)
def test_whole_robots_from_their_urdf_equal_pinocchio_s_own_parse(tmp_path, name):
    """Baxter with both arms and the head (15 joints, tips = the two grippers and the head), the
    G1's upper body (17 joints; a waist carrying two arms; the legs held) and the PR2 (17 joints:
    its prismatic torso lift, direct, carrying the head and two arms with continuous rolls; casters,
    laser and grippers held): the link tree from
    Pinocchio's own URDF parser (fixed links merged, held joints removed by its
    buildReducedModel), the rotors as bodies, equal to ours; the hands' placements equal
    Pinocchio's frames of those URDF links."""
    arm = whole_robot(tmp_path, name)
    urdf, tips, joints = ROBOTS[name]
    assert [jt.name for jt in arm.model.joints] == joints and not arm.model.is_chain
    route = PinocchioRoute.from_urdf(arm.model)
    rng = np.random.default_rng(5)
    check_against_pinocchio(arm, route, rng, [links[0] for links in arm.model.extra["links"][1:]])
    reduced = urdf_model(arm.model)
    data = reduced.createData()
    for _ in range(2):
        theta = rng.uniform(-1, 1, arm.n)
        q = pin.neutral(reduced)
        for name_j, th in zip(joints, theta):
            jm = reduced.joints[reduced.getJointId(name_j)]
            q[jm.idx_q:jm.idx_q + jm.nq] = [np.cos(th), np.sin(th)] if jm.nq == 2 else [th]
        pin.framesForwardKinematics(reduced, data, q)
        for tip in tips:
            R, p = (np.array(v) for v in arm.frame_placement(tip)(theta))
            oMf = data.oMf[reduced.getFrameId(tip)]
            assert np.max(np.abs(R - oMf.rotation)) < 1e-9 and np.max(np.abs(p.ravel() - oMf.translation)) < 1e-9


def test_energy_is_conserved_and_the_paper_s_sweeps_agree_on_a_tree(tmp_path):
    """With no losses and no torque, dE/dt = dE/dx . f(x) vanishes (E from poses and velocities,
    f from the articulated sweep: two routes through the tree); the paper's eq. (23) and
    eqs. (29)-(32) give back the forward dynamics' accelerations (a fixed point) on a tree."""
    doc = random_tree_doc(np.random.default_rng(11), 7)
    for jt in doc["joints"]:
        jt["sea"]["d"], jt["gear_loss"] = 0.0, {"b": 0.0, "c": 0.0}
    arm = rscasadi.load(write_arm(tmp_path, doc))
    n = arm.n
    x = [ca.SX.sym(s, n) for s in ("theta", "phi", "dtheta", "dphi")]
    ddth, ddph = arm.forward_dynamics()(*x, ca.DM.zeros(n))
    E = arm.energy()(*x)
    dE = ca.Function("dE", x, [ca.jtimes(E, ca.vertcat(*x), ca.vertcat(x[2], x[3], ddth, ddph)),
                               ca.norm_2(ca.gradient(E, ca.vertcat(*x))) * ca.norm_2(ca.vertcat(x[2], x[3], ddth, ddph))])
    rng = np.random.default_rng(2)
    for _ in range(3):
        state = random_state(rng, n, 2.0)
        rate, scale = (float(v) for v in dE(*state))
        assert abs(rate) < 1e-12 * scale and scale > 1.0
        tau = rng.normal(size=n)
        a, b = arm.forward_dynamics()(*state, tau)
        assert rel(dm(arm.arm_forward_dynamics()(*state, b, a)), dm(a)) < 1e-10
        assert rel(dm(arm.joint_forward_dynamics()(*state, tau, a)), dm(b)) < 1e-10


def test_a_tree_written_by_hand_reads_back_and_every_bad_parent_is_named(tmp_path):
    """`parent = "joint"` in [[joints]] makes a tree; the link-list form written from it (and
    from a URDF-based tree) reads back the same dynamics; parents that name no joint, or a
    joint listed later, are all named in one message before any work."""
    doc = random_tree_doc(np.random.default_rng(4), 6)
    model = parse(tomllib.loads(to_toml(doc)))
    assert model.parent == tuple(-1 if jt["parent"] == "base" else int(jt["parent"][1:]) - 1 for jt in doc["joints"])
    again = parse(tomllib.loads(to_toml(document(model))))
    assert again.parent == model.parent
    whole = whole_robot(tmp_path, "g1").model
    written = parse(tomllib.loads(to_toml(document(whole))), str(tmp_path / "g1-link-list.toml"))
    assert written.parent == whole.parent
    rng = np.random.default_rng(8)
    x, tau = random_state(rng, whole.n, 1.0), rng.normal(size=whole.n)
    a, b = (np.concatenate([dm(v) for v in rscasadi.Arm(m).forward_dynamics()(*x, tau)]) for m in (whole, written))
    assert rel(a, b) < 1e-12
    bad = copy.deepcopy(doc)
    bad["joints"][2]["parent"] = "nowhere"
    bad["joints"][3]["parent"] = "j6"
    with pytest.raises(ModelFileError) as err:
        parse(tomllib.loads(to_toml(bad)), "hand.toml")
    message = str(err.value)
    assert "hand.toml" in message and "'j3': parent 'nowhere' is no joint" in message
    assert "'j4': parent 'j6' comes after it" in message


def test_tips_choose_the_branches_and_wrong_ones_are_named(tmp_path):
    """tips keeps the union of the paths to them (the rest held at lock_others); a joint listed
    off those paths, a tip that is no link, tip and tips together, and a joint listed before the
    joint that carries it are refused by name."""
    urdf, tips, joints = ROBOTS["baxter"]
    rng = np.random.default_rng(1)
    base = {"name": "baxter", "urdf": str(urdf), "tips": tips, "joints": [actuator(j, rng) for j in joints]}
    held = whole_robot(tmp_path, "baxter").model.extra["locked"]
    assert set(held) == {"l_gripper_l_finger_joint", "l_gripper_r_finger_joint", "r_gripper_l_finger_joint",
                         "r_gripper_r_finger_joint"}
    cases = [({"tips": ["left_gripper", "head"]}, "'right_s0'"),
             ({"tips": ["left_gripper", "nowhere"]}, "no link 'nowhere'"),
             ({"tip": "left_gripper"}, "not both"),
             ({"joints": [base["joints"][2], base["joints"][1]] + base["joints"][3:] + base["joints"][:1]},
              "after the joint that carries it: 'left_s1' before 'left_s0'")]
    for over, words in cases:
        doc = {**copy.deepcopy(base), **over}
        with pytest.raises(ModelFileError) as err:
            rscasadi.load(write_arm(tmp_path, doc, "bad.toml"))
        assert words in str(err.value) and "bad.toml" in str(err.value), str(err.value)


def test_generated_c_of_a_tree_equals_its_functions_and_pinocchio(tmp_path):
    """codegen on a tree: the compiled forward dynamics equals the Function and Pinocchio."""
    from rscasadi.codegen import generate
    path = write_arm(tmp_path, random_tree_doc(np.random.default_rng(6), 5))
    out = tmp_path / "gen"
    generate(path, out, opt="-O1", log=lambda m: None)
    compiled, arm = rscasadi.load_compiled(out), rscasadi.load(path)
    route, rng = PinocchioRoute(arm.model), np.random.default_rng(3)
    for _ in range(3):
        x, tau = random_state(rng, arm.n, 2.0), rng.normal(size=arm.n)
        c = np.concatenate([dm(v) for v in compiled["forward_dynamics"](*x, tau)])
        assert rel(c, np.concatenate([dm(v) for v in arm.forward_dynamics()(*x, tau)])) < 1e-12
        assert rel(c, np.concatenate(route.forward_dynamics(*x, tau))) < 1e-9


def dual_arm_doc(pairs=True) -> dict:
    """A two-armed SEA robot: a torso column (the reference arm's yaw joint) carrying two arms of
    yaw, shoulder and elbow joints; hands at the forearms' ends; capsules on the torso, upper arms
    and forearms, the forearms paired with each other and with the torso."""
    with open(ROOT / "problems" / "arm3.toml", "rb") as fh:
        yaw, pitch, elbow = tomllib.load(fh)["joints"]
    joints = [dict(yaw, name="torso")]
    for side, y in (("left", 0.2), ("right", -0.2)):
        joints += [dict(copy.deepcopy(yaw), name=f"{side}_yaw", parent="torso", origin_xyz=[0.0, y, 0.25],
                        link={"mass": 1.0, "com": [0.0, 0.0, 0.02], "inertia": [0.002, 0.002, 0.001, 0.0, 0.0, 0.0]}),
                   dict(copy.deepcopy(pitch), name=f"{side}_pitch", parent=f"{side}_yaw", origin_xyz=[0.0, 0.0, 0.05]),
                   dict(copy.deepcopy(elbow), name=f"{side}_elbow", parent=f"{side}_pitch")]
    capsules = [{"frame": "torso", "a": [0.0, 0.0, 0.0], "b": [0.0, 0.0, 0.3], "radius": 0.06}]
    for side in ("left", "right"):
        capsules += [{"frame": f"{side}_pitch", "a": [0.05, 0.0, 0.0], "b": [0.35, 0.0, 0.0], "radius": 0.04},
                     {"frame": f"{side}_elbow", "a": [0.05, 0.0, 0.0], "b": [0.35, 0.0, 0.0], "radius": 0.035}]
    collision = {"margin": 0.01, "capsules": capsules}
    if pairs:
        collision["pairs"] = [["left_elbow", "right_elbow"], ["left_elbow", "torso"], ["right_elbow", "torso"]]
    return {"name": "dual-arm-sea", "gravity": [0.0, 0.0, -9.81], "joints": joints, "collision": collision,
            "frames": {"left_hand": {"parent": "left_elbow", "xyz": [0.35, 0.0, 0.0]},
                       "right_hand": {"parent": "right_elbow", "xyz": [0.35, 0.0, 0.0]}}}


def test_paired_capsules_keep_apart_by_a_conservative_smooth_clearance_and_an_exact_one(tmp_path):
    """Between the paired capsules of the two arms and the torso, at random poses: the exact
    clearance the verification measures equals coal's capsule-to-capsule distance (to the
    sampling, 1/8 of a radius); the optimiser's row of each pair of links never exceeds it and
    stays within its bound below it (half the 1 cm sampling and the soft minima's log(count) /
    beta), with several capsules on a link too; a pair on one link, or naming no frame, is
    refused by name."""
    import coal
    from rscasadi.dynamics.collision import clearance_function, exact_clearance
    from rscasadi.dynamics.kinematics import body_poses
    from rscasadi.model.collision import capsule_pairs
    arm = rscasadi.load(write_arm(tmp_path, dual_arm_doc(), "dual.toml"))
    pairs = capsule_pairs(arm.model)
    assert len(pairs) == 3
    smooth, exact = clearance_function(arm.model, []), exact_clearance(arm.model, [])
    place = ca.Function("poses", [th := ca.SX.sym("th", arm.n)],
                        [ca.horzcat(*[ca.horzcat(R, o) for R, o in body_poses(arm.model, th)])])

    def shape(c, P):
        a, b = (np.asarray(v, float) for v in (c.a, c.b))
        R, o = P[:, 4 * c.body:4 * c.body + 3], P[:, 4 * c.body + 3]
        axis = b - a
        z = axis / np.linalg.norm(axis)
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
        x /= np.linalg.norm(x)
        frame = R @ np.column_stack([x, np.cross(z, x), z])
        return coal.Capsule(c.radius, float(np.linalg.norm(axis))), coal.Transform3s(frame, o + R @ ((a + b) / 2))
    rng, closest = np.random.default_rng(0), np.inf
    for _ in range(60):
        theta = rng.uniform(-1.5, 1.5, arm.n)
        P = np.array(place(theta))
        truth = min(coal.distance(*shape(c, P), *shape(d, P), coal.DistanceRequest(), coal.DistanceResult())
                    for c, d in pairs) - 0.01
        measured = float(exact(theta))
        assert abs(measured - truth) < 0.035 / 8 * 1.01, (measured, truth)
        assert -0.005 - np.log(31) / 2000 - 1e-9 <= float(np.min(np.array(smooth(theta)))) - truth <= 1e-9
        closest = min(closest, truth)
    assert closest < 0                           # the poses drawn include arms that touch
    doc = dual_arm_doc()                         # the forearms in three capsules each: one row
    for side in ("left", "right"):
        doc["collision"]["capsules"] += [{"frame": f"{side}_elbow", "a": [0.1, 0.0, 0.05], "b": [0.3, 0.0, 0.05],
                                          "radius": 0.02}, {"frame": f"{side}_elbow", "a": [0.2, 0.05, 0.0],
                                                            "b": [0.2, -0.05, 0.0], "radius": 0.03}]
    doc["collision"]["pairs"] = [["left_elbow", "right_elbow"]]
    arm = rscasadi.load(write_arm(tmp_path, doc, "many.toml"))
    pairs, smooth = capsule_pairs(arm.model), clearance_function(arm.model, [])
    assert len(pairs) == 9 and smooth.size1_out(0) == 1
    for _ in range(30):
        theta = rng.uniform(-1.5, 1.5, arm.n)
        P = np.array(place(theta))
        truth = min(coal.distance(*shape(c, P), *shape(d, P), coal.DistanceRequest(), coal.DistanceResult())
                    for c, d in pairs) - 0.01
        assert -0.005 - np.log(31 * 9) / 2000 - 1e-9 <= float(smooth(theta)) - truth <= 1e-9
    doc = dual_arm_doc()
    for bad, words in (([["left_elbow", "left_elbow"]], "same link"), ([["left_elbow", "nose"]], "no frame 'nose'"),
                       ([["left_elbow", "left_hand"]], "same link")):
        doc["collision"]["pairs"] = bad
        with pytest.raises(ModelFileError, match=rf"field 'collision.pairs\[0\]'.*{words}"):
            rscasadi.load(write_arm(tmp_path, doc, "bad.toml"))


def test_two_hands_meet_at_a_handover_with_the_arms_kept_apart(tmp_path):
    """The OCP with a goal for each hand ([[goal]] twice: 10 cm apart in front of the torso),
    the forearms paired with each other and the torso: solved on one coarse mesh, replayed on the
    complete model and verified, both hands within a millimetre, no pair closer than the margin between the nodes
    either (and at the end the forearms within 3 cm of it: the pairing is what holds them)."""
    from rscasadi.ocp import load_problem, run
    write_arm(tmp_path, dual_arm_doc(), "dual.toml")
    (tmp_path / "handover.toml").write_text(
        'model = "dual.toml"\nobjective = "min_effort"\ntheta_start = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]\n'
        'duration = 1.5\n[transcription]\nintervals = 40\nlimit_margin = 0.005\n[refinement]\nrounds = 1\n'
        '[verification]\nfinal_speed_tol = 0.05\nfinal_angle_tol = 1e-3\n'    # one coarse mesh: the end's rest to 0.05 rad/s
        '[[goal]]\nframe = "left_hand"\nposition = [0.45, 0.05, 0.45]\n'
        '[[goal]]\nframe = "right_hand"\nposition = [0.45, -0.05, 0.45]\n')
    problem = load_problem(tmp_path / "handover.toml")
    assert [g.frame for g in problem.task.goals] == ["left_hand", "right_hand"]
    solution = run(problem, tmp_path / "out", log=lambda m: None, print_level=0)
    report = solution["verification"]
    assert report["passed"], report
    assert report["goal_position_error"] < 1e-3 and report["min_clearance"] > -1e-4
    assert [g["frame"] for g in solution["goal"]] == ["left_hand", "right_hand"]
    from rscasadi.dynamics.collision import exact_clearance
    arm = rscasadi.load(tmp_path / "dual.toml")
    assert float(exact_clearance(arm.model, [])(np.array(solution["theta"])[:, -1])) < 0.03


def test_the_pr2_s_lift_is_a_slide_in_mujoco_with_the_model_s_dynamics(tmp_path, capsys):
    """The PR2 (its torso lift a prismatic direct joint carrying the head and both arms of SEAs)
    exported to MuJoCo: the lift a slide, the mass matrix and the forces (bias, springs, dampers,
    motors) equal the model's at random states, and MuJoCo's body placements the model's frames.
    `rscasadi info` reports it: the lift slides and holds the tree's weight (its input the
    tree's weight in N, from Pinocchio), the SEAs' rest deflections and motor torques."""
    mujoco = pytest.importorskip("mujoco")
    from rscasadi.cli import main
    from rscasadi.export.mujoco import gear_map, mujoco_xml
    arm = whole_robot(tmp_path, "pr2")
    assert arm.model.joints[0].type == "prismatic" and arm.model.joints[0].kind == "direct"
    assert main(["info", str(tmp_path / "pr2.toml")]) in (0, None)
    report = capsys.readouterr().out
    row = next(line for line in report.splitlines() if line.startswith("| 1 | torso_lift_joint | direct | slides"))
    lift = float(next(line for line in report.splitlines()[::-1] if "| torso_lift_joint |" in line).split("|")[-2])
    pm = urdf_model(arm.model)                        # the URDF's links the lift carries, by Pinocchio
    lift_id = pm.getJointId("torso_lift_joint")
    carried = sum(pm.inertias[i].mass for i in range(1, pm.njoints) if lift_id in pm.supports[i])
    carried += sum(jt.slow_rotor.mass + jt.fast_rotor.mass for jt in arm.model.joints[1:])   # the rotors ride on it
    assert row and abs(lift - 9.81 * carried) < 1e-3 * 9.81 * carried, (lift, carried)
    m = mujoco.MjModel.from_xml_string(mujoco_xml(arm.model))
    assert m.jnt_type[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "torso_lift_joint")] == mujoco.mjtJoint.mjJNT_SLIDE
    d, T = mujoco.MjData(m), gear_map(arm, m)
    rng = np.random.default_rng(2)
    for _ in range(3):
        theta = np.r_[rng.uniform(0.0, 0.31), rng.uniform(-np.pi, np.pi, arm.n - 1)]   # the lift within its travel (m)
        motors = theta[list(arm.model.motors)] + rng.normal(size=arm.m) * 0.05
        x = [theta, motors, rng.normal(size=arm.n), rng.normal(size=arm.m)]
        mass, forces = mujoco_against_model(arm, m, d, T, x, rng.normal(size=arm.u))
        assert mass < 1e-12 and forces < 1e-10
        R, p = (np.array(v) for v in arm.frame_placement("r_gripper_tool_frame")(x[0]))
        site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "r_gripper_tool_frame")
        assert np.max(np.abs(d.site_xpos[site] - p.ravel())) < 1e-9
        assert np.max(np.abs(d.site_xmat[site].reshape(3, 3) - R)) < 1e-9
