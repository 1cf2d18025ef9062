"""Parameters as inputs: the parametric twins equal the constant Functions at the nominal values,
and, fed another arm's parameters, equal *that* arm's constant Functions (one compiled library
for every arm with the same joints and axes)."""
import copy

import numpy as np
import pytest

import rscasadi
from rscasadi.model.modelfile import Body
from rscasadi.model.parameters import body_from_parameters, body_parameters

from conftest import dm, random_arm_doc, random_body, random_state, write_arm

FUNCTIONS = ("forward_dynamics", "inverse_dynamics", "energy", "joint_forward_dynamics", "arm_forward_dynamics")


def _inputs(f, x, rng):
    extra = [rng.normal(size=f.size1_in(i)) for i in range(4, f.n_in())]
    return list(x) + extra


def _compare(arm_a, arm_b, p, rng, names=FUNCTIONS, tol=1e-11):
    """arm_a's parametric Functions at p against arm_b's constant ones."""
    for name in names:
        const, twin = getattr(arm_b, name)(), getattr(arm_a, name)(parametric=True)
        for _ in range(2):
            x = random_state(rng, arm_a.n, 1.5)
            args = _inputs(const, x, rng)
            a = np.concatenate([dm(v) for v in const.call(args)])
            b = np.concatenate([dm(v) for v in twin.call(args + [p])])
            assert np.max(np.abs(a - b)) <= tol * max(1.0, np.max(np.abs(a))), name


def test_names_and_nominal_values(arm3):
    names, p = arm3.parameters()
    assert len(names) == len(p) == 3 * 38 + 3 and len(set(names)) == len(names)
    assert names[:3] == ["shoulder_yaw.link.mass", "shoulder_yaw.link.mx", "shoulder_yaw.link.my"]
    assert p[names.index("elbow_pitch.sea.k1")] == 600.0
    assert p[names.index("elbow_pitch.fast_rotor.Izz")] == pytest.approx(1.6e-5)
    assert p[names.index("shoulder_pitch.link.mx")] == pytest.approx(2.0 * 0.175)      # m c_x
    # Izz about the frame origin: 0.022 + 2.0 * 0.175^2
    assert p[names.index("shoulder_pitch.link.Izz")] == pytest.approx(0.022 + 2.0 * 0.175 ** 2)
    assert list(p[-3:]) == [0.0, 0.0, -9.81]


def test_body_parameters_round_trip():
    rng = np.random.default_rng(3)
    for _ in range(20):
        doc = random_body(rng, (0.1, 3.0), 0.3)
        body = Body(doc["mass"], np.asarray(doc["com"]), np.array(doc["inertia"])[[[0, 3, 4], [3, 1, 5], [4, 5, 2]]])
        back = body_from_parameters(body_parameters(body))
        assert back.mass == pytest.approx(body.mass)
        assert np.allclose(back.com, body.com, atol=1e-14) and np.allclose(back.inertia, body.inertia, atol=1e-14)


def test_twins_equal_constant_versions_at_nominal(arm3, random_arms):
    rng = np.random.default_rng(11)
    for arm in [arm3] + random_arms:
        _compare(arm, arm, arm.parameters()[1], rng)
        x = random_state(rng, arm.n)
        M = np.array(arm.mass_matrix()(x[0], x[1]))
        assert np.allclose(np.array(arm.mass_matrix(parametric=True)(x[0], x[1], arm.parameters()[1])), M,
                           rtol=0, atol=1e-12 * np.max(np.abs(M)))


def _other_arm(tmp_path, doc, rng, balanced=False):
    """The same joints and axes with every physical number changed."""
    other = copy.deepcopy(doc)
    twin = random_arm_doc(rng, len(doc["joints"]), balanced)
    for jt, new in zip(other["joints"], twin["joints"]):
        for key in ("sea", "gear_loss", "link", "slow_rotor", "fast_rotor"):
            jt[key] = new[key]
        jt["gear_loss"]["eps"] = doc_eps(doc, jt)
    other["gravity"] = twin["gravity"]
    return rscasadi.load(write_arm(tmp_path, other, "other.toml"))


def doc_eps(doc, jt):
    return next(j for j in doc["joints"] if j["name"] == jt["name"]).get("gear_loss", {}).get("eps", 0.01)


def test_twin_of_one_arm_is_every_arm_with_its_joints(tmp_path):
    rng = np.random.default_rng(12)
    for n, balanced in ((2, False), (4, True), (6, False)):
        doc = random_arm_doc(rng, n, balanced)
        arm = rscasadi.load(write_arm(tmp_path, doc))
        other = _other_arm(tmp_path, doc, rng, balanced)
        names = FUNCTIONS + (("reduced_forward_dynamics", "reduced_inverse_dynamics") if balanced else ())
        _compare(arm, other, other.parameters()[1], rng, names)


def test_parametric_forward_dynamics_jacobian(arm3):
    rng = np.random.default_rng(4)
    x, tau = random_state(rng, 3), rng.normal(size=3)
    J = np.array(arm3.forward_dynamics_jacobian()(*x, tau))
    Jp = np.array(arm3.forward_dynamics_jacobian(parametric=True)(*x, tau, arm3.parameters()[1]))
    assert np.max(np.abs(J - Jp)) < 1e-10 * np.max(np.abs(J))


@pytest.mark.parametrize("balanced", [False, True])
def test_free_gear_ratios_equal_a_model_file_with_those_ratios(tmp_path, balanced):
    """Arm(model, free=[gear ratios, ...]) at values v = the constant arm of the model file with v:
    the fast rotor's spin, its reflected inertia and the motor torque all scale with mu (design
    studies and sweeps free gear ratios this way; identification keeps them fixed)."""
    from rscasadi.dynamics.arm import Arm
    from rscasadi.model.parameters import designable, value, with_values
    rng = np.random.default_rng(31 + balanced)
    for n in (1, 3, 7):                              # 7: the implicit-function forward-dynamics Jacobian
        arm = rscasadi.load(write_arm(tmp_path, random_arm_doc(rng, n, balanced), f"g{n}.toml"))
        jts = arm.model.joints
        free = [f"{jts[-1].name}.gear_ratio", f"{jts[0].name}.gear_ratio", f"{jts[0].name}.sea.k1"]
        if not balanced:
            free.append(f"{jts[-1].name}.fast_rotor.Izz")            # with the inertias symbolic too
        free = list(dict.fromkeys(free))
        assert set(free) <= set(designable(arm.model))
        v = [value(arm.model, k) * rng.uniform(0.5, 2.0) for k in free]
        twin, const = Arm(arm.model, free=free), Arm(with_values(arm.model, dict(zip(free, v))))
        assert const.model.joints[0].gear_ratio == pytest.approx(v[free.index(f"{jts[0].name}.gear_ratio")])
        for name in ("forward_dynamics", "inverse_dynamics", "mass_matrix", "forward_dynamics_jacobian"):
            c, t = getattr(const, name)(), getattr(twin, name)(parametric=True)
            for _ in range(2):
                x = random_state(rng, n, 1.5)
                args = (list(x) + [rng.normal(size=c.size1_in(i)) for i in range(4, c.n_in())])[:c.n_in()]
                a = np.concatenate([np.ravel(dm(o)) for o in c.call(args)])
                b = np.concatenate([np.ravel(dm(o)) for o in t.call(args + [v])])
                assert np.max(np.abs(a - b)) <= 1e-10 * max(1.0, np.max(np.abs(a))), (n, name)
