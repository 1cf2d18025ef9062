"""Inverse kinematics: the configuration closest to a guess that puts a frame at a pose, within
the joint limits, solved by IPOPT through casadi.nlpsol:

    min |theta - theta_guess|^2   s.t.  p(theta) = p,  skew(R^T R(theta)) = 0,  tr(R^T R(theta)) >= 1,
                                        theta_lo <= theta <= theta_hi

(the trace condition keeps the rotation error below 90 degrees, away from the half-turns whose
skew part also vanishes).  Position only when no R is given.  An arm with fewer joints than
the pose has conditions (3, or 6 with R) reaches such a pose, if at all, at isolated
configurations: there the least squares of the pose error are minimised instead.  The answer is checked on the
model afterwards; a pose that is not reached within the tolerances is reported as a failure,
never returned as a success.
"""
from __future__ import annotations

import casadi as ca
import numpy as np
from rscasadi.interrupt import raise_if_interrupted
from rscasadi.errors import InvalidArgument


def _vee(S):
    return ca.vertcat(S[2, 1], S[0, 2], S[1, 0])


def inverse_kinematics(arm, frame: str, *, position, R=None, theta_guess=None, position_tol: float = 1e-6,
                       angle_tol: float = 1e-6, max_iter: int = 200) -> dict:
    """The configuration closest to `theta_guess` (default: the middle of the limits, else zero)
    that puts `frame`'s origin at `position` (3) and its rotation at `R` (3x3, or None: position
    only), within the joint limits.  Returns {theta, success, status, position_error,
    angle_error, iterations}; success only if the pose is reached within `position_tol` (m) and
    `angle_tol` (rad) and the limits hold."""
    return reach(arm, [(frame, position, R)], theta_guess, position_tol, angle_tol, max_iter)


def reach(arm, targets, theta_guess=None, position_tol: float = 1e-6, angle_tol: float = 1e-6,
          max_iter: int = 200) -> dict:
    """`inverse_kinematics` for several frames at once: targets, a list of (frame, position, R or
    None); every frame at its pose in one configuration (two hands at a handover, a head looking
    on).  position_error and angle_error are the largest over the targets."""
    for frame, p, R in targets:
        if np.size(p) != 3 or (R is not None and np.shape(R) != (3, 3)):
            raise InvalidArgument(f"inverse_kinematics: {frame}: position must be 3 numbers and R 3 x 3 "
                                  f"(got {np.shape(p)} and {np.shape(R) if R is not None else None})")
    n = arm.n
    lo = np.array([jt.limits.get("theta", (-np.inf, np.inf))[0] for jt in arm.model.joints], float)
    hi = np.array([jt.limits.get("theta", (-np.inf, np.inf))[1] for jt in arm.model.joints], float)
    if theta_guess is None:
        theta_guess = np.where(np.isfinite(lo) & np.isfinite(hi), (lo + hi) / 2, 0.0)
    guess = np.clip(np.asarray(theta_guess, float).ravel(), lo, hi)
    theta = ca.SX.sym("theta", n)
    g: list = []
    lbg: list = []
    ubg: list = []
    err: list = []
    for frame, p, R in targets:
        R_f, p_f = arm.frame_placement(frame)(theta)
        p_t = ca.DM(np.asarray(p, float).ravel())
        g, lbg, ubg, err = g + [p_f - p_t], lbg + [0.0] * 3, ubg + [0.0] * 3, err + [p_f - p_t]
        if R is not None:
            R_t = ca.DM(np.asarray(R, float))
            E = R_t.T @ R_f                                          # the rotation error
            g += [_vee(E - E.T) / 2, ca.trace(E)]
            lbg += [0.0] * 3 + [1.0]
            ubg += [0.0] * 3 + [np.inf]     # not 3: met with a zero gradient at the pose, a degenerate row
            err.append(ca.vec(R_f - R_t))
    if len(lbg) - sum(R is not None for *_, R in targets) > n:
        # fewer joints than pose conditions: the pose, where reachable, is isolated; the least
        # squares of its error finds it (and says how far it stays where it is not)
        nlp = {"x": theta, "f": ca.sumsqr(ca.vertcat(*err)) + 1e-12 * ca.sumsqr(theta - guess)}
        g, lbg, ubg = [], [], []
    else:
        nlp = {"x": theta, "f": ca.sumsqr(theta - guess)}
    nlp["g"] = ca.vertcat(*g)
    solver = ca.nlpsol("inverse_kinematics", "ipopt", nlp,
                       {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "ipopt.max_iter": max_iter,
                        "ipopt.tol": 1e-12, "ipopt.constr_viol_tol": 1e-10})
    res = solver(x0=guess, lbx=lo, ubx=hi, lbg=lbg, ubg=ubg)
    stats = solver.stats()
    raise_if_interrupted(stats)
    th = np.array(res["x"]).ravel()
    position_error = angle_error = 0.0
    for frame, p, R in targets:
        R_got, p_got = (np.array(v) for v in arm.frame_placement(frame)(th))
        position_error = max(position_error, float(np.linalg.norm(p_got.ravel() - np.asarray(p, float).ravel())))
        if R is not None:
            c = (np.trace(np.asarray(R, float).T @ R_got) - 1) / 2
            angle_error = max(angle_error, float(np.arccos(np.clip(c, -1.0, 1.0))))
    within = bool(np.all(th >= lo - 1e-9) and np.all(th <= hi + 1e-9))
    reached = position_error <= position_tol and angle_error <= angle_tol
    return {"theta": th, "success": bool(reached and within), "status": stats["return_status"],
            "position_error": position_error, "angle_error": angle_error, "iterations": int(stats["iter_count"])}


def inverse_kinematics_along(arm, frame: str, points, theta_start, position_tol: float = 1e-6) -> dict:
    """Configurations putting `frame`'s origin at each of `points` (k x 3) in turn, each the one
    closest to the one before (from `theta_start`) within the joint limits: a path's
    configurations, continuous where the path is.  One IPOPT solver, its target and guess as
    parameters.  Returns {theta (n x k), success, position_error (the largest), index (the first
    point missed, or None)}."""
    n = arm.n
    lo = np.array([jt.limits.get("theta", (-np.inf, np.inf))[0] for jt in arm.model.joints], float)
    hi = np.array([jt.limits.get("theta", (-np.inf, np.inf))[1] for jt in arm.model.joints], float)
    theta, target, near = ca.SX.sym("theta", n), ca.SX.sym("p", 3), ca.SX.sym("near", n)
    p_f = arm.frame_placement(frame)(theta)[1]
    solver = ca.nlpsol("inverse_kinematics_along", "ipopt",
                       {"x": theta, "p": ca.vertcat(target, near), "f": ca.sumsqr(theta - near), "g": p_f - target},
                       {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "ipopt.max_iter": 100,
                        "ipopt.tol": 1e-12, "ipopt.constr_viol_tol": 1e-10})
    place = arm.frame_placement(frame)
    th = np.clip(np.asarray(theta_start, float).ravel(), lo, hi)
    out: list[np.ndarray] = []
    worst = 0.0
    for i, p in enumerate(np.asarray(points, float).reshape(-1, 3)):
        res = solver(x0=th, p=np.r_[p, th], lbx=lo, ubx=hi, lbg=0.0, ubg=0.0)
        raise_if_interrupted(solver.stats())
        th = np.array(res["x"]).ravel()
        err = float(np.linalg.norm(np.array(place(th)[1]).ravel() - p))
        worst = max(worst, err)
        if err > position_tol:
            return {"theta": np.array(out).T, "success": False, "position_error": err, "index": i}
        out.append(th)
    return {"theta": np.array(out).T, "success": True, "position_error": worst, "index": None}
