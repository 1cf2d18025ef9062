"""Joints of every kind (rscasadi.model.kinds): sea, geared, spring, free, direct, on random trees,
checked against Pinocchio with the rotors as bodies (a geared joint's rotors geared to its link
coordinate, an SEA's to its motor coordinate) and against the SEA with a rigid spring."""
import copy
import tomllib

import numpy as np
import pytest

import rscasadi
from rscasadi import ModelFileError
from rscasadi.model.modelfile import document, parse
from rscasadi.reference.pinocchio_route import PinocchioRoute

from conftest import (ROOT, check_against_pinocchio, dm, mujoco_against_model, random_tree_doc, to_toml, with_kinds,
                      write_arm)

KINDS = ("sea", "geared", "spring", "free", "direct")


def mixed(seed, n, kinds=None, balanced=False, slides=False):
    """A random tree of `kinds` (default: every kind, shuffled); with `slides`, every other joint
    without rotors prismatic."""
    rng = np.random.default_rng(seed)
    kinds = kinds or [KINDS[i % len(KINDS)] for i in rng.permutation(n)]
    doc = with_kinds(random_tree_doc(rng, n, balanced), kinds, rng)
    if slides:
        for jt in [jt for jt in doc["joints"] if jt.get("kind") in ("spring", "free", "direct")][::2]:
            jt["type"] = "prismatic"
    return parse(tomllib.loads(to_toml(doc)))


def state(rng, arm, scale=1.0):
    n, m = arm.n, arm.m
    return [rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi, np.pi, m), rng.normal(size=n) * scale,
            rng.normal(size=m) * scale], rng.normal(size=arm.u)


def rel(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)


@pytest.mark.parametrize("seed,n,slides", [(1, 5, False), (2, 9, True), (3, 14, True)])
def test_every_kind_equals_pinocchio_with_its_rotors_as_bodies(seed, n, slides):
    """Random trees whose joints are of every kind (unbalanced rotors, random axes and gravity,
    losses), some of the joints without rotors prismatic: the coordinates are named, forward and
    inverse dynamics, the mass matrix, the centre of mass and every link's placement and Jacobian
    equal Pinocchio's (its prismatic joints for ours) to 1e-9."""
    model = mixed(seed, n, slides=slides)
    assert sum(jt.type == "prismatic" for jt in model.joints) >= (2 if slides else 0)
    arm, route = rscasadi.Arm(model), PinocchioRoute(model)
    kinds = [jt.kind for jt in model.joints]
    assert set(kinds) == set(KINDS)
    motors = [jt.name for jt in model.joints if jt.kind == "sea"]
    assert arm.coordinates == [jt.name for jt in model.joints] + [f"{j}.motor" for j in motors]
    assert arm.inputs == [jt.name for jt in model.joints if jt.kind in ("sea", "geared", "direct")]
    fd = arm.forward_dynamics()
    assert fd.size1_in("phi") == arm.m == len(motors) and fd.size1_in("tau") == arm.u
    check_against_pinocchio(arm, route, np.random.default_rng(seed))


def test_a_geared_joint_is_an_sea_whose_spring_is_rigid():
    """The geared joint's dynamics is the SEA's constrained to phi = theta (k1 -> infinity): its
    mass matrix is P^T M_sea P and its forward dynamics (P^T M_sea P)^-1 P^T (Q_sea - c_sea), where
    P puts theta in the motor's place, the spring's torque cancelling (computed through the SEA's
    leaf, the geared joint's cluster: two routes through the articulated sweep)."""
    kinds = ["sea", "geared", "sea", "geared", "direct", "geared"]
    geared = mixed(5, 6, kinds)
    as_sea = [dict(**{k: v for k, v in jt.items() if k != "kind"}, sea={"k1": 1e3, "d": 0.0})
              if jt.get("kind") == "geared" else jt for jt in document(geared)["joints"]]
    sea = parse(tomllib.loads(to_toml({**document(geared), "joints": as_sea})))
    G, S = rscasadi.Arm(geared), rscasadi.Arm(sea)
    n, motor_of = G.n, {j: i for i, j in enumerate(sea.motors)}
    P = np.zeros((n + S.m, n + G.m))                 # (theta, phi_sea) = P (theta, phi_geared)
    for j in range(n):
        P[j, j] = 1.0
        if j in motor_of:
            P[n + motor_of[j], j if kinds[j] == "geared" else n + geared.motors.index(j)] = 1.0
    rng = np.random.default_rng(4)
    for _ in range(3):
        (th, ph, dth, dph), tau = state(rng, G, 2.0)
        q, dq = P @ np.r_[th, ph], P @ np.r_[dth, dph]
        M_s = np.array(S.mass_matrix()(q[:n], q[n:]))
        assert rel(np.array(G.mass_matrix()(th, ph)), P.T @ M_s @ P) < 1e-12
        tau_s = tau                                   # the same inputs: every geared joint keeps its motor
        a_s = np.concatenate([dm(v) for v in S.forward_dynamics()(q[:n], q[n:], dq[:n], dq[n:], tau_s)])
        rhs = P.T @ M_s @ a_s                         # P^T (Q - c): the spring's torque cancels in P^T
        a_g = np.concatenate([dm(v) for v in G.forward_dynamics()(th, ph, dth, dph, tau)])
        assert rel(a_g, np.linalg.solve(P.T @ M_s @ P, rhs)) < 1e-10


def test_energy_of_passive_kinds_is_conserved():
    """Spring and free joints (the first spring and the free one prismatic) with an SEA and a geared
    joint, no losses, no torque: dE/dt = 0."""
    import casadi as ca
    doc = with_kinds(random_tree_doc(np.random.default_rng(9), 6), ["sea", "geared", "spring", "free", "spring", "geared"])
    doc["joints"][2]["type"] = doc["joints"][3]["type"] = "prismatic"     # one on a turning link
    for jt in doc["joints"]:
        if "sea" in jt:
            jt["sea"]["d"] = 0.0
        if "gear_loss" in jt:
            jt["gear_loss"] = {"b": 0.0, "c": 0.0}
    arm = rscasadi.Arm(parse(tomllib.loads(to_toml(doc))))
    x = [ca.SX.sym(s, arm._size(s)) for s in ("theta", "phi", "dtheta", "dphi")]
    a, b = arm.forward_dynamics()(*x, ca.DM.zeros(arm.u))
    E = arm.energy()(*x)
    v = ca.vertcat(x[2], x[3], a, b)
    f = ca.Function("f", x, [ca.jtimes(E, ca.vertcat(*x), v), ca.norm_2(ca.gradient(E, ca.vertcat(*x))) * ca.norm_2(v)])
    rng = np.random.default_rng(1)
    for _ in range(3):
        rate, scale = (float(r) for r in f(*state(rng, arm, 2.0)[0]))
        assert abs(rate) < 1e-12 * scale and scale > 1.0


def test_kinds_read_back_and_every_misfit_is_named(tmp_path):
    """A link-list file of every kind, prismatic joints among them, writes and reads back the same
    robot; a kind that is no kind, a geared joint with a spring, a spring joint with rotors, a psi
    limit on a joint with no SEA, a type that is no type, an SEA that slides are each refused naming
    the joint and field; on a URDF, every joint whose kind cannot model its type is named in one
    message."""
    model = mixed(7, 7, slides=True)
    again = parse(tomllib.loads(to_toml(document(model))))
    assert [jt.kind for jt in again.joints] == [jt.kind for jt in model.joints]
    assert [jt.type for jt in again.joints] == [jt.type for jt in model.joints] and "prismatic" in {
        jt.type for jt in model.joints}
    rng = np.random.default_rng(2)
    x, tau = state(rng, rscasadi.Arm(model))
    a, b = (np.concatenate([dm(v) for v in rscasadi.Arm(m).forward_dynamics()(*x, tau)]) for m in (model, again))
    assert rel(a, b) < 1e-14
    base = document(model)
    names = {jt["kind"] if "kind" in jt else "sea": i for i, jt in enumerate(base["joints"])}
    cases = [(names["free"], {"kind": "wobbly"}, "kind", "expected one of sea, geared"),
             (names["geared"], {"sea": {"k1": 10.0}}, "sea", "a geared joint has no sea"),
             (names["spring"], {"gear_ratio": 10.0}, "gear_ratio", "a spring joint has no gear_ratio"),
             (names["direct"], {"limits": {"psi": 0.1}}, "limits.psi", "a direct joint has no psi"),
             (names["geared"], {"gear_loss": {"b": 0.1, "c1": 0.01}}, "gear_loss.c1", "no load term"),
             (names["free"], {"type": "helical"}, "type", 'expected "revolute" or "prismatic"'),
             (names["sea"], {"type": "prismatic"}, "type", "a sea joint cannot be prismatic")]
    for j, over, fld, words in cases:
        doc = copy.deepcopy(base)
        doc["joints"][j].update(over)
        with pytest.raises(ModelFileError) as err:
            parse(tomllib.loads(to_toml(doc)), "kinds.toml")
        assert f"'{fld}'" in str(err.value) and words in str(err.value) and doc["joints"][j]["name"] in str(err.value)
    urdf = ROOT / "tests" / "data" / "baxter_description" / "urdf" / "baxter.urdf"
    rotor = {"mass": 0.2, "com": [0.0, 0.0, 0.0], "inertia": [1e-4, 1e-4, 1.6e-4, 0.0, 0.0, 0.0]}
    joints = [{"name": "left_s0", "gear_ratio": 50.0, "sea": {"k1": 900.0}, "slow_rotor": rotor, "fast_rotor": rotor}]
    joints += [{"name": j, "kind": "free"} for j in ("left_s1", "left_e0", "left_e1", "left_w0", "left_w1", "left_w2")]
    joints += [{"name": "l_gripper_l_finger_joint", "kind": "geared", "gear_ratio": 10.0, "slow_rotor": rotor,
                "fast_rotor": rotor}, {"name": "l_gripper_r_finger_joint", "kind": "sea", "gear_ratio": 10.0,
                                       "sea": {"k1": 10.0}, "slow_rotor": rotor, "fast_rotor": rotor}]
    path = write_arm(tmp_path, {"name": "baxter", "urdf": str(urdf), "joints": joints}, "misfit.toml")
    with pytest.raises(ModelFileError) as err:
        rscasadi.load(path)
    message = str(err.value)
    assert "'l_gripper_l_finger_joint' is prismatic, which a geared joint cannot model" in message
    assert "'l_gripper_r_finger_joint' is prismatic, which a sea joint cannot model" in message
    assert "misfit.toml" in message


def test_a_whole_robot_of_mixed_kinds_from_its_urdf(tmp_path):
    """Baxter with SEA shoulders, geared wrists, a direct-drive head and its grippers' prismatic
    fingers (one driven, one on a spring, per hand): equal to Pinocchio's own parse of the URDF
    with the rotors as bodies, and exported to MuJoCo (hinges and slides), whose mass matrix
    and forces equal the model's."""
    import mujoco
    from rscasadi.export.mujoco import gear_map, mujoco_xml
    urdf = ROOT / "tests" / "data" / "baxter_description" / "urdf" / "baxter.urdf"
    rng = np.random.default_rng(3)
    def rotor(m, i):
        return {"mass": m, "com": list(rng.uniform(-1e-3, 1e-3, 3)), "inertia": [i, 1.1 * i, 1.6 * i, 0.0, 0.0, 0.0]}
    joints = [{"name": "head_pan", "kind": "direct", "limits": {"tau": 5.0}}]
    for side in ("left", "right"):
        for j in ("s0", "s1", "e0", "e1"):
            joints.append({"name": f"{side}_{j}", "gear_ratio": 100.0, "sea": {"k1": 3000.0, "d": 3.0},
                           "gear_loss": {"b": 1.0}, "slow_rotor": rotor(0.3, 2e-4), "fast_rotor": rotor(0.2, 1.5e-5)})
        for j in ("w0", "w1", "w2"):
            joints.append({"name": f"{side}_{j}", "kind": "geared", "gear_ratio": 80.0, "gear_loss": {"b": 0.2},
                           "slow_rotor": rotor(0.1, 5e-5), "fast_rotor": rotor(0.05, 5e-6)})
        joints += [{"name": f"{side[0]}_gripper_l_finger_joint", "kind": "direct", "limits": {"tau": 20.0}},
                   {"name": f"{side[0]}_gripper_r_finger_joint", "kind": "spring", "spring": {"k": 300.0, "theta0": -0.01},
                    "link_loss": {"b": 0.7}}]
    fingers = [f"{s}_gripper_{f}_finger" for s in "lr" for f in "lr"]
    doc = {"name": "baxter-kinds", "urdf": str(urdf), "tips": ["left_gripper", "right_gripper", "head"] + fingers,
           "joints": joints}
    arm = rscasadi.load(write_arm(tmp_path, doc, "baxter.toml"))
    assert (arm.n, arm.m, arm.u) == (19, 8, 17)
    assert [jt.name for jt in arm.model.joints if jt.type == "prismatic"] == [f + "_joint" for f in fingers]
    route = PinocchioRoute.from_urdf(arm.model)
    m = mujoco.MjModel.from_xml_string(mujoco_xml(arm.model))
    d, T = mujoco.MjData(m), gear_map(arm, m)
    for _ in range(3):
        x, tau = state(rng, arm)
        ddq = np.concatenate([dm(v) for v in arm.forward_dynamics()(*x, tau)])
        assert rel(ddq, np.concatenate(route.forward_dynamics(*x, tau))) < 1e-9
        mass, forces = mujoco_against_model(arm, m, d, T, x, tau)
        assert mass < 1e-12 and forces < 1e-12


def test_generated_c_of_a_robot_of_every_kind_equals_its_functions(tmp_path):
    """codegen on a tree of every kind, some joints sliding: the sizes are macros of the header
    (NQ joints, NM motors, NU inputs, NX state), every compiled Function equals its symbolic twin,
    the step equals RK4 of the forward dynamics, and the paper's SEA feedforward is omitted with
    the reason."""
    from rscasadi.codegen import functions, generate
    model = mixed(12, 7, slides=True)
    assert "prismatic" in {jt.type for jt in model.joints}
    path = write_arm(tmp_path, document(model), "kinds.toml")
    out = tmp_path / "gen"
    manifest = generate(path, out, opt="-O1", log=lambda m: None)
    arm = rscasadi.load(path)
    header = (out / manifest["header"]).read_text()
    for macro, value in (("NQ", arm.n), ("NM", arm.m), ("NU", arm.u), ("NX", 2 * (arm.n + arm.m))):
        assert f"#define ARM_{macro} {value} " in header
    assert "feedforward_step" in manifest["omitted"] and "controllers" not in manifest or not manifest["controllers"]
    compiled, (twins, _) = rscasadi.load_compiled(out), functions(arm)
    rng = np.random.default_rng(2)
    for name in manifest["functions"]:
        f, g = compiled[name], twins[name]
        args = [rng.normal(size=(g.size1_in(i), g.size2_in(i))) * (0.01 if g.name_in(i) == "h" else 1.0)
                for i in range(g.n_in())]
        for a, b in zip(f(*args) if f.n_out() > 1 else [f(*args)], g(*args) if g.n_out() > 1 else [g(*args)]):
            assert rel(np.array(a), np.array(b)) < 1e-11, name
    x, tau = state(rng, arm)
    x = np.concatenate(x)
    fd, h = arm.forward_dynamics(), 1e-3
    def f(z):
        parts = np.split(z, np.cumsum([arm.n, arm.m, arm.n]))
        return np.concatenate([parts[2], parts[3]] + [dm(v) for v in fd(*parts, tau)])
    k1 = f(x); k2 = f(x + h / 2 * k1); k3 = f(x + h / 2 * k2); k4 = f(x + h * k3)
    assert rel(dm(compiled["step"](x, tau, h)), x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)) < 1e-12


@pytest.mark.parametrize("seed,n,slides,method", [(12, 7, False, "rk4"), (3, 9, True, "rk4"), (3, 9, True, "ros2")])
def test_the_mpc_step_kernel_of_every_kind_equals_the_implicit_function_graph(seed, n, slides, method):
    """The MPC's structured step-Jacobian kernel (codegen.step_kernel, chained: three substeps of
    an interval) on trees of every kind (a state of 18 and 22 entries: not whole vectors of 4;
    inputs on motor rows, geared links and direct joints) against interval_functions without
    it (RK4: the step Function, the implicit-function graph's Jacobian chained by CasADi; ROS2:
    codegen.rosenbrock's graph): the state, A and B to 1e-12 of their size at random states and
    torques; the second tree has prismatic joints."""
    from rscasadi.mpc.formulation import interval_functions
    from rscasadi.mpc.generate import step_kernel
    from rscasadi.native.build import compiler
    arm = rscasadi.Arm(mixed(seed, n, slides=slides))
    _, kernel = step_kernel(arm, ["-O1", "-std=c99"], compiler(), log=lambda m: None, method=method)
    assert kernel is not None and kernel.size1_in(1) == arm.u
    chained, _ = interval_functions(arm, 0.002, 3, kernel, method)
    graph, _ = interval_functions(arm, 0.002, 3, integrator=method)
    rng = np.random.default_rng(seed)
    for _ in range(3):
        x, tau = state(rng, arm, 0.05)
        x = 0.05 * np.concatenate(x)
        for a, b in zip(chained(x, tau, []), graph(x, tau, [])):
            assert rel(np.array(a), np.array(b)) < 1e-12


def test_what_takes_only_seas_refuses_other_kinds_by_name(tmp_path):
    """Identification, the frequency response and the interaction controllers are written for
    robots of SEAs: given a geared joint, each refuses before any work, naming the joint and its
    kind."""
    from rscasadi.errors import InvalidArgument
    from rscasadi.identification import frf, identify
    from rscasadi.identification.excitation import design
    from rscasadi.interaction import generate_observer
    doc = with_kinds(random_tree_doc(np.random.default_rng(1), 3), ["sea", "geared", "sea"])
    for jt in doc["joints"]:
        jt["limits"] = {"tau": 1.0}
    path = write_arm(tmp_path, doc, "geared.toml")
    arm = rscasadi.load(path)
    calls = [lambda: design(arm, period=1.0, harmonics=1),
             lambda: identify.run(path, [tmp_path / "none.csv"], tmp_path / "id"),
             lambda: frf.run(path, tmp_path / "frf"),
             lambda: generate_observer(path, tmp_path / "obs", 10.0),
             ]
    for call in calls:
        with pytest.raises(InvalidArgument, match=r"all SEAs; joints of other kinds: j2 \(geared\)"):
            call()
    assert not (tmp_path / "id").exists() and not (tmp_path / "frf").exists() and not (tmp_path / "obs").exists()


def test_simulation_of_every_kind_follows_pinocchio(tmp_path):
    """simulate (CVODES on the model's forward dynamics) on a tree of every kind under varying
    torques = scipy's integrator on Pinocchio's M, h and the kinds' forces (no shared code)."""
    from scipy.integrate import solve_ivp
    from rscasadi.sim.simulation import simulate
    arm = rscasadi.Arm(mixed(4, 5, ["sea", "geared", "direct", "spring", "free"], slides=True))   # direct, free slide
    route, rng = PinocchioRoute(arm.model), np.random.default_rng(4)
    x0 = [0.3 * v for v in state(rng, arm, 0.3)[0]]
    t = np.linspace(0.0, 0.05, 11)
    tau = rng.normal(size=(arm.u, len(t)))
    sim = simulate(arm, np.concatenate(x0), t, tau, tol=1e-11)
    n, q = arm.n, arm.nq
    def f(s, z):
        u = np.array([np.interp(s, t, row) for row in tau])
        a, b = route.forward_dynamics(z[:n], z[n:q], z[q:q + n], z[q + n:], u)
        return np.r_[z[q:], a, b]
    ref = solve_ivp(f, (0.0, 0.05), np.concatenate(x0), t_eval=t, rtol=1e-11, atol=1e-11, method="DOP853").y
    assert sim["phi"].shape == (arm.m, len(t)) and sim["psi"].shape == (arm.m, len(t))
    assert np.max(np.abs(sim["x"] - ref)) < 1e-8 * np.max(np.abs(ref))


def test_optimal_control_of_every_kind_is_verified_and_rests_where_it_hangs(tmp_path):
    """A minimum-time motion of a tree with an SEA, a geared joint (speed-limited), a prismatic
    direct drive and a passive spring: the condensed implicit form with fatrop and the lifted explicit
    form with IPOPT find the same duration; the torques replayed on the complete model verify;
    the geared joint runs at its speed limit, which sets most of the time; the passive joint starts and ends
    balanced by its spring and gravity (Pinocchio's M, h and forces, to 1e-6 of gravity)."""
    import dataclasses
    from rscasadi.ocp.problem import load_problem
    from rscasadi.ocp.solving import solve
    rng = np.random.default_rng(5)
    doc = with_kinds(random_tree_doc(rng, 4), ["sea", "geared", "direct", "spring"], rng)
    doc["joints"][2]["type"] = "prismatic"
    for jt in doc["joints"]:
        jt["limits"] = {"tau": 200.0 if jt.get("type") else 50.0} if jt.get("kind") != "spring" else {}
        if jt.get("kind") == "geared":
            jt["limits"]["dphi"] = 1.0
    write_arm(tmp_path, doc, "kinds.toml")
    (tmp_path / "ocp.toml").write_text(
        'model = "kinds.toml"\nobjective = "min_time"\ntheta_start = [0.0, 0.0, 0.0, 0.0]\n'
        'theta_end = [0.5, -0.4, 0.3, 0.0]\nduration = 1.0\nmax_duration = 3.0\neffort_weight = 1e-3\n'
        '[transcription]\nintervals = 20\n')
    problem = load_problem(tmp_path / "ocp.toml")
    fatrop = solve(problem, log=lambda m: None, print_level=0)
    lifted = dataclasses.replace(problem.transcription, condense=False, dynamics="explicit")
    ipopt = solve(problem.replace(solver="ipopt", transcription=lifted), log=lambda m: None, print_level=0)
    assert fatrop.success and ipopt.success and fatrop.verified and ipopt.verified
    assert abs(fatrop.t[-1] - ipopt.t[-1]) < 1e-6 * fatrop.t[-1]
    arm = fatrop.arm()
    assert fatrop.phi.shape[0] == arm.m == 1 and fatrop.tau.shape[0] == arm.u == 3
    assert 0.4 <= fatrop.t[-1] < 0.5        # 0.4 rad at the geared joint's 1 rad/s, the spring on the slide settling
    speed = fatrop.sample("dtheta", np.linspace(0, fatrop.t[-1], 200))[1]
    assert abs(np.abs(speed).max() - 1.0) < 5e-3
    route = PinocchioRoute(arm.model)
    for k in (0, -1):
        th, ph = fatrop.theta[:, k], fatrop.phi[:, k]
        M, h = route.mass_bias(th, ph, np.zeros(4), np.zeros(1))
        Q = route.forces(th, ph, np.zeros(4), np.zeros(1), np.zeros(3))
        assert abs((Q - h)[3]) < 1e-6 * np.abs(h).max()


def test_the_c_mpc_drives_a_robot_of_every_kind_in_mujoco(tmp_path):
    """The generated MPC of a tree with an SEA, a speed-limited geared joint, a prismatic direct
    drive and a damped passive spring (its inputs one per actuated joint, its state the 10
    coordinates' and speeds),
    closing the loop at 1 kHz on the MuJoCo export: from rest to rest at a pose (the passive
    joint where it then hangs) in 1.5 s, every torque within its limit, the geared joint within
    its speed limit; fuzzed, bad measurements and targets refused by code with the holding
    torque of the last good state."""
    from rscasadi.dynamics.statics import rest, rest_state
    from rscasadi.export.mujoco import mujoco_plant
    from rscasadi.mpc.compiled import CompiledMPC
    from rscasadi.mpc.generate import generate_mpc
    from rscasadi.mpc.study import _MPC
    from rscasadi.sim.loop import Encoders, limit_violation, run_loop
    rng = np.random.default_rng(5)
    doc = with_kinds(random_tree_doc(rng, 4), ["sea", "geared", "direct", "spring"], rng)
    doc["joints"][2]["type"] = "prismatic"
    for jt in doc["joints"]:
        kind = jt.get("kind", "sea")
        jt["limits"] = {"tau": 100.0} if kind == "direct" else {} if kind == "spring" else {"tau": 0.5}
        if kind == "sea":
            jt["sea"]["k3"] = 0.0                                # MuJoCo's tendon is linear
        if "gear_loss" in jt:
            jt["gear_loss"] = {"b": jt["gear_loss"].get("b", 0.0)}   # and its friction another law
        if kind == "geared":
            jt["limits"]["dphi"] = 1.0
        if kind == "spring":
            jt["link_loss"] = {"b": 0.5}
    write_arm(tmp_path, doc, "kinds.toml")
    (tmp_path / "mpc.toml").write_text('model = "kinds.toml"\nsample_time = 0.001\nhorizon = 10\ninterval = 0.01\n'
                                       'substeps = "auto"\n[weights]\ntheta = 1e5\ndtheta = 1.0\ntau = 1e-3\n'
                                       'limits = 1e5\n')
    manifest = generate_mpc(tmp_path / "mpc.toml", tmp_path / "mpc", opt="-O1", log=lambda m: None)
    arm = rscasadi.load(tmp_path / "kinds.toml")
    assert manifest["sizes"]["x"] == 2 * arm.nq == 10 and manifest["sizes"]["tau"] == arm.u == 3
    target = rest(arm, np.array([0.4, -0.3, 0.2, 0.0]))[0]       # the slide to 0.2 m
    dt = 0.001
    run = run_loop(arm, mujoco_plant(arm, dt), _MPC(CompiledMPC(tmp_path / "mpc"), target=target),
                   rest_state(arm, np.zeros(4)), 1500, dt, sensors=Encoders(arm, dt, exact=True))
    error = np.abs(run.x[:arm.n, -1] - target)
    assert np.all(error[:3] < 1e-3) and error[3] < 5e-3, error
    assert np.all(np.abs(run.tau) <= np.array([0.5, 0.5, 100.0])[:, None] + 1e-12)
    assert np.abs(run.x[arm.nq + 1]).max() < 1.0 * 1.01 and limit_violation(arm, run) < 0.01
    # fuzzed: a bad entry in 40 % of the measurements or targets is refused by its code (6, 7), the
    # output stays finite and within the limits, and the next good sample is acted on
    from rscasadi.dynamics.statics import holding_torque
    limit = np.array([0.5, 0.5, 100.0])
    hold = lambda x: np.clip(np.array(holding_torque(arm)(x[:4], x[4:5])).ravel(), -limit, limit)   # noqa: E731
    mpc, x0 = CompiledMPC(tmp_path / "mpc"), rest_state(arm, np.zeros(4))
    assert mpc.init(x0) == 0
    codes, good = [], x0
    for k in range(100):
        x, goal = x0 + rng.normal(0, 1e-3, x0.size), target.copy()
        bad = rng.choice(["good", "x", "target"], p=[0.6, 0.2, 0.2])
        if bad != "good":
            v = x if bad == "x" else goal
            v[rng.integers(v.size)] = [np.nan, np.inf, -np.inf, 1e300, 1e3][rng.integers(5)]
        tau, _, code = mpc.step_to(x, goal)
        assert code == {"good": 0, "x": 6, "target": 7}[bad], (k, bad, code)
        assert np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= limit + 1e-12), k
        good = good if bad == "x" else x
        if bad != "good":                                # the holding torque of the last good state
            assert np.max(np.abs(tau - hold(good))) < 1e-9, (k, bad)
        codes.append(code)
    assert {0, 6, 7} <= set(codes)


@pytest.mark.parametrize("seed,n,parametric,pieces", [(3, 9, False, True), (5, 14, True, False)])
def test_the_forward_dynamics_jacobian_kernel_equals_finite_differences(seed, n, parametric, pieces, tmp_path,
                                                                       monkeypatch):
    """The forward dynamics' Jacobian as the structured kernel (codegen.step_kernel, method
    "fd_jacobian": M^-1 [-dr/dx | dQ/dtau] in column blocks) on random trees of every kind with
    prismatic joints, with and without the parameter vector: equal to central differences of the
    forward dynamics (nothing shared but the dynamics) to 1e-6, and to the Function it replaces
    to 1e-12.  Past straight-line SX (the 14-joint tree: an MX graph) `rscasadi codegen` puts the
    kernel in the library in the Function's place (manifest "kernels"): that library is checked.
    pieces: dr/dx written by codegen.lanes in functions of a few statements (as on large trees)."""
    import rscasadi.codegen.lanes as lanes
    import rscasadi.codegen.step_kernel as step_kernel
    if pieces:
        monkeypatch.setattr(step_kernel, "JR_PIECES_FROM", 0)
        monkeypatch.setattr(lanes, "CHUNK", 7)
    import casadi as ca
    from rscasadi.codegen import generate, load_compiled
    from rscasadi.codegen.generate import forward_dynamics_jacobian
    from rscasadi.codegen.step_kernel import kernel_source
    from rscasadi.native.build import casadi_c, cached_library, compiler
    model = mixed(seed, n, slides=True)
    arm = rscasadi.Arm.family(model) if parametric else rscasadi.Arm(model)
    function = forward_dynamics_jacobian(arm, parametric)
    if function.is_a("SXFunction"):               # codegen keeps the Function here: the kernel compiled alone
        k = kernel_source(arm, "fdj", parametric, method="fd_jacobian")
        lib = cached_library({"fdj.c": casadi_c(k.functions, "fdj.c") + k.body}, ["-O1", "-std=c99"], name="fdj",
                             cc=compiler())
        kernel = ca.external("fdj", str(lib))
    else:
        manifest = generate(arm, tmp_path / "c", opt="-O1", log=lambda m: None, only=["forward_dynamics_jacobian"],
                            parametric="family" if parametric else "none")
        assert "forward_dynamics_jacobian" in manifest["kernels"]
        kernel = load_compiled(tmp_path / "c")["forward_dynamics_jacobian"]
    fd = arm.forward_dynamics(parametric=parametric)
    rng = np.random.default_rng(seed)
    names, values = arm.parameters()
    p = [np.array([values[names.index(k)] for k in arm.free])] if parametric else []
    for _ in range(2):
        x, tau = state(rng, arm, 0.5)
        J = np.array(kernel(*x, tau, *p))
        assert rel(J, np.array(function(*x, tau, *p))) < 1e-12
        z, h = np.concatenate(x + [tau]), 1e-6
        split = np.cumsum([len(v) for v in x])

        def acc(zz):
            return np.concatenate([np.array(v).ravel() for v in fd(*np.split(zz, split), *p)])
        E = np.eye(len(z))
        numeric = np.stack([(acc(z + h * E[i]) - acc(z - h * E[i])) / (2 * h) for i in range(len(z))], axis=1)
        assert rel(J, numeric) < 1e-6, rel(J, numeric)
