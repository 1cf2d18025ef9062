"""Floating bases and contacts (docs/user-guide/floating.md) against Pinocchio with a free-flyer
and the rotors as bodies (reference.pinocchio_route: its crba, rnea, frame Jacobians, classical
and spatial frame accelerations, centroidal momentum and integrate; the KKT system solved here in
numpy as one dense system), on random floating trees of every kind and on public robots parsed
by Pinocchio itself: ANYmal C and Solo-12 (quadrupeds) and the Unitree G1 (humanoid); then
physics: momentum and energy conserved in flight, contacts held still, impacts."""
from __future__ import annotations

import tomllib

import numpy as np
import pinocchio as pin
import pytest

from conftest import ROOT, random_tree_doc, to_toml, with_kinds, write_arm
import rscasadi
from rscasadi.dynamics.floating import FloatingRobot, from_mujoco, to_mujoco
from rscasadi.errors import InvalidArgument, NotFound
from rscasadi.model.modelfile import ModelFileError, parse, read
from rscasadi.reference.pinocchio_route import PinocchioRoute

DATA = ROOT / "tests" / "data"
ANYMAL = ROOT / "problems" / "anymal_c_sea.toml"
FEET = ["LF_FOOT", "RF_FOOT", "LH_FOOT", "RH_FOOT"]
G1_LEG = ("hip_pitch", "hip_roll", "hip_yaw", "knee", "ankle_pitch", "ankle_roll")
G1_ARM = ("shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow", "wrist_roll", "wrist_pitch", "wrist_yaw")


def rel(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)


def col(x):
    return np.asarray(x, float).ravel()


def random_q(robot, rng, spread=np.pi):
    quat = rng.normal(size=4)
    return np.r_[rng.normal(size=3), quat / np.linalg.norm(quat), rng.uniform(-spread, spread, robot.n + robot.m)]


def floating_tree(seed, n, kinds=None):
    rng = np.random.default_rng(seed)
    doc = random_tree_doc(rng, n)
    if kinds:
        doc = with_kinds(doc, kinds, rng)
    doc.update(floating=True, base={"mass": 6.0, "com": [0.03, -0.01, 0.02], "inertia": [0.12, 0.15, 0.09, 0.01, 0.0, -0.004]})
    return FloatingRobot(parse(tomllib.loads(to_toml(doc))))


def g1_doc():
    rng = np.random.default_rng(29)

    def rotor(m, i):
        return {"mass": m, "com": list(rng.uniform(-2e-3, 2e-3, 3)), "inertia": [i, 1.1 * i, 1.6 * i, 1e-2 * i, 0, 0]}
    joints = ([f"{s}_{j}_joint" for s in ("left", "right") for j in G1_LEG] + ["waist_yaw_joint", "waist_roll_joint",
              "waist_pitch_joint"] + [f"{s}_{j}_joint" for s in ("left", "right") for j in G1_ARM])
    entries = []
    for name in joints:                   # SEA legs, geared waist and shoulders, direct wrists and elbows
        kind = ("sea" if "hip" in name or "knee" in name or "ankle" in name else
                "geared" if "waist" in name or "shoulder" in name else "direct")
        e = {"name": name, **({} if kind == "sea" else {"kind": kind})}
        if kind != "direct":
            e.update(gear_ratio=float(rng.uniform(30, 120)), gear_loss={"b": 0.5}, slow_rotor=rotor(0.2, 1e-4),
                     fast_rotor=rotor(0.1, 1e-5))
        if kind == "sea":
            e["sea"] = {"k1": 1500.0, "d": 1.0}
        entries.append(e)
    return {"name": "g1-floating", "urdf": str(DATA / "g1_description" / "urdf" / "g1_29dof_rev_1_0.urdf"),
            "floating": True, "joints": entries}


def solo_doc():
    joints = [f"{leg}_{j}" for leg in ("FL", "FR", "HL", "HR") for j in ("HAA", "HFE", "KFE")]
    rotor = {"mass": 0.05, "com": [0.0, 0.0, 0.0], "inertia": [2e-6, 2e-6, 3e-6, 0.0, 0.0, 0.0]}
    return {"name": "solo12-sea", "urdf": str(DATA / "solo_description" / "robots" / "solo12.urdf"), "floating": True,
            "joints": [{"name": j, "gear_ratio": 9.0, "sea": {"k1": 40.0, "d": 0.05}, "gear_loss": {"b": 0.001},
                        "slow_rotor": rotor, "fast_rotor": rotor} for j in joints]}


def public(tmp_path, name):
    if name == "anymal":
        return FloatingRobot(read(ANYMAL))
    doc = g1_doc() if name == "g1" else solo_doc()
    return FloatingRobot(rscasadi.load(write_arm(tmp_path, doc, f"{name}.toml")).model)


def pinocchio_kkt(route, q, v, Q, contacts):
    """a and f from Pinocchio's M, nle, frame Jacobians and drifts: one dense KKT solve."""
    M, h = route.dynamics(q, v)
    J, gamma = [], []
    for frame, kind in contacts:
        if kind == "point":      # the origin's velocity and classical acceleration, world axes
            Jf, classical, _, _ = route.frame_motion(frame, q, v, pin.LOCAL_WORLD_ALIGNED)
            J.append(Jf[:3]), gamma.append(classical[:3])
        else:                    # the frame's velocity and spatial acceleration, its own axes
            Jf, _, spatial, _ = route.frame_motion(frame, q, v, pin.LOCAL)
            J.append(Jf), gamma.append(spatial)
    J, gamma = np.vstack(J), np.concatenate(gamma)
    K = np.block([[M, -J.T], [J, np.zeros((len(gamma), len(gamma)))]])
    sol = np.linalg.solve(K, np.r_[Q - h, -gamma])
    return sol[:len(v)], sol[len(v):], J, gamma, M, h


def check(robot, route, rng, frames, contacts, states=2):
    """Every Function against the Pinocchio route at random states, to 1e-9."""
    fd, inv, mass, nle, forces = (robot.forward_dynamics(), robot.inverse_dynamics(), robot.mass_matrix(),
                                  robot.nonlinear_effects(), robot.generalized_forces())
    cd, cinv, imp = robot.contact_dynamics(contacts), robot.contact_inverse_dynamics(contacts), robot.impact(contacts)
    for _ in range(states):
        q, v, tau = random_q(robot, rng, 1.0), rng.normal(size=robot.nv), rng.normal(size=robot.u)
        qt, vt = route.tree_state(q, v)
        Q = col(forces(q, v, tau))
        a_ref, f_ref, J, gamma, M, h = pinocchio_kkt(route, q, v, Q, contacts)
        assert rel(mass(q), M) < 1e-9 and rel(col(nle(q, v)), h) < 1e-9
        a_free = col(fd(q, v, tau))
        assert rel(a_free, np.linalg.solve(M, Q - h)) < 1e-9
        tau_back, _, base = inv(q, v, a_free)
        assert rel(col(tau_back), tau) < 1e-9 and np.max(np.abs(col(base))) < 1e-9 * max(1, np.max(np.abs(h)))
        assert rel(np.asarray(robot.contact_jacobian(contacts)(q)), J) < 1e-9
        assert rel(col(robot.contact_drift(contacts)(q, v)), gamma) < 1e-9
        a, f = (col(x) for x in cd(q, v, tau))
        assert rel(a, a_ref) < 1e-9 and rel(f, f_ref) < 1e-9
        tau_c, _, base_c = cinv(q, v, a, f)
        assert rel(col(tau_c), tau) < 1e-8 and np.max(np.abs(col(base_c))) < 1e-8 * max(1, np.max(np.abs(h)))
        v_plus, impulse = (col(x) for x in imp(q, v))
        assert np.max(np.abs(J @ v_plus)) < 1e-9 * max(1, np.max(np.abs(v)))
        assert rel(M @ (v_plus - v), J.T @ impulse) < 1e-9
        pin.computeCentroidalMomentum(route.model, route.data, qt, vt)
        assert rel(col(robot.centroidal_momentum()(q, v)), route.data.hg.vector) < 1e-9
        assert rel(col(robot.center_of_mass()(q)), pin.centerOfMass(route.model, route.data, qt)) < 1e-9
        A = pin.ccrba(route.model, route.data, qt, vt) @ route.G
        assert rel(np.asarray(robot.centroidal_momentum_matrix()(q)), A) < 1e-9
        for frame in frames:
            for ref, pref in (("local", pin.LOCAL), ("local_world_aligned", pin.LOCAL_WORLD_ALIGNED)):
                Jf, classical, _, oMf = route.frame_motion(frame, q, v, pref)
                assert rel(np.asarray(robot.frame_jacobian(frame, ref)(q)), Jf) < 1e-9
                got = col(robot.frame_classical_acceleration(frame, ref)(q, v, np.zeros(robot.nv)))
                assert np.max(np.abs(got - classical)) < 1e-9 * max(1, np.max(np.abs(classical)))
            R, p = robot.frame_placement(frame)(q)
            assert np.max(np.abs(np.asarray(R) - oMf.rotation)) < 1e-9
            assert np.max(np.abs(col(p) - oMf.translation)) < 1e-9
        dt = rng.uniform(0.01, 0.5)
        q_next = col(robot.integrate()(q, v, dt))
        assert np.max(np.abs(q_next[:7] - pin.integrate(route.model, qt, vt * dt)[:7])) < 1e-12
        assert abs(np.linalg.norm(q_next[3:7]) - 1) < 1e-14


@pytest.mark.parametrize("seed,kinds", [(1, None), (2, ["sea", "geared", "spring", "sea", "free", "direct", "geared", "sea"])])
def test_random_floating_trees_equal_pinocchio(seed, kinds):
    """Random trees on a free-flyer (branching on the base and on links, random axes, unbalanced
    rotors, random gravity, every joint kind): M, h, the free and the contact dynamics (a point
    and a flat contact), the inverse dynamics with and without contact forces, the impact, the
    frames, the centre of mass, the centroidal momentum and its matrix, integrate."""
    robot = floating_tree(seed, 8, kinds)
    rng = np.random.default_rng(seed)
    leaves = [f"j{j + 1}" for j in range(robot.n) if not robot.model.children(j)]
    contacts, q = [], random_q(robot, rng, 1.0)
    for frame, kind in [(leaves[0], "flat")] + [(f, "point") for f in leaves[1:]]:   # those the tree can hold
        try:
            robot.check_contacts(contacts + [(frame, kind)], q)
            contacts.append((frame, kind))
        except InvalidArgument as err:
            assert "undetermined" in str(err) and repr(frame) in str(err)
    assert len(contacts) >= 2 and contacts[0][1] == "flat"
    check(robot, PinocchioRoute(robot.model), rng, leaves + ["base"], contacts)


@pytest.mark.parametrize("name", ["anymal", "solo", "g1"])
def test_public_legged_robots_equal_pinocchio_s_own_urdf_parse(tmp_path, name):
    """ANYmal C and Solo-12 (SEAs in all 12 joints, four point feet) and the Unitree G1 (29 joints:
    SEA legs, geared waist and shoulders, direct elbows and wrists; two flat feet) with a
    free-flyer at the URDF's root: Pinocchio parses the URDF itself (fixed links merged into the
    base and the links), our rotors added as bodies."""
    robot = public(tmp_path, name)
    route = PinocchioRoute.from_urdf(robot.model)
    if name == "g1":
        feet = ["left_ankle_roll_link", "right_ankle_roll_link"]
        contacts = [(f, "flat") for f in feet]
    else:
        feet = FEET if name == "anymal" else ["FL_FOOT", "FR_FOOT", "HL_FOOT", "HR_FOOT"]
        contacts = [(f, "point") for f in feet]
    assert robot.model.floating and robot.n == (29 if name == "g1" else 12)
    check(robot, route, np.random.default_rng(7), feet[:2] + ["base" if name == "anymal" else robot.frames()[0]],
          contacts, states=1)


def test_momentum_and_energy_are_conserved_in_flight():
    """No losses, no input: along the flight's flow (central differences on the manifold), the
    energy is constant, the momentum about the world origin (rotors' spin included) changes as
    gravity says (d/dt linear = m g, angular = c x m g) and, without gravity, not at all: the
    articulated sweep's accelerations against momentum and energy summed body by body."""
    robot = floating_tree(4, 6)
    doc = tomllib.loads(to_toml(rscasadi.model.modelfile.document(robot.model)))
    for jt in doc["joints"]:
        jt["gear_loss"] = {"b": 0.0, "c": 0.0, "eps": 0.01}
        jt["sea"]["d"] = 0.0
    rng = np.random.default_rng(4)
    for gravity in ([0.0, 0.0, 0.0], [0.5, -1.0, -9.81]):
        robot = FloatingRobot(parse({**doc, "gravity": gravity}))
        fd, step, h, E, com = (robot.forward_dynamics(), robot.integrate(), robot.centroidal_momentum(),
                               robot.energy(), robot.center_of_mass())
        mass = sum(b.mass for jt in robot.model.joints for b in (jt.link, jt.slow_rotor, jt.fast_rotor)) + 6.0

        def world(q, v):               # momentum about the world origin: centroidal + c x linear
            hg, c = col(h(q, v)), col(com(q))
            return np.r_[hg[:3], hg[3:] + np.cross(c, hg[:3])]
        for _ in range(3):
            q, v = random_q(robot, rng, 0.5), 0.5 * rng.normal(size=robot.nv)
            q[7 + robot.n:] = q[7:7 + robot.n] + 0.05 * rng.normal(size=robot.n)     # springs near rest
            a, eps = col(fd(q, v, np.zeros(robot.u))), 1e-6
            ahead, back = (col(step(q, v, eps)), v + eps * a), (col(step(q, v, -eps)), v - eps * a)
            dh = (world(*ahead) - world(*back)) / (2 * eps)
            dE = (float(E(*ahead)) - float(E(*back))) / (2 * eps)
            g = mass * np.array(gravity)
            expected = np.r_[g, np.cross(col(com(q)), g)]
            scale = max(np.max(np.abs(world(q, v))), np.max(np.abs(g)), 1.0)
            assert np.max(np.abs(dh - expected)) < 1e-6 * scale
            assert abs(dE) < 1e-6 * max(abs(float(E(q, v))), 1.0)


def test_the_rotors_spin_is_in_the_centroidal_momentum():
    """ANYmal with its base and links still and every motor turning at 10 rad/s: the centroidal
    momentum is the rotors' spin alone, sum over joints of (I_slow - mu I_fast) 10 rad/s about
    each joint's axis in the world (the fast rotor turns at -mu dphi), and no linear momentum:
    what an armature model (the links' momentum only) leaves out and what turns a flying base."""
    robot = FloatingRobot(read(ANYMAL))
    rng = np.random.default_rng(8)
    q = np.r_[0.1, -0.2, 0.5, 0.0, 0.0, np.sin(0.3), np.cos(0.3), 0.3 * rng.normal(size=robot.n), np.zeros(robot.m)]
    v = np.zeros(robot.nv)
    v[6 + robot.n:] = 10.0
    hg = col(robot.centroidal_momentum()(q, v))
    expected = np.zeros(3)
    for j, jt in enumerate(robot.model.joints):
        frame = next(f for f in robot.model.frames if f.body == j + 1)
        axis = (np.asarray(robot.frame_placement(frame.name)(q)[0]) @ frame.R.T)[:, 2]   # the link frame's z
        spin = jt.slow_rotor.inertia_origin[2, 2] - jt.gear_ratio * jt.fast_rotor.inertia_origin[2, 2]
        expected += axis * spin * 10.0
    assert np.max(np.abs(hg[:3])) < 1e-12 and np.linalg.norm(expected) > 0.1
    assert np.max(np.abs(hg[3:] - expected)) < 1e-12


def test_contacts_are_held_and_the_base_is_pinocchio_s_and_mujoco_s():
    """ANYmal standing on four point feet: 0.2 s of contact dynamics keeps the feet within 1e-6 m
    of where they started (the KKT with a small damping); the conversions to MuJoCo's free joint
    and back are exact and rotate the linear velocity into world axes."""
    robot = FloatingRobot(read(ANYMAL))
    rng = np.random.default_rng(3)
    q = np.r_[0, 0, 0.6, 0, 0, 0, 1, 0.1 * rng.normal(size=robot.n), np.zeros(robot.m)]
    q[7 + robot.n:] = q[7:7 + robot.n]
    v = np.zeros(robot.nv)
    cd, step = robot.contact_dynamics(FEET, damping=20.0), robot.integrate()
    feet = [robot.frame_placement(f) for f in FEET]
    p0 = np.concatenate([col(f(q)[1]) for f in feet])
    tau, dt = np.zeros(robot.u), 5e-4
    for _ in range(400):
        a, _ = cd(q, v, tau)
        v = v + dt * col(a)
        q = col(step(q, v, dt))
    p1 = np.concatenate([col(f(q)[1]) for f in feet])
    assert np.max(np.abs(p1 - p0)) < 1e-6 and np.max(np.abs(q[:3] - [0, 0, 0.6])) > 1e-3   # it moved
    quat = rng.normal(size=4)
    qb, vb = np.r_[rng.normal(size=3), quat / np.linalg.norm(quat)], rng.normal(size=6)
    qpos, qvel = to_mujoco(qb, vb)
    assert np.allclose(qpos[3:], np.r_[qb[6], qb[3:6]]) and np.isclose(np.linalg.norm(qvel[:3]), np.linalg.norm(vb[:3]))
    back = from_mujoco(qpos, qvel)
    assert np.allclose(back[0], qb, atol=1e-15) and np.allclose(back[1], vb, atol=1e-14)


def test_bad_floating_input_is_named(tmp_path):
    """A [base] without floating, floating without a [base], a floating flag that is no bool, an
    unknown contact frame or kind, a frame given twice, a fixed-base model given to FloatingRobot:
    clear errors naming the field or the frame."""
    doc = random_tree_doc(np.random.default_rng(1), 3)
    base = {"mass": 1.0, "com": [0, 0, 0], "inertia": [0.1, 0.1, 0.1, 0, 0, 0]}
    for change, words in (({"base": base}, "floating = true"), ({"floating": True}, "[base]"),
                          ({"floating": "yes", "base": base}, "'floating'")):
        with pytest.raises(ModelFileError, match=None) as err:
            parse(tomllib.loads(to_toml({**doc, **change})), "legs.toml")
        assert words in str(err.value) and "legs.toml" in str(err.value)
    with pytest.raises(InvalidArgument, match="floating = true"):
        FloatingRobot(parse(tomllib.loads(to_toml(doc))))
    with pytest.raises(ModelFileError, match="floating robot's"):
        parse(tomllib.loads(to_toml({**doc, "contacts": [{"frame": "j2"}]})), "legs.toml")
    contacts = [{"frame": "j2"}, {"frame": "toe"}, {"frame": "j3", "kind": "line"}, {"frame": "j2"},
                {"frame": "j1", "size": [0.1, 0.05]}, {"frame": "base", "kind": "flat", "size": [0.1, -1.0]}]
    with pytest.raises(ModelFileError) as err:
        parse(tomllib.loads(to_toml({**doc, "floating": True, "base": base, "contacts": contacts})), "legs.toml")
    assert all(w in str(err.value) for w in ("'toe'", "'line'", "'j2' given twice", "legs.toml", "('j1'): size",
                                             "('base'): size"))
    robot = floating_tree(1, 4)
    with pytest.raises(InvalidArgument) as err:
        robot.contact_dynamics(["j2", ("nowhere", "point"), ("j3", "line"), "j2"])
    assert all(w in str(err.value) for w in ("'nowhere'", "'line'", "'j2' given twice"))
    with pytest.raises(NotFound):
        robot.frame_placement("nowhere")
    from rscasadi.dynamics.floating import unit_configuration
    q = random_q(robot, np.random.default_rng(0))
    with pytest.warns(UserWarning, match="norm 2"):
        assert np.allclose(unit_configuration(robot, np.r_[q[:3], 2 * q[3:7], q[7:]], "q0"), q)
    with pytest.raises(InvalidArgument, match="zero"):
        unit_configuration(robot, np.r_[q[:3], np.zeros(4), q[7:]], "q0")
    with pytest.raises(InvalidArgument, match="finite"):
        unit_configuration(robot, q[:-1], "q0")
    with pytest.raises(InvalidArgument, match="reference"):
        robot.frame_jacobian("j2", "world")


@pytest.mark.parametrize("stiffness", [0.0, 100.0])
def test_contact_dynamics_jacobian_equals_finite_differences_on_the_manifold(stiffness):
    """ANYmal on its four feet (damping 5/s; and a Baumgarte stiffness towards anchors 1 cm off):
    the implicit-function Jacobian of the contact dynamics by
    (dq, v, tau), dq moving q along integrate(q, dq), equals central differences of the contact
    dynamics themselves to 1e-6."""
    robot = FloatingRobot(read(ANYMAL))
    rng = np.random.default_rng(1)
    quat = rng.normal(size=4)
    q = np.r_[0, 0, 0.6, quat / np.linalg.norm(quat), 0.3 * rng.normal(size=robot.n + robot.m)]
    v, tau = rng.normal(size=robot.nv), rng.normal(size=robot.u)
    anchors = [np.concatenate([col(robot.frame_placement(f)(q)[1]) + 0.01 for f in FEET])] if stiffness else []
    da, df = (np.asarray(x) for x in robot.contact_dynamics_jacobian(damping=5.0, stiffness=stiffness)(q, v, tau, *anchors))
    cd, step, eps = robot.contact_dynamics(damping=5.0, stiffness=stiffness), robot.integrate(), 1e-6
    for i in rng.choice(2 * robot.nv + robot.u, 12, replace=False):
        e = np.zeros(2 * robot.nv + robot.u)
        e[i] = eps
        ahead = [col(x) for x in cd(col(step(q, e[:robot.nv], 1.0)), v + e[robot.nv:-robot.u], tau + e[-robot.u:],
                                    *anchors)]
        back = [col(x) for x in cd(col(step(q, -e[:robot.nv], 1.0)), v - e[robot.nv:-robot.u], tau - e[-robot.u:],
                                   *anchors)]
        assert np.max(np.abs(da[:, i] - (ahead[0] - back[0]) / (2 * eps))) < 1e-6 * max(1, np.max(np.abs(da)))
        assert np.max(np.abs(df[:, i] - (ahead[1] - back[1]) / (2 * eps))) < 1e-6 * max(1, np.max(np.abs(df)))


def test_baumgarte_gains_pull_the_feet_back_to_their_anchors():
    """ANYmal standing with its feet 5 mm from where they are held (anchors), damping 20/s and
    stiffness 100/s^2 (critically damped at 10 rad/s): over 1 s of contact dynamics the feet's
    errors (contacts.errors, as the constraint sees them) shrink a hundredfold and more, a flat
    contact's rotation error too; without the stiffness they stay."""
    from rscasadi.dynamics.contacts import contact_set, errors
    from rscasadi.dynamics.stance import stand
    from rscasadi.export.mujoco import standing_height
    import casadi as ca
    robot = FloatingRobot(read(ANYMAL))
    theta = anymal_crouch()
    s = stand(robot, theta, np.r_[0, 0, standing_height(robot.model, theta), 0, 0, 0, 1])
    cs = [("LF_FOOT", "point"), ("RF_FOOT", "flat"), ("LH_FOOT", "point"), ("RH_FOOT", "point")]
    R, p = (np.asarray(x) for x in robot.frame_placement("RF_FOOT")(s.q))
    from scipy.spatial.transform import Rotation
    turned = (Rotation.from_matrix(R) * Rotation.from_rotvec([0.0, 0.0, 0.01])).as_quat()     # xyzw
    anchors = np.concatenate([col(robot.frame_placement(f)(s.q)[1]) + [0.005, 0, 0] for f in ("LF_FOOT",)]
                             + [p.ravel() + [0.005, 0, 0], turned]
                             + [col(robot.frame_placement(f)(s.q)[1]) + [0.005, 0, 0] for f in ("LH_FOOT", "RH_FOOT")])
    q_sym = ca.SX.sym("q", robot.nq)
    error = ca.Function("e", [q_sym], [errors(robot, contact_set(robot.model, cs), q_sym, anchors)])
    for stiffness in (100.0, 0.0):
        cd, q, v = robot.contact_dynamics(cs, damping=20.0, stiffness=stiffness), s.q.copy(), np.zeros(robot.nv)
        e0 = np.max(np.abs(col(error(q))))
        for _ in range(1000):
            a = col(cd(q, v, s.tau, *([anchors] if stiffness else []))[0])
            v = v + 1e-3 * a
            q = col(robot.integrate()(q, v, 1e-3))
        e1 = np.max(np.abs(col(error(q))))
        assert e0 > 4e-3 and (e1 < 1e-2 * e0 if stiffness else e1 > 0.9 * e0)


def test_generated_c_of_a_floating_robot_equals_its_functions(tmp_path):
    """A floating tree with two contacts in its model file, through codegen: every Function of
    the library (the contact dynamics and its Jacobian included) equals the symbolic one, and the
    header gives the sizes."""
    from rscasadi.codegen import load_compiled
    from rscasadi.codegen.generate import generate
    rng = np.random.default_rng(5)
    doc = random_tree_doc(rng, 4)
    doc["joints"][3]["parent"] = "base"
    doc.update(floating=True, base={"mass": 3.0, "com": [0, 0, 0.01], "inertia": [0.05, 0.06, 0.04, 0, 0, 0]},
               contacts=[{"frame": "j3", "kind": "point"}, {"frame": "j4"}])
    path = write_arm(tmp_path, doc, "legs.toml")
    manifest = generate(path, tmp_path / "c", frames=["j3"], opt="-O1", log=lambda *a: None)
    robot, lib = rscasadi.load_robot(path), load_compiled(tmp_path / "c")
    assert {"contact_dynamics", "contact_dynamics_jacobian", "impact", "integrate"} <= set(manifest["functions"])
    header = (tmp_path / "c" / manifest["header"]).read_text()
    assert f"#define ROBOT_NQ {robot.nq} " in header and "#define ROBOT_NC 6 " in header
    q, v, tau = random_q(robot, rng, 1.0), rng.normal(size=robot.nv), rng.normal(size=robot.u)
    given = {"q": q, "v": v, "tau": tau, "a": rng.normal(size=robot.nv), "f": rng.normal(size=6), "dt": 0.01}
    ours = {name: getattr(robot, name)() for name in manifest["functions"] if hasattr(robot, name)}
    ours["frame_placement_j3"] = robot.frame_placement("j3")
    ours["frame_jacobian_j3_local"] = robot.frame_jacobian("j3", "local")
    ours["frame_jacobian_j3_local_world_aligned"] = robot.frame_jacobian("j3")
    assert set(ours) == set(manifest["functions"])
    for name, f in ours.items():
        args = [given[i] for i in f.name_in()]
        for a, b in zip(lib[name].call(args), f.call(args)):
            assert np.max(np.abs(np.asarray(a) - np.asarray(b))) <= 1e-12 * max(1, np.max(np.abs(np.asarray(b))))


def anymal_crouch():
    """ANYmal's links in a crouch: hips 0.5 rad, knees 1 rad, front and hind legs mirrored."""
    theta = np.zeros(12)
    theta[[1, 4]], theta[[2, 5]], theta[[7, 10]], theta[[8, 11]] = 0.5, -1.0, -0.5, 1.0
    return theta


def test_mujoco_s_floating_robot_is_the_model_and_flies_as_it():
    """ANYmal C exported: at random states MuJoCo's mass matrix and generalised forces, mapped to
    our v (the free joint's linear velocity in world axes), equal the model's to 1e-12; from a
    spinning throw, 1 s of flight in MuJoCo (RK4, 1 ms) ends where CVODES integrating our
    forward dynamics with the quaternion's kinematics ends, to 1e-7 rad and 1e-6 rad/s."""
    import casadi as ca
    import mujoco
    from rscasadi.dynamics.floating import _quaternion_product, rotation
    from rscasadi.export.mujoco import gear_map, mujoco_state, mujoco_xml, state_from_mujoco
    robot = FloatingRobot(read(ANYMAL))
    m = mujoco.MjModel.from_xml_string(mujoco_xml(robot.model))
    d, rng = mujoco.MjData(m), np.random.default_rng(2)
    mass, fd = robot.mass_matrix(), robot.forward_dynamics()
    for _ in range(3):
        q = random_q(robot, rng, 1.0)
        q[7 + robot.n:] = q[7:7 + robot.n] + rng.uniform(-0.05, 0.05, robot.m)
        v, tau = rng.normal(size=robot.nv), rng.uniform(-1, 1, robot.u)
        d.qpos[:], d.qvel[:] = mujoco_state(robot, m, q, v)
        d.ctrl[:] = tau
        mujoco.mj_forward(m, d)
        M = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, M)
        R = np.asarray(ca.DM(rotation(ca.DM(q[3:7]))))
        T = np.c_[np.zeros((m.nv, 6)), gear_map(robot, m)]
        T[:3, :3], T[3:6, 3:6] = R, np.eye(3)
        Tdot_v = np.r_[R @ np.cross(v[3:6], v[:3]), np.zeros(m.nv - 3)]     # d/dt (R v) = R (dv + w x v)
        ours = np.asarray(mass(q))
        forces = ours @ col(fd(q, v, tau))
        assert rel(T.T @ M @ T, ours) < 1e-12
        assert rel(T.T @ (d.qfrc_passive + d.qfrc_actuator - d.qfrc_bias - M @ Tdot_v), forces) < 1e-12
    theta = 0.1 * rng.normal(size=robot.n)
    q0, v0 = np.r_[0, 0, 5.0, 0, 0, 0, 1, theta, theta], np.r_[0.5, 0, 3.0, rng.normal(size=3), 0.2 * rng.normal(size=robot.nv - 6)]
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = mujoco_state(robot, m, q0, v0)
    for _ in range(1000):
        mujoco.mj_step(m, d)
    x = ca.SX.sym("x", robot.nq + robot.nv)
    q, v = x[:robot.nq], x[robot.nq:]
    qdot = ca.vertcat(rotation(q[3:7]) @ v[:3], 0.5 * _quaternion_product(q[3:7], ca.vertcat(v[3:6], 0)), v[6:])
    ode = {"x": x, "ode": ca.vertcat(qdot, fd(q, v, np.zeros(robot.u)))}
    xf = col(ca.integrator("flight", "cvodes", ode, 0, 1.0, {"abstol": 1e-11, "reltol": 1e-11})(x0=np.r_[q0, v0])["xf"])
    q_ours, v_ours = xf[:robot.nq], xf[robot.nq:]
    q_ours[3:7] /= np.linalg.norm(q_ours[3:7])
    q_mj, v_mj = state_from_mujoco(robot, m, d.qpos, d.qvel)
    q_mj[3:7] *= np.sign(q_mj[6] * q_ours[6])
    assert np.max(np.abs(q_ours[:3] - q0[:3])) > 0.5 and np.max(np.abs(q_ours[3:7] - q0[3:7])) > 0.3
    assert np.max(np.abs(q_mj - q_ours)) < 1e-7 and np.max(np.abs(v_mj - v_ours)) < 1e-6


def test_standing_statics_hold_in_the_model_and_on_mujoco_s_floor():
    """ANYmal crouching on its four feet: `stand` finds the motors' deflections, the inputs of
    least effort and forces inside the friction cones (mu 0.7) that the contact dynamics hold at
    a = 0 with exactly those forces; in MuJoCo, on the floor, the motors held by a PD about that
    posture, after 2 s the base has settled within 3 cm and MuJoCo's foot forces equal the model's
    contact forces at MuJoCo's own state within 1 % of the weight, the normal ones the posture's."""
    import mujoco
    from rscasadi.dynamics.stance import stand
    from rscasadi.export.mujoco import mujoco_state, mujoco_xml, standing_height, state_from_mujoco
    robot = FloatingRobot(read(ANYMAL))
    theta = anymal_crouch()
    s = stand(robot, theta, np.r_[0, 0, standing_height(robot.model, theta), 0, 0, 0, 1], mu=0.7)
    f = s.f.reshape(4, 3)
    assert np.all(f[:, 2] > 0) and np.all(np.hypot(f[:, 0], f[:, 1]) <= 0.7 * f[:, 2] + 1e-6)
    a, f_kkt = robot.contact_dynamics()(s.q, np.zeros(robot.nv), s.tau)
    assert np.max(np.abs(col(a))) < 1e-8 and rel(col(f_kkt), s.f) < 1e-8
    weight = float(np.sum(f[:, 2]))
    m = mujoco.MjModel.from_xml_string(mujoco_xml(robot.model))
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = mujoco_state(robot, m, s.q, np.zeros(robot.nv))
    phi = s.q[7 + robot.n:]
    for _ in range(2000):                     # motor PD: 20 N m/rad and 0.5 N m s/rad at the fast side
        q, v = state_from_mujoco(robot, m, d.qpos, d.qvel)
        d.ctrl[:] = s.tau + 20.0 * (q[7 + robot.n:] - phi) + 0.5 * v[6 + robot.n:]
        mujoco.mj_step(m, d)
    q, v = state_from_mujoco(robot, m, d.qpos, d.qvel)
    assert np.max(np.abs(q[:3] - s.q[:3])) < 0.03 and np.max(np.abs(v)) < 0.1
    feet = {}
    for i in range(d.ncon):
        c, f6 = d.contact[i], np.zeros(6)
        mujoco.mj_contactForce(m, d, i, f6)
        foot = c.geom2 if m.geom(c.geom2).name.startswith("contact_") else c.geom1
        sign = 1.0 if foot == c.geom2 else -1.0            # the force on geom2, from geom1
        feet[m.geom(foot).name] = feet.get(m.geom(foot).name, 0) + sign * c.frame.reshape(3, 3).T @ f6[:3]
    f_mj = np.concatenate([feet[f"contact_{name}"] for name in FEET])
    f_model = col(robot.contact_dynamics()(q, v, d.ctrl)[1])
    assert np.max(np.abs(f_mj - f_model)) < 0.01 * weight
    assert np.max(np.abs(f_mj[2::3] - s.f[2::3])) < 0.01 * weight


def test_the_rotor_spin_study_conserves_momentum_and_finds_the_armature_model_off():
    """The study's four flights (0.15 s): the models with the rotors as bodies keep the angular
    momentum they started with (zero) to 1e-6 N m s; the reduced and armature models' motions
    carry momentum nothing gave them, and their bases end elsewhere."""
    from rscasadi.studies.rotor_spin import study
    r = study(ANYMAL, duration=0.15, log=lambda *a: None)
    held = r["angular_momentum_at_end_Nms"]
    assert held["complete"] < 1e-6 and held["rigid"] < 1e-6
    assert held["reduced"] > 1e-3 and held["armature"] > 1e-3
    assert r["rigid_vs_armature_deg"] > 0.01 and r["complete_vs_reduced_deg"] > 0.01


def test_a_drop_through_a_contact_schedule_lands_plastically_and_holds_the_feet():
    """ANYmal dropped 2 cm above its crouch, the motors held by a PD about the stance: in flight
    (the first phase, no contacts) the base falls as gravity says; at touchdown (the second
    phase, four feet) the plastic impact stops the feet (J v = 0), the impulse is the change of
    the momentum, kinetic energy is lost, not made; then the feet stay within 1e-6 m and push
    (no pulling force)."""
    from rscasadi.dynamics.stance import stand
    from rscasadi.export.mujoco import standing_height
    from rscasadi.sim.legged import simulate_schedule
    robot = FloatingRobot(read(ANYMAL))
    theta = anymal_crouch()
    s = stand(robot, theta, np.r_[0, 0, standing_height(robot.model, theta), 0, 0, 0, 1])
    q0 = s.q.copy()
    q0[2] += 0.02
    phi, n = s.q[7 + robot.n:], robot.n

    def pd(t, q, v):
        return s.tau + 20.0 * (q[7 + n:] - phi) + 0.5 * v[6 + n:]
    t_down = float(np.sqrt(2 * 0.02 / 9.81))
    r = simulate_schedule(robot, q0, np.zeros(robot.nv), [(0.0, ()), (t_down, FEET)], pd, duration=0.2, dt=5e-4)
    (t_hit, frames, impulse, before, after), = r["impacts"]
    k = int(round(t_hit / 5e-4))
    assert frames == sorted(FEET) and abs(t_hit - t_down) < 5e-4 and after < before
    assert abs(r["v"][k, 2] + 9.81 * t_hit) < 0.02                      # free fall until then
    q_hit, v_before = r["q"][k], r["v"][k]
    v_after = col(robot.impact(FEET)(q_hit, v_before)[0])
    assert np.max(np.abs(np.asarray(robot.contact_jacobian(FEET)(q_hit)) @ v_after)) < 1e-9
    h = robot.centroidal_momentum()
    assert rel(col(h(q_hit, v_after))[:3] - col(h(q_hit, v_before))[:3], impulse.reshape(4, 3).sum(axis=0)) < 1e-9
    feet = [robot.frame_placement(f) for f in FEET]
    landed = np.concatenate([col(f(r["q"][k + 1])[1]) for f in feet])
    end = np.concatenate([col(f(r["q"][-1])[1]) for f in feet])
    assert np.max(np.abs(end - landed)) < 1e-6 and r["pulling"] == 0.0


def test_a_humanoid_on_two_soles_stands_in_the_model_and_on_mujoco_s_floor(tmp_path):
    """The G1 (29 joints: SEA legs, geared waist and shoulders, direct elbows and wrists) on two
    flat contacts at sole frames under its ankles, soles 17 x 5 cm: `stand` keeps each centre of
    pressure on its sole; exported, each sole a sphere at each corner, MuJoCo holds it 20 ms
    for 1.5 s on the stance's torques and a PD about it (each geared or SEA joint's motor
    coordinate 500 N m/rad and 10 N m s/rad at the link, a direct joint 20 and 0.2: the wrists are
    light) still, at least six corners down, and its two feet's summed wrenches
    (force and moment about the sole's origin, sole axes) equal the model's flat contact forces
    at MuJoCo's state within 1 % of the weight (moments: of the weight times 10 cm)."""
    import mujoco
    from rscasadi.dynamics.stance import stand
    from rscasadi.export.mujoco import mujoco_state, mujoco_xml, standing_height, state_from_mujoco
    doc = g1_doc()
    doc["frames"] = {f"{s}_sole": {"parent": f"{s}_ankle_roll_link", "xyz": [0.035, 0.0, -0.035], "rpy": [0.0, 0.0, 0.0]}
                     for s in ("left", "right")}
    doc["contacts"] = [{"frame": f"{s}_sole", "kind": "flat", "size": [0.17, 0.05]} for s in ("left", "right")]
    robot = FloatingRobot(rscasadi.load(write_arm(tmp_path, doc, "g1.toml")).model)
    theta = np.zeros(robot.n)
    s = stand(robot, theta, np.r_[0, 0, standing_height(robot.model, theta), 0, 0, 0, 1])
    f = s.f.reshape(2, 6)
    assert np.all(np.abs(f[:, 3]) <= 0.025 * f[:, 2] + 1e-9) and np.all(np.abs(f[:, 4]) <= 0.085 * f[:, 2] + 1e-9)
    weight = float(np.sum(f[:, 2]))
    m = mujoco.MjModel.from_xml_string(mujoco_xml(robot.model))
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = mujoco_state(robot, m, s.q, np.zeros(robot.nv))
    model, n = robot.model, robot.n
    held = np.array([7 + n + model.motor_of[j] if model.joints[j].kind == "sea" else 7 + j for j in model.actuated])
    rate = held - 1
    geared = np.array([bool(model.joints[j].joint_kind.rotors) for j in model.actuated])
    mu = np.where(geared, [model.joints[j].gear_ratio for j in model.actuated], -1.0)
    kp, kd = np.where(geared, 500.0, 20.0), np.where(geared, 10.0, 0.2)      # the direct wrists are light
    for _ in range(1500):                                 # through a gear the input acts as -mu tau
        q, v = state_from_mujoco(robot, m, d.qpos, d.qvel)
        d.ctrl[:] = s.tau + (kp * (q[held] - s.q[held]) + kd * v[rate]) / mu
        mujoco.mj_step(m, d)
    q, v = state_from_mujoco(robot, m, d.qpos, d.qvel)
    assert d.ncon >= 6 and abs(q[2] - s.q[2]) < 0.02 and np.max(np.abs(v)) < 0.05
    ours = col(robot.contact_dynamics()(q, v, d.ctrl)[1]).reshape(2, 6)
    for k, side in enumerate(("left", "right")):
        R, o = (np.asarray(x) for x in robot.frame_placement(f"{side}_sole")(q))
        force, moment = np.zeros(3), np.zeros(3)
        for i in range(d.ncon):
            c, f6 = d.contact[i], np.zeros(6)
            if not m.geom(c.geom1 if m.geom(c.geom1).name.startswith("contact_") else c.geom2).name.startswith(
                    f"contact_{side}_sole"):
                continue
            mujoco.mj_contactForce(m, d, i, f6)
            foot = c.geom2 if m.geom(c.geom2).name.startswith("contact_") else c.geom1
            fw = (1.0 if foot == c.geom2 else -1.0) * c.frame.reshape(3, 3).T @ f6[:3]
            force, moment = force + fw, moment + np.cross(c.pos - o.ravel(), fw)
        assert np.max(np.abs(R.T @ force - ours[k, :3])) < 0.01 * weight
        assert np.max(np.abs(R.T @ moment - ours[k, 3:])) < 0.01 * weight * 0.1
