"""The one closed loop (rscasadi.sim.loop): its order of events, its sensors and its figures,
against a hand-made plant and controller whose every sample is known."""
import numpy as np
import pytest

import rscasadi
from rscasadi.errors import InvalidArgument
from rscasadi.sim.loop import Encoders, Run, limit_violation, rk4_plant, run_loop, step_times, tracking
from rscasadi.sim.sensors import LINK_COUNTS, MOTOR_COUNTS

from conftest import REFERENCE

DT = 1e-3


class Recorder:
    """Returns 10 k + joint index (beyond the torque limits from k = 1 on) and times itself."""

    def __init__(self):
        self.inits, self.steps, self.seconds = [], [], None

    def init(self, meas):
        self.inits.append(meas.copy())

    def step(self, k, meas):
        self.steps.append((k, meas.copy()))
        self.seconds = 1e-6 * (k + 1)
        return 10.0 * k + np.arange(len(meas) // 4)


def test_the_loop_measures_controls_clamps_and_advances_in_that_order():
    arm = rscasadi.load(REFERENCE)
    n, limit = arm.n, np.array([jt.limits["tau"] for jt in arm.model.joints])
    seen = []
    plant = lambda x, tau, t: (x + np.r_[tau, np.zeros(3 * n)] + t, None)      # a plant whose samples are known
    ctrl, x0 = Recorder(), np.zeros(4 * n)
    run = run_loop(arm, plant, ctrl, x0, 8, DT, sensors=Encoders(arm, DT, exact=True),
                   watch=lambda k, t, x, meas, tau, w: seen.append((k, t, x.copy(), None if tau is None else tau.copy())))
    taus = np.clip(np.array([10.0 * k + np.arange(n) for k in range(8)]).T, -limit[:, None], limit[:, None])
    assert np.array_equal(run.tau, taus) and np.array_equal(run.tau[:, -1], limit)    # clamped to the motor limits
    x = x0.copy()
    for k in range(8):
        assert np.array_equal(ctrl.steps[k][1], x) and np.array_equal(run.meas[:, k], x)   # measured before the step
        x = x + np.r_[taus[:, k], np.zeros(3 * n)] + k * DT
        assert np.allclose(run.x[:, k + 1], x)
    assert len(ctrl.inits) == 1 and np.array_equal(ctrl.inits[0], x0)
    assert [s[0] for s in seen] == list(range(9)) and seen[0][3] is None     # every sample and once after
    assert all(np.array_equal(seen[k][3], taus[:, k - 1]) for k in range(1, 9))   # the torque held before
    assert np.allclose(run.t, np.arange(9) * DT) and np.allclose(run.seconds, 1e-6 * np.arange(1, 9))
    assert step_times(run) == {"step_median_s": pytest.approx(4.5e-6), "step_worst_s": pytest.approx(8e-6)}


def test_encoders_quantise_and_difference():
    arm = rscasadi.load(REFERENCE)
    n, mu = arm.n, arm.model.column("gear_ratio")
    enc, rng = Encoders(arm, DT), np.random.default_rng(1)
    x0, x1 = rng.normal(size=4 * n), rng.normal(size=4 * n)
    m0, m1 = enc(x0), enc(x1)
    q_link, q_motor = 2 * np.pi / LINK_COUNTS, 2 * np.pi / MOTOR_COUNTS / mu
    assert np.allclose(m0[:n] / q_link, np.round(m0[:n] / q_link)) and np.all(np.abs(m0[:n] - x0[:n]) <= q_link / 2)
    assert np.all(np.abs(m0[n:2 * n] - x0[n:2 * n]) <= q_motor / 2 + 1e-15)
    assert np.array_equal(m0[2 * n:], x0[2 * n:])                            # the true speeds at the first sample
    assert np.allclose(m1[2 * n:], (m1[:2 * n] - m0[:2 * n]) / DT)           # then backward differences
    assert np.array_equal(Encoders(arm, DT, exact=True)(x1), x1)


def test_a_resting_arm_stays_at_rest_and_the_figures_say_so():
    """The RK4 plant holding the static torques: no motion, no violation, zero tracking error."""
    from rscasadi.dynamics.statics import rest_state
    arm = rscasadi.load(REFERENCE)
    n, x0 = arm.n, rest_state(arm, [0.1, 0.4, -0.7])
    zero = np.zeros(n)
    hold = np.array(arm.inverse_dynamics()(x0[:n], x0[n:2 * n], zero, zero, zero, zero)[0]).ravel()

    class Hold:
        def init(self, meas):
            pass

        def step(self, k, meas):
            return hold
    run = run_loop(arm, rk4_plant(arm, DT), Hold(), x0, 200, DT)
    assert np.max(np.abs(run.x - x0[:, None])) < 1e-9
    assert limit_violation(arm, run) == 0.0 and step_times(run) == {}
    figures = tracking(run.t[1:], np.max(np.abs(run.x[:n, 1:] - x0[:n, None]), axis=0))
    assert figures["max_error"] < 1e-9 and figures["rms_error"] < 1e-9


def test_the_loop_refuses_nonsense_before_running():
    arm = rscasadi.load(REFERENCE)
    with pytest.raises(InvalidArgument, match="samples must be >= 1"):
        run_loop(arm, None, Recorder(), np.zeros(4 * arm.n), 0, DT)
    assert isinstance(Run(np.zeros(1), np.zeros((1, 1)), np.zeros((1, 0)), np.zeros((1, 0)), np.zeros(0)).wrenches, list)
