"""A floating robot simulated through a schedule of contact modes (docs/user-guide/floating.md,
"Simulating a contact schedule"), OCS2's view of a gait: phases, each from a time on with a set
of contacts held.

Within a phase the contact dynamics (rscasadi.dynamics.contacts, with `damping` pulling the held
contacts' velocity to zero) give the accelerations; at a phase's start the contacts it adds land
in a plastic impact (the impact map of the phase's whole set: J v_plus = 0), the contacts it
drops are let go.  The schedule decides; nothing checks that a held contact pushes: the forces
are returned, and `pulling` reports the most negative normal force of a point contact (world z)
or a flat one (its own z).  Steps: semi-implicit Euler on the manifold (v first, then
q = integrate(q, v dt)); then q is moved back onto where the held contacts landed (one
Gauss-Newton step in the kinetic metric) and their velocity projected to zero (the impact map's
projection): what a discrete step leaves, about dt^2 of their acceleration, never accumulates.
The SEAs' fastest modes bound dt (5e-4 s by default).
"""
from __future__ import annotations

import numpy as np

from rscasadi.dynamics.contacts import contact_set
from rscasadi.errors import InvalidArgument


def _phases(robot, schedule, duration) -> list:
    """[(start, contacts)] sorted, validated: starts in [0, duration), the first at 0."""
    if not schedule:
        raise InvalidArgument("schedule: expected at least one phase (start, contacts)")
    out = []
    for i, phase in enumerate(schedule):
        try:
            start, contacts = phase
        except (TypeError, ValueError):
            raise InvalidArgument(f"schedule[{i}]: expected (start time, contacts), got {phase!r}") from None
        if not np.isfinite(start) or not 0 <= start < duration:
            raise InvalidArgument(f"schedule[{i}]: start {start!r} is not in [0, {duration:g}) s")
        out.append((float(start), contact_set(robot.model, list(contacts)) if contacts else ()))
    out.sort(key=lambda p: p[0])
    if out[0][0] != 0.0 or len({p[0] for p in out}) != len(out):
        raise InvalidArgument("schedule: the first phase starts at 0 and no two start together")
    return out


def _hold(robot, held, q, anchors) -> np.ndarray:
    """q moved back onto the held contacts' frames where they landed (one Gauss-Newton step,
    least kinetic metric: dq = -M^-1 J^T (J M^-1 J^T)^-1 e, e the rows' position errors: a point's
    origin in world axes, a flat contact's origin and rotation vector in its own axes)."""
    from scipy.spatial.transform import Rotation
    rows: list = []
    for c, (R0, p0) in zip(held, anchors):
        R, p = (np.asarray(x, float) for x in robot.frame_placement(c.frame)(q))
        R0, p0 = np.asarray(R0, float), np.asarray(p0, float)
        if c.kind == "point":
            rows.append((p - p0).ravel())
        else:
            rows += [(R.T @ (p - p0)).ravel(), Rotation.from_matrix(R0.T @ R).as_rotvec()]
    e = np.concatenate(rows)
    J, M = np.asarray(robot.contact_jacobian(held)(q)), np.asarray(robot.mass_matrix()(q))
    MiJt = np.linalg.solve(M, J.T)
    dq = -MiJt @ np.linalg.solve(J @ MiJt, e)
    return np.asarray(robot.integrate()(q, dq, 1.0), float).ravel()


def simulate_schedule(robot, q0, v0, schedule, controller=None, duration: float = 1.0, dt: float = 5e-4,
                      damping: float = 20.0) -> dict:
    """Simulate `robot` (a FloatingRobot) from (q0, v0) for `duration` s through `schedule`
    ([(start, contacts)], module docstring); `controller(t, q, v) -> tau` (default: no torque).
    Returns t, q, v, tau (one row per step), f (per step the held contacts' forces), impacts
    [(t, frames, impulse, kinetic energy before, after)] and pulling (N)."""
    from rscasadi.dynamics.floating import unit_configuration
    q, v = unit_configuration(robot, q0, "simulate_schedule: q0"), np.array(v0, float).ravel()
    if v.shape != (robot.nv,) or not np.all(np.isfinite(v)):
        raise InvalidArgument(f"simulate_schedule: v0 must be {robot.nv} finite numbers, got shape {v.shape}")
    if not (duration > 0 and dt > 0 and damping >= 0):
        raise InvalidArgument(f"simulate_schedule: duration {duration!r} and dt {dt!r} must be > 0, damping >= 0")
    phases = _phases(robot, schedule, duration)
    step, energy = robot.integrate(), robot.energy()
    free = robot.forward_dynamics()
    controller = controller or (lambda t, q, v: np.zeros(robot.u))
    steps = int(round(duration / dt))
    out: dict = {"t": np.arange(steps + 1) * dt, "q": [q.copy()], "v": [v.copy()], "tau": [], "f": [],
                 "impacts": [], "pulling": 0.0}
    held: tuple = ()
    anchors: list = []
    for k in range(steps):
        t = k * dt
        now = [c for start, c in phases if start <= t + 1e-12][-1]
        if now != held:
            landing = {c.frame for c in now} - {c.frame for c in held}
            if landing:                                           # a plastic impact on the new set
                before = float(energy(q, v))
                v_plus, impulse = robot.impact(now)(q, v)
                v = np.asarray(v_plus, float).ravel()
                out["impacts"].append((t, sorted(landing), np.asarray(impulse, float).ravel(), before,
                                       float(energy(q, v))))
            held = now
            anchors = [robot.frame_placement(c.frame)(q) for c in held]
        tau = np.asarray(controller(t, q, v), float).ravel()
        if held:
            a, f = robot.contact_dynamics(held, damping)(q, v, tau)
            f = np.asarray(f, float).ravel()
            row = 0
            for c in held:                                        # the normal: world z or the frame's z
                out["pulling"] = min(out["pulling"], float(f[row + 2]))
                row += c.rows
        else:
            a, f = free(q, v, tau), np.zeros(0)
        v = v + dt * np.asarray(a, float).ravel()
        q = np.asarray(step(q, v, dt), float).ravel()
        if held:                                  # back onto the held contacts, then their velocity to zero
            q = _hold(robot, held, q, anchors)
            v = np.asarray(robot.impact(held)(q, v)[0], float).ravel()
        out["q"].append(q.copy())
        out["v"].append(v.copy())
        out["tau"].append(tau)
        out["f"].append(f)
    out["q"], out["v"], out["tau"] = np.array(out["q"]), np.array(out["v"]), np.array(out["tau"])
    return out
