"""Excitation trajectories for identification (`rscasadi excite`), after Swevers et al.: a
periodic link motion as a finite Fourier series whose stacked base regressor is as well
conditioned as the limits allow.

Unknowns: the offsets and the sine and cosine coefficients of every joint (trajectory.fourier).
At rest at t = 0 (and so at the end of every period): velocity, acceleration and jerk vanish,
which are linear constraints on the coefficients.  On M sample points of one period the design
model gives the regressor rows and the limits:

- the link motion theta(t) is the series; the SEA deflection is the one of the rigid motion,
  psi = T/k1 with T from eq. (26) at phi = theta, its rate by forward AD in time;
- rows: motor torque (weighted by 1 / its noise, 0.5 % of the limit) and the spring-driven
  link rows (weighted by 1 / 1 % of the spring torque at the deflection limit), in the base
  parameters, each column scaled by the size of its parameter (relative errors);
- limits (times `margin`): motor torque, slow-side speed, deflection, link angles.

The design minimises tr(A^-1), A = sum Y^T Y / M (A-optimal: the sum of the relative variances
of the base parameters, which also bounds the condition number, kappa <= tr(A) tr(A^-1)), with
IPOPT (a limited-memory Hessian by default, or the exact one) from a few deterministic starts; a
start ends when the criterion stalls (STALL).  Each result is scaled down until
the exact feedforward (the paper's pipeline) respects every limit, then checked: every joint
sweeps at least MIN_SWEEP of its angle range and kappa stays below MAX_CONDITION.  The best
checked design is kept; if none passes, ExcitationError names each start's cause.
"""
from __future__ import annotations

import functools
import os
from pathlib import Path

import casadi as ca
import numpy as np

from rscasadi.sim.simulation import feedforward
from rscasadi.sim.trajectory import Trajectory
from rscasadi.dynamics.arm import Arm, load
from rscasadi.files import CheckError, fresh_directory, write_json
from rscasadi.model.parameters import n_linear
from rscasadi.identification.identify import Unknowns, prior_scale, structural_base
from rscasadi.identification.regressor import regressor, spring_regressor
from rscasadi.interrupt import happened, raise_if_interrupted
from rscasadi.errors import InvalidArgument
from rscasadi.model.kinds import require_sea

TORQUE_NOISE = 0.005
MAX_CONDITION = 1e5  # a design above this is refused (a hand-picked bump on every joint: ~1e9)
SIZE_FLOOR = 0.1     # the design's relative variances: a parameter sized at least a tenth of its kind
                     # (a product of inertia of 6e-8 kg m^2 beside moments of 1e-3 is not wanted to 1e-8)
MIN_SWEEP = 0.1      # every joint sweeps at least this fraction of its angle range
STARTS = 3           # deterministic starts; the best checked design is kept
PROGRESS_S = 5.0     # seconds between progress lines of a start
HESSIANS = ("limited-memory", "exact")
STALL = (10, 1e-3)   # a start ends when log tr(A^-1) fell by less than 1e-3 (0.1 % of tr A^-1) in 10
                     # iterations: limited-memory (L-BFGS) iterations approach the optimum slowly and
                     # never reach IPOPT's tolerance


def _basis(period, K, t):
    """Matrices B_d (K x M), d = 0..4, with d-th derivative of theta = offset (d = 0) + a B_d^s + b B_d^c."""
    w = 2 * np.pi / period
    out = []
    for d in range(5):
        S, C = np.zeros((K, len(t))), np.zeros((K, len(t)))
        for l in range(1, K + 1):
            wl = w * l
            # d/dt^d of sin(wl t)/wl and of -cos(wl t)/wl
            s, c = np.sin(wl * t), np.cos(wl * t)
            S[l - 1] = (s / wl, c, -wl * s, -wl ** 2 * c, wl ** 3 * s)[d]
            C[l - 1] = (-c / wl, s, wl * c, -wl ** 2 * s, -wl ** 3 * c)[d]
        out.append((S, C))
    return out


def _sample_function(arm: Arm, unknowns: Unknowns, columns, col_scale, weights):
    """(q, dq, ddq, d3q, d4q) -> weighted, scaled base rows (2n x r), and -> tau, psi, dphi, for
    one sample.  psi = T/k1 of the rigid motion, its time derivatives by forward AD along the motion."""
    n = arm.n
    q, dq, ddq, d3q, d4q = (ca.SX.sym(s, n) for s in ("q", "dq", "ddq", "d3q", "d4q"))
    inv = arm.inverse_dynamics()
    _, T = inv(q, q, dq, dq, ddq, ddq)
    psi = T / ca.DM(arm.model.column("k1"))
    x, dx = ca.vertcat(q, dq, ddq, d3q), ca.vertcat(dq, ddq, d3q, d4q)
    dpsi = ca.jtimes(psi, x, dx)
    ddpsi = ca.jtimes(dpsi, x, dx)
    phi, dphi, ddphi = q + psi, dq + dpsi, ddq + ddpsi
    tau, _ = inv(q, phi, dq, dphi, ddq, ddphi)
    Y = regressor(arm)(q, phi, dq, dphi, ddq, ddphi)[0] @ ca.DM(unknowns.E)
    Ys = spring_regressor(arm)(q, phi, dq, dphi) @ ca.DM(unknowns.E)
    rows = ca.vertcat(Y[:n, :], Y[n:, :] - Ys)[:, columns]
    rows = ca.diag(ca.DM(weights)) @ rows @ ca.diag(ca.DM(col_scale))
    inputs = [q, dq, ddq, d3q, d4q]
    # two Functions: the limits' Jacobian (the NLP's dearest part) then never differentiates the rows
    return ca.Function("sample_rows", inputs, [rows]), ca.Function("sample_limits", inputs, [tau, psi, dphi])


def _limits(arm: Arm):
    lim = {}
    for key in ("tau", "dphi", "psi"):
        lim[key] = np.array([jt.limits.get(key, np.inf) for jt in arm.model.joints])
    lo = np.array([jt.limits.get("theta", (-np.pi, np.pi))[0] for jt in arm.model.joints])
    hi = np.array([jt.limits.get("theta", (-np.pi, np.pi))[1] for jt in arm.model.joints])
    return lim, lo, hi


def _svd(arm: Arm, traj: Trajectory, samples: int = 400, fixed: tuple = ()):
    """Singular values (normalised by the number of samples like A = Z Z^T / M) and right singular
    vectors (rows, in the base parameters less `fixed`) of the weighted, scaled base regressor of
    the design model along traj (one period)."""
    (g, _), _ = _design_parts(arm, fixed)
    t = np.linspace(0, traj.period, samples, endpoint=False)
    rows = np.array(g.map(samples)(*traj(t)))
    Z = rows.reshape(2 * arm.n, samples, -1).reshape(-1, rows.shape[1] // samples)
    _, sv, Vt = np.linalg.svd(Z, full_matrices=False)
    return sv / np.sqrt(samples), Vt


def _singular_values(arm: Arm, traj: Trajectory, samples: int = 400, fixed: tuple = ()) -> np.ndarray:
    return _svd(arm, traj, samples, fixed)[0]


def weakest(arm: Arm, traj: Trajectory, share: float = 0.1, fixed: tuple = ()) -> tuple[list[tuple[str, float]], float]:
    """The least determined direction of the design: the base parameters (named by their
    independent unknown) that make up more than `share` of it, with their weights, and the
    condition number without it."""
    sv, Vt = _svd(arm, traj, fixed=fixed)
    _, names = _design_parts(arm, fixed)
    v = Vt[-1] ** 2
    order = [i for i in np.argsort(-v) if v[i] > share]
    return [(names[i], float(v[i])) for i in order], float(sv[0] / sv[-2]) if len(sv) > 1 else float("nan")


def condition_number(arm: Arm, traj: Trajectory, samples: int = 400, fixed: tuple = ()) -> float:
    """kappa of the weighted, scaled base regressor of the design model along traj (one period),
    the base parameters `fixed` left out."""
    sv = _singular_values(arm, traj, samples, fixed)
    return float(sv[0] / sv[-1])


@functools.lru_cache(maxsize=8)
def _design_parts(arm: Arm, fixed: tuple = ()):
    """The design model's sample functions (rows, limits) and the names of the base parameters it
    excites (each named by its independent unknown), those in `fixed` left out (built once per arm
    and set)."""
    unknowns = Unknowns.of(arm.model, load_losses=False)      # the design excites the linear part
    base = structural_base(arm, unknowns)
    th_nom = unknowns.from_p(arm.parameters()[1][:n_linear(arm.model)])
    keep = [c for c, i in enumerate(base.independent) if base.names[i] not in fixed]
    col_scale = (np.abs(base.P) @ prior_scale(unknowns, th_nom, floor=SIZE_FLOOR))[keep]
    lim, _, _ = _limits(arm)
    tau_noise = TORQUE_NOISE * np.where(np.isfinite(lim["tau"]), lim["tau"], 1.0)
    spring = 0.01 * arm.model.column("k1") * np.where(np.isfinite(lim["psi"]), lim["psi"], 0.1)
    weights = np.r_[1.0 / tau_noise, 1.0 / spring]
    return (_sample_function(arm, unknowns, [base.independent[c] for c in keep], col_scale, weights),
            [base.names[base.independent[c]] for c in keep])


ADVICE = ("What to change: a longer --period or more --harmonics (slower, richer motions); "
          "--margin closer to 1 if the limits allow; --max-condition above the least determined "
          "direction's condition number to accept it (identify then reports those parameters as "
          "uncertain, held near the model file's values)")


RIDGE = 1e-14        # A + RIDGE tr(A) / r: tr A^-1 stays finite and positive in floating point
UNEXCITABLE = 1e-16  # a base direction whose information at a probe motion filling the limits is below
                     # this fraction of the largest (kappa 1e8: 1000x past MAX_CONDITION) is fixed


def unexcitable(arm: Arm, period: float, K: int, t, log=print) -> dict:
    """The base parameters that no motion within the limits can excite, {name: why}: a probe
    motion (the first start, grown until a limit binds) is taken, and while its information has
    a direction below UNEXCITABLE of the largest, the parameter that makes up most of it is
    fixed at the file's value (a light wrist's cubic spring term: the deflections stay far too
    small to show it; products of inertia the axes never turn).  identify still fits them, with
    the file's value as the prior; their uncertainty shows in its report."""
    n = arm.n
    w = _start(arm, K, 1)
    a, b = w[:n * K].reshape(n, K, order="F"), w[n * K:2 * n * K].reshape(n, K, order="F")
    probe = Trajectory(model_path=Path(arm.model.path), period=period, duration=period, kind="fourier",
                       offset=w[2 * n * K:], a=a * 20.0, b=b * 20.0)
    try:
        probe = within_limits(arm, probe, t, log=lambda m: None)[0]
    except ExcitationError:
        return {}
    fixed: dict = {}
    for _ in range(len(_design_parts(arm)[1])):
        sv, Vt = _svd(arm, probe, fixed=tuple(fixed))
        if sv[-1] >= np.sqrt(UNEXCITABLE) * sv[0]:
            break
        _, names = _design_parts(arm, tuple(fixed))
        name = names[int(np.argmax(Vt[-1] ** 2))]
        fixed[name] = (f"fixed at the file's value: a motion filling the limits gives it {sv[-1] ** 2 / sv[0] ** 2:.1e} "
                       "of the best-determined direction's information")
        log(f"excitation: {name} cannot be excited within the limits; {fixed[name]}")
    return fixed


class ExcitationError(CheckError):
    """No designed trajectory passed its checks; the message names each start's cause."""


def _design_problem(arm: Arm, period: float, K: int, margin: float, M: int, max_iter: int = 500, log=print,
                    hessian: str = "limited-memory", fixed: tuple = ()):
    """The design NLP over (a, b, q0) and its bounds: min log tr A^-1 subject to rest at t = 0 and
    the limits at the M sample points (IPOPT; `hessian` "limited-memory" or "exact"); the base
    parameters `fixed` left out of A."""
    n = arm.n
    (g_rows, g_limits), names = _design_parts(arm, fixed)
    r = len(names)
    lim, lo, hi = _limits(arm)
    t = np.linspace(0, period, M, endpoint=False)
    B = _basis(period, K, t)
    a, b, q0 = ca.MX.sym("a", n, K), ca.MX.sym("b", n, K), ca.MX.sym("q0", n)
    Q = _series(a, b, q0, B)
    rows = g_rows.map(M)(*Q)
    x = ca.vertcat(ca.vec(a), ca.vec(b), q0)
    limits = _limit_function(g_limits, B, n, K)(x)
    Z = ca.reshape(rows.T, r, 2 * n * M)
    A = Z @ Z.T / M
    A = A + RIDGE * ca.trace(A) / r * ca.DM.eye(r)             # round-off never makes tr A^-1 negative
    # A-optimal: tr(A^-1) is the sum of the (column-scaled, so relative) parameter variances; it
    # bounds the condition number (kappa <= tr(A) tr(A^-1)) and, unlike kappa, rewards amplitude
    f = ca.log(ca.trace(ca.solve(A, ca.DM.eye(r))))
    lvec = lambda v: np.repeat(v, M)                           # limits per sample, joint-major after vec
    rest = ca.vertcat(ca.sum2(a), b @ ca.DM(np.arange(1, K + 1)), a @ ca.DM(np.arange(1, K + 1) ** 2))
    cons = ca.vertcat(rest, limits, ca.vec(Q[0].T))
    fin = lambda v: np.where(np.isfinite(v), v, 1e20)
    bound = np.r_[margin * lvec(fin(lim["tau"])), margin * lvec(fin(lim["psi"])), margin * lvec(fin(lim["dphi"]))]
    room = (1 - margin) * (hi - lo) / 2
    progress = _Progress(x.shape[0], cons.shape[0], log)
    solver = ca.nlpsol("excite", "ipopt", {"x": x, "f": f, "g": cons}, {
        "ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "ipopt.max_iter": max_iter, "ipopt.tol": 1e-8,
        "ipopt.hessian_approximation": hessian, "iteration_callback": progress})
    solver.progress = progress                                 # kept alive with the solver
    bounds = {"lbg": np.r_[np.zeros(3 * n), -bound, lvec(lo + room)], "ubg": np.r_[np.zeros(3 * n), bound, lvec(hi - room)],
              "lbx": np.r_[-np.inf * np.ones(2 * n * K), lo], "ubx": np.r_[np.inf * np.ones(2 * n * K), hi]}
    return solver, bounds, r


def _series(a, b, q0, B):
    """The Fourier series and its first four time derivatives at the samples (n x M each)."""
    M = B[0][0].shape[1]
    return [(q0 @ ca.DM.ones(1, M) if d == 0 else 0) + a @ ca.DM(B[d][0]) + b @ ca.DM(B[d][1]) for d in range(5)]


def _limit_function(g_limits, B, n: int, K: int) -> ca.Function:
    """x = (vec a, vec b, q0) -> (vec tau', vec psi', vec dphi') at the M samples, with its Jacobian
    assembled by the chain rule: each sample's (3n x 5n) Jacobian of g_limits times the basis,
    d vec(Q_d) / dx = (B_d' kron I_n) (a constant).  CasADi's own AD of the mapped samples takes
    a forward sweep of the whole map per coefficient: four fifths of the design's time on 7 joints."""
    M = B[0][0].shape[1]
    u = [ca.SX.sym(f"u{d}", n) for d in range(5)]
    jac = ca.Function("sample_limits_jacobian", u, [ca.jacobian(ca.vertcat(*g_limits(*u)), ca.vertcat(*u))])
    a, b, q0 = ca.MX.sym("a", n, K), ca.MX.sym("b", n, K), ca.MX.sym("q0", n)
    x = ca.vertcat(ca.vec(a), ca.vec(b), q0)
    Q = _series(a, b, q0, B)
    tau, psi, dphi = g_limits.map(M)(*Q)
    out = ca.vertcat(ca.vec(tau.T), ca.vec(psi.T), ca.vec(dphi.T))
    eye = np.eye(n)
    dQ = [np.hstack([np.kron(B[d][0].T, eye), np.kron(B[d][1].T, eye), np.kron(np.ones((M, 1)), eye) * (d == 0)])
          for d in range(5)]                                          # d vec(Q_d) / dx, rows j + n s
    J_samples = jac.map(M)(*Q)                                        # 3n x 5n M: sample s, then d
    J = sum(ca.mtimes(ca.diagcat(*[J_samples[:, (5 * s + d) * n:(5 * s + d + 1) * n] for s in range(M)]),
                      ca.DM(ca.sparsify(ca.DM(dQ[d])))) for d in range(5))     # rows i + 3n s
    order = [i * M + s for s in range(M) for i in range(3 * n)]       # to vec(tau'), vec(psi'), vec(dphi')
    perm = np.argsort(order)
    jac_x = ca.Function("jac_limits", [x, ca.MX.sym("out", out.shape)], [J[perm.tolist(), :]])
    return ca.Function("limits", [x], [out], {"custom_jacobian": jac_x, "jac_penalty": 0, "never_inline": True})


class _Progress(ca.Callback):
    """IPOPT's iterations as a progress line every PROGRESS_S seconds: the start, the iteration,
    the objective (log tr A^-1) and the time so far."""

    def __init__(self, nx: int, ng: int, log):
        ca.Callback.__init__(self)
        self.nx, self.ng, self.log = nx, ng, log
        self.reset("")
        self.construct("excite_progress", {})

    def reset(self, label: str):
        import time
        self.label, self.k, self.t0, self.last = label, 0, time.perf_counter(), time.perf_counter()
        self.history: list = []
        self.stalled = False

    def get_n_in(self):
        return ca.nlpsol_n_out()

    def get_n_out(self):
        return 1

    def get_name_in(self, i):
        return ca.nlpsol_out(i)

    def get_name_out(self, i):
        return "ret"

    def get_sparsity_in(self, i):
        name = ca.nlpsol_out(i)
        size = {"f": 1, "x": self.nx, "lam_x": self.nx, "g": self.ng, "lam_g": self.ng}.get(name, 0)
        return ca.Sparsity.dense(size) if size else ca.Sparsity(0, 0)

    def eval(self, arg):
        import time
        self.k += 1
        f = float(arg[1])
        now = time.perf_counter()
        if now - self.last >= PROGRESS_S:
            self.last = now
            self.log(f"excitation: {self.label}iteration {self.k}, log tr(A^-1) {f:.4g}, {now - self.t0:.0f} s")
        self.history.append(f)
        span, drop = STALL
        self.stalled = len(self.history) > span and self.history[-span - 1] - f < drop
        return [1 if self.stalled else 0]                      # 1: IPOPT stops (User_Requested_Stop)


def _start(arm: Arm, K: int, seed: int):
    """A feasible start: small random coefficients at rest at t = 0, mid-range."""
    rng = np.random.default_rng(seed)
    lim, lo, hi = _limits(arm)
    a0, b0 = _rest_projection(rng.normal(0, 1, (arm.n, K)), rng.normal(0, 1, (arm.n, K)))
    peak = np.max(np.abs(np.hstack([a0, b0]))) + 1e-12
    dphi = np.where(np.isfinite(lim["dphi"]), lim["dphi"], 1.0)
    k = 0.5 * np.min(dphi) / (K * peak)
    return np.r_[(k * a0).ravel(order="F"), (k * b0).ravel(order="F"), 0.5 * (lo + hi)]


def check_design(arm: Arm, traj: Trajectory, t, kappa: float, max_condition: float = MAX_CONDITION,
                 fixed: tuple = ()) -> list[str]:
    """What makes a designed trajectory unfit for identification: a joint that hardly moves, a
    condition number above the bound, or numbers that are not finite."""
    _, lo, hi = _limits(arm)
    q = traj(t)[0]
    if not np.all(np.isfinite(q)) or not np.isfinite(kappa):
        return ["the trajectory or its condition number is not finite"]
    sweep = np.ptp(q, axis=1) / (hi - lo)
    out = [f"joint {jt.name} sweeps {100 * s:.2g} % of its angle range (at least {100 * MIN_SWEEP:g} % needed)"
           for jt, s in zip(arm.model.joints, sweep) if s < MIN_SWEEP]
    if kappa > max_condition:
        names, rest = weakest(arm, traj, fixed=fixed)
        out.append(f"condition number {kappa:.3g} above {max_condition:.3g}; least determined: "
                   + ", ".join(f"{name} ({100 * w:.0f} %)" for name, w in names)
                   + f" (without that direction {rest:.3g})")
    return out


def design(arm: Arm, period: float = 10.0, harmonics: int = 5, margin: float = 0.85, samples: int | None = None,
           starts: int = STARTS, rate: float = 1000.0, max_condition: float = MAX_CONDITION, max_iter: int = 500,
           hessian: str = "limited-memory", log=print) -> tuple[Trajectory, dict, dict, dict]:
    """The best checked design of `starts` deterministic starts: (trajectory, its exact
    feedforward, the limits' use, info).  Raises ExcitationError when no start passes.  Fewer
    `starts`, `samples` (the points the design's limits and information are taken at) or
    `max_iter` trade the design's quality for time; `hessian` "exact" takes IPOPT's exact Hessian
    (fewer, much dearer iterations: on 7 joints worse designs in the same time)."""
    require_sea(arm.model, "the excitation design")
    n, K = arm.n, harmonics
    M = samples or max(60, 12 * K)
    if hessian not in HESSIANS:
        raise InvalidArgument(f"hessian: must be one of {', '.join(HESSIANS)}, got {hessian!r}")
    t = np.arange(int(round(period * rate)) + 1) / rate
    fixed = unexcitable(arm, period, K, t, log)
    solver, bounds, r = _design_problem(arm, period, K, margin, M, max_iter, log, hessian, tuple(fixed))
    log(f"excitation: {n} joints, {K} harmonics, period {period} s, {M} samples, {r} base parameters"
        + (f" ({len(fixed)} fixed at the file's values)" if fixed else "") + f"; {starts} starts")
    tried: list[dict] = []
    best = None
    for seed in range(1, starts + 1):
        solver.progress.reset(f"start {seed}/{starts}: ")
        res = solver(x0=_start(arm, K, seed), **bounds)
        stats = solver.stats()
        if happened() or not solver.progress.stalled:          # a stop of our own is no Ctrl-C
            raise_if_interrupted(stats)
        w = np.array(res["x"]).ravel()
        a = w[:n * K].reshape(n, K, order="F")
        b = w[n * K:2 * n * K].reshape(n, K, order="F")
        a, b = _rest_projection(a, b)                       # exactly at rest, whatever IPOPT's last iterate
        traj = Trajectory(model_path=Path(arm.model.path), period=period, duration=period, kind="fourier",
                          offset=w[2 * n * K:], a=a, b=b)
        try:
            traj, ff, use = within_limits(arm, traj, t, log=lambda m: None)
            sv = _singular_values(arm, traj, fixed=tuple(fixed))
            kappa, variance = float(sv[0] / sv[-1]), float(np.sum(sv ** -2.0))     # tr A^-1, the criterion
            problems = check_design(arm, traj, t, kappa, max_condition, tuple(fixed))
        except ExcitationError as exc:
            kappa, variance, problems = float("nan"), float("nan"), [str(exc)]
        status = "Stalled" if solver.progress.stalled else stats["return_status"]
        entry = {"start": seed, "status": status, "iterations": int(stats["iter_count"]),
                 "condition_number": kappa if np.isfinite(kappa) else None, "refused": problems}
        tried.append(entry)
        log(f"excitation: start {seed}/{starts}: IPOPT {_worded(status)} after "
            f"{entry['iterations']} iterations, condition number {kappa:.4g}"
            + (f"; refused: {'; '.join(problems)}" if problems else ""))
        if not problems and (best is None or variance < best[3]):
            best = (traj, ff, use, variance, entry)
    if best is None:
        raise ExcitationError(f"{arm.model.path}: no excitation design passed its checks: "
                              + " | ".join(f"start {e['start']}: {'; '.join(e['refused'])}" for e in tried)
                              + ". " + ADVICE)
    traj, ff, use, _, entry = best
    return traj, ff, use, {"status": entry["status"], "iterations": entry["iterations"], "start": entry["start"],
                           "starts": tried, "samples": M, "base_parameters": r, "hessian": hessian,
                           "fixed": fixed}


def _worded(status: str) -> str:
    """IPOPT's return status as what it means for a design."""
    return {"Solve_Succeeded": "converged", "Solved_To_Acceptable_Level": "converged to its acceptable tolerance",
            "Stalled": f"stopped: log tr(A^-1) fell by less than {STALL[1]:g} in {STALL[0]} iterations",
            "Maximum_Iterations_Exceeded": "stopped at its iteration limit (the design is checked below)"
            }.get(status, status)


def _tril(X, tri):
    return ca.vertcat(*[X[i, j] for i, j in zip(*tri)])


def _rest_projection(a, b):
    """The nearest coefficients with velocity, acceleration and jerk zero at t = 0."""
    K = a.shape[1]
    l = np.arange(1, K + 1, dtype=float)
    Ca = np.vstack([np.ones(K), l ** 2])                    # sum a = 0, sum a l^2 = 0
    Cb = l[None, :]                                          # sum b l = 0
    proj = lambda C: np.eye(K) - C.T @ np.linalg.solve(C @ C.T, C)
    return a @ proj(Ca).T, b @ proj(Cb).T


def check_limits(arm: Arm, ff: dict) -> dict:
    """Largest use of each limit by the exact feedforward (1 = at the limit)."""
    lim, lo, hi = _limits(arm)
    th = ff["theta_d"]
    use = {"tau": np.max(np.abs(ff["tau"]) / lim["tau"][:, None]),
           "dphi": np.max(np.abs(ff["dphi"]) / lim["dphi"][:, None]),
           "psi": np.max(np.abs(ff["phi"] - th) / lim["psi"][:, None]),
           "theta": np.max(np.maximum((th - hi[:, None]) / (hi - lo)[:, None], (lo[:, None] - th) / (hi - lo)[:, None])) + 1}
    return {k: float(v) for k, v in use.items() if np.isfinite(v)}


def _theta_scale(arm: Arm, traj: Trajectory, t) -> float:
    """The largest factor on the Fourier coefficients that keeps the link angles in their limits."""
    _, lo, hi = _limits(arm)
    q = traj(t)[0]
    up, down = np.max(q - traj.offset[:, None], axis=1), np.max(traj.offset[:, None] - q, axis=1)
    room_up, room_down = hi - traj.offset, traj.offset - lo
    with np.errstate(divide="ignore"):
        return float(np.min(np.r_[np.where(up > 0, room_up / up, np.inf), np.where(down > 0, room_down / down, np.inf)]))


def within_limits(arm: Arm, traj: Trajectory, t, log=print, iterations: int = 20):
    """Scale the motion (about its offset) until the exact feedforward (the paper's pipeline)
    respects every limit: the link angles exactly, the rest by their ratio to the limit."""
    _, lo, hi = _limits(arm)
    offset = np.clip(traj.offset, lo + 0.02 * (hi - lo), hi - 0.02 * (hi - lo))
    scaled = lambda k: Trajectory(model_path=traj.model_path, period=traj.period, duration=traj.duration,
                                  kind="fourier", offset=offset, a=traj.a * k, b=traj.b * k)
    traj = scaled(1.0)
    for _ in range(iterations):
        room = _theta_scale(arm, traj, t)
        ff = feedforward(arm, traj, t)
        use = check_limits(arm, ff)
        worst = max(v for k, v in use.items() if k != "theta")
        if worst <= 1.0 and room >= 1.0:
            return traj, ff, use
        k = min(0.99 * room, 0.97 / worst, 1.0)
        log(f"excitation: the exact feedforward uses {worst:.3f} of a limit (angles: room {room:.3f}); "
            f"scaling the motion by {k:.3f}")
        traj = Trajectory(model_path=traj.model_path, period=traj.period, duration=traj.duration, kind="fourier",
                          offset=offset, a=traj.a * k, b=traj.b * k)
    raise ExcitationError(f"could not bring the motion within the limits in {iterations} scalings")


def hand_picked(arm: Arm, period: float, amplitude: float = 0.5) -> Trajectory:
    """The baseline: the paper's raised-cosine bump on every joint, `amplitude` rad, mid-range."""
    _, lo, hi = _limits(arm)
    return Trajectory(model_path=Path(arm.model.path), period=period, duration=period, kind="bump",
                      start=0.5 * (lo + hi), amplitude=np.full(arm.n, amplitude))


def run(model_file, out, period: float = 10.0, harmonics: int = 5, rate: float = 1000.0, starts: int = STARTS,
        samples: int | None = None, max_iter: int = 500, hessian: str = "limited-memory", margin: float = 0.85,
        max_condition: float = MAX_CONDITION, log=print) -> dict:
    """`rscasadi excite`: design and check an excitation trajectory for `model_file` and write it,
    its exact feedforward and its figures into `out` (whole or not at all); returns its summary."""
    arm = load(model_file)
    with fresh_directory(out) as tmp:       # checked writable before the design
        traj, ff, use, info = design(arm, period, harmonics, samples=samples, starts=starts, rate=rate,
                                     max_iter=max_iter, hessian=hessian, margin=margin, max_condition=max_condition,
                                     log=log)
        t = np.arange(int(round(period * rate)) + 1) / rate
        fixed = tuple(info["fixed"])
        kappa, kappa_hand = (condition_number(arm, tr, fixed=fixed) for tr in (traj, hand_picked(arm, period)))
        log(f"excitation: condition number {kappa:.4g} (hand-picked bump of 0.5 rad: {kappa_hand:.4g})")
        summary = {"model": os.path.relpath(Path(model_file).resolve(), Path(out).resolve()), **info, "period": period,
                   "harmonics": harmonics, "condition_number": kappa, "condition_number_hand_picked": kappa_hand,
                   "limit_use": use}
        # the model as seen from DIR, as trajectory files name theirs
        traj.write(tmp / "trajectory.toml", os.path.relpath(Path(model_file).resolve(), Path(out).resolve()))
        cols = ["t"] + [f"tau_{j + 1}" for j in range(arm.n)] + [f"theta_{j + 1}" for j in range(arm.n)] \
            + [f"phi_{j + 1}" for j in range(arm.n)]
        data = np.vstack([t, ff["tau"], ff["theta_d"], ff["phi"]]).T
        np.savetxt(tmp / "feedforward.csv", data, delimiter=",", header=",".join(cols), comments="", fmt="%.10g")
        write_json(tmp / "excitation.json", summary, indent=2)
        _plot(tmp / "excitation", t, ff, arm)
    log(f"wrote {Path(out) / 'trajectory.toml'}, feedforward.csv, excitation.json")
    return summary


def _plot(stem: Path, t, ff, arm: Arm):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    for j in range(arm.n):
        axes[0].plot(t, ff["theta_d"][j], label=f"theta_{j + 1}")
        axes[1].plot(t, ff["tau"][j] / arm.model.joints[j].limits.get("tau", 1.0), label=f"tau_{j + 1} / limit")
    axes[0].set_ylabel("link angle (rad)")
    axes[1].set_ylabel("motor torque / limit")
    axes[1].set_xlabel("t (s)")
    for ax in axes:
        ax.legend(fontsize=7, ncol=arm.n)
    fig.tight_layout()
    fig.savefig(stem.with_suffix(".png"), dpi=110)
    plt.close(fig)
