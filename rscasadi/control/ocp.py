"""Direct-collocation optimal control of the motor torques (IPOPT through CasADi).

Problem file (TOML), every field checked and named in errors:

    model = "arm3.toml"                  # relative to the problem file
    objective = "min_effort"             # min_time | min_effort | tracking
    theta_start = [0.0, 0.3, -0.5]       # rest poses (not for tracking); the arm starts and
    theta_end = [0.8, 0.9, -1.2]         # ends at rest in the SEA's static equilibrium
    duration = 1.5                       # s: fixed (min_effort, tracking) or the initial guess (min_time)
    max_duration = 5.0                   # min_time only (default 10 s)
    trajectory = "trajectory_arm3.toml"  # tracking only
    effort_weight = 1e-3                 # min_time and tracking: weight of the integral of tau^2
    [transcription]
    method = "radau"                     # radau | legendre | hermite-simpson
    degree = 3                           # collocation points per interval (radau, legendre)
    intervals = 100
    dynamics = "explicit"                # explicit (forward dynamics) | implicit (inverse-dynamics residual)
    compiled = true                      # generate the NLP's functions to C, compile once, cache
    [verification]                       # the replay on the complete model must meet these
    final_angle_tol = 1e-3               # theta, phi at the end (rad); also the tracking error
    final_speed_tol = 1e-2               # dtheta, dphi at the end (rad/s): 1e-2 rad/s of SEA ringing
                                         # at ~100 rad/s is 1e-4 rad of amplitude
    limit_tol = 1e-3                     # largest violation between grid points, relative to the limit
    [solver]
    hessian = "exact"                    # exact | limited-memory (L-BFGS: no second derivatives to
                                         # generate; for large arms, where the exact Hessian's C is huge)

Controls are held constant on each interval (tau_interpolation "constant"), so the effort
integral is exact.  Every limit of the model file is imposed at every node and collocation point.
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import os
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from ..dynamics.arm import Arm, load
from ..codegen import _compiler, cache_dir
from ..model.modelfile import ModelFileError, read_toml
from .simulation import simulate_held, spring_deflection
from .trajectory import load_trajectory

OBJECTIVES = ("min_time", "min_effort", "tracking")
METHODS = ("radau", "legendre", "hermite-simpson")
TOP = {"model", "objective", "theta_start", "theta_end", "duration", "max_duration", "trajectory",
       "effort_weight", "transcription", "verification", "solver"}
SOLVER = {"hessian"}
HESSIANS = ("exact", "limited-memory")
VERIFICATION = {"final_angle_tol", "final_speed_tol", "limit_tol"}
TRANSCRIPTION = {"method", "degree", "intervals", "dynamics", "compiled"}


@dataclass
class Problem:
    path: Path
    model_path: Path
    objective: str
    duration: float
    theta_start: np.ndarray | None = None
    theta_end: np.ndarray | None = None
    max_duration: float = 10.0
    trajectory: Path | None = None
    effort_weight: float = 1e-3
    method: str = "radau"
    degree: int = 3
    intervals: int = 100
    dynamics: str = "explicit"
    compiled: bool = True
    hessian: str = "exact"
    final_angle_tol: float = 1e-3
    final_speed_tol: float = 1e-2
    limit_tol: float = 1e-3


def load_problem(path) -> Problem:
    path = Path(path)
    d = read_toml(path, "problem")

    def fail(fld, msg):
        raise ModelFileError(f"{path}: field '{fld}': {msg}")

    def number(fld, v, positive=True):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or (positive and v <= 0):
            fail(fld, f"must be a{' positive' if positive else ''} number, got {v!r}")
        return float(v)

    for key in d:
        if key not in TOP:
            fail(key, f"unknown key (allowed: {', '.join(sorted(TOP))})")
    for key in ("model", "objective", "duration"):
        if key not in d:
            fail(key, "missing required field")
    if d["objective"] not in OBJECTIVES:
        fail("objective", f"must be one of {', '.join(OBJECTIVES)}, got {d['objective']!r}")
    def table(name, allowed):
        t = d.get(name, {})
        if not isinstance(t, dict):
            fail(name, "expected a table")
        for key in t:
            if key not in allowed:
                fail(f"{name}.{key}", f"unknown key (allowed: {', '.join(sorted(allowed))})")
        return t

    tr = table("transcription", TRANSCRIPTION)
    p = Problem(path=path, model_path=(path.parent / str(d["model"])).resolve(), objective=d["objective"],
                duration=number("duration", d["duration"]))
    if d["objective"] == "tracking":
        if "trajectory" not in d:
            fail("trajectory", "missing required field (objective tracking)")
        p.trajectory = (path.parent / str(d["trajectory"])).resolve()
    else:
        for key in ("theta_start", "theta_end"):
            v = d.get(key)
            if v is None:
                fail(key, f"missing required field (objective {d['objective']})")
            if not isinstance(v, list) or not v:
                fail(key, f"expected a list of numbers, got {v!r}")
            setattr(p, key, np.array([number(f"{key}[{i}]", x, positive=False) for i, x in enumerate(v)]))
    if "max_duration" in d:
        p.max_duration = number("max_duration", d["max_duration"])
    if "effort_weight" in d:
        p.effort_weight = number("effort_weight", d["effort_weight"], positive=False)
    p.method = tr.get("method", "radau")
    if p.method not in METHODS:
        fail("transcription.method", f"must be one of {', '.join(METHODS)}, got {p.method!r}")
    for key, lo in (("degree", 1), ("intervals", 2)):
        v = tr.get(key, getattr(p, key))
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            fail(f"transcription.{key}", f"must be an integer >= {lo}, got {v!r}")
        setattr(p, key, v)
    p.dynamics = tr.get("dynamics", "explicit")
    if p.dynamics not in ("explicit", "implicit"):
        fail("transcription.dynamics", f"must be explicit or implicit, got {p.dynamics!r}")
    for key, value in table("verification", VERIFICATION).items():
        setattr(p, key, number(f"verification.{key}", value))
    p.hessian = table("solver", SOLVER).get("hessian", "exact")
    if p.hessian not in HESSIANS:
        fail("solver.hessian", f"must be one of {', '.join(HESSIANS)}, got {p.hessian!r}")
    p.compiled = tr.get("compiled", True)
    if not isinstance(p.compiled, bool):
        fail("transcription.compiled", f"must be true or false, got {p.compiled!r}")
    return p


def rest_state(arm: Arm, theta) -> np.ndarray:
    """At rest at theta with the SEAs holding the links statically (no residual oscillation)."""
    z, theta = np.zeros(arm.n), np.asarray(theta, float)
    T = np.array(arm.inverse_dynamics()(theta, theta, z, z, z, z)[1]).ravel()
    return np.concatenate([theta, theta + spring_deflection(arm, T), z, z])


def _check_model_fits(problem: Problem, arm: Arm):
    for key in ("theta_start", "theta_end"):
        v = getattr(problem, key)
        if v is not None and len(v) != arm.n:
            raise ModelFileError(f"{problem.path}: field '{key}': {len(v)} entries for a {arm.n}-joint arm")


class Transcription:
    """The NLP of one problem: variables, bounds, constraints and the interval function."""

    def __init__(self, problem: Problem, arm: Arm):
        self.p, self.arm, n = problem, arm, arm.n
        self.n, N = n, problem.intervals
        if problem.method == "hermite-simpson":
            self.points = 1                                              # the midpoint
        else:
            self.points = problem.degree
            tau = ca.collocation_points(problem.degree, problem.method)
            self.C, self.D, _ = (np.array(m) for m in ca.collocation_coeff(tau))
        n_acc = {"explicit": 0, "implicit": 3 if problem.method == "hermite-simpson" else self.points}[problem.dynamics]
        self.n_acc = n_acc
        self.interval = self._interval_function()
        # decision variables
        self.Xs = ca.MX.sym("Xs", 4 * n, N + 1)
        self.Xc = ca.MX.sym("Xc", 4 * n, self.points * N)
        self.U = ca.MX.sym("U", n, N)
        self.A = ca.MX.sym("A", 2 * n, max(n_acc, 0) * N)
        self.T = ca.MX.sym("T") if problem.objective == "min_time" else None

    def _f(self, x, u):
        q = ca.vertsplit(x, self.n)
        return ca.vertcat(q[2], q[3], *self.arm.forward_dynamics()(*q, u))

    def _residual(self, x, a, u):
        """Implicit dynamics: M ddq + c - Q = 0 (MODEL.md section 3) from the inverse dynamics; the
        rotor rows mu (u - tau_id) are generalized forces like the link rows (N m)."""
        n, q = self.n, ca.vertsplit(x, self.n)
        tau_id, T_id = self.arm.inverse_dynamics()(*q, a[:n], a[n:])
        mu = ca.DM(self.arm.model.column("gear_ratio"))
        return ca.vertcat(T_id - self.arm.sea_torque(*q), mu * (u - tau_id))

    def _interval_function(self) -> ca.Function:
        """(x_start, x_end, Xc, A, u, h) -> defects of one interval (SX, mapped over the grid)."""
        n, m = self.n, self.points
        xs, xe, u, h = ca.SX.sym("xs", 4 * n), ca.SX.sym("xe", 4 * n), ca.SX.sym("u", n), ca.SX.sym("h")
        Xc, A = ca.SX.sym("Xc", 4 * n, m), ca.SX.sym("A", 2 * n, max(self.n_acc, 1))
        implicit = self.p.dynamics == "implicit"
        defects = []

        def f_at(x, j):
            if not implicit:
                return self._f(x, u)
            defects.append(self._residual(x, A[:, j], u))
            return ca.vertcat(x[2 * n:], A[:, j])

        if self.p.method == "hermite-simpson":
            xm = Xc[:, 0]
            fs, fm, fe = f_at(xs, 0), f_at(xm, 1), f_at(xe, 2)
            defects += [xe - xs - h / 6 * (fs + 4 * fm + fe), xm - (xs + xe) / 2 - h / 8 * (fs - fe)]
        else:
            P = [xs] + [Xc[:, j] for j in range(m)]
            for j in range(m):
                defects.append(sum(self.C[r, j] * P[r] for r in range(m + 1)) - h * f_at(P[j + 1], j))
            defects.append(sum(self.D[r, 0] * P[r] for r in range(m + 1)) - xe)
        return ca.Function("interval", [xs, xe, Xc, A, u, h], [ca.vertcat(*defects)],
                           ["xs", "xe", "Xc", "A", "u", "h"], ["defects"])

    def nlp(self, x0, xf, theta_ref=None):
        p, n, N = self.p, self.n, self.p.intervals
        T = self.T if self.T is not None else p.duration
        h = T / N
        A = self.A if self.n_acc else ca.MX.zeros(2 * n, N)
        defects = self.interval.map(N, "serial")(self.Xs[:, :N], self.Xs[:, 1:], self.Xc, A, self.U, h)
        states = ca.horzcat(self.Xs, self.Xc)
        psi = states[n:2 * n, :] - states[:n, :]                          # SEA deflection at every point
        g = [ca.vec(defects), ca.vec(psi), self.Xs[:, 0] - x0]
        lbg = [np.zeros(defects.numel()), None, np.zeros(4 * n)]
        ubg = [np.zeros(defects.numel()), None, np.zeros(4 * n)]
        psi_max = np.array([jt.limits.get("psi", np.inf) for jt in self.arm.model.joints])
        lbg[1] = np.tile(-psi_max, states.shape[1])
        ubg[1] = np.tile(psi_max, states.shape[1])
        if xf is not None:
            g.append(self.Xs[:, N] - xf)
            lbg.append(np.zeros(4 * n)), ubg.append(np.zeros(4 * n))
        effort = h * ca.sumsqr(self.U)
        if p.objective == "min_time":
            f = T + p.effort_weight * effort
        elif p.objective == "min_effort":
            f = effort
        else:
            e = self.Xs[:n, 1:] - theta_ref
            f = h * ca.sumsqr(e) / max(p.effort_weight, 1e-12) + effort
        x = ca.vertcat(ca.vec(self.Xs), ca.vec(self.Xc), ca.vec(self.U), ca.vec(self.A),
                       *( [self.T] if self.T is not None else []))
        return {"x": x, "f": f, "g": ca.vertcat(*g)}, np.concatenate(lbg), np.concatenate(ubg)

    def bounds(self):
        """Simple bounds: theta and dphi limits on every state point, tau limits on every control."""
        n, N, jts = self.n, self.p.intervals, self.arm.model.joints
        lo_x, hi_x = np.full(4 * n, -np.inf), np.full(4 * n, np.inf)
        for j, jt in enumerate(jts):
            if "theta" in jt.limits:
                lo_x[j], hi_x[j] = jt.limits["theta"]
            if "dphi" in jt.limits:
                lo_x[3 * n + j], hi_x[3 * n + j] = -jt.limits["dphi"], jt.limits["dphi"]
        tau_max = np.array([jt.limits.get("tau", np.inf) for jt in jts])
        n_states = (N + 1) + self.points * N
        lb = [np.tile(lo_x, n_states), np.tile(-tau_max, N), np.full(2 * n * self.n_acc * N, -np.inf)]
        ub = [np.tile(hi_x, n_states), np.tile(tau_max, N), np.full(2 * n * self.n_acc * N, np.inf)]
        if self.T is not None:
            lb.append([1e-3]), ub.append([self.p.max_duration])
        return np.concatenate(lb), np.concatenate(ub)

    def guess(self, x0, xf, theta_ref=None, warm=None):
        """Straight line between the rest states (or along the reference), holding torques; or a
        previous solution interpolated onto this grid."""
        n, N, m = self.n, self.p.intervals, self.points
        T = warm["t"][-1] if warm else self.p.duration
        s = np.linspace(0, 1, N + 1)
        sc = (np.repeat(np.arange(N), m) + np.tile(self._fractions(), N)) / N
        if warm:
            tw = np.asarray(warm["t"]) / T
            X = np.vstack([np.asarray(warm[k]) for k in ("theta", "phi", "dtheta", "dphi")])
            interp = lambda s: np.vstack([np.interp(s, tw, row) for row in X])
            U = np.vstack([np.interp(np.arange(N) / N, tw[:-1], row[:-1]) for row in np.asarray(warm["tau"])])
            Xs, Xc = interp(s), interp(sc)
        else:
            xe = xf if xf is not None else x0
            Xs, Xc = np.outer(x0, 1 - s) + np.outer(xe, s), np.outer(x0, 1 - sc) + np.outer(xe, sc)
            if theta_ref is not None:
                Xs[:n, 1:] = theta_ref
                Xs[n:2 * n, 1:] = theta_ref + (x0[n:2 * n] - x0[:n])[:, None]
            z = np.zeros(n)
            U = np.repeat(np.array(self.arm.inverse_dynamics()(Xs[:n, 0], Xs[n:2 * n, 0], z, z, z, z)[0]), N, axis=1)
        parts = [Xs.ravel("F"), Xc.ravel("F"), U.ravel("F"), self._acceleration_guess(Xs, Xc, U)]
        if self.T is not None:
            parts.append([T])
        return np.concatenate(parts)

    def _acceleration_guess(self, Xs, Xc, U):
        """Implicit dynamics: the accelerations of the forward dynamics at the guessed points."""
        if not self.n_acc:
            return np.zeros(0)
        n, N, m = self.n, self.p.intervals, self.points
        if self.p.method == "hermite-simpson":
            pts = np.stack([Xs[:, :N], Xc, Xs[:, 1:]], axis=2)                # (4n, N, 3)
        else:
            pts = Xc.reshape(4 * n, N, m)
        X = pts.reshape(4 * n, -1)
        u = np.repeat(U, pts.shape[2], axis=1)
        fd = self.arm.forward_dynamics().map(X.shape[1])
        acc = np.vstack([np.array(v) for v in fd(X[:n], X[n:2 * n], X[2 * n:3 * n], X[3 * n:], u)])
        return acc.ravel("F")

    def _fractions(self):
        if self.p.method == "hermite-simpson":
            return np.array([0.5])
        return np.array(ca.collocation_points(self.p.degree, self.p.method))

    def unpack(self, w):
        n, N, m = self.n, self.p.intervals, self.points
        i = 0

        def take(rows, cols):
            nonlocal i
            out = np.asarray(w[i:i + rows * cols]).reshape(cols, rows).T
            i += rows * cols
            return out
        Xs, _, U = take(4 * n, N + 1), take(4 * n, m * N), take(n, N)
        take(2 * n, self.n_acc * N)
        T = float(w[i]) if self.T is not None else self.p.duration
        return Xs, U, T


def _compiled_solver(nlp, opts, log):
    """IPOPT on the NLP's functions generated to C, compiled once and cached by source hash."""
    plain = ca.nlpsol("ocp", "ipopt", nlp, opts)
    directory = cache_dir() / "nlp"
    directory.mkdir(parents=True, exist_ok=True)
    # CasADi writes into the working directory and prefixes internal symbols with the file name,
    # so the name must be fixed (or the source, and its hash, change every run); a lock keeps
    # two processes from writing it at once.
    src = directory / f"rscasadi_nlp_{os.getpid()}.c"
    with open(directory / "generate.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        plain.generate_dependencies("rscasadi_nlp.c", {"with_header": False})
        Path("rscasadi_nlp.c").replace(src)
    cc = _compiler()
    key = hashlib.sha256((src.read_text() + " ".join(cc) + ca.__version__).encode()).hexdigest()[:24]
    lib = directory / f"nlp_{key}.so"
    if lib.exists():
        log(f"compiled NLP: cache hit {lib}")
        src.unlink()
    else:
        t0 = time.perf_counter()
        part = lib.with_suffix(f".{os.getpid()}.part")
        run = subprocess.run([*cc, "-O1", "-fPIC", "-shared", str(src), "-o", str(part), "-lm"],
                             capture_output=True, text=True)
        src.unlink()
        if run.returncode != 0:
            raise RuntimeError(f"compiling the NLP failed:\n{run.stderr[-2000:]}")
        part.replace(lib)
        log(f"compiled NLP in {time.perf_counter() - t0:.1f} s: {lib}")
    return ca.nlpsol("ocp", "ipopt", str(lib), opts)


def solve(problem: Problem, warm: dict | None = None, log=print, print_level: int = 5, ipopt: dict | None = None) -> dict:
    """Transcribe, solve with IPOPT (exact Hessians), and return the solution record."""
    arm = load(problem.model_path)
    _check_model_fits(problem, arm)
    theta_ref, xf = None, None
    if problem.objective == "tracking":
        traj = load_trajectory(problem.trajectory)
        t_ref = np.linspace(0, problem.duration, problem.intervals + 1)
        q_ref = traj(t_ref)[0]
        theta_ref, x0 = q_ref[:, 1:], rest_state(arm, q_ref[:, 0])
    else:
        x0, xf = rest_state(arm, problem.theta_start), rest_state(arm, problem.theta_end)
    tr = Transcription(problem, arm)
    nlp, lbg, ubg = tr.nlp(x0, xf, theta_ref)
    lbx, ubx = tr.bounds()
    w0 = tr.guess(x0, xf, theta_ref, warm)
    # the objective is scaled to about 1 at the guess: an effort of 1e-2 otherwise leaves IPOPT
    # crawling with a tiny dual infeasibility (seen: 1000+ iterations instead of 20, implicit form)
    f0 = float(ca.Function("f", [nlp["x"]], [nlp["f"]])(w0))
    scale = float(np.clip(1.0 / max(abs(f0), 1e-12), 1e-2, 1e4))
    opts = {"ipopt.print_level": print_level, "print_time": False, "ipopt.sb": "yes",
            "ipopt.max_iter": 1000, "ipopt.tol": 1e-8, "ipopt.mu_strategy": "adaptive",
            "ipopt.mumps_pivot_order": 0,          # AMD: min-time N = 100 in 1.8 s instead of 4.5 s here
            "ipopt.obj_scaling_factor": scale, "ipopt.hessian_approximation": problem.hessian,
            **{f"ipopt.{k}": v for k, v in (ipopt or {}).items()}}
    t0 = time.perf_counter()
    solver = _compiled_solver(nlp, opts, log) if problem.compiled else ca.nlpsol("ocp", "ipopt", nlp, opts)
    setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = solver(x0=w0, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
    solve_time = time.perf_counter() - t0
    stats = solver.stats()
    Xs, U, T = tr.unpack(np.array(res["x"]).ravel())
    n, N = arm.n, problem.intervals
    t = np.linspace(0, T, N + 1)
    tau = np.hstack([U, U[:, -1:]])                                   # the last sample repeats: held constant
    return {"model": str(problem.model_path), "status": stats["return_status"], "success": bool(stats["success"]),
            "solve_time_s": solve_time, "setup_time_s": setup, "iterations": int(stats["iter_count"]),
            "objective": float(res["f"]), "t": t.tolist(),
            **{k: Xs[i * n:(i + 1) * n].tolist() for i, k in enumerate(("theta", "phi", "dtheta", "dphi"))},
            "tau": tau.tolist(), "tau_interpolation": "constant",
            "target_state": None if xf is None else xf.tolist(),
            "trajectory": None if problem.trajectory is None else str(problem.trajectory),
            "theta_reference": None if theta_ref is None else np.hstack([q_ref[:, :1], theta_ref]).tolist()}


def verify(solution: dict, substeps: int = 20, tol: float = 1e-10) -> dict:
    """Replay the torques on the complete model with CVODES, on a grid `substeps` times finer than
    the collocation grid; report the final-state error and the largest limit violation anywhere."""
    arm = load(solution["model"])
    n, t, tau = arm.n, np.asarray(solution["t"]), np.asarray(solution["tau"])
    x0 = np.concatenate([np.asarray(solution[k])[:, 0] for k in ("theta", "phi", "dtheta", "dphi")])
    sim = simulate_held(arm, x0, t, tau, substeps, tol)
    fine = sim["t"]
    violation = 0.0                                                   # relative to each limit
    for j, jt in enumerate(arm.model.joints):
        lim = jt.limits
        for key in ("psi", "dphi"):
            if key in lim:
                violation = max(violation, float(np.max(np.abs(sim[key][j]) - lim[key])) / lim[key])
        if "theta" in lim:
            lo, hi = lim["theta"]
            violation = max(violation, float(np.max(np.maximum(lo - sim["theta"][j], sim["theta"][j] - hi))) / (hi - lo))
    report = {"max_limit_violation": max(violation, 0.0), "substeps": substeps}
    if solution.get("target_state") is not None:
        err = np.abs(sim["x"][:, -1] - np.asarray(solution["target_state"]))
        report["final_angle_error"] = float(np.max(err[:2 * n]))
        report["final_speed_error"] = float(np.max(err[2 * n:]))
    if solution.get("trajectory"):                                     # between the nodes too
        report["tracking_error"] = float(np.max(np.abs(sim["theta"] - load_trajectory(solution["trajectory"])(fine)[0])))
    report["max_collocation_deviation"] = float(np.max(np.abs(sim["theta"][:, ::substeps] - np.asarray(solution["theta"]))))
    return report


def run(problem_file, out, warm_file=None, log=print, print_level: int = 5) -> dict:
    """`rscasadi ocp`: solve, verify, write DIR/solution.json and the plots; return the record."""
    from ..files import fresh_directory
    problem = load_problem(problem_file)
    warm = json.loads(Path(warm_file).read_text()) if warm_file else None
    log(f"{problem.path}: {problem.objective}, {problem.method}"
        + (f" degree {problem.degree}" if problem.method != "hermite-simpson" else "")
        + f", {problem.intervals} intervals, {problem.dynamics} dynamics, {'compiled' if problem.compiled else 'not compiled'}")
    log("solving with IPOPT" + (" (log quieted)" if print_level == 0 else "") + " ...")
    sol = solve(problem, warm, log=log, print_level=print_level)
    log(f"IPOPT: {sol['status']} after {sol['iterations']} iterations, {sol['solve_time_s']:.2f} s, "
        f"objective {sol['objective']:.6g}")
    report = verify(sol)
    checks = {"final_angle_error": problem.final_angle_tol, "final_speed_error": problem.final_speed_tol,
              "tracking_error": problem.final_angle_tol, "max_limit_violation": problem.limit_tol}
    failed = [f"{k} {report[k]:.2e} > {tol:g}" for k, tol in checks.items() if k in report and report[k] > tol]
    report["passed"] = not failed
    sol["verification"] = report
    solver_ok = sol["success"]
    sol["success"] = bool(solver_ok and not failed)
    log("verification (replay on the complete model, CVODES, 20x finer): "
        + ", ".join(f"{k} {v:.2e}" for k, v in report.items() if isinstance(v, float))
        + ("" if not failed else " -- FAILED: " + "; ".join(failed)))
    with fresh_directory(out, "solution.json") as tmp:
        (tmp / "solution.json").write_text(json.dumps(sol, indent=1) + "\n")
        plot_solution(sol, load(sol["model"]), tmp)
    if not solver_ok:
        hint = (" (the limits cannot all be met: widen them or allow more time)"
                if "Infeasible" in sol["status"] else "")
        log(f"FAILED: solver status {sol['status']}{hint}")
    elif failed:
        log("FAILED: the solver converged, but its torques do not do on the complete model what the "
            "collocation promised; refine the grid (more intervals or a higher degree)")
    return sol


def plot_solution(sol: dict, arm: Arm, out: Path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    t = np.asarray(sol["t"])
    th, ph, dph, tau = (np.asarray(sol[k]) for k in ("theta", "phi", "dphi", "tau"))
    panels = [("theta", th, "link angle theta (rad)", "theta"), ("psi", ph - th, "SEA deflection psi (rad)", "psi"),
              ("tau", tau, "motor torque tau (N m)", "tau"), ("dphi", dph, "slow-side speed dphi (rad/s)", "dphi")]
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for ax, (key, data, label, lim) in zip(axes.ravel(), panels):
        for j, jt in enumerate(arm.model.joints):
            line = ax.step(t, data[j], where="post", label=jt.name)[0] if key == "tau" else ax.plot(t, data[j], label=jt.name)[0]
            bound = jt.limits.get(lim)
            if bound is not None:
                lo, hi = bound if isinstance(bound, tuple) else (-bound, bound)
                for b in (lo, hi):
                    ax.axhline(b, color=line.get_color(), ls=":", lw=1)
        ax.set(ylabel=label)
    for ax in axes[1]:
        ax.set(xlabel="t (s)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"{Path(sol['model']).name}: {sol['status']}, success {sol['success']} (dotted: limits)")
    fig.tight_layout()
    for ext in ("png", "pdf"):
        fig.savefig(out / f"solution.{ext}", dpi=120)
    plt.close(fig)
