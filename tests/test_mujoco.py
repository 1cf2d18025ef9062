"""rscasadi export mujoco: the complete model in MuJoCo, checked by MuJoCo itself (an engine that
shares no code with rscasadi): its mass matrix and every generalised force, projected onto the
model's coordinates, equal the model's; its RK4 motion follows the model's CVODES replay."""
import numpy as np
import pytest

import rscasadi
from rscasadi.dynamics.statics import rest_state
from rscasadi.errors import InvalidArgument
from rscasadi.export.mujoco import mujoco_xml

from conftest import ROOT

mujoco = pytest.importorskip("mujoco")

ARMS = {"arm3": (ROOT / "problems" / "arm3.toml", [0.1, 0.4, -0.6]),
        "panda": (ROOT / "problems" / "panda_sea.toml", [0.0, -0.3, 0.0, -2.0, 0.0, 1.7, 0.8])}


def loaded(name, variant="complete"):
    """The arm, its MuJoCo model and data, and T: (theta, phi) to MuJoCo's coordinates through the gear."""
    from rscasadi.export.mujoco import gear_map
    arm = rscasadi.load(ARMS[name][0]) if name in ARMS else name
    m = mujoco.MjModel.from_xml_string(mujoco_xml(arm.model, variant))
    return arm, m, mujoco.MjData(m), gear_map(arm, m)


MIXED = ("sea", "geared", "spring", "direct", "sea", "free", "geared", "direct")


def random_arm(tmp_path, n, tree=False, kinds=(), balanced=False):
    """A random arm of conftest (axes at any angle, unbalanced rotors, random gravity), or a
    random tree of them (joints of `kinds`), with a linear spring and no Coulomb loss, as MJCF
    holds them."""
    from conftest import random_arm_doc, random_tree_doc, with_kinds, write_arm
    doc = with_kinds((random_tree_doc if tree else random_arm_doc)(np.random.default_rng(100 + n), n, balanced), kinds)
    for jt in doc["joints"]:
        jt.get("sea", {})["k3"] = 0.0
        jt.get("gear_loss", {})["c"] = 0.0
    return rscasadi.load(write_arm(tmp_path, doc))


def holding_a_part():
    """The reference arm with its tool frame, capsules and a 0.5 kg part (off-centre, with a
    collision sphere) at the tool."""
    from rscasadi.model.frames import holding
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    return rscasadi.Arm(holding(arm.model, frame="tool", mass=0.5, com=[0.02, -0.01, 0.015],
                                inertia=[2e-3, 1e-3, 1.5e-3, 1e-4, 0.0, -2e-4], radius=0.04))


@pytest.mark.parametrize("name,variant", [(name, "complete") for name in (*ARMS, 2, 5, 7, "part", "tree", "kinds")]
                         + [("arm3", "reduced"), ("panda", "reduced"), ("part", "reduced"), ("kinds", "reduced")])
def test_mujoco_s_mass_matrix_and_forces_are_the_model_s(name, variant, tmp_path):
    """At random states and torques within the limits: T' M T equals the model's mass matrix and
    T' (passive + actuator - bias) its generalised forces (M ddq of its forward dynamics), to 1e-12;
    the reference arm, the Panda from its URDF, random arms, a random tree and a random tree of
    joints of every kind with unbalanced rotors, and the arm holding a part (its capsules exported as geoms, which must not change the inertias); the
    reduced export against the reduced model (Arm.reduced_forward_dynamics)."""
    arm = (holding_a_part() if name == "part" else name if name in ARMS
           else random_arm(tmp_path, 8, tree=True) if name == "tree"
           else random_arm(tmp_path, 8, tree=True, kinds=MIXED, balanced=variant == "reduced") if name == "kinds"
           else random_arm(tmp_path, name))
    arm, m, d, T = loaded(arm, variant)
    n, m_, rng = arm.n, arm.m, np.random.default_rng(7)
    limit = np.array([arm.model.joints[j].limits.get("tau", 1.0) for j in arm.model.actuated])
    reduced = variant == "reduced"
    fd = arm.reduced_forward_dynamics() if reduced else arm.forward_dynamics()
    mass = arm.mass_matrix(reduced=reduced)
    for _ in range(5):
        th = rng.uniform(-1, 1, n)
        ph, dth, dph = th[arm.model.motors] + rng.uniform(-0.05, 0.05, m_), rng.normal(size=n), rng.normal(size=m_)
        tau = rng.uniform(-1, 1, arm.u) * limit
        d.qpos[:], d.qvel[:], d.ctrl[:] = T @ np.r_[th, ph], T @ np.r_[dth, dph], tau
        mujoco.mj_forward(m, d)
        M = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, M)
        ours = np.array(mass(th, ph))
        forces = ours @ np.concatenate([np.array(a).ravel() for a in fd(th, ph, dth, dph, tau)])
        assert np.max(np.abs(T.T @ M @ T - ours)) < 1e-12 * np.max(np.abs(ours))
        assert np.max(np.abs(T.T @ (d.qfrc_passive + d.qfrc_actuator - d.qfrc_bias) - forces)) < 1e-12 * np.max(np.abs(forces))


@pytest.mark.parametrize("name,seconds", [("arm3", 2.0), ("panda", 1.0)])
def test_mujoco_s_motion_follows_the_model(name, seconds):
    """From a rest pose pushed to 0.3 rad/s on every link, the motors holding their static torques:
    MuJoCo (RK4 at 1 ms, the gear's equality nearly hard) ends within 1e-6 rad and 1e-5 rad/s of
    the model's CVODES replay, after moving the links by several tenths of a radian."""
    from rscasadi.sim.simulation import simulate
    arm, m, d, T = loaded(name)
    n = arm.n
    x0 = rest_state(arm, ARMS[name][1])
    z = np.zeros(n)
    tau = np.array(arm.inverse_dynamics()(x0[:n], x0[n:2 * n], z, z, z, z)[0]).ravel()
    x0[2 * n:3 * n] += 0.3
    d.qpos[:], d.qvel[:], d.ctrl[:] = T @ x0[:2 * n], T @ x0[2 * n:], tau
    for _ in range(int(round(seconds / m.opt.timestep))):
        mujoco.mj_step(m, d)
    t = np.linspace(0.0, seconds, 11)
    ours = simulate(arm, x0, t, np.tile(tau[:, None], (1, len(t))))["x"][:, -1]
    back = np.linalg.pinv(T)
    assert np.max(np.abs(ours[:n] - x0[:n])) > 0.3
    assert np.max(np.abs(back @ d.qpos - ours[:2 * n])) < 1e-6
    assert np.max(np.abs(back @ d.qvel - ours[2 * n:])) < 1e-5


def test_what_mjcf_cannot_hold_is_refused_by_name(tmp_path):
    import dataclasses
    arm = rscasadi.load(ARMS["arm3"][0])
    joints = list(arm.model.joints)
    joints[1] = dataclasses.replace(joints[1], k3=5e4)
    joints[2] = dataclasses.replace(joints[2], c=0.1)
    with pytest.raises(InvalidArgument, match=r"shoulder_pitch: k3 = 50000.*elbow_pitch: gear_loss c = 0\.1"):
        mujoco_xml(dataclasses.replace(arm.model, joints=tuple(joints)))
    with pytest.raises(InvalidArgument, match=r"reduced model assumes balanced rotors.*joint 1 \('j1'\) slow_rotor"):
        mujoco_xml(random_arm(tmp_path, 2).model, "reduced")
    with pytest.raises(InvalidArgument, match="variant must be one of complete, reduced, armature"):
        mujoco_xml(arm.model, "rigid")


def test_frames_are_sites_and_capsules_are_geoms_that_touch_the_world_not_each_other():
    """At random angles each site is where the model puts its frame (placement, 1e-12) and each
    capsule geom spans the model's capsule (its ends in the world); no pose makes the arm's geoms
    touch each other, and a table a user adds under the part is touched."""
    from rscasadi.dynamics.kinematics import body_poses
    from rscasadi.model.collision import capsules
    arm, m, d, T = loaded(holding_a_part())
    n, rng = arm.n, np.random.default_rng(11)
    assert m.nsite == len(arm.model.frames) and m.ngeom == len(capsules(arm.model))
    for _ in range(5):
        th = rng.uniform(-2, 2, n)
        d.qpos[:] = T @ np.r_[th, th]
        mujoco.mj_forward(m, d)
        for f in arm.model.frames:
            R, p = (np.array(v) for v in arm.frame_placement(f.name)(th))
            site = m.site(f.name).id
            assert np.allclose(d.site_xpos[site], p.ravel(), atol=1e-12)
            assert np.allclose(d.site_xmat[site].reshape(3, 3), R, atol=1e-12)
        poses = body_poses(arm.model, th)
        for i, c in enumerate(capsules(arm.model)):
            R, o = (np.array(v) for v in poses[c.body])
            ends = [R @ c.a + o.ravel(), R @ c.b + o.ravel()]
            g = m.geom(i).id
            axis = d.geom_xmat[g].reshape(3, 3)[:, 2] * m.geom_size[g][1]
            theirs = [d.geom_xpos[g] - axis, d.geom_xpos[g] + axis] if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE \
                else [d.geom_xpos[g]] * 2
            assert m.geom_size[g][0] == pytest.approx(c.radius)
            assert min(max(np.linalg.norm(a - b) for a, b in zip(ends, pair)) for pair in (theirs, theirs[::-1])) < 1e-12
        assert d.ncon == 0
    tool = np.array(arm.frame_placement("tool")(np.zeros(n))[1]).ravel()
    text = mujoco_xml(arm.model).replace("  <worldbody>\n", f'  <worldbody>\n    <geom type="box" size="0.1 0.1 0.01" '
                                         f'pos="{tool[0]} {tool[1]} {tool[2] - 0.05}"/>\n', 1)
    m2 = mujoco.MjModel.from_xml_string(text)
    d2 = mujoco.MjData(m2)
    d2.qpos[:] = 0.0
    mujoco.mj_forward(m2, d2)
    assert d2.ncon >= 1                                      # the part's sphere reaches into the table


def test_the_command_writes_a_file_mujoco_loads(tmp_path):
    from rscasadi.cli import main
    assert main(["export", "mujoco", str(ARMS["panda"][0]), "--out", str(tmp_path / "mj")]) in (0, None)
    m = mujoco.MjModel.from_xml_path(str(tmp_path / "mj" / "model.xml"))
    assert (m.nv, m.neq, m.ntendon, m.nu) == (21, 7, 7, 7) and m.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    assert main(["export", "mujoco", str(ARMS["panda"][0]), "--out", str(tmp_path / "dlr"), "--reduced"]) in (0, None)
    m = mujoco.MjModel.from_xml_path(str(tmp_path / "dlr" / "model.xml"))
    assert (m.nv, m.neq, m.ntendon, m.nu) == (14, 0, 7, 7)


def test_the_generated_mpc_tracks_on_mujoco_s_plant(tmp_path):
    """The C MPC of problems/mpc_arm3.toml, through the one closed loop at 1 kHz with quantised
    encoders, on MuJoCo simulating the exported arm with a 20 % heavier tip: it tracks as on
    rscasadi's own RK4 plant (within 1.5x and 1e-3 rad over 0.5 s) and 5x better than
    feedforward + PD on the same MuJoCo plant."""
    from rscasadi.export.mujoco import mujoco_plant
    from rscasadi.mpc import closed_loop, generate_mpc
    problem = ROOT / "problems" / "mpc_arm3.toml"
    generate_mpc(problem, tmp_path / "mpc", opt="-O1", log=lambda m: None)
    on_mujoco = closed_loop(problem, tmp_path / "mpc", duration=0.5, log=lambda m: None, simulator=mujoco_plant)
    on_ours = closed_loop(problem, tmp_path / "mpc", duration=0.5, log=lambda m: None)
    mpc, ours = on_mujoco["MPC (C)"]["max_error"], on_ours["MPC (C)"]["max_error"]
    assert mpc < 1e-3 and mpc < 1.5 * ours and ours < 1.5 * mpc
    assert mpc * 5 < on_mujoco["feedforward + PD"]["max_error"]


@pytest.mark.parametrize("name,trajectory", [("arm3", "trajectory_arm3.toml"), ("panda", "trajectory_panda.toml")])
def test_the_armature_model_misses_what_the_complete_one_keeps(name, trajectory):
    """The feedforward torques of the arm's 2 s trajectory, held over each millisecond, open loop:
    MuJoCo's complete export follows the model's CVODES replay of the same torques within 2e-5
    rad, the rigid-joint armature export MuJoCo users write is off by more than 1e-3 rad and a
    hundred times further, and the DLR/Spong reduced export (springs, no rotor coupling) more than
    ten times: what rotor separation and the springs keep, in MuJoCo's own terms (measured
    2026-11-26: complete 1.7e-7, reduced 4.2e-3, armature 7.9e-3 rad on the reference arm;
    3.7e-6, 6.1e-2, 3.1e-2 on the Panda)."""
    from rscasadi.export.mujoco import compare_variants
    from rscasadi.sim.trajectory import load_trajectory
    arm = rscasadi.load(ARMS[name][0])
    err = compare_variants(arm, load_trajectory(ROOT / "problems" / trajectory))
    print(name, err)
    assert err["complete"] < 2e-5 and err["armature"] > max(1e-3, 100 * err["complete"]), err
    assert err["reduced"] > 10 * err["complete"], err


def test_impedance_presses_a_mujoco_table_at_the_stiffness_it_realises_and_the_observer_sees_it(tmp_path):
    """The generated C Cartesian impedance controller at 1 kHz with quantised
    encoders on MuJoCo's plant, its target moved 5 mm below a MuJoCo table the tool's capsule
    touches (MuJoCo's own contact, not rscasadi's): the settled force MuJoCo reports is K times the
    tool's distance from the target where MuJoCo holds it (within 1 %), without chatter, and the
    momentum observer's link torques are MuJoCo's J^T f and it flags the contact, after it only
    (measured 2026-11-26: 0.06 %, 0.008 % peak-to-peak, 2e-5 of 0.94 N m, 9 ms)."""
    from rscasadi.interaction.generate import generate_impedance
    from rscasadi.interaction.study import table_in_mujoco
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    generate_impedance(arm, tmp_path / "impedance", "tool", opt="-O1", log=lambda m: None)
    res = table_in_mujoco(arm, "tool", [0.0, 0.3, -0.5], 300.0, compiled=tmp_path / "impedance")
    assert res["force"] > 1.0                                          # it presses
    assert abs(res["error_percent"]) < 1.0 and res["chatter_percent"] < 1.0, res
    assert res["observer_error"] < 0.01 * res["observer_torque"], res
    assert 0 <= res["delay_ms"] < 20 and np.isnan(res["false_alarm_s"]), res          # flagged, only after


def test_a_push_in_mujoco_moves_the_impedance_controlled_tool_by_force_over_stiffness():
    """The impedance controller holding arm3's tool on MuJoCo's plant, pushed with 2 N down at the
    tool from 0.2 s (mj_applyFT at the frame's site): the tool settles F / K below its target
    (within 0.5 %), sideways within 0.1 mm, and the momentum observer reads J^T F within 1 % of its
    largest joint torque; a push without a frame is refused."""
    from rscasadi.export.mujoco import mujoco_plant
    from rscasadi.interaction.study import push_in_mujoco
    arm = rscasadi.load(ROOT / "problems" / "arm3_tool.toml")
    res = push_in_mujoco(arm, "tool", [0.0, 0.3, -0.5], 300.0)
    assert abs(res["error_percent"]) < 0.5 and max(abs(v) for v in res["displacement"][:2]) < 1e-4, res
    assert res["observer_error"] < 0.01 * res["observer_torque"], res
    with pytest.raises(Exception, match="push needs the frame"):
        mujoco_plant(arm, 1e-3, push=lambda t: np.zeros(6))


def _off_zero_arm(tmp_path):
    """A random arm whose first and last joints' ranges exclude 0 (MuJoCo's default qpos)."""
    from conftest import random_arm_doc, write_arm
    doc = random_arm_doc(np.random.default_rng(104), 4)
    for jt in doc["joints"]:
        jt.get("sea", {})["k3"] = 0.0
        jt.get("gear_loss", {})["c"] = 0.0
    doc["joints"][0].setdefault("limits", {})["theta"] = [0.4, 2.0]
    doc["joints"][-1].setdefault("limits", {})["theta"] = [-2.5, -0.7]
    return rscasadi.load(write_arm(tmp_path, doc))


def _kinds_tree(tmp_path, balanced=False):
    """A random tree of joints of every kind, its first joint's range excluding 0: the spring and
    free joints rest where their links hang."""
    arm = random_arm(tmp_path, 8, tree=True, kinds=MIXED, balanced=balanced)
    from conftest import write_arm
    from rscasadi.model.modelfile import document
    doc = document(arm.model)
    doc["joints"][0].setdefault("limits", {})["theta"] = [0.4, 2.0]
    return rscasadi.load(write_arm(tmp_path, doc, "kinds.toml"))


def _baxter_left(tmp_path):
    """Baxter's left arm with motors strong enough to hold it level (1 N m at gear 100)."""
    from test_whole_robot import sidecar, write
    doc = sidecar()
    for jt in doc["joints"]:
        jt["limits"]["tau"] = 1.0
    return rscasadi.load(write(tmp_path, doc))


@pytest.mark.parametrize("name,variant", [(n, "complete") for n in ("arm3", "panda", "off_zero", "baxter", "kinds")]
                         + [("panda", "reduced"), ("panda", "armature"), ("off_zero", "armature"),
                            ("kinds", "armature")])
def test_the_export_starts_at_rest_inside_its_ranges(name, variant, tmp_path):
    """MuJoCo's qpos0 lies inside every link's range (the Panda's fourth joint and a random arm
    have ranges without 0), and the keyframe "rest" (qpos0 and the holding torques) is a static
    equilibrium in MuJoCo's own terms: the generalised forces it computes there (springs, gravity,
    motors), projected through the gear, cancel to 1e-9 of the gravity's; from it 0.2 s of
    MuJoCo's motion touches no limit."""
    from rscasadi.export.mujoco import gear_map
    makers = {"off_zero": _off_zero_arm, "baxter": _baxter_left,      # the armature file welds the rotors at 0:
              "kinds": lambda p: _kinds_tree(p, balanced=variant == "armature")}   # its rest is exact if balanced
    arm = makers[name](tmp_path) if name in makers else rscasadi.load(ARMS[name][0])
    m = mujoco.MjModel.from_xml_string(mujoco_xml(arm.model, variant))
    d = mujoco.MjData(m)
    limited = np.flatnonzero(m.jnt_limited)
    assert len(limited) > 0
    q0 = m.qpos0[m.jnt_qposadr[limited]]
    lo, hi = m.jnt_range[limited].T
    assert np.all((lo < q0) & (q0 < hi)), (q0, lo, hi)
    if name in ("panda", "off_zero"):
        assert np.any(lo > 0) or np.any(hi < 0)                # the test can tell qpos 0 from the rest
    assert m.nkey == 1 and m.key(0).name == "rest"
    mujoco.mj_resetDataKeyframe(m, d, 0)
    mujoco.mj_forward(m, d)
    T = gear_map(arm, m)[:, :arm.n] if variant == "armature" else gear_map(arm, m)
    residual = T.T @ (d.qfrc_passive + d.qfrc_actuator - d.qfrc_bias)
    assert np.max(np.abs(residual)) < 1e-9 * np.max(np.abs(T.T @ d.qfrc_bias)), residual
    for _ in range(200):
        mujoco.mj_step(m, d)
        assert mujoco.mjtConstraint.mjCNSTR_LIMIT_JOINT not in set(d.efc_type[:d.nefc])


def test_the_export_says_which_joints_cannot_hold_the_rest(tmp_path, capsys):
    """Baxter's left arm with motors too weak to hold it level: the keyframe's torques are the
    limits, and the command names the joints that cannot hold the rest."""
    from rscasadi.cli import main
    from test_whole_robot import sidecar, write
    path = write(tmp_path, sidecar())
    assert main(["export", "mujoco", str(path), "--out", str(tmp_path / "mj")]) == 0
    out = capsys.readouterr().out
    assert "cannot hold the rest pose" in out and "left_s1" in out, out
