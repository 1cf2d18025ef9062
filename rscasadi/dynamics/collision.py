"""Clearance between the arm's capsules (the [collision] table's and the payload's sphere,
rscasadi.model.collision.capsules) and obstacles (spheres, axis-aligned boxes), and between the
capsules of the links the [collision] table pairs (two arms of a tree, an arm and the torso).

For the optimiser, smooth and conservative: each capsule is covered by spheres centred along
its segment, spaced s <= max(r, 3 cm) and of radius sqrt(r^2 + (s/2)^2) (the union contains
the capsule);
a sphere's distance to an obstacle sphere is |p - c| - R, to a box the norm of softplus(|p - c|
- h) per axis less its largest excess over max(., 0): never more than the true distance outside
the box and <= 0 inside, so a clearance the optimiser sees as positive is a true one.
Two paired links keep one row: the soft minimum over their capsule pairs, m - log(sum exp(-beta
(d_i - m))) / beta with m = min d_i (never more than the smallest; at most log(K) / beta less,
1.2 mm for ten pairs), of a lower bound of each pair's distance: the shorter segment sampled
every PAIR_SPACING or less, each sample's exact distance to the other segment (its closest point
clamped to the segment, derivatives bounded), the smallest less half the spacing (the distance
changes by at most the step between samples) and both radii.  K small expressions per pair of
links where the covering spheres of two many-shaped links made thousands of rows; the closed form
of two segments' closest points was tried and left: near-parallel segments (two arms side by
side) put its 2 x 2 solve's determinant, squared, under the Hessian.
For the verification, exact up to sampling: the segment sampled every r / 8, each point's
exact distance to the obstacle (or to the paired capsule's segment) less the radii.
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from rscasadi.dynamics.kinematics import body_poses
from rscasadi.interrupt import raise_if_interrupted
from rscasadi.model.collision import capsule_pairs, capsules, margin
from rscasadi.model.limits import limit_arrays

MIN_SPACING = 0.03           # m: the covering spheres' spacing on capsules thinner than that
BETA_PER_M = 2000.0          # softplus sharpness (1/m): it overestimates max(x, 0) by at most 0.35 mm
PAIR_SPACING = 0.01          # m: the samples' spacing on a paired capsule (its bound is 5 mm conservative at most)


def _softplus(x, beta):
    return ca.log1p(ca.exp(-ca.fabs(beta * x))) / beta + ca.fmax(x, 0)


def covering_spheres(capsule) -> tuple[np.ndarray, float]:
    """Centres (k x 3, in the capsule's body frame) and radius of spheres whose union holds it,
    spaced at most max(r, MIN_SPACING) apart: a thin capsule (a finger's box) gets a few spheres a
    few millimetres fatter rather than many."""
    a, b, r = np.asarray(capsule.a, float), np.asarray(capsule.b, float), capsule.radius
    length = float(np.linalg.norm(b - a))
    if length == 0.0:                                    # a sphere
        return a[None, :], r
    k = max(2, math.ceil(length / max(r, MIN_SPACING)) + 1)
    s = length / (k - 1)
    return np.linspace(a, b, k), math.sqrt(r ** 2 + (s / 2) ** 2)


def _sphere_distance(p, rho, obstacle):
    """Smooth, conservative distance between a sphere (centre p, radius rho) and an obstacle."""
    c = ca.DM(obstacle.center)
    if obstacle.kind == "sphere":
        return ca.norm_2(p - c) - obstacle.radius - rho
    h, beta = ca.DM(np.asarray(obstacle.size, float) / 2), BETA_PER_M
    q = ca.sqrt((p - c) ** 2 + 1e-12) - h                                 # |p - c| - h, smooth at the faces
    return ca.norm_2(_softplus(q, beta)) - math.sqrt(3) * (math.log(2) / beta + 1e-6) - rho


def _spheres(capsule, poses) -> tuple:
    """The covering spheres' centres in the world at `poses`, and their radius."""
    R, o = poses[capsule.body]
    centres, rho = covering_spheres(capsule)
    return [o + R @ ca.DM(centre) for centre in centres], rho


def clearances(model, obstacles, theta):
    """Every covering sphere's smooth clearance to every obstacle, then one row per pair of links
    of [collision] pairs (the soft minimum of their capsules' `capsule_distance`), less the margin
    (>= 0: clear)."""
    pairs = capsule_pairs(model)
    if not (capsules(model) and obstacles) and not pairs:
        return ca.DM.zeros(0)
    poses = body_poses(model, theta)
    rows = []
    for capsule in capsules(model) if obstacles else ():
        centres, rho = _spheres(capsule, poses)
        rows += [_sphere_distance(p, rho, obstacle) - margin(model) for p in centres for obstacle in obstacles]
    links: dict = {}                                 # the capsule pairs of each pair of links
    for a, b in pairs:
        links.setdefault((a.body, b.body), []).append((a, b))
    for both in links.values():
        gaps = [capsule_distance(a, b, poses) for a, b in both]
        rows.append(_soft_min(ca.vertcat(*gaps), BETA_PER_M) - margin(model))
    return ca.vertcat(*rows)


def _segment(capsule, poses) -> tuple:
    """The capsule's segment's ends in the world at `poses`."""
    R, o = poses[capsule.body]
    return o + R @ ca.DM(np.asarray(capsule.a, float)), o + R @ ca.DM(np.asarray(capsule.b, float))


def capsule_distance(a, b, poses):
    """A lower bound of the distance between two capsules at `poses` (negative: overlapping),
    within PAIR_SPACING / 2 of it: the shorter one's segment sampled, each sample's exact distance
    to the other's segment (`_to_segment`), less half the samples' spacing and both radii."""
    ends = [_segment(c, poses) for c in (a, b)]
    lengths = [float(np.linalg.norm(np.subtract(c.b, c.a))) for c in (a, b)]
    i = int(lengths[1] < lengths[0])                          # sample the shorter
    (p, q), other = ends[i], ends[1 - i]
    k = max(2, math.ceil(lengths[i] / PAIR_SPACING) + 1)
    gaps = [_to_segment(p + (q - p) * (j / (k - 1)), *other) for j in range(k)]
    return _soft_min(ca.vertcat(*gaps), BETA_PER_M) - lengths[i] / (k - 1) / 2 - a.radius - b.radius


def _to_segment(point, a, b):
    """The distance of a point to the segment a-b, its closest point's parameter clamped."""
    d = b - a
    t = ca.fmin(ca.fmax(ca.dot(point - a, d) / ca.fmax(ca.dot(d, d), 1e-12), 0), 1)
    gap = point - a - t * d
    return ca.sqrt(ca.dot(gap, gap) + 1e-18)


def _soft_min(d, beta):
    """m - log(sum exp(-beta (d - m))) / beta, m = min d: <= min d, smooth (m cancels)."""
    if d.numel() == 1:
        return d
    m = ca.mmin(d)
    return m - ca.log(ca.sum1(ca.exp(-beta * (d - m)))) / beta


def _exact_distance(point, obstacle):
    """Exact signed distance of a point to an obstacle (fmax and fmin: for evaluation, not for
    the optimiser)."""
    c = ca.DM(obstacle.center)
    if obstacle.kind == "sphere":
        return ca.norm_2(point - c) - obstacle.radius
    q = ca.fabs(point - c) - ca.DM(np.asarray(obstacle.size, float) / 2)
    return ca.norm_2(ca.fmax(q, 0)) + ca.fmin(ca.mmax(q), 0)


_BUILT: dict = {}          # (kind, the geometry's key) -> its clearance Function (refinement rounds reuse it)
_KEPT = 16


def _geometry_key(model, obstacles) -> tuple:
    """What the clearance Functions depend on: the tree's joint frames, the capsules and their
    pairs, the margin and the obstacles."""
    return (tuple((tuple(np.ravel(jt.origin_xyz)), tuple(np.ravel(jt.R))) for jt in model.joints), model.parent,
            tuple((c.body, tuple(np.ravel(c.a)), tuple(np.ravel(c.b)), float(c.radius)) for c in capsules(model)),
            model.collision.pairs if model.collision is not None else (),
            margin(model), tuple((o.kind, tuple(np.ravel(o.center)), float(o.radius),
                                  None if o.size is None else tuple(np.ravel(o.size))) for o in obstacles))


def _once(kind: str, model, obstacles, build) -> ca.Function:
    key = (kind, _geometry_key(model, obstacles))
    if key not in _BUILT:
        while len(_BUILT) >= _KEPT:
            _BUILT.pop(next(iter(_BUILT)))
        _BUILT[key] = build()
    return _BUILT[key]


def clearance_function(model, obstacles) -> ca.Function:
    """theta -> clearances(model, obstacles, theta) as the Function `clearance`, built once per
    geometry (the task's transcription, its first guess and every refinement round share it)."""
    def build():
        theta = ca.SX.sym("theta", model.n)
        return ca.Function("clearance", [theta], [clearances(model, obstacles, theta)])
    return _once("smooth", model, obstacles, build)


def exact_clearance(model, obstacles) -> ca.Function:
    """theta -> the smallest distance between the capsules and the obstacles, less the margin
    (each segment sampled every r / 8): what the verification checks at every replay sample.
    Built once per geometry (the Panda's: 0.1 s)."""
    return _once("exact", model, obstacles, lambda: _exact_clearance(model, obstacles))


def _samples(capsule, poses) -> list:
    """Points along the capsule's segment every r / 8, in the world at `poses`."""
    R, o = poses[capsule.body]
    k = max(2, math.ceil(8 * np.linalg.norm(np.asarray(capsule.b) - capsule.a) / capsule.radius) + 1)
    return [o + R @ ca.DM(point) for point in np.linspace(capsule.a, capsule.b, k)]


def _segment_distance(point, a, b):
    """Exact distance of a point to the segment from a to b (fmin and fmax: for evaluation)."""
    d = b - a
    t = ca.fmin(ca.fmax(ca.dot(point - a, d) / ca.fmax(ca.dot(d, d), 1e-300), 0), 1)
    return ca.norm_2(point - a - t * d)


def _exact_clearance(model, obstacles) -> ca.Function:
    theta = ca.SX.sym("theta", model.n)
    pairs = capsule_pairs(model)
    if not (capsules(model) and obstacles) and not pairs:
        return ca.Function("exact_clearance", [theta], [ca.SX(np.inf)])
    poses = body_poses(model, theta)
    gaps = []
    for capsule in capsules(model) if obstacles else ():
        gaps += [_exact_distance(point, obstacle) - capsule.radius
                 for point in _samples(capsule, poses) for obstacle in obstacles]
    for a, b in pairs:                              # a's segment sampled, b's exact
        R, o = poses[b.body]
        ends = o + R @ ca.DM(np.asarray(b.a, float)), o + R @ ca.DM(np.asarray(b.b, float))
        gaps += [_segment_distance(point, *ends) - a.radius - b.radius for point in _samples(a, poses)]
    return ca.Function("exact_clearance", [theta], [ca.mmin(ca.vertcat(*gaps)) - margin(model)])


def clear_path(model, obstacles, theta_start, theta_end, nodes: int = 24, clearance: float = 0.01) -> dict:
    """A joint-space path from theta_start to theta_end whose capsules keep `clearance` (m) from
    the obstacles at `nodes` - 1 evenly spaced interior points: the shortest polygon (the sum of
    squared segment lengths, which also spaces the points evenly) within the joint limits, solved
    by IPOPT from the straight line.  Returns {theta (n, nodes + 1), success, status,
    min_clearance}: the optimiser's first guess around the obstacles (a straight line through a
    ball is a guess the collocation solver spends a hundred iterations leaving)."""
    n = model.n
    start, end = (np.asarray(v, float).ravel() for v in (theta_start, theta_end))
    clear = clearance_function(model, obstacles)
    lim = limit_arrays(model)
    lo, hi = lim["theta_lo"], lim["theta_hi"]
    inner = ca.MX.sym("inner", n, nodes - 1)
    polygon = ca.horzcat(ca.DM(start), inner, ca.DM(end))
    nlp = {"x": ca.vec(inner), "f": ca.sumsqr(ca.diff(polygon, 1, 1)), "g": ca.vec(clear.map(nodes - 1)(inner))}
    solver = ca.nlpsol("clear_path", "ipopt", nlp, {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
                                                    "ipopt.max_iter": 300})
    line = np.linspace(start, end, nodes + 1)[1:-1].T
    res = solver(x0=line.ravel("F"), lbx=np.tile(lo, nodes - 1), ubx=np.tile(hi, nodes - 1),
                 lbg=clearance, ubg=np.inf)
    stats = solver.stats()
    raise_if_interrupted(stats)
    path = np.hstack([start[:, None], np.array(res["x"]).reshape(n, nodes - 1, order="F"), end[:, None]])
    gap = float(np.min(np.array(clear.map(nodes - 1)(path[:, 1:-1])))) if nodes > 1 else np.inf
    return {"theta": path, "success": bool(stats["success"]), "status": stats["return_status"], "min_clearance": gap}
