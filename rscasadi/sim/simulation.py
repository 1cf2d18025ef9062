"""Simulation: the exact complete (or reduced) model, the feedforward pipeline, and the
paper's cascade of flexible-joint and whole-arm dynamics with an Adams predictor-corrector.

Torques are samples tau[:, k] at uniform times t[k], linearly interpolated in between.
States are x = (theta, phi, dtheta, dphi) stacked (2 nq: every joint's link, then the SEAs'
motors); torques tau have one row per actuated joint.
"""
from __future__ import annotations

import hashlib
import pickle

import casadi as ca
import numpy as np

from rscasadi.dynamics.arm import Arm
from rscasadi.dynamics.statics import spring_deflection  # noqa: F401  (part of this module's API)
from rscasadi.errors import InvalidArgument
from rscasadi.files import sources_digest
from rscasadi.model.kinds import require_sea


def _uniform_step(t):
    t = np.asarray(t, float)
    h = np.diff(t)
    if len(t) < 2 or np.max(np.abs(h - h[0])) > 1e-9 * max(1.0, abs(t[-1])):
        raise InvalidArgument("simulation times must be a uniform grid of at least two points")
    return float(h[0])


def _xdot(arm: Arm, reduced: bool):
    fd = arm.reduced_forward_dynamics() if reduced else arm.forward_dynamics()
    return lambda x, tau: ca.vertcat(*arm.split_state(x)[2:], *fd(*arm.split_state(x), tau))


def simulate(arm: Arm, x0, t, tau, method: str = "cvodes", tol: float = 1e-10, substeps: int = 4,
             reduced: bool = False, interpolation: str = "linear") -> dict:
    """Integrate from x0 over the uniform grid t with torque samples tau (u, len(t)),
    interpolated "linear"ly or held "constant" on [t_k, t_k+1).

    method "cvodes": adaptive BDF/Adams (CasADi's CVODES) to relative/absolute `tol`;
    method "rk4": `substeps` classical RK4 steps per sample interval.
    Returns t, theta, dtheta (n, len(t)), phi, dphi, psi = phi - theta (the SEAs'), and energy."""
    n, nx, dt = arm.u, 2 * arm.nq, _uniform_step(t)
    tau = np.asarray(tau, float).reshape(n, len(t))
    if interpolation not in ("linear", "constant"):
        raise InvalidArgument(f"unknown interpolation {interpolation!r} (linear or constant)")
    slope = 1.0 if interpolation == "linear" else 0.0
    x, p = ca.MX.sym("x", nx), ca.MX.sym("p", 2 * n)
    f = _xdot(arm, reduced)
    torque = lambda s: p[:n] + slope * s / dt * (p[n:] - p[:n])      # within one interval
    if method == "cvodes":
        xs, ps, ts = ca.SX.sym("x", nx), ca.SX.sym("p", 2 * n), ca.SX.sym("t")
        fs = _xdot(arm, reduced)
        ode = {"x": xs, "p": ps, "t": ts, "ode": fs(xs, ps[:n] + slope * ts / dt * (ps[n:] - ps[:n]))}
        F = ca.integrator("F", "cvodes", ode, 0.0, dt, {"abstol": tol, "reltol": tol, "max_num_steps": 100000})
        x_end = F(x0=x, p=p)["xf"]
    elif method == "rk4":
        h, x_end = dt / substeps, x
        for i in range(substeps):
            s0 = i * h
            k1 = f(x_end, torque(s0))
            k2 = f(x_end + h / 2 * k1, torque(s0 + h / 2))
            k3 = f(x_end + h / 2 * k2, torque(s0 + h / 2))
            k4 = f(x_end + h * k3, torque(s0 + h))
            x_end = x_end + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    else:
        raise InvalidArgument(f"unknown method {method!r} (cvodes or rk4)")
    interval = ca.Function("interval", [x, p], [x_end])
    P = np.vstack([tau[:, :-1], tau[:, 1:]])
    X = np.hstack([np.asarray(x0, float).reshape(-1, 1), np.array(interval.mapaccum(len(t) - 1)(x0, P))])
    return trajectory_record(arm, t, X)


def simulate_held(arm: Arm, x0, t, tau, substeps: int, tol: float = 1e-10, energy: bool = True) -> dict:
    """Torque samples tau[:, k] held on [t_k, t_k+1) (tau_interpolation "constant"; t may be
    non-uniform), simulated with CVODES and reported `substeps` times finer than t.  One CVODES
    run per interval, reporting on its grid without restarting (a restart per fine sample, from
    order 1 and a tiny step, was 11x slower and 30x less accurate at the same tolerance).
    `energy`: the record has the energy at each sample (False: not computed)."""
    t = np.asarray(t, float)
    N = len(t) - 1
    F = held_interval(arm, tol, substeps)
    _, X = F.mapaccum(N)(x0, np.vstack([np.asarray(tau, float)[:, :N], np.diff(t)]))
    h = np.diff(t) / substeps
    fine = np.concatenate([[t[0]], (t[:-1, None] + h[:, None] * np.arange(1, substeps + 1)).ravel()])
    return trajectory_record(arm, fine, np.hstack([np.asarray(x0, float).reshape(-1, 1), np.array(X)]), energy)


# from this many joints on, the replay's right-hand side and its Jacobian are compiled: CVODES
# then spends 6x less (the Panda's 100 intervals: 0.50 -> 0.085 s) for a compile of about 7 s at
# -O1, once per arm structure; on 3 joints CasADi's virtual machine costs milliseconds
COMPILED_FROM_JOINTS = 6
_ODES: dict = {}          # a model's digest -> its family's compiled right-hand side and free parameters
_GENERATOR = sources_digest(__file__)         # part of the library's index key


def held_ode(arm: Arm, log=None) -> ca.Function:
    """(x, [tau; h]) -> h dx/dt of the complete model under the held torque tau: CVODES' right-hand
    side for `held_interval`.  SX (CasADi's virtual machine) below COMPILED_FROM_JOINTS joints;
    from there on, the arm family's dynamics (Arm.family: the model's numbers as an input, so a
    payload or a swept parameter shares the library) and their Jacobian, compiled once into a
    cached library (`log` says so when it compiles)."""
    n, nx = arm.u, 2 * arm.nq
    if arm.n < COMPILED_FROM_JOINTS:
        x, p = ca.SX.sym("x", nx), ca.SX.sym("p", n + 1)
        return ca.Function("held_ode", [x, p], [p[n] * _xdot(arm, False)(x, p[:n])], ["x", "p"], ["ode"])
    digest = hashlib.sha256(pickle.dumps(arm.model)).hexdigest()
    if digest not in _ODES:
        _ODES[digest] = _compiled_rhs(arm, log)
        while len(_ODES) > 16:
            _ODES.pop(next(iter(_ODES)))
    rhs, free = _ODES[digest]
    values = dict(zip(*Arm(arm.model).parameters()))
    x, p = ca.MX.sym("x", nx), ca.MX.sym("p", n + 1)
    return ca.Function("held_ode", [x, p], [rhs(x, p, [float(values[k]) for k in free])], ["x", "p"], ["ode"])


def _compiled_rhs(arm: Arm, log) -> tuple:
    """(the external (x, p, q) -> h dx/dt, q's parameter names) of the arm's family, from the
    cache's index or compiled now."""
    from rscasadi.native.build import cached_library, casadi_c, compiler, indexed
    n, nx, family = arm.u, 2 * arm.nq, Arm.family(arm.model)
    x, p, q = ca.SX.sym("x", nx), ca.SX.sym("p", n + 1), ca.SX.sym("q", family.n_p)
    xs = family.split_state(x)
    rhs = p[n] * ca.vertcat(xs[2], xs[3], *family.forward_dynamics(parametric=True)(*xs, p[:n], q))
    name = "rsode" + hashlib.sha256(ca.Function("ode", [x, p, q], [rhs]).serialize().encode()).hexdigest()[:16]
    f = ca.Function(name, [x, p, q], [rhs], ["x", "p", "q"], ["ode"])
    # casadi.external's Jacobian, jac_<name>: with respect to x and p only (q always enters as the
    # model's numbers, a constant; its block is structurally zero): 27k instructions for the Panda
    # where the full Jacobian has 72k
    out = ca.SX.sym("out_ode", nx)
    J = ca.jacobian(rhs, ca.vertcat(x, p))
    jac = ca.Function("jac_" + name, [x, p, q, out], [J[:, :nx], J[:, nx:], ca.SX(ca.Sparsity(nx, family.n_p))],
                      ["x", "p", "q", "out_ode"], ["jac_ode_x", "jac_ode_p", "jac_ode_q"])
    key = "\n".join(["replay ode", name, *compiler(), ca.__version__, _GENERATOR])
    # no -march=native: CVODES is SSE code, and AVX code that returns with the vector registers'
    # upper halves in use slows every SSE instruction after it (docs/design/kernels.md)
    (lib, *_), _ = indexed(key, lambda: [cached_library(
        {f"{name}.c": casadi_c([f, jac], f"{name}.c")}, ["-O1"], name="ode",
        what=f"the replay's dynamics of {arm.model.name!r} ({arm.n} joints)", log=log or (lambda m: None))])
    return ca.external(name, lib), list(family.free)


def held_interval(arm: Arm, tol: float = 1e-10, substeps: int | None = None) -> ca.Function:
    """(x, [tau; h]) -> x after h seconds of the complete model under the held torque tau (CVODES,
    time scaled to [0, 1] so that one Function serves every interval length); with `substeps`,
    (x, [tau; h]) -> (x at h, x at h/substeps, 2 h/substeps, ..., h as columns), one run."""
    n, nx = arm.u, 2 * arm.nq
    rhs = held_ode(arm)
    sym = ca.SX.sym if rhs.is_a("SXFunction") else ca.MX.sym
    x, p = sym("x", nx), sym("p", n + 1)
    ode = {"x": x, "p": p, "ode": rhs(x, p)}
    grid = [1.0] if substeps is None else (np.arange(1, substeps + 1) / substeps).tolist()
    F = ca.integrator("F", "cvodes", ode, 0.0, grid, {"abstol": tol, "reltol": tol, "max_num_steps": 100000})
    xs, ps = ca.MX.sym("x", nx), ca.MX.sym("p", n + 1)
    X = F(x0=xs, p=ps)["xf"]
    if substeps is None:
        return ca.Function("held", [xs, ps], [X])
    return ca.Function("held_grid", [xs, ps], [X[:, -1], X])


def trajectory_record(arm: Arm, t, X, energy: bool = True) -> dict:
    """A simulated run as a record: t, theta, phi, dtheta, dphi, psi (the SEAs': phi - their
    theta) and (`energy`) the energy at each sample."""
    n, q = arm.n, arm.nq
    theta, phi, dtheta, dphi = X[:n], X[n:q], X[q:q + n], X[q + n:]
    record = {"t": np.asarray(t, float), "theta": theta, "phi": phi, "dtheta": dtheta, "dphi": dphi,
              "psi": phi - theta[arm.model.motors], "x": X}
    if energy:
        record["energy"] = np.array(arm.energy().map(X.shape[1])(theta, phi, dtheta, dphi)).ravel()
    return record


# ------------------------------------------------------------------ feedforward along a trajectory

MOTOR_PD_HZ, MOTOR_PD_ZETA = 4.0, 0.8     # the motor-position loop around a feedforward


def motor_pd_gains(model, hz: float = MOTOR_PD_HZ, zeta: float = MOTOR_PD_ZETA) -> tuple:
    """(kp, kd) per joint of the motor-position PD that runs around a feedforward (slow side,
    divided by the gear ratio at the motor): each rotor's inertia B as a mass-spring-damper at
    `hz` with damping ratio `zeta`, kp = B w^2, kd = 2 zeta B w."""
    B, w = np.array([jt.rotor_inertia for jt in model.joints]), 2 * np.pi * hz
    return B * w ** 2, 2 * zeta * B * w


def feedforward(arm: Arm, trajectory, t, reduced: bool = False) -> dict:
    """Motor torques that make the arm follow the expected link motion: the paper's cascade of
    the whole-arm inverse dynamics (eq. 26), the spring law integrated by the trapezoidal rule
    (implicit: d/k1 is about a millisecond) and the flexible-joint inverse dynamics (eq. 22),
    one sample at a time by `feedforward_step` (rscasadi.dynamics.feedforward, also generated to C).
    Starts in the spring-consistent static equilibrium of theta(0) (the trajectory starts at rest).
    Returns tau (n, len(t)), the initial state x0, and the rotor motion phi, dphi, ddphi."""
    from rscasadi.dynamics.feedforward import feedforward_functions
    require_sea(arm.model, "the feedforward")
    n, h, N = arm.n, _uniform_step(t), len(t)
    th, dth, ddth = trajectory(t)[:3]
    init, step = feedforward_functions(arm, reduced)
    tau0, s0 = init(th[:, 0], dth[:, 0], ddth[:, 0])
    tau, states = step.mapaccum("feedforward", N - 1, [0], [1])(s0, th[:, 1:], dth[:, 1:], ddth[:, 1:], h)
    S = np.hstack([np.array(s0), np.array(states)])
    psi, dpsi, ddpsi = S[:n], S[n:2 * n], S[2 * n:3 * n]
    phi, dphi, ddphi = th + psi, dth + dpsi, ddth + ddpsi
    x0 = np.concatenate([th[:, 0], phi[:, 0], dth[:, 0], dphi[:, 0]])
    return {"t": np.asarray(t, float), "tau": np.hstack([np.array(tau0), np.array(tau)]), "x0": x0,
            "theta_d": th, "phi": phi, "dphi": dphi, "ddphi": ddphi}


# ------------------------------------------------------------------ the paper's cascade, forward

def cascade_accelerations(arm: Arm) -> ca.Function:
    """(x, tau, ddtheta_guess) -> (ddtheta, ddphi): flexible-joint eq. (23) with the guessed link
    accelerations, then whole-arm eqs. (30)-(32) with those rotor accelerations."""
    n = arm.n
    x, tau, guess = ca.SX.sym("x", 4 * n), ca.SX.sym("tau", n), ca.SX.sym("guess", n)
    q = ca.vertsplit(x, n)
    ddphi = arm.joint_forward_dynamics()(*q, tau, guess)
    ddtheta = arm.arm_forward_dynamics()(*q, ddphi, guess)
    return ca.Function("cascade", [x, tau, guess], [ddtheta, ddphi])


AB4 = np.array([55, -59, 37, -9]) / 24          # Adams-Bashforth, newest first
AM4 = np.array([9, 19, -5, 1]) / 24             # Adams-Moulton: new, then newest first
EXTRAPOLATE = np.array([4, -6, 4, -1])          # cubic extrapolation of the link accelerations


def cascade_simulate(arm: Arm, x0, t, tau, h: float, start_iterations: int = 6) -> dict:
    """The paper's forward simulation: eqs. (23) and (30)-(32) computed alternately, coupled by a
    fourth-order Adams-Bashforth-Moulton predictor-corrector (PECE) with step h.  The link
    accelerations that eq. (23) needs are extrapolated (cubic) for the predictor and taken from
    the predictor's evaluation for the corrector.  Start: three RK4 steps, in each stage the
    cascade iterated `start_iterations` times from the previous accelerations.
    Returns the states at the sample times t (t must be multiples of h)."""
    require_sea(arm.model, "the paper's cascade simulation")
    n, dt = arm.n, _uniform_step(t)
    m = int(round(dt / h))
    if m < 1 or abs(m * h - dt) > 1e-9 * dt:
        raise InvalidArgument(f"the sample interval {dt} must be a whole number of steps h = {h}")
    casc = cascade_accelerations(arm)
    tau = np.asarray(tau, float).reshape(n, len(t))
    t_fine = np.arange(0, (len(t) - 1) * m + 1) * h + t[0]
    torque = lambda s: np.array([np.interp(s, t, tau[i]) for i in range(n)])

    def accel(x, s, guess, iterations=1):
        for _ in range(iterations):
            a, b = casc(x, torque(s), guess)
            guess = np.array(a).ravel()
        return np.concatenate([guess, np.array(b).ravel()])

    def f(x, a):
        return np.concatenate([x[2 * n:], a])

    x, a = np.asarray(x0, float), accel(np.asarray(x0, float), t_fine[0], np.zeros(n), start_iterations)
    X, F, A = [x], [f(x, a)], [a[:n]]
    for k in range(min(3, len(t_fine) - 1)):                        # starting procedure: RK4
        stages: list = []
        s, guess = t_fine[k], a[:n]
        for c, base in ((0.0, None), (0.5, 0), (0.5, 1), (1.0, 2)):
            xs = x if base is None else x + c * h * stages[base]
            a_s = accel(xs, s + c * h, guess, start_iterations)
            guess = a_s[:n]
            stages.append(f(xs, a_s))
        x = x + h / 6 * (stages[0] + 2 * stages[1] + 2 * stages[2] + stages[3])
        a = accel(x, s + h, guess, start_iterations)
        X.append(x)
        F.append(f(x, a))
        A.append(a[:n])
    for k in range(3, len(t_fine) - 1):                             # ABM4, PECE
        s = t_fine[k + 1]
        x_p = x + h * sum(c * F[-1 - i] for i, c in enumerate(AB4))
        guess = sum(c * A[-1 - i] for i, c in enumerate(EXTRAPOLATE))
        a_p = accel(x_p, s, guess)
        x = x + h * (AM4[0] * f(x_p, a_p) + sum(c * F[-1 - i] for i, c in enumerate(AM4[1:])))
        a = accel(x, s, a_p[:n])
        X.append(x)
        F.append(f(x, a))
        A.append(a[:n])
        if len(F) > 4:
            del F[0], A[0]
    return trajectory_record(arm, t, np.array(X).T[:, ::m])
