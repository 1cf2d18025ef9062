"""Terms (rscasadi.task.terms): a term a user writes, taken from the documentation, holds in the
optimal-control problem (on the CVODES replay, not at the collocation points alone) and in the
MPC's closed loop on a simulated arm; the MPC's stage cost equals the cost its documentation
states, written out by hand; bad terms are refused by name before any work."""
import re
from pathlib import Path

import numpy as np
import pytest

from rscasadi.dynamics.arm import Arm
from rscasadi.dynamics.statics import rest_state
from rscasadi.errors import InvalidArgument
from rscasadi.mpc import MPCProblem, hold_function, rti_function
from rscasadi.mpc.formulation import controller_arm, limit_arrays, stage_residual
from rscasadi.mpc.problem import SOFT, mpc_model
from rscasadi.ocp import Problem, Task, TranscriptionOptions, Verification, solve
from rscasadi.sim.loop import Encoders, rk4_plant, run_loop
from rscasadi.task.terms import Effort, Term

ROOT = Path(__file__).resolve().parents[1]
TOOL = ROOT / "problems" / "arm3_tool.toml"
START, END = [0.0, 0.3, -0.5], [0.8, 0.9, -1.2]


def documented_term():
    """The AboveTable class exactly as docs/user-guide/problems.md shows it."""
    page = (ROOT / "docs" / "user-guide" / "problems.md").read_text()
    code = next(b for b in re.findall(r"```python\n(.*?)```", page, re.S) if "class AboveTable" in b)
    space: dict = {}
    exec(code, space)
    return space["AboveTable"]


def tool_height(arm, theta):
    place = arm.frame_placement("tool").map(theta.shape[1])
    return np.array(place(theta)[1])[2]


def test_the_documented_term_holds_on_the_replay_of_an_optimal_motion():
    AboveTable = documented_term()
    height = 0.33                        # the free motion dips to 0.271 m (docs)
    task = Task(TOOL, "min_effort", duration=1.5, theta_start=START, theta_end=END,
                terms=[AboveTable("tool", height)])
    # the rest at the end checked loosely: the term's rows are what this test is about
    problem = Problem(task, TranscriptionOptions(intervals=30), verification=Verification(final_angle_tol=1e-3,
                                                                                         final_speed_tol=2e-2))
    sol = solve(problem, log=lambda m: None, print_level=0)
    assert sol.verified and "term.above_table" in sol["verification"]
    arm = sol.arm()
    times = np.linspace(0.0, sol.t[-1], 3001)
    z = tool_height(arm, sol.sample("theta", times))         # the CVODES replay, between the nodes too
    assert z.min() > height - 1e-4
    assert z.min() < height + 2e-3                            # it binds: the free motion goes below


class PythonMPC:
    """The MPC's real-time iteration as CasADi Functions, as the loop's controller."""

    def __init__(self, p, ref):
        self.arm = controller_arm(mpc_model(p), p.parametric)
        self.rti, self.hold, self.ref = rti_function(self.arm, p), hold_function(self.arm, p), ref

    def init(self, meas):
        self.params = meas[:self.arm.n]
        self.X, self.U = (np.array(v) for v in self.hold(meas, self.params))

    def step(self, k, meas):
        tau, X, U = self.rti(meas, self.ref, self.X, self.U, self.params)
        self.X, self.U = np.array(X), np.array(U)
        return np.array(tau).ravel()


def test_the_documented_term_keeps_the_mpc_above_a_table_its_reference_goes_through():
    """The reference holds the tool 5 cm below its start; a table 2 cm below: without the term
    the tool follows the reference through it, with it the tool stays on the table (soft: within
    2 mm) on a simulated arm at 1 kHz."""
    AboveTable = documented_term()
    theta = np.array(START)
    base = dict(model=TOOL, frame="tool", weights={"position": 1e6, "velocity": 10.0, "posture": 1.0})
    arm = Arm(mpc_model(MPCProblem(**base)))
    tool = np.array(arm.frame_placement("tool")(theta)[1]).ravel()
    ref = np.tile(np.r_[tool - [0.0, 0.0, 0.05], 0.0, 0.0, 0.0][:, None], (1, 10))
    lowest = {}
    for table in (None, tool[2] - 0.02):
        p = MPCProblem(**base, terms=[] if table is None else [AboveTable("tool", table)]).check()
        run = run_loop(arm, rk4_plant(arm, 1e-3), PythonMPC(p, ref), rest_state(arm, theta), 400, 1e-3,
                       sensors=Encoders(arm, 1e-3, exact=True))
        lowest[table] = tool_height(arm, run.x[:3]).min() - tool[2]
    assert lowest[None] < -0.045
    assert -0.022 < lowest[tool[2] - 0.02] < -0.015


def test_the_mpc_stage_cost_is_the_documented_cost():
    """0.5 |r|^2 of the stage residual (built from terms) against mpc.md's cost written out:
    w_theta |theta - theta_ref|^2 + w_dtheta |dtheta - dtheta_ref|^2 + w_limits (|c| - 0.9 c_max)^2
    beyond 90 % of the psi and dphi limits, and w_angle_limits on the angles beyond 90 % of the
    range's half-width or beyond the reference's own distance from the middle where that is
    larger (never beyond the range), all halved; and the torque enters through no term (the QP's
    w_tau).  Some angles and references lie near the ranges' ends, some beyond them."""
    p = MPCProblem(ROOT / "problems" / "arm3.toml", trajectory=ROOT / "problems" / "trajectory_arm3.toml").check()
    arm = Arm(mpc_model(p))
    lim, w, n = limit_arrays(arm), p.weights, arm.n
    f = stage_residual(arm, p, lim)
    rng = np.random.default_rng(3)
    for _ in range(20):
        x = np.r_[rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), rng.uniform(-30, 30, 2 * n)]
        mid, half = (lim["theta_lo"] + lim["theta_hi"]) / 2, (lim["theta_hi"] - lim["theta_lo"]) / 2
        side = rng.choice([-1.0, 1.0], n)
        if rng.uniform() < 0.5:                                   # near or past the ends of the ranges
            x[:n] = mid + side * rng.uniform(0.85, 1.1, n) * half
        x[n:2 * n] = x[:n] + rng.uniform(-1.5, 1.5, n) * lim["psi"]
        ref, u = rng.normal(size=2 * n), rng.normal(size=n)
        if rng.uniform() < 0.5:
            ref[:n] = mid + side * rng.uniform(0.85, 1.1, n) * half
        r, _, Ju = (np.array(v) for v in f(x, u, ref, np.zeros(n)))
        theta, psi, dtheta, dphi = x[:n], x[n:2 * n] - x[:n], x[2 * n:3 * n], x[3 * n:]
        beyond = lambda c, cmax: np.sum(np.maximum(np.abs(c) - SOFT * cmax, 0) ** 2)
        band = np.minimum(np.maximum(SOFT * half, np.abs(ref[:n] - mid)), half)
        cost = (w["theta"] * np.sum((theta - ref[:n]) ** 2) + w["dtheta"] * np.sum((dtheta - ref[n:]) ** 2)
                + w["limits"] * (beyond(psi, lim["psi"]) + beyond(dphi, lim["dphi"]))
                + w["angle_limits"] * np.sum(np.maximum(np.abs(theta - mid) - band, 0) ** 2)) / 2
        assert 0.5 * np.sum(r ** 2) == pytest.approx(cost, rel=1e-12, abs=1e-9)
        assert not np.any(Ju)


class Broken(Term):
    name = "broken"

    def expression(self, arm, x, u, p):
        return x[:arm.n] @ x[:arm.n].T                       # a matrix, not a column


class Misbounded(Term):
    name = "misbounded"
    constraint = True

    def expression(self, arm, x, u, p):
        return x[:2]

    def bounds(self, arm):
        return np.zeros(3), np.ones(3)


class Asks(Term):
    name = "asks"
    n_p = 2

    def expression(self, arm, x, u, p):
        return x[:2] - p


@pytest.mark.parametrize("terms, words", [([Broken()], "term 'broken': expected a column"),
                                          ([Misbounded()], "term 'misbounded': bounds must be 2 pairs"),
                                          ([Asks()], "term 'asks': n_p = 2"),
                                          ([Effort(), Effort(2.0)], "two terms are named 'effort'"),
                                          (["effort"], "expected rscasadi.task.terms.Term objects")])
def test_a_bad_term_is_refused_by_name_before_any_work(terms, words):
    from rscasadi.ocp.problem import check_against_model
    from rscasadi.model.modelfile import read
    problem = Problem(Task(TOOL, "min_effort", duration=1.5, theta_start=START, theta_end=END, terms=terms))
    with pytest.raises(InvalidArgument, match=re.escape(words)):
        check_against_model(problem, read(TOOL))
    with pytest.raises(InvalidArgument, match=re.escape(words)):
        mpc_model(MPCProblem(TOOL, frame="tool", terms=terms))
