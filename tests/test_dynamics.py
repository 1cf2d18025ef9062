"""The symbolic recursions against the numerical core (1e-12) and the Lagrangian oracle (1e-9)."""
import numpy as np
import pytest

from rscasadi.reference.numeric import Numeric, ReducedNumeric

from conftest import REFERENCE, dm, random_state
from lagrange import Lagrange


def rel(a, b):
    a, b = np.concatenate([np.ravel(x) for x in a]), np.concatenate([np.ravel(x) for x in b])
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)


def arms_under_test(request):
    return [request.getfixturevalue("arm3")] + request.getfixturevalue("random_arms")


def test_symbolic_equals_numeric_core(request):
    rng = np.random.default_rng(1)
    for arm in arms_under_test(request):
        num = Numeric(arm.model)
        fd, idf = arm.forward_dynamics(), arm.inverse_dynamics()
        jfd, afd, en = arm.joint_forward_dynamics(), arm.arm_forward_dynamics(), arm.energy()
        for _ in range(3):
            x, tau = random_state(rng, arm.n), rng.normal(size=arm.n)
            dd = [dm(v) for v in fd(*x, tau)]
            assert rel(dd, num.forward_dynamics(*x, tau)) < 1e-12
            acc = [rng.normal(size=arm.n) * 10 for _ in range(2)]
            assert rel([dm(v) for v in idf(*x, *acc)], num.inverse_dynamics(*x, *acc)) < 1e-12
            assert rel([dm(jfd(*x, tau, acc[0]))], [num.joint_forward_dynamics(*x, tau, acc[0])]) < 1e-12
            assert rel([dm(afd(*x, acc[1], acc[0]))], [num.arm_forward_dynamics(*x, acc[1], acc[0])]) < 1e-12
            assert rel([dm(en(*x))], [num.energy(*x)]) < 1e-12


def test_reduced_symbolic_equals_numeric_core(request):
    rng = np.random.default_rng(2)
    for arm in [request.getfixturevalue("arm3")] + request.getfixturevalue("balanced_arms"):
        num = ReducedNumeric(arm.model)
        fd, idf = arm.reduced_forward_dynamics(), arm.reduced_inverse_dynamics()
        for _ in range(3):
            x, tau = random_state(rng, arm.n), rng.normal(size=arm.n)
            assert rel([dm(v) for v in fd(*x, tau)], num.forward_dynamics(*x, tau)) < 1e-12
            acc = [rng.normal(size=arm.n) * 10 for _ in range(2)]
            assert rel([dm(v) for v in idf(*x, *acc)], num.inverse_dynamics(*x, *acc)) < 1e-12


def test_complete_model_equals_lagrange(request):
    rng = np.random.default_rng(3)
    for arm in arms_under_test(request) + request.getfixturevalue("balanced_arms")[-2:]:
        lag, n = Lagrange(arm.model), arm.n
        fd, idf, Mf = arm.forward_dynamics(), arm.inverse_dynamics(), arm.mass_matrix()
        for _ in range(2):
            x, tau = random_state(rng, n), rng.normal(size=n)
            M_lag, c_lag = lag.mass_bias(*x)
            assert rel([np.array(Mf(x[0], x[1]))], [M_lag]) < 1e-9
            tau0, T0 = (dm(v) for v in idf(*x, np.zeros(n), np.zeros(n)))     # bias = ID at zero acceleration
            T_s, TB2, mu = lag._Q(*x, 0)
            assert rel([T0, -mu * tau0 - T_s - TB2], [c_lag[:n], c_lag[n:]]) < 1e-9
            assert rel([dm(v) for v in fd(*x, tau)], lag.forward(*x, tau)) < 1e-9
            acc = [rng.normal(size=n) * 10 for _ in range(2)]
            assert rel([dm(v) for v in idf(*x, *acc)], lag.inverse(*x, *acc)) < 1e-9
            assert rel([dm(arm.energy()(*x))], [lag.energy(*x)]) < 1e-9


def consistent_psi(model, T, dpsi):
    """Solve the spring law k1 psi + k3 psi^3 + d dpsi = T for psi (Newton; monotone in psi)."""
    k1, k3, d = (model.column(a) for a in ("k1", "k3", "d"))
    rhs = T - d * dpsi
    psi = rhs / k1
    for _ in range(50):
        psi = psi - (k1 * psi + k3 * psi ** 3 - rhs) / (k1 + 3 * k3 * psi ** 2)
    return psi


def test_inverse_of_forward_is_identity(request):
    """ID(FD(x, tau)) returns tau, and eq. (26) returns the spring torque: the state is consistent."""
    rng = np.random.default_rng(4)
    for arm in arms_under_test(request):
        x, tau = random_state(rng, arm.n), rng.normal(size=arm.n)
        acc = arm.forward_dynamics()(*x, tau)
        tau_back, T = (dm(v) for v in arm.inverse_dynamics()(*x, *acc))
        assert rel([tau_back], [tau]) < 1e-10
        assert rel([T], [dm(arm.sea_torque(*[np.array(v)[:, None] for v in x]))]) < 1e-10


@pytest.mark.parametrize("reduced", [False, True])
def test_forward_of_inverse_is_identity(request, reduced):
    """Expected motion (theta, dtheta, ddtheta) and rotor motion (dphi, ddphi): eq. (26) gives T,
    the spring law gives the consistent phi, eq. (22) gives tau, and FD gives the motion back.
    (With balanced rotors T does not depend on phi.)"""
    rng = np.random.default_rng(4)
    for arm in [request.getfixturevalue("arm3")] + request.getfixturevalue("balanced_arms"):
        fd = arm.reduced_forward_dynamics() if reduced else arm.forward_dynamics()
        idf = arm.reduced_inverse_dynamics() if reduced else arm.inverse_dynamics()
        theta, _, dtheta, dphi = random_state(rng, arm.n)
        acc = [rng.normal(size=arm.n) * 10 for _ in range(2)]
        T = dm(idf(theta, theta, dtheta, dphi, *acc)[1])
        phi = theta + consistent_psi(arm.model, T, dphi - dtheta)
        tau, T2 = (dm(v) for v in idf(theta, phi, dtheta, dphi, *acc))
        assert rel([T2], [T]) < 1e-12
        assert rel([dm(v) for v in fd(theta, phi, dtheta, dphi, tau)], acc) < 1e-10


def test_mass_matrix_structure(request):
    """B constant diagonal, S strictly upper triangular, reduced M = complete M with S zeroed."""
    rng = np.random.default_rng(5)
    for arm in [request.getfixturevalue("arm3")] + request.getfixturevalue("balanced_arms"):
        n = arm.n
        B = np.array([jt.rotor_inertia for jt in arm.model.joints])
        for _ in range(3):
            x = random_state(rng, n)
            M, Mr = np.array(arm.mass_matrix()(x[0], x[1])), np.array(arm.mass_matrix(reduced=True)(x[0], x[1]))
            scale = np.max(np.abs(M))
            assert np.allclose(M, M.T, rtol=0, atol=1e-14 * scale)
            assert np.allclose(M[n:, n:], np.diag(B), rtol=0, atol=1e-14 * scale)
            S = M[:n, n:]
            assert np.all(np.abs(np.tril(S)) <= 1e-14 * scale), "S must be strictly upper triangular"
            expected = M.copy()
            expected[:n, n:] = expected[n:, :n] = 0
            assert np.allclose(Mr, expected, rtol=0, atol=1e-12 * scale)


def test_reference_coupling_is_the_elbow_rotor(arm3):
    """On the reference arm only S_23 = Izz(S_3) - mu_3 Izz(F_3) survives (docs/user-guide/model.md, the reference arm)."""
    M = np.array(arm3.mass_matrix()(np.array([0.3, -0.7, 1.1]), np.array([0.31, -0.69, 1.12])))
    S = M[:3, 3:]
    assert S[1, 2] == pytest.approx(2.5e-4 - 80 * 1.6e-5, rel=1e-12)
    S[1, 2] = 0
    assert np.max(np.abs(S)) < 1e-15


def test_complete_and_reduced_differ_measurably(arm3):
    """With realistic numbers the models differ by 0.1-1 % at most; tight tolerances tell them apart."""
    x = [np.array([0.2, 0.5, -0.8]), np.array([0.21, 0.52, -0.79]), np.array([1.0, -1.5, 2.0]), np.array([1.2, -1.3, 2.4])]
    tau = np.array([0.1, -0.2, 0.15])
    a = np.concatenate([dm(v) for v in arm3.forward_dynamics()(*x, tau)])
    b = np.concatenate([dm(v) for v in arm3.reduced_forward_dynamics()(*x, tau)])
    d = np.max(np.abs(a - b)) / np.max(np.abs(a))
    assert 1e-6 < d < 0.05


def test_reduced_model_refuses_unbalanced_rotors(request):
    arm = request.getfixturevalue("random_arms")[1]
    with pytest.raises(ValueError, match=r"balanced rotors.*joint 1 \('j1'\) slow_rotor"):
        arm.reduced_forward_dynamics()


def test_paper_cascade_functions_have_the_complete_model_as_fixed_point(request):
    """Eq. (23) given the exact ddtheta returns the exact ddphi; eqs. (30)-(32) given the exact
    ddphi and ddtheta return ddtheta; with a wrong guess they do not."""
    rng = np.random.default_rng(6)
    for arm in arms_under_test(request):
        x, tau = random_state(rng, arm.n), rng.normal(size=arm.n)
        ddth, ddph = (dm(v) for v in arm.forward_dynamics()(*x, tau))
        assert rel([dm(arm.joint_forward_dynamics()(*x, tau, ddth))], [ddph]) < 1e-10
        assert rel([dm(arm.arm_forward_dynamics()(*x, ddph, ddth))], [ddth]) < 1e-10
        if arm.n > 1:
            wrong = dm(arm.arm_forward_dynamics()(*x, ddph, ddth + 50.0))
            assert rel([wrong], [ddth]) > 1e-8


def test_forward_dynamics_jacobian_against_finite_differences(request):
    """The implicit-function Jacobian (M J = [-dr/dx | dQ/dtau]) against central differences of
    the numpy core, on random arms."""
    rng = np.random.default_rng(8)
    for arm in arms_under_test(request)[::2]:
        n, num = arm.n, Numeric(arm.model)
        x, tau = random_state(rng, n), rng.normal(size=n)
        z = np.concatenate(x + [tau])
        fd = lambda z: np.concatenate(num.forward_dynamics(*np.split(z[:4 * n], 4), z[4 * n:]))
        eps = 1e-6 * max(1.0, np.max(np.abs(z)))
        J_fd = np.column_stack([(fd(z + eps * e) - fd(z - eps * e)) / (2 * eps) for e in np.eye(5 * n)])
        J = np.array(arm.forward_dynamics_jacobian()(*x, tau))
        assert rel([J], [J_fd]) < 1e-6


def test_arms_of_equal_models_share_their_functions_and_only_they():
    # an OCP's rounds, guesses and replays make many Arms of one model: its Functions are built once
    from rscasadi.dynamics.arm import Arm
    from rscasadi.model.modelfile import read
    from rscasadi.model.parameters import with_values
    first, again = Arm(read(REFERENCE)), Arm(read(REFERENCE))          # read twice: equal, not the same object
    assert first.inverse_dynamics() is again.inverse_dynamics()
    heavier = Arm(with_values(read(REFERENCE), {"elbow_pitch.link.mass": 3.0}))
    assert heavier.inverse_dynamics() is not first.inverse_dynamics()
    assert Arm(read(REFERENCE), free=["elbow_pitch.link.mass"]).inverse_dynamics(parametric=True) \
        is not first.inverse_dynamics(parametric=True)
    # the heavier elbow link: a larger holding torque at the shoulder pitch, by its weight times its lever
    x = [np.array([0.0, 0.4, -0.3])] * 2 + [np.zeros(3)] * 4
    light, heavy = (np.array(a.inverse_dynamics()(*x)[1]).ravel() for a in (first, heavier))
    assert abs(heavy[1]) > abs(light[1]) + 1e-3
    np.testing.assert_array_equal(light, np.array(again.inverse_dynamics()(*x)[1]).ravel())
