"""What real joints have beyond the FS-SEA: the bearings' viscous and Coulomb loss after the
spring, a counterbalance spring (docs/user-guide/model.md section 2, T_L), and a gear loss that
grows with the torque transmitted (c1 |T|) and towards rest (Stribeck).  The dynamics against the numeric recursions and
Pinocchio (independent code), the model file both ways, MuJoCo's export, and identification from
logs of an arm that has them (a URDF does not list them)."""
import dataclasses

import numpy as np
import pytest

import rscasadi
from conftest import ROOT, random_arm_doc, to_toml
from rscasadi import ModelFileError
from rscasadi.dynamics.arm import Arm
from rscasadi.model.modelfile import document
from rscasadi.reference.numeric import Numeric, ReducedNumeric
from rscasadi.reference.pinocchio_route import PinocchioRoute


def with_link_side(tmp_path, seed=7, n=4):
    rng = np.random.default_rng(seed)
    doc = random_arm_doc(rng, n, balanced=True)
    for jt in doc["joints"]:
        jt["link_loss"] = {"b": float(rng.uniform(0.1, 2)), "c": float(rng.uniform(0.1, 1))}
        jt["counterbalance"] = {"k": float(rng.uniform(1, 20)), "theta0": float(rng.uniform(-1, 1))}
        jt["gear_loss"]["c1"] = float(rng.uniform(0.01, 0.1))
        jt["gear_loss"].update(stribeck=float(rng.uniform(0.1, 0.5)), v_stribeck=float(rng.uniform(0.3, 1.0)))
    (tmp_path / "arm.toml").write_text(to_toml(doc))
    return rscasadi.load(tmp_path / "arm.toml"), rng


def test_the_dynamics_with_link_losses_equal_the_independent_routes(tmp_path):
    """Complete and reduced forward dynamics against the numeric recursions, the complete one
    against Pinocchio's mass matrix and bias (1e-9 of the accelerations); inverse of forward
    returns the torque; the file round-trips the tables."""
    arm, rng = with_link_side(tmp_path)
    fd, inv, red = arm.forward_dynamics(), arm.inverse_dynamics(), arm.reduced_forward_dynamics()
    num, rnum, pin_route = Numeric(arm.model), ReducedNumeric(arm.model), PinocchioRoute(arm.model)
    for _ in range(5):
        x, tau = [rng.normal(0, 1, arm.n) for _ in range(4)], rng.normal(0, 1, arm.n)
        acc = [np.array(v).ravel() for v in fd(*x, tau)]
        scale = max(np.max(np.abs(a)) for a in acc)
        for route in (num.forward_dynamics(*x, tau), pin_route.forward_dynamics(*x, tau)):
            assert max(np.max(np.abs(a - b)) for a, b in zip(acc, route)) < 1e-9 * scale
        ra, rb = [np.array(v).ravel() for v in red(*x, tau)], rnum.forward_dynamics(*x, tau)
        assert max(np.max(np.abs(a - b)) for a, b in zip(ra, rb)) < 1e-9 * max(np.max(np.abs(a)) for a in ra)
        back = [np.array(v).ravel() for v in inv(*x, *acc)]
        assert np.max(np.abs(back[0] - tau)) < 1e-9 and np.allclose(back[1], num.inverse_dynamics(*x, *acc)[1])
    again = document(arm.model)["joints"]
    for jt, d in zip(arm.model.joints, again):
        assert d["link_loss"] == {"b": jt.link_b, "c": jt.link_c} and d["gear_loss"]["c1"] == jt.c1
        assert (d["gear_loss"]["stribeck"], d["gear_loss"]["v_stribeck"]) == (jt.stribeck, jt.v_stribeck) and jt.stribeck > 0
        assert d["counterbalance"] == {"k": jt.cb_k, "theta0": jt.cb_theta0}
    assert "link_loss" not in document(rscasadi.load(ROOT / "problems" / "arm3.toml").model)["joints"][0]


@pytest.mark.parametrize("table, words", [
    ({"link_loss": {"b": -0.1}}, "link_loss.b"),
    ({"link_loss": {"mu": 0.1}}, "link_loss.mu"),
    ({"counterbalance": {"theta0": 0.1}}, "counterbalance.k"),
    ({"gear_loss": {"stribeck": 0.2}}, "gear_loss.v_stribeck"),
    ({"gear_loss": {"v_stribeck": 0.1}}, "gear_loss.stribeck"),
    ({"gear_loss": {"stribeck": 0.2, "v_stribeck": 0.0}}, "gear_loss.v_stribeck"),
])
def test_bad_link_side_tables_are_refused_by_field(tmp_path, table, words):
    doc = document(rscasadi.load(ROOT / "problems" / "arm3.toml").model)
    doc["joints"][1].update(table)
    (tmp_path / "bad.toml").write_text(to_toml(doc))
    with pytest.raises(ModelFileError, match=rf"bad.toml.*shoulder_pitch.*{words}"):
        rscasadi.load(tmp_path / "bad.toml")


def test_mujoco_holds_the_viscous_link_loss_and_the_counterbalance(tmp_path):
    """arm3 with link_b and a counterbalance on every joint: MuJoCo's export (the link hinge's
    damping, stiffness and springref) follows rscasadi's replay as without them; a link Coulomb
    loss is refused by name."""
    from rscasadi.export.mujoco import compare_variants, mujoco_xml
    from rscasadi.sim.trajectory import load_trajectory
    arm3 = rscasadi.load(ROOT / "problems" / "arm3.toml")
    joints = tuple(dataclasses.replace(jt, link_b=0.3 * (j + 1), cb_k=5.0 * (j + 1), cb_theta0=0.2)
                   for j, jt in enumerate(arm3.model.joints))
    arm = Arm(dataclasses.replace(arm3.model, joints=joints))
    err = compare_variants(arm, load_trajectory(ROOT / "problems" / "trajectory_arm3.toml"))
    assert err["complete"] < 2e-5, err
    coulomb = Arm(dataclasses.replace(arm3.model, joints=(dataclasses.replace(joints[0], link_c=0.1),) + joints[1:]))
    with pytest.raises(Exception, match="shoulder_yaw: link_loss c = 0.1"):
        mujoco_xml(coulomb.model)
    loaded = Arm(dataclasses.replace(arm3.model, joints=joints[:2] + (dataclasses.replace(joints[2], c1=0.02),)))
    with pytest.raises(Exception, match="elbow_pitch: gear_loss c1 = 0.02"):
        mujoco_xml(loaded.model)
    sticky = Arm(dataclasses.replace(arm3.model, joints=joints[:2] + (dataclasses.replace(joints[2], stribeck=0.1),)))
    with pytest.raises(Exception, match="elbow_pitch: gear_loss stribeck = 0.1"):
        mujoco_xml(sticky.model)


OFFSETS = [0.05, -0.3, 0.1]          # N m: what each joint's torque sensor reads at zero torque


def test_a_link_side_log_identifies_link_losses_and_a_counterbalance(tmp_path):
    """A perturbed arm3 with link losses and counterbalance springs the model file only declares
    (zeros; theta0 given), its torque sensors offset: from a link-side log (theta, T) at 1 kHz,
    each recovered within 2 % (or 0.05 of a zero), the offsets within three of their reported
    standard deviations (below 0.05 N m), and the held-out
    link torques within 2 %; the same log identified on the file without the tables misses them
    by more than 20 % and names the joint whose residual is a friction, and the table to declare."""
    from rscasadi.identification.identify import run
    from rscasadi.identification.logs import write_log
    from rscasadi.identification.synthetic import perturbed_arm, record
    from rscasadi.sim.trajectory import load_trajectory
    doc = document(rscasadi.load(ROOT / "problems" / "arm3.toml").model)
    (tmp_path / "plain.toml").write_text(to_toml(doc))
    for jt in doc["joints"]:
        jt["link_loss"] = {"b": 0.0, "c": 0.0}
        jt["counterbalance"] = {"k": 0.0, "theta0": 0.3}
    (tmp_path / "declared.toml").write_text(to_toml(doc))
    nominal = rscasadi.load(tmp_path / "declared.toml")
    true = perturbed_arm(nominal, np.random.default_rng(11), coulomb=0.0)
    truth = [(0.4, 0.15, 0.0), (0.8, 0.3, 25.0), (0.3, 0.1, 8.0)]
    true = Arm(dataclasses.replace(true.model, joints=tuple(dataclasses.replace(jt, link_b=b, link_c=c, cb_k=k)
                                                             for jt, (b, c, k) in zip(true.model.joints, truth))))
    for name, traj in (("ident", ROOT / "results" / "identification" / "excitation" / "trajectory.toml"),
                       ("valid", ROOT / "problems" / "trajectory_arm3.toml")):
        log, _ = record(true, nominal, load_trajectory(traj), rng=np.random.default_rng(1), columns=("theta", "T"))
        log.T = log.T + np.array(OFFSETS)[:, None]            # the torque sensors' offsets
        write_log(tmp_path / f"{name}.csv", log)
    errors = {}
    for model in ("declared", "plain"):
        rep, ident = run(tmp_path / f"{model}.toml", [tmp_path / "ident.csv"], tmp_path / model,
                         validate=tmp_path / "valid.csv", log=lambda m: None)
        errors[model] = max(v["relative"] for v in rep["validation"]["prediction"].values())
        hints = [w for w in rep["warnings"] if "a link-side friction" in w]
        if model == "plain":                     # the file without the tables is told which to declare
            assert any(w.startswith("joint shoulder_pitch:") and "[joints.link_loss]" in w for w in hints), rep["warnings"]
        else:
            assert not hints, hints
        if model == "declared":
            for jt, want in zip(ident.model.joints, truth):
                for got, w in zip((jt.link_b, jt.link_c, jt.cb_k), want):
                    assert abs(got - w) <= max(0.02 * w, 0.05), (jt.name, got, w)
            for jt, offset in zip(ident.model.joints, OFFSETS):
                got = rep["parameters"][f"{jt.name}.T_offset"]        # the shoulder's trades with gravity
                assert abs(got["estimate"] - offset) < 3 * got["std"] + 0.005 and got["std"] < 0.05, (jt.name, got)
    assert errors["declared"] < 0.02 and errors["plain"] > 0.2, errors


def test_a_load_dependent_gear_loss_and_stribeck_are_identified_from_motor_side_logs(tmp_path):
    """A perturbed arm3 whose gears lose (c + c1 |T| + s exp(-(dphi / v_s)^2)) tanh(dphi / eps),
    c1 = 3-5 % of the torque they transmit, s = 0.4-0.8 N m beyond c at rest; the model file
    declares c1 = 0 and s = 0 (at the true v_s): from a motor-side log (theta, phi, tau; T from
    the spring law, a fixed point) c1 and s come out within 15 % and k1 within 0.1 %, and the
    held-out motor torques are predicted better than by the file without them (the elbow's error
    halved)."""
    from rscasadi.identification.identify import run
    from rscasadi.identification.logs import write_log
    from rscasadi.identification.synthetic import perturbed_arm, record
    from rscasadi.sim.trajectory import load_trajectory
    doc = document(rscasadi.load(ROOT / "problems" / "arm3.toml").model)
    (tmp_path / "plain.toml").write_text(to_toml(doc))
    for jt in doc["joints"]:
        jt["gear_loss"].update(c1=0.0, stribeck=0.0, v_stribeck=0.3)
    (tmp_path / "declared.toml").write_text(to_toml(doc))
    nominal = rscasadi.load(tmp_path / "declared.toml")
    true = perturbed_arm(nominal, np.random.default_rng(12))
    c1, s = [0.03, 0.05, 0.04], [0.6, 0.8, 0.4]
    true = Arm(dataclasses.replace(true.model, joints=tuple(dataclasses.replace(jt, c1=c, stribeck=si)
                                                             for jt, c, si in zip(true.model.joints, c1, s))))
    for name, traj in (("ident", ROOT / "results" / "identification" / "excitation" / "trajectory.toml"),
                       ("valid", ROOT / "problems" / "trajectory_arm3.toml")):
        log, _ = record(true, nominal, load_trajectory(traj), rng=np.random.default_rng(1))
        write_log(tmp_path / f"{name}.csv", log)
    held_out = {}
    for model in ("declared", "plain"):
        rep, ident = run(tmp_path / f"{model}.toml", [tmp_path / "ident.csv"], tmp_path / model,
                         validate=tmp_path / "valid.csv", log=lambda m: None)
        held_out[model] = [rep["validation"]["prediction"][f"tau_{j}"]["relative"] for j in (1, 2, 3)]
        if model == "declared":
            for jt, truth in zip(ident.model.joints, true.model.joints):
                assert abs(jt.c1 - truth.c1) < 0.15 * truth.c1 and abs(jt.k1 / truth.k1 - 1) < 1e-3, (jt.name, jt.c1, jt.k1)
                assert abs(jt.stribeck - truth.stribeck) < 0.15 * truth.stribeck, (jt.name, jt.stribeck)
    assert max(held_out["declared"]) < max(held_out["plain"]), held_out
    assert held_out["declared"][1] < 0.5 * held_out["plain"][1], held_out


def test_the_implicit_jacobian_carries_the_link_side_terms(tmp_path):
    """The forward-dynamics Jacobian the OCP and the MPC use (implicit-function theorem on the
    residual) equals AD through the forward dynamics on an arm with link losses, counterbalance
    springs and load-dependent gear losses (1e-8 relative)."""
    import casadi as ca
    arm, rng = with_link_side(tmp_path, seed=9, n=3)
    xs = [ca.SX.sym(s, arm.n) for s in ("theta", "phi", "dtheta", "dphi", "tau")]
    ad = ca.Function("ad", xs, [ca.jacobian(ca.vertcat(*arm.forward_dynamics()(*xs)), ca.vertcat(*xs))])
    for _ in range(3):
        v = [rng.normal(0, 1, arm.n) for _ in range(5)]
        J, want = np.array(arm.forward_dynamics_jacobian()(*v)), np.array(ad(*v))
        assert np.max(np.abs(J - want)) < 1e-8 * np.max(np.abs(want))
