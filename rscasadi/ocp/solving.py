"""Solve an optimal-control problem, verify it on the complete model, refine the mesh where the
verification fails, and write the result (`rscasadi ocp`).

One round: transcribe (transcription.py) on the current mesh, solve with fatrop or IPOPT
(solvers.py), replay the held torques on the complete model with CVODES (verify).  If the
replay misses a tolerance, the intervals whose local error (each interval integrated from its
own start node) or limit violation is largest are halved, the previous solution is
interpolated onto the new mesh as the initial guess, and the problem is solved again, until
the verification passes or `[refinement] rounds` is spent.  solution.json records each round.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from rscasadi.native.build import compiler
from rscasadi.native.parallel import available_cores, openmp_flags, set_threads
from rscasadi.dynamics.arm import Arm
from rscasadi.model.collision import with_collision
from rscasadi.task.objects import holding_payload
from rscasadi.model.modelfile import ModelFileError, document, read, to_toml
from rscasadi.model.parameters import family, value, with_values
from rscasadi.dynamics.statics import holding_torque, rest_state  # noqa: F401  (rest_state: exported by rscasadi.ocp)
from rscasadi.sim.simulation import held_interval, held_ode
from rscasadi.sim.trajectory import load_trajectory
from rscasadi.ocp.problem import Goal, Problem, check_against_model, load_problem
from rscasadi.ocp.solvers import direct, make_solver
from rscasadi.ocp.solution import Solution, solution_arm, verify
from rscasadi.ocp.transcription import Transcription
from rscasadi.interrupt import raise_if_interrupted


# a refinement round's barrier: fatrop at 1e-5 took 52, 45 and 54 iterations where 1e-6 took 115
# (the Panda's shelf task), 82 (reach_around) and 85 (tool_circle)
WARM: dict[str, dict] = {"ipopt": {"mu_strategy": "monotone", "mu_init": 1e-6, "bound_push": 1e-8, "bound_frac": 1e-8},
                         "fatrop": {"mu_init": 1e-5}}


def _reference(problem: Problem, t):
    return load_trajectory(problem.task.trajectory)(t)[0]


def guess(tr: Transcription, problem: Problem, arm: Arm, t, warm: dict | None):
    """Straight line between the rest states (or along the reference), holding the start's
    torque; or a previous solution interpolated onto this mesh (states at every point, the
    torque of the old interval that holds each new interval's midpoint).  Accelerations at the
    collocation points: the forward dynamics there."""
    n, nq, N, m = tr.n, tr.nq, tr.N, tr.m
    T = t[-1]
    tc = (t[:-1, None] + np.diff(t)[:, None] * tr.fractions[None, :]).ravel()       # interval-major
    design = np.array([np.clip(v, *problem.task.design[k]) for k, v in _design_start(problem, arm).items()])
    arc = None
    if warm:
        tw = np.asarray(warm["t"]) * T / warm["t"][-1]
        if tr.ns:
            arc = np.interp(t, tw, warm["path_arc"])
        Xw = np.vstack([np.asarray(warm[k]) for k in ("theta", "phi", "dtheta", "dphi")])
        interp = lambda s: np.vstack([np.interp(s, tw, row) for row in Xw])
        mid = (t[:-1] + t[1:]) / 2
        k = np.clip(np.searchsorted(tw, mid, side="right") - 1, 0, len(tw) - 2)
        Xs, Xc, U = interp(t), interp(tc), np.asarray(warm["tau"])[:, k]
        if warm.get("design"):
            design = np.array([warm["design"].get(name, v) for name, v in zip(problem.task.design, design)])
    elif tr.tool_path is not None:
        Xs, Xc, U, arc = _along_path(tr, problem, arm, t, tc)
    elif problem.task.obstacles and problem.task.theta_end is not None and not tr.tracking:
        Xs, Xc, U = _around_obstacles(problem, arm, t, tc)
    else:
        x0 = rest_state(arm, problem.task.theta_start if problem.task.theta_start is not None else _reference(problem, t[:1])[:, 0])
        xe = rest_state(arm, problem.task.theta_end) if problem.task.theta_end is not None else x0
        s, sc = t / T, tc / T
        Xs, Xc = np.outer(x0, 1 - s) + np.outer(xe, s), np.outer(x0, 1 - sc) + np.outer(xe, sc)
        if tr.tracking:
            ref, refc = _reference(problem, t), _reference(problem, tc)
            motors = arm.model.motors
            for X, r in ((Xs, ref), (Xc, refc)):
                X[:n], X[n:nq] = r, r[motors] + (x0[n:nq] - x0[motors])[:, None]
        z, zm = np.zeros(n), np.zeros(arm.m)
        U = np.repeat(np.array(arm.inverse_dynamics()(Xs[:n, 0], Xs[n:nq, 0], z, zm, z, zm)[0]), N, axis=1)
    u = np.repeat(U, m, axis=1)
    fd = arm.forward_dynamics().map(N * m)
    acc = np.vstack([np.array(a) for a in fd(*np.split(Xc, [n, nq, nq + n]), u)])
    return tr.pack(Xs, U, T, design, acc.reshape(nq, N, m).transpose(0, 2, 1), arc, t)


def _along_path(tr: Transcription, problem: Problem, arm: Arm, t, tc):
    """The guess along a path: the frame on it at every node and collocation point with the
    path's timing law over the guess's duration (inverse kinematics, each configuration the
    closest to the one before), moving through those angles (_moving_through).  Returns Xs,
    Xc, U and the arc lengths at the nodes."""
    from rscasadi.dynamics.inverse_kinematics import inverse_kinematics_along
    path, T = tr.tool_path, t[-1]
    law = dataclasses.replace(path, speed=path.length / T)              # the fixed timing over T
    times = np.union1d(t, tc)
    ik = inverse_kinematics_along(arm, path.frame, law(times), problem.task.theta_start, position_tol=path.tolerance / 4)
    if not ik["success"]:
        raise ModelFileError(f"{problem.path}: field 'path': frame {path.frame!r} cannot reach the path's point "
                             f"{np.round(law(times[ik['index']:ik['index'] + 1])[0], 4).tolist()} (at "
                             f"{ik['index'] / (len(times) - 1):.0%} of it) within the joint limits")
    return (*_moving_through(arm, ik["theta"], times, t, tc), law.arc_length(t))


def _around_obstacles(problem: Problem, arm: Arm, t, tc):
    """The guess along a path around the obstacles (collision.clear_path) over the guess's
    duration, timed by the minimum-jerk law s = 10 r^3 - 15 r^4 + 6 r^5 (r = t / T): at rest at
    both ends, as the start and end rows ask, and smooth between (_moving_through).  At a
    constant speed the guess leaves and reaches the rest poses at full speed (fatrop's
    iterations, Baxter's obstacle task from guesses of 0.8-2 s: 48-53 against 52-94; the
    Panda's shelf 59-64 against 61-74).  Returns Xs, Xc, U."""
    from rscasadi.dynamics.collision import clear_path
    path = clear_path(arm.model, problem.task.obstacles, problem.task.theta_start, problem.task.theta_end)["theta"]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=1), axis=0))])
    arc = arc / arc[-1] if arc[-1] > 0 else np.linspace(0.0, 1.0, len(arc))
    times = np.union1d(t, tc)
    r = times / t[-1]
    s = r ** 3 * (10 - 15 * r + 6 * r ** 2)
    return _moving_through(arm, np.array([np.interp(s, arc, row) for row in path]), times, t, tc)


def _moving_through(arm: Arm, theta, times, t, tc):
    """A guess through link angles theta at `times` (the nodes t and collocation points tc): the
    SEAs in their static deflection, the speeds of that motion and the torques holding each
    node still.  Returns Xs, Xc, U."""
    n, nq, z, zm = arm.n, arm.nq, np.zeros(arm.n), np.zeros(arm.m)
    dtheta = np.gradient(theta, times, axis=1)
    X = np.array([rest_state(arm, th) for th in theta.T]).T
    X[nq:nq + n], X[nq + n:] = dtheta, dtheta[arm.model.motors]
    at = lambda tt: X[:, np.searchsorted(times, tt)]
    Xs, Xc = at(t), at(tc)
    U = np.array(arm.inverse_dynamics().map(len(t) - 1)(Xs[:n, :-1], Xs[n:nq, :-1], z, zm, z, zm)[0])
    return Xs, Xc, U


def _design_start(problem: Problem, arm: Arm) -> dict:
    return {k: value(arm.model, k) for k in problem.task.design}


def solve_once(problem: Problem, w=None, warm: dict | None = None, log=print, print_level: int = 5,
               options: dict | None = None) -> Solution:
    """One solve on the mesh w (interval fractions; uniform over problem.transcription.intervals by default)."""
    base = read(problem.task.model)
    check_against_model(problem, base)
    base = holding_payload(base, problem.task.payload, problem.path)   # the task's payload on the model's arm
    if problem.task.collision is not None:                        # and the task's collision geometry
        base = with_collision(base, problem.task.collision, problem.path)
    if problem.transcription.parametric == "family":              # the family's numbers as NLP parameters
        free, _ = family(base)
        values = dict(zip(*Arm(base).parameters()))
        problem = problem.replace(parameters={**{k: float(values[k]) for k in free if k not in problem.task.design},
                                              **problem.task.parameters})
    arm = Arm(with_values(base, problem.task.parameters))              # the plant for guesses and replay
    w = np.full(problem.transcription.intervals, 1.0 / problem.transcription.intervals) if w is None else np.asarray(w, float)
    path = problem.task.path
    if path is not None:                                            # the start must be on the path
        on = np.array(arm.frame_placement(path.frame)(problem.task.theta_start)[1]).ravel()
        try:
            path = path.anchored(on)                                # a circle starts where the frame is
        except ValueError as exc:
            raise ModelFileError(f"{problem.path}: field 'path.circle': {exc}") from None
        problem = problem.replace(tool_path=path)
        if np.linalg.norm(on - path.first) > path.tolerance:
            raise ModelFileError(f"{problem.path}: field 'path.points[0]': theta_start puts {path.frame!r} at "
                                 f"{np.round(on, 4).tolist()}, {np.linalg.norm(on - path.first):.3g} m from it")
    if not problem.task.design:             # (a design may change the gears and springs that hold it)
        for key in ("theta_start", "theta_end"):
            theta = getattr(problem.task, key)
            why = None if theta is None else unheld(arm, theta)
            if why:
                raise ModelFileError(f"{problem.path}: field '{key}': the arm cannot rest there: {why}")
    tr = Transcription(problem, Arm(base), N=len(w))
    goals = problem.task.goals if path is None else (Goal(path.frame, path.end, position_tol=path.tolerance),)
    goal = goals or None
    if goals and problem.task.theta_end is None:                   # the guess's end: inverse kinematics
        problem = problem.replace(theta_end=goal_configuration(arm, goals, problem.task.theta_start, problem.path))
        why = None if problem.task.design or warm else unheld(arm, problem.task.theta_end)
        if why:                                  # the solver may find another configuration at the goal (said once)
            log(f"note: the arm cannot rest at the goal in the first configuration found for it: {why}")
    t_guess = (warm["t"][-1] if warm else problem.task.duration) * np.concatenate([[0.0], np.cumsum(w)])
    ref = _reference(problem, t_guess)[:, 1:] if tr.tracking else None
    theta_start = _reference(problem, t_guess[:1])[:, 0] if tr.tracking else problem.task.theta_start
    P = tr.parameters(theta_start, None if goal is not None else problem.task.theta_end, problem.task.duration, problem.task.effort_weight, w, ref,
                      list(problem.task.parameters.values()))
    # the loops are parallel only in a library compiled with OpenMP (solvers.compiled_nlp); set
    # before the solver is built (the direct fatrop sizes its per-thread memory then)
    threads = set_threads(problem.solver.threads or available_cores()) if problem.transcription.compiled and openmp_flags(tuple(compiler())) else 1
    t0 = time.perf_counter()                       # setup: the NLP, its kernel and library (cached)
    nlp, lbg, ubg = tr.nlp(log)
    lbx, ubx = tr.bounds(problem.task.max_duration)
    w0 = guess(tr, problem, arm, t_guess, warm)
    solver, objective = make_solver(problem, tr, nlp, log, print_level, options)
    if hasattr(solver, "prepare"):                 # the direct fatrop's solver, built for these bounds
        solver.prepare(lbx, ubx, lbg, ubg)
    held_ode(arm, log)                             # the replay's dynamics: compiled (if at all) now, in the log
    setup = time.perf_counter() - t0
    # the objective is scaled to about 1 at the guess: an effort of 1e-2 otherwise leaves the
    # solver crawling with a tiny dual infeasibility (seen: 1000+ iterations instead of 20)
    f0 = float(objective(w0, P))
    scaled = P.copy()
    scaled[tr.parameter_layout()[0]["scale"]] = np.clip(1.0 / max(abs(f0), 1e-12), 1e-2, 1e4)
    if tr.kernel is not None:
        # no state from earlier solves, nor from f0 (in this thread only): the solve starts
        # alike on any number of threads
        tr.kernel.reset()
    t0 = time.perf_counter()
    res = solver(x0=w0, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg, p=scaled)
    solve_time = time.perf_counter() - t0
    stats = solver.stats()
    raise_if_interrupted(stats)
    out = tr.unpack(np.array(res["x"]))
    n, T = arm.n, out["T"] if out["T"] is not None else problem.task.duration
    t = T * np.concatenate([[0.0], np.cumsum(w)])
    Xs, U = out["Xs"], out["U"]
    design = dict(zip(problem.task.design, out["design"].tolist()))
    target = None
    if not tr.tracking:                            # at rest at theta_end, or where the solver ended (a goal)
        theta_end = problem.task.theta_end if goal is None else Xs[:n, -1]
        target = rest_state(Arm(with_values(base, {**problem.task.parameters, **design})), theta_end).tolist()
    solved = _success(stats)
    return Solution({"model": str(problem.task.model), "solver": problem.solver.name,
            "interface": ("direct" if direct(problem) else "casadi") if problem.solver.name == "fatrop" else None,
            "blasfeo": stats.get("blasfeo"),          # fatrop's linear algebra library (direct interface)
            # where fatrop's time went (s): its evaluations of the NLP's functions and its own algebra
            "solver_times": {k: v for k, v in stats.get("fatrop", {}).items() if k.endswith("_time")} or None,
            "threads": stats.get("threads", threads), "status": _status(stats),   # the direct fatrop's: what ran
            "success": solved, "solver_success": solved, "solve_time_s": solve_time, "setup_time_s": setup,
            "iterations": int(stats["iter_count"]), "objective": float(objective(res["x"], P)),
            "intervals": len(w), "mesh": (np.asarray(w) / np.sum(w)).tolist(), "t": t.tolist(),
            **{k: part.tolist() for k, part in zip(("theta", "phi", "dtheta", "dphi"),
                                                   np.split(Xs, [n, arm.nq, arm.nq + n]))},
            "tau": np.hstack([U, U[:, -1:]]).tolist(), "tau_interpolation": "constant",
            "design": design, "parameters": dict(problem.task.parameters), "target_state": target,
            "trajectory": None if problem.task.trajectory is None else str(problem.task.trajectory),
            "theta_reference": None if ref is None else _reference(problem, t).tolist(),
            "payload": problem.task.payload, "collision": problem.task.collision,
            "path": None if path is None else path.to_dict(),
            "path_arc": None if out["arc"] is None else out["arc"].tolist(),
            "obstacles": [o.to_dict() for o in problem.task.obstacles],
            "goal": None if not goals else goals[0].to_dict() if len(goals) == 1 else [g.to_dict() for g in goals]})


# fatrop 1.1.8's return flags (IpSolverReturnFlag, include/fatrop/ip_algorithm/ip_algorithm.hpp in
# the CasADi wheel) in IPOPT's words where they mean the same
FATROP_STATUS = {0: "Solve_Succeeded", 1: "Maximum_Iterations_Exceeded", 2: "Solved_To_Acceptable_Level",
                 3: "Infeasible_Problem_Detected", 4: "Line_Search_Failed", 5: "Error_In_Step_Computation",
                 6: "Unknown"}


def _status(stats: dict) -> str:
    """IPOPT's return status, or fatrop's (named as IPOPT's where they mean the same)."""
    if "fatrop" not in stats:
        return stats["return_status"]
    flag = stats["fatrop"]["return_flag"]
    failed = ", an NLP evaluation failed" if stats.get("evaluation_failed") else ""
    if flag == 0 and stats["success"]:
        return "Solve_Succeeded"
    return f"{FATROP_STATUS.get(flag, 'Unknown')} (fatrop return flag {flag}{failed})"


def _success(stats: dict) -> bool:
    """The solver's success: fatrop's acceptable point counts as IPOPT's does (CasADi calls IPOPT's
    Solved_To_Acceptable_Level a success, fatrop's through its plugin not); the replay decides."""
    return bool(stats["success"]) or ("fatrop" in stats and stats["fatrop"]["return_flag"] == 2)


def unheld(arm: Arm, theta) -> str | None:
    """Why the arm cannot rest at theta (a motor torque or a spring deflection beyond its limit,
    the task's payload included), or None if it can."""
    x = rest_state(arm, theta)
    n, model = arm.n, arm.model
    tau = np.array(holding_torque(arm)(x[:n], x[n:arm.nq])).ravel()
    for j, jt in enumerate(model.joints):
        tau_max, psi_max = jt.limits.get("tau", np.inf), jt.limits.get("psi", np.inf)
        held = abs(tau[model.input_of[j]]) if j in model.input_of else 0.0
        psi = x[n + model.motor_of[j]] - x[j] if j in model.motor_of else 0.0
        if held > tau_max * (1 + 1e-9):
            return f"joint {jt.name!r} needs {held:.3g} N m at its motor to hold it (limit {tau_max:g})"
        if abs(psi) > psi_max * (1 + 1e-9):
            return f"joint {jt.name!r}'s spring deflects {abs(psi):.3g} rad to hold it (limit {psi_max:g})"
    return None


def goal_configuration(arm: Arm, goals, theta_guess, where) -> np.ndarray:
    """A configuration at the goals (each frame at its pose, all at once) within the joint limits
    (inverse kinematics from the start), for the initial guess; the solver then chooses its own.
    Unreachable: an error naming the frames."""
    from rscasadi.dynamics.inverse_kinematics import reach
    res = reach(arm, [(g.frame, g.position, g.R) for g in goals], theta_guess=theta_guess)
    where = where if where is not None else "<Problem>"
    if not res["success"]:
        frames = ", ".join(repr(g.frame) for g in goals)
        raise ModelFileError(f"{where}: field 'goal': {'frame' if len(goals) == 1 else 'frames'} {frames} cannot reach "
                             f"it within the joint limits (inverse kinematics: {res['status']}, "
                             f"{res['position_error']:.3g} m, {res['angle_error']:.3g} rad away)")
    return res["theta"]


def failures(problem: Problem, report: dict) -> dict:
    """The verification's failures: {check: readable string} (empty: passed)."""
    tols = {"final_angle_error": problem.verification.final_angle_tol, "final_speed_error": problem.verification.final_speed_tol,
            "tracking_error": problem.verification.tracking_tol, "max_limit_violation": problem.verification.limit_tol}
    if problem.task.goals:
        tols.update(goal_position_error=min(g.position_tol for g in problem.task.goals),
                    goal_angle_error=min(g.angle_tol for g in problem.task.goals))
    if problem.task.path is not None:
        tols.update(path_error=problem.task.path.tolerance)
    tols.update({f"term.{t.name}": t.tolerance for t in problem.task.terms if t.constraint})
    failed = {k: f"{k} {report[k]:.2e} > {tol:g}" for k, tol in tols.items() if k in report and report[k] > tol}
    for key in ("min_clearance", "urdf_min_clearance"):
        if report.get(key, np.inf) < -problem.verification.clearance_tol:
            failed[key] = f"{key} {report[key]:.2e} m < -{problem.verification.clearance_tol:g}"
    return failed


def checks(problem: Problem, report: dict) -> list:
    """The verification's failures, as readable strings (empty: passed)."""
    return list(failures(problem, report).values())


def local_errors(problem: Problem, solution: dict) -> np.ndarray:
    """Each interval integrated on the complete model from its own start node, compared with
    its end node; normalised by the tolerances (angles, speeds)."""
    arm = solution_arm(solution)
    n, t = arm.n, np.asarray(solution["t"])
    X = np.vstack([np.asarray(solution[k]) for k in ("theta", "phi", "dtheta", "dphi")])
    N = len(t) - 1
    # the intervals are independent: on every core (the same numbers as one after another)
    each = held_interval(arm).map(N, "thread", available_cores())
    ends = np.array(each(X[:, :N], np.vstack([np.asarray(solution["tau"])[:, :N], np.diff(t)])))
    err = np.abs(ends - X[:, 1:])
    angle_tol = problem.verification.tracking_tol if solution.get("trajectory") else problem.verification.final_angle_tol
    q = arm.nq
    return np.maximum(err[:q].max(axis=0) / angle_tol, err[q:].max(axis=0) / problem.verification.final_speed_tol)


# failures the replay places in intervals (a limit, an obstacle's margin, the path), by the
# report's per-interval list; any other (an end state, the goal, a task term) is the mesh's accuracy
LOCATED = {"max_limit_violation": "interval_violation", "min_clearance": "interval_clearance",
           "urdf_min_clearance": "interval_urdf_clearance",
           "term.clearance": "interval_clearance", "path_error": "interval_path_error"}


def refined_mesh(problem: Problem, solution: dict, report: dict, failed=None) -> np.ndarray:
    """Halve the intervals where the replay fails a located check (a limit, an obstacle's
    margin, the path between nodes) and their neighbours; and, if another check failed (the end
    state, the goal, a task term; or none did), those that carry most of the local error (the
    largest, until the others sum to at most a quarter of the tolerance).  `failed`: the checks
    that failed (by default from the report).  Refining for accuracy when only a limit
    failed spends intervals where nothing failed (Baxter's obstacle task: 109 intervals and 45
    iterations where the local-error rule took 168 and 52, for a T 0.03 % longer)."""
    w = np.asarray(solution["mesh"])
    failed = set(failures(problem, report) if failed is None else failed)
    located = np.zeros(len(w), bool)
    located |= np.asarray(report["interval_violation"]) > problem.verification.limit_tol
    for key in ("interval_clearance", "interval_urdf_clearance"):
        if key in report:
            located |= np.asarray(report[key]) < -problem.verification.clearance_tol
    if "interval_path_error" in report:
        located |= np.asarray(report["interval_path_error"]) > problem.task.path.tolerance
    split = located.copy()
    split[1:] |= located[:-1]
    split[:-1] |= located[1:]
    if not failed or failed - set(LOCATED) or not located.any():
        e = local_errors(problem, solution)
        order = np.argsort(e)[::-1]
        rest = np.cumsum(e[order][::-1])[::-1]                 # rest[i] = sum of e[order[i:]]
        count = int(np.searchsorted(-rest, -0.25))              # first i with rest[i] <= 0.25
        split[order[:max(count, 1)]] = True
    return np.concatenate([[wk / 2, wk / 2] if s else [wk] for wk, s in zip(w, split)])


def solve(problem: Problem, warm: dict | None = None, log=print, print_level: int = 5,
          options: dict | None = None, mesh=None) -> Solution:
    """Solve, verify, and refine the mesh until the verification passes (or the rounds run out).
    A co-design problem first solves the nominal arm (design at the model file's values) and
    starts from that solution: the design can then only improve on it (a local solver from a
    straight-line guess found a worse local minimum here).  `mesh`: the first round's interval
    widths (fractions summing to 1; a refined mesh of an earlier solve), with `warm` its solution:
    the first round then starts with the small barrier of a refinement round."""
    nominal = None
    if problem.task.design and warm is None:
        log("co-design: first the nominal arm, as the starting point")
        nominal = solve(problem.replace(design={}), None, log, print_level, options)
        warm = nominal if nominal["solver_success"] else None
    # on the nominal's refined mesh: a coarse mesh lets the design exploit the discretisation
    # (seen: a stiffer design 'faster' on 100 intervals whose replay broke a limit)
    w, rounds = (np.asarray(nominal["mesh"]) if nominal is not None and warm else mesh), []
    fallback = None
    for r in range(problem.verification.rounds + 1):
        # a refinement round starts next to the answer: a small barrier keeps the solver there
        # (seen: a co-design round wandered from T = 0.2472 s to another local minimum, 0.2506 s)
        near = r or mesh is not None                   # a refinement round, or a kept solution's mesh
        extra = {**(WARM.get(problem.solver.name, {}) if near else {}), **(options or {})}
        sol = dict(solve_once(problem, w, warm, log, print_level, extra))
        if not sol["success"] and problem.solver.name == "fatrop":
            # fatrop fails on some problems where IPOPT does not (maximum iterations, a failed
            # line search): the same start with IPOPT
            log(f"fatrop: {sol['status']}; solving again with IPOPT from the same start")
            problem = problem.replace(solver="ipopt")
            fallback = {"solver": "fatrop", "round": r, "status": sol["status"], "iterations": sol["iterations"]}
            options = None                                     # fatrop's own options mean nothing to IPOPT
            sol = dict(solve_once(problem, w, warm, log, print_level, WARM["ipopt"] if near else None))
        if fallback:
            sol["fallback_from"] = fallback                    # kept through the later rounds (IPOPT's)
        report = verify(sol, terms=problem.task.terms)
        misses = failures(problem, report)
        failed = list(misses)
        rounds.append({"round": r, "intervals": sol["intervals"], "solver": sol["solver"], "status": sol["status"],
                       "iterations": sol["iterations"], "solve_time_s": sol["solve_time_s"],
                       "setup_time_s": sol["setup_time_s"], "objective": sol["objective"],
                       **{k: v for k, v in report.items() if isinstance(v, float)}, "passed": not failed})
        log(f"round {r}: {sol['intervals']} intervals, {sol['solver']} {sol['status']} after {sol['iterations']} "
            f"iterations, {sol['solve_time_s']:.2f} s; replay: "
            + ", ".join(f"{k} {v:.1e}" for k, v in report.items() if isinstance(v, float))
            + ("" if not failed else " -- misses " + "; ".join(misses.values())))
        if not failed or not sol["success"] or r == problem.verification.rounds:
            break
        w, warm = refined_mesh(problem, sol, report, failed), sol
        where = "where the replay misses" if set(failed) <= set(LOCATED) else "where the local error is largest or the replay misses"
        log(f"refining: {sol['intervals']} -> {len(w)} intervals {where}")
    report["passed"] = not failed
    report.pop("interval_violation")
    for key in ("interval_clearance", "interval_urdf_clearance", "interval_path_error"):
        report.pop(key, None)
    sol["verification"], sol["rounds"] = report, rounds
    sol["success"] = bool(sol["solver_success"] and not failed)
    if nominal is not None:
        sol["nominal"] = {"objective": nominal["objective"], "duration": nominal["t"][-1],
                          "success": nominal["success"], "design": _design_start(problem, solution_arm(nominal))}
        sol["improved"] = bool(sol["objective"] <= nominal["objective"] * (1 + 1e-9))
        if not sol["improved"]:
            log(f"note: the co-design ended in a local minimum worse than the nominal arm ({sol['objective']:.6g} "
                f"> {nominal['objective']:.6g}); try the other solver or other design bounds")
    return Solution(sol)


REUSED = ("t", "theta", "phi", "dtheta", "dphi", "tau", "mesh", "design", "path_arc")
KEPT_SOLUTIONS = 32           # verified solutions kept in the cache (the oldest go first)


def problem_key(problem: Problem) -> str | None:
    """A digest of everything that decides `problem`'s solution: its parts as written (arrays in
    full) and the contents of the model it loads (URDF included) and of its trajectory file; None
    for a problem with Python terms (objects without a stable written form)."""
    import hashlib
    import pickle
    import sys
    if problem.task.terms:
        return None
    with np.printoptions(threshold=sys.maxsize, precision=17):
        text = repr((problem.task, problem.transcription, problem.solver, problem.verification))
    digest = hashlib.sha256(text.encode())
    digest.update(pickle.dumps(read(problem.task.model)))
    if problem.task.trajectory is not None:
        digest.update(Path(problem.task.trajectory).read_bytes())
    return digest.hexdigest()


def _solutions_dir() -> Path:
    from rscasadi.files import cache_dir
    return cache_dir() / "ocp-solutions"


def reused_solution(problem: Problem) -> dict | None:
    """The verified solution of the same problem (problem_key) from the cache, or None."""
    key = problem_key(problem)
    path = _solutions_dir() / f"{key}.json"
    if key is None or not path.is_file():
        return None
    try:
        sol = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return sol if isinstance(sol, dict) and set(REUSED[:7]) <= set(sol) else None


def keep_solution(problem: Problem, sol) -> None:
    """Keep a verified solution for the next run of the same problem (its mesh and its states)."""
    from rscasadi.files import write_json
    key = problem_key(problem)
    if key is None or not sol["success"]:
        return
    folder = _solutions_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        write_json(folder / f"{key}.json", {k: sol[k] for k in REUSED if sol.get(k) is not None})
        for old in sorted(folder.glob("*.json"), key=lambda f: f.stat().st_mtime)[:-KEPT_SOLUTIONS]:
            old.unlink(missing_ok=True)
    except OSError:                        # a read-only cache: the next run starts cold
        pass


def run(problem, out, warm_file=None, log=print, print_level: int = 5, solver: str | None = None,
        reuse: bool = True) -> Solution:
    """`rscasadi ocp`: solve `problem` (a `Problem`, or the path of a problem file), verify,
    refine, write DIR/solution.json and the plots; return the solution.  A verified solution is
    kept in the cache for the next run of the same problem; `reuse`: without a `warm_file`, start
    from the one an earlier run kept (its refined mesh and its states: one round where the first
    run took several)."""
    from rscasadi.files import check_writable, fresh_directory
    from rscasadi.model.modelfile import ModelFileError
    check_writable(out)
    problem = problem.check() if isinstance(problem, Problem) else load_problem(problem)
    if solver:
        problem = problem.replace(solver=solver)
    warm = None
    if warm_file:
        try:
            warm = json.loads(Path(warm_file).read_text())
        except json.JSONDecodeError as exc:
            raise ModelFileError(f"{warm_file}: --warm: not a solution.json ({exc})") from None
        if not isinstance(warm, dict) or not {"t", "theta", "phi", "tau"} <= set(warm):
            raise ModelFileError(f"{warm_file}: --warm: not a solution.json (no t, theta, phi, tau)")
    log(f"{problem.path}: {problem.task.objective}, {problem.transcription.method}"
        + (f" degree {problem.transcription.degree}" if problem.transcription.method != "hermite-simpson" else "")
        + f", {problem.transcription.intervals} intervals, "
        + ("condensed (each interval's collocation solved in C)" if problem.transcription.condense
           else f"lifted, {problem.transcription.dynamics} dynamics, {'compiled' if problem.transcription.compiled else 'not compiled'}")
        + (f", designing {', '.join(problem.task.design)}" if problem.task.design else ""))
    kept = reused_solution(problem) if reuse and warm is None else None
    if kept is not None:
        log(f"starting from the verified solution of the same problem in the cache ({len(kept['mesh'])} "
            "intervals; --cold to start from the problem's own guess)")
    log(f"solving with {problem.solver.name}" + (" (log quieted)" if print_level == 0 else "") + " ...")
    sol = solve(problem, warm or kept, log=log, print_level=print_level,
                mesh=None if kept is None else np.asarray(kept["mesh"]))
    keep_solution(problem, sol)
    if sol["design"]:
        log("optimal design: " + ", ".join(f"{k} = {v:.6g}" for k, v in sol["design"].items()))
    with fresh_directory(out) as tmp:
        if sol["design"]:                  # the arm the torques are for, as a complete model file
            designed = solution_arm(sol).model
            (tmp / "designed_model.toml").write_text(
                f"# {designed.name}: {Path(sol['model']).name} with the optimal design of {Path(problem.path).name}\n"
                + "# (" + ", ".join(f"{k} = {v:.10g}" for k, v in sol["design"].items()) + ")\n"
                + to_toml(document(dataclasses.replace(designed, name=designed.name + "-designed"))))
            sol = sol.replace(designed_model="designed_model.toml")
        sol.to_json(tmp / "solution.json")
        sol.plot(tmp)
    if not sol["solver_success"]:
        hint = (" (the limits cannot all be met: widen them or allow more time)"
                if "nfeasible" in sol["status"] else "")
        log(f"FAILED: solver status {sol['status']}{hint}")
    elif not sol["verification"]["passed"]:
        log("FAILED: the solver converged, but its torques do not do on the complete model what the "
            "collocation promised, after the last refinement round; allow more [refinement] rounds or "
            "start with more intervals")
    return sol
