"""Frames, kinematics and external wrenches against outside references: Pinocchio parsing the
same URDF (Panda, UR5, the reference arm's URDF), the Lagrangian oracle, finite differences and
the energy balance; and the [frames] table's refusals."""
import re

import casadi as ca
import numpy as np
import pytest

import rscasadi
from rscasadi import ModelFileError
from rscasadi.model.modelfile import document, to_toml
from rscasadi.reference.pinocchio_route import PinocchioRoute, configuration, urdf_model

from conftest import ROOT, dm, random_state
from lagrange import Lagrange
from test_urdf import old_doc, reference_urdf, urdf_form_doc  # noqa: F401  (old_doc: a fixture)

pin = pytest.importorskip("pinocchio")
REFS = {"local_world_aligned": pin.LOCAL_WORLD_ALIGNED, "local": pin.LOCAL, "world": pin.WORLD}


@pytest.fixture(scope="module")
def arm3_urdf(tmp_path_factory, old_doc):  # noqa: F811
    d = tmp_path_factory.mktemp("arm3_urdf")
    arm3 = rscasadi.load(ROOT / "problems" / "arm3.toml")
    (d / "arm3.urdf").write_text(reference_urdf(arm3.model))
    (d / "arm3_urdf.toml").write_text(to_toml(urdf_form_doc(old_doc, "arm3.urdf")))
    return rscasadi.load(d / "arm3_urdf.toml")


@pytest.fixture(scope="module", params=["panda", "ur5", "arm3_urdf"])
def urdf_arm(request):
    if request.param == "arm3_urdf":
        return request.getfixturevalue("arm3_urdf")
    return rscasadi.load(ROOT / "problems" / f"{request.param}_sea.toml")


class PinocchioURDF:
    """Pinocchio's own model of the URDF, the locked joints held at their values."""

    def __init__(self, model):
        self.model = urdf_model(model)
        assert [self.model.names[i] for i in range(1, self.model.njoints)] == [jt.name for jt in model.joints]
        self.data = self.model.createData()

    def q(self, theta):
        return configuration(self.model, theta)


def test_frames_are_the_urdf_links(urdf_arm):
    pm = PinocchioURDF(urdf_arm.model).model
    links = {pm.frames[i].name for i in range(pm.nframes) if pm.frames[i].type == pin.FrameType.BODY}
    assert set(urdf_arm.frames()) == links                       # merged and locked links included


def test_kinematics_equal_pinocchio_on_the_same_urdf(urdf_arm):
    ref, arm, rng = PinocchioURDF(urdf_arm.model), urdf_arm, np.random.default_rng(3)
    pm, data, n = ref.model, ref.data, urdf_arm.n
    for _ in range(3):
        th, dth, ddth = rng.uniform(-2, 2, n), rng.normal(size=n), rng.normal(size=n)
        q = ref.q(th)
        pin.forwardKinematics(pm, data, q, dth, ddth)
        pin.updateFramePlacements(pm, data)
        pin.computeJointJacobians(pm, data, q)
        pin.computeJointJacobiansTimeVariation(pm, data, q, dth)
        for name in arm.frames():
            fid = pm.getFrameId(name)
            R, p = (np.array(v) for v in arm.frame_placement(name)(th))
            assert np.allclose(R, data.oMf[fid].rotation, atol=1e-9) and np.allclose(p.ravel(), data.oMf[fid].translation, atol=1e-9), name
            for ref_name, rf in REFS.items():
                J = np.array(arm.frame_jacobian(name, ref_name)(th))
                assert np.allclose(J, pin.getFrameJacobian(pm, data, fid, rf), atol=1e-9), (name, ref_name)
                v = dm(arm.frame_velocity(name, ref_name)(th, dth))
                assert np.allclose(v, pin.getFrameVelocity(pm, data, fid, rf).vector, atol=1e-9), (name, ref_name)
                a = dm(arm.frame_acceleration(name, ref_name)(th, dth, ddth))
                a_pin = pin.getFrameClassicalAcceleration(pm, data, fid, rf).vector
                assert np.allclose(a, a_pin, atol=1e-8 * max(1.0, np.abs(a_pin).max())), (name, ref_name)
            dJ = pin.getFrameJacobianTimeVariation(pm, data, fid, pin.LOCAL_WORLD_ALIGNED)
            assert np.allclose(dm(arm.frame_jacobian_dot_times_v(name)(th, dth)), dJ @ dth, atol=1e-9), name


def test_center_of_mass_equals_pinocchio_with_the_rotors(request):
    """Links and rotors as bodies of a Pinocchio tree (unbalanced rotors on the random arms, so
    phi matters there)."""
    rng = np.random.default_rng(4)
    arms = [request.getfixturevalue("arm3")] + request.getfixturevalue("random_arms")
    routes = [PinocchioRoute(a.model) for a in arms]
    routes += [PinocchioRoute.from_urdf(rscasadi.load(ROOT / "problems" / "panda_sea.toml").model)]
    arms += [rscasadi.load(ROOT / "problems" / "panda_sea.toml")]
    for arm, route in zip(arms, routes):
        th, ph = random_state(rng, arm.n)[:2]
        q_tree = route.G @ np.r_[th, ph]
        c_pin = pin.centerOfMass(route.model, route.data, q_tree)
        assert np.allclose(dm(arm.center_of_mass()(th, ph)), c_pin, atol=1e-12)
        Jc_pin = pin.jacobianCenterOfMass(route.model, route.data, q_tree) @ route.G
        assert np.allclose(np.array(arm.center_of_mass_jacobian()(th, ph)), Jc_pin, atol=1e-10)


def test_jacobian_is_the_derivative_of_the_placement(random_arms):
    """Finite differences of p and of R (angular: vee(dR R^T)) on random arms with user frames."""
    rng = np.random.default_rng(6)
    for arm in random_arms:
        frame = arm.frames()[-1]
        th, h = rng.uniform(-2, 2, arm.n), 1e-6
        J = np.array(arm.frame_jacobian(frame)(th))
        place = arm.frame_placement(frame)
        for j in range(arm.n):
            e = np.zeros(arm.n)
            e[j] = h
            (Rp, pp), (Rm, pm) = [(np.array(v) for v in place(th + s * e)) for s in (1, -1)]
            assert np.allclose((pp - pm).ravel() / (2 * h), J[:3, j], atol=1e-7)
            W = (Rp - Rm) / (2 * h) @ np.array(place(th)[0]).T
            assert np.allclose([W[2, 1], W[0, 2], W[1, 0]], J[3:, j], atol=1e-7)


def test_wrench_dynamics_equal_pinocchio_and_lagrange(urdf_arm, arm3):
    """Forward and inverse dynamics with a wrench at a frame: Pinocchio's J^T f on the link
    coordinates with its tree of links and rotors; the Lagrangian oracle on the reference arm."""
    rng, arm = np.random.default_rng(7), urdf_arm
    frame = arm.frames()[-1]
    ref, route = PinocchioURDF(arm.model), PinocchioRoute.from_urdf(arm.model)
    fd, inv = arm.forward_dynamics(external=[frame]), arm.inverse_dynamics(external=[frame])
    for _ in range(2):
        x, tau, f = random_state(rng, arm.n), rng.normal(size=arm.n), rng.normal(size=6) * 5
        q = ref.q(x[0])
        J = pin.computeFrameJacobian(ref.model, ref.data, q, ref.model.getFrameId(frame), pin.LOCAL_WORLD_ALIGNED)
        M, c = route.mass_bias(*x)
        k = {a: arm.model.column(a) for a in ("k1", "k3", "d", "b", "c", "eps", "gear_ratio")}
        psi, dpsi = x[1] - x[0], x[3] - x[2]
        T = k["k1"] * psi + k["k3"] * psi ** 3 + k["d"] * dpsi
        TB2 = k["b"] * x[3] + k["c"] * np.tanh(x[3] / k["eps"])
        ddq = np.linalg.solve(M, np.r_[T + J.T @ f, -T - TB2 - k["gear_ratio"] * tau] - c)
        ours = np.concatenate([dm(v) for v in fd(*x, tau, f)])
        assert np.allclose(ours, ddq, atol=1e-9 * max(1.0, np.abs(ddq).max()))
        tau_back, T_back = (dm(v) for v in inv(*x, ddq[:arm.n], ddq[arm.n:], f))
        assert np.allclose(tau_back, tau, atol=1e-8) and np.allclose(T_back, T, atol=1e-8)
    # the Lagrangian oracle, a wrench at the reference arm's last link frame shifted off its origin
    doc = document(arm3.model)
    doc["frames"] = {"probe": {"parent": "elbow_pitch", "xyz": [0.2, 0.03, -0.05], "rpy": [0.3, 0.1, 0.0]}}
    probe_arm = rscasadi.Arm(rscasadi.model.modelfile.parse(doc, "probe.toml"))
    lag, fr = Lagrange(probe_arm.model), probe_arm.model.frame("probe")
    x, tau, f = random_state(rng, 3), rng.normal(size=3), rng.normal(size=6) * 5
    Qw = dm(lag.wrench_force(fr.body, fr.p)(np.r_[x[0], x[1]], f))
    expected = np.concatenate(lag.forward_with_wrench(*x, tau, Qw))
    ours = np.concatenate([dm(v) for v in probe_arm.forward_dynamics(external=["probe"])(*x, tau, f)])
    assert np.allclose(ours, expected, atol=1e-9 * np.abs(expected).max())


def test_power_balance_with_a_wrench(random_arms):
    """dE/dt = motor power + wrench power (f . v of the frame) - losses, on random arms."""
    rng = np.random.default_rng(8)
    for arm in random_arms[2:5]:
        n, frame = arm.n, arm.frames()[-1]
        th, ph, dth, dph, tau = (ca.SX.sym(s, n) for s in ("th", "ph", "dth", "dph", "tau"))
        f = ca.SX.sym("f", 6)
        ddth, ddph = arm.forward_dynamics(external=[frame])(th, ph, dth, dph, tau, f)
        E = arm.energy()(th, ph, dth, dph)
        dE = ca.jtimes(E, ca.vertcat(th, ph, dth, dph), ca.vertcat(dth, dph, ddth, ddph))
        d, mu = ca.DM(arm.model.column("d")), ca.DM(arm.model.column("gear_ratio"))
        v = arm.frame_velocity(frame)(th, dth)
        power = ca.sum1(-d * (dph - dth) ** 2 - arm.gear_loss(dph) * dph - mu * tau * dph) + ca.dot(f, v)
        F = ca.Function("F", [th, ph, dth, dph, tau, f], [dE, power])
        x = random_state(rng, n)
        lhs, rhs = (float(val) for val in F(*x, rng.normal(size=n), rng.normal(size=6) * 10))
        assert abs(lhs - rhs) <= 1e-9 * max(abs(rhs), 1.0)


@pytest.mark.parametrize("frames,field,words", [
    ({"tool": {"parent": "nowhere"}}, "frames.tool.parent", "no frame 'nowhere'"),
    ({"tool": {"parent": "elbow_pitch", "xyz": [0.0, 0.1]}}, "frames.tool.xyz", "list of 3"),
    ({"tool": {"parent": "elbow_pitch", "colour": 1}}, "frames.tool.colour", "unknown key"),
    ({"elbow_pitch": {"parent": "base"}}, "frames.elbow_pitch", "exists already"),
    ({"a": {"parent": "b"}, "b": {"parent": "a"}}, "frames.a.parent", "cycle"),
])
def test_bad_frames_are_refused_by_name(arm3, tmp_path, frames, field, words):
    doc = document(arm3.model)
    doc["frames"] = frames
    path = tmp_path / "framed.toml"
    path.write_text(to_toml(doc))
    with pytest.raises(ModelFileError, match=rf"framed.toml: field '{field}'.*{words}"):
        rscasadi.load(path)


def test_user_frames_chain_and_round_trip(arm3, tmp_path):
    doc = document(arm3.model)
    doc["frames"] = {"tip": {"parent": "flange", "xyz": [0.0, 0.0, 0.05]},
                     "flange": {"parent": "elbow_pitch", "xyz": [0.3, 0.0, 0.0], "rpy": [0.0, 1.5707963267948966, 0.0]}}
    path = tmp_path / "framed.toml"
    path.write_text(to_toml(doc))
    arm = rscasadi.load(path)
    th = np.array([0.3, -0.4, 0.9])
    R_f, p_f = (np.array(v) for v in arm.frame_placement("flange")(th))
    _, p_t = (np.array(v) for v in arm.frame_placement("tip")(th))
    assert np.allclose(p_t, p_f + R_f @ [[0.0], [0.0], [0.05]])     # the child placed on its parent
    again = tmp_path / "again.toml"
    again.write_text(to_toml(document(arm.model)))
    twin = rscasadi.load(again)
    for name in arm.frames():
        assert np.allclose(np.array(twin.frame_placement(name)(th)[1]), np.array(arm.frame_placement(name)(th)[1]))


def test_a_urdf_arm_written_as_a_link_list_keeps_its_frames(tmp_path):
    panda = rscasadi.load(ROOT / "problems" / "panda_sea.toml")
    path = tmp_path / "panda_list.toml"
    path.write_text(to_toml(document(panda.model)))
    twin = rscasadi.load(path)
    th = np.linspace(-1, 1, 7)
    for name in panda.frames():
        a, b = panda.frame_placement(name)(th), twin.frame_placement(name)(th)
        assert all(np.allclose(np.array(u), np.array(v), atol=1e-12) for u, v in zip(a, b)), name


def test_inverse_kinematics_reaches_the_closest_pose_within_the_limits():
    """Poses of random configurations of the Panda: reached (checked by Pinocchio), within the
    limits, and no farther from the guess than the configuration that made the pose."""
    arm = rscasadi.load(ROOT / "problems" / "panda_sea.toml")
    ref, rng = PinocchioURDF(arm.model), np.random.default_rng(10)
    lo, hi = (np.array([jt.limits["theta"][i] for jt in arm.model.joints]) for i in (0, 1))
    fid = ref.model.getFrameId("panda_hand_tcp")
    for _ in range(4):
        true = rng.uniform(lo + 0.2, hi - 0.2)
        guess = np.clip(true + rng.normal(size=7) * 0.2, lo, hi)
        R, p = (np.array(v) for v in arm.frame_placement("panda_hand_tcp")(true))
        for target_R in (R, None):
            res = rscasadi.inverse_kinematics(arm, "panda_hand_tcp", position=p.ravel(), R=target_R, theta_guess=guess)
            assert res["success"], res["status"]
            pin.framesForwardKinematics(ref.model, ref.data, ref.q(res["theta"]))
            placed = ref.data.oMf[fid]
            assert np.allclose(placed.translation, p.ravel(), atol=1e-6)
            if target_R is not None:
                assert np.allclose(placed.rotation, R, atol=1e-6)
            assert np.all(res["theta"] >= lo - 1e-9) and np.all(res["theta"] <= hi + 1e-9)
            assert np.linalg.norm(res["theta"] - guess) <= np.linalg.norm(true - guess) + 1e-6


def test_inverse_kinematics_reports_an_unreachable_pose():
    arm = rscasadi.load(ROOT / "problems" / "panda_sea.toml")
    res = rscasadi.inverse_kinematics(arm, "panda_hand_tcp", position=[2.0, 0.0, 0.5])       # 2 m away: too far
    assert not res["success"] and res["position_error"] > 0.5 and "nfeasible" in res["status"]
    R_flip = np.diag([1.0, -1.0, -1.0])                  # reachable position, the tool upside down at the base
    res = rscasadi.inverse_kinematics(arm, "panda_link1", position=[0.0, 0.0, 0.333], R=R_flip)
    assert not res["success"]


def test_parametric_twins_and_the_reduced_model_take_frames_too(arm3):
    """Each kinematic Function's parametric twin equals it at the nominal p (the centre of mass
    moves with the masses); the reduced model takes a wrench as the complete one does."""
    th, dth, p = np.array([0.2, -0.5, 0.9]), np.array([0.3, 0.1, -0.4]), arm3.parameters()[1]
    for const, param, args in ((arm3.frame_placement("elbow_pitch"), arm3.frame_placement("elbow_pitch", parametric=True), [th]),
                               (arm3.frame_jacobian("elbow_pitch", "world"),
                                arm3.frame_jacobian("elbow_pitch", "world", parametric=True), [th]),
                               (arm3.frame_acceleration("elbow_pitch"), arm3.frame_acceleration("elbow_pitch", "local_world_aligned", parametric=True),
                                [th, dth, dth]),
                               (arm3.center_of_mass(), arm3.center_of_mass(parametric=True), [th, th])):
        for a, b in zip(const(*args) if const.n_out() > 1 else [const(*args)],
                        param(*args, p) if param.n_out() > 1 else [param(*args, p)]):
            assert np.allclose(np.array(a), np.array(b), atol=1e-14)
    heavier = p.copy()
    heavier[arm3.parameters()[0].index("elbow_pitch.link.mass")] *= 2
    assert not np.allclose(np.array(arm3.center_of_mass(parametric=True)(th, th, heavier)), np.array(arm3.center_of_mass()(th, th)))
    x, tau, f = [th, th + 0.01, dth, dth], np.array([0.1, -0.2, 0.05]), np.array([1.0, -2.0, 3.0, 0.1, 0.2, -0.3])
    J = np.array(arm3.frame_jacobian("elbow_pitch")(th))
    red, red_f = arm3.reduced_forward_dynamics(), arm3.reduced_forward_dynamics(external=["elbow_pitch"])
    M = np.array(arm3.mass_matrix(reduced=True)(th, th + 0.01))
    dd = np.concatenate([dm(v) for v in red_f(*x, tau, f)]) - np.concatenate([dm(v) for v in red(*x, tau)])
    assert np.allclose(M @ dd, np.r_[J.T @ f, np.zeros(3)], atol=1e-9)      # the wrench's share: M^-1 [J^T f; 0]


# ----------------------------------------------------------------------------- URDF collision geometry

PRIMITIVES = {"panda_link5": '<collision><origin xyz="0 0.08 -0.12" rpy="0.3 0 0.2"/><geometry>'
                             '<cylinder radius="0.06" length="0.12"/></geometry></collision>',
              "panda_link7": '<collision><origin xyz="0.01 0.02 0.05" rpy="0 0 0"/><geometry>'
                             '<sphere radius="0.05"/></geometry></collision>'}


@pytest.fixture(scope="module")
def panda_with_primitives(tmp_path_factory):
    """The Panda whose URDF gives link 5 a cylinder and link 7 a sphere (besides their meshes)."""
    d = tmp_path_factory.mktemp("primitives")
    text = (ROOT / "problems" / "urdf" / "panda.urdf").read_text()
    text = re.sub(r"<collision>(?:(?!</collision>).)*<mesh(?:(?!</collision>).)*</collision>", "", text, flags=re.S)
    for link, xml in PRIMITIVES.items():
        head = f'<link name="{link}">'
        assert head in text
        text = text.replace(head, head + xml, 1)
    (d / "panda.urdf").write_text(text)
    model = (ROOT / "problems" / "panda_sea.toml").read_text().replace('urdf = "urdf/panda.urdf"', 'urdf = "panda.urdf"')
    own = re.search(r"\[collision\].*?\n\n", model, re.S)                 # the model's own table, replaced
    model = model.replace(own.group(0), '[collision]\nmargin = 0.01\ntip = "panda_hand_tcp"\n'
                          'links = { panda_link3 = 0.06, panda_link5 = "urdf", panda_link7 = "urdf" }\n\n')
    (d / "panda.toml").write_text(model)
    return d


def test_urdf_cylinders_and_spheres_are_the_links_geometry(panda_with_primitives):
    """Their ends, placed by our kinematics, equal Pinocchio's placements of the same URDF
    collision geometries (built by pinocchio/coal); a link without primitives keeps its
    capsule from joint to joint."""
    arm = rscasadi.load(panda_with_primitives / "panda.toml")
    by_link = {c.link: c for c in arm.model.collision.capsules}
    assert set(by_link) == {"panda_link3", "panda_link5", "panda_link7", "panda_leftfinger", "panda_rightfinger"}
    assert by_link["panda_link5"].radius == 0.06 and by_link["panda_link7"].radius == 0.05
    assert np.allclose(by_link["panda_link3"].a, 0.0)                 # a capsule from the joint's origin
    ref = PinocchioURDF(arm.model)
    geom = pin.buildGeomFromUrdf(ref.model, str(panda_with_primitives / "panda.urdf"), pin.GeometryType.COLLISION)
    gdata = geom.createData()
    from rscasadi.dynamics.kinematics import body_poses
    theta_sym = ca.SX.sym("theta", arm.n)
    poses = body_poses(arm.model, theta_sym)
    rng = np.random.default_rng(5)
    for _ in range(3):
        th = rng.uniform(-1.5, 1.5, arm.n)
        pin.updateGeometryPlacements(ref.model, ref.data, geom, gdata, ref.q(th))
        for link, capsule in (("panda_link5", by_link["panda_link5"]), ("panda_link7", by_link["panda_link7"])):
            g = next(i for i, o in enumerate(geom.geometryObjects)
                     if o.name.startswith(link) and type(o.geometry).__name__ in ("Cylinder", "Sphere"))
            M = gdata.oMg[g]
            half = M.rotation[:, 2] * (0.06 if link == "panda_link5" else 0.0)
            R, o = (np.array(ca.Function("pose", [theta_sym], list(poses[capsule.body]))(th)[i]) for i in (0, 1))
            ends = [o.ravel() + R @ capsule.a, o.ravel() + R @ capsule.b]
            want = [M.translation - half, M.translation + half]
            assert min(np.linalg.norm(ends[0] - want[0]) + np.linalg.norm(ends[1] - want[1]),
                       np.linalg.norm(ends[0] - want[1]) + np.linalg.norm(ends[1] - want[0])) < 1e-9, link


def test_urdf_geometry_asked_for_where_there_is_none_is_refused(panda_with_primitives, tmp_path):
    text = (panda_with_primitives / "panda.toml").read_text().replace('panda_link3 = 0.06', 'panda_link3 = "urdf"')
    (panda_with_primitives / "no_primitives.toml").write_text(text)
    with pytest.raises(rscasadi.ModelFileError, match=r"no_primitives.toml.*'collision.links.panda_link3'.*no <collision>"):
        rscasadi.load(panda_with_primitives / "no_primitives.toml")
