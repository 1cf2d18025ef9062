"""The joints' limits, read one way everywhere: a limit the model does not give is no limit.

`limit_arrays(model)`: per joint the motor torque `tau`, SEA deflection `psi` and slow-side speed
`dphi` (inf where none) and the link-angle range `theta_lo`, `theta_hi` (-inf, inf where none).

`violation(model, theta, phi, dphi, dtheta)`: the one limit-violation figure of every replay and
closed loop: at each sample the largest excess over a limit relative to it,

    max_j max( (|psi_j| - psi_max) / psi_max,  (|dphi_j| - dphi_max) / dphi_max,
               (theta_lo - theta_j) / (theta_hi - theta_lo),  (theta_j - theta_hi) / (theta_hi - theta_lo) ),

<= 0 within every limit (the motor torques are the controllers' outputs, clamped, so not counted).
phi and dphi are the motor coordinates' (one per SEA); `slow_sides` gives every joint's slow
side: an SEA's motor, the link itself for the others (a geared joint's rotors turn with it, so
its `dphi` limit bounds dtheta).

`measurement_bounds(model)`: the box a measured state x = (theta, phi, dtheta, dphi) must lie in
for a generated controller to act on it (beyond it the sample is taken for a sensor fault):
angles within ANGLE_MARGIN of the joint's range (phi twice that, the spring between) or within
+-UNLIMITED_ANGLE where the joint has none; speeds within SPEED_FACTOR times the slow-side speed
limit, or +-UNLIMITED_SPEED where there is none.
"""
from __future__ import annotations

import numpy as np

ANGLE_MARGIN = 0.5          # rad beyond a joint's range still taken for a measurement
UNLIMITED_ANGLE = 100.0     # rad: |theta| of a joint without a range (16 turns)
SPEED_FACTOR = 5.0          # speeds up to this multiple of the slow-side speed limit
UNLIMITED_SPEED = 100.0     # rad/s where the joint has no speed limit
TORQUE_FACTOR = 10.0        # an applied torque (observer input) up to this multiple of the limit
UNLIMITED_TORQUE = 1e6      # N m where the joint has no torque limit


def limit_arrays(model) -> dict:
    """tau, psi, dphi (inf where none), theta_lo, theta_hi (-inf, inf where none), per joint."""
    joints = model.joints
    out = {key: np.array([jt.limits.get(key, np.inf) for jt in joints], float) for key in ("tau", "psi", "dphi")}
    ranges = [jt.limits.get("theta", (-np.inf, np.inf)) for jt in joints]
    out["theta_lo"] = np.array([r[0] for r in ranges], float)
    out["theta_hi"] = np.array([r[1] for r in ranges], float)
    return out


def slow_sides(model, theta, phi, dtheta, dphi) -> tuple[np.ndarray, np.ndarray]:
    """Every joint's slow-side angle and speed (n x K, or n): an SEA's motor coordinate, the
    link's own elsewhere; phi, dphi: the motor coordinates' (m x K)."""
    angle, speed = np.array(theta, float, copy=True), np.array(dtheta, float, copy=True)
    angle[model.motors], speed[model.motors] = phi, dphi
    return angle, speed


def violation(model, theta, phi, dphi, dtheta=None) -> np.ndarray:
    """The largest limit violation at each sample relative to its limit (<= 0: within every
    limit; -inf: the model has none); theta, dtheta: n x K; phi, dphi: the motors' (m x K);
    without dtheta the joints without a motor coordinate have no speed checked."""
    lim = limit_arrays(model)
    theta, phi, dphi = (np.atleast_2d(np.asarray(v, float).T).T for v in (theta, phi, dphi))
    if len(phi) != len(theta):
        speed = np.full_like(theta, 0.0) if dtheta is None else np.atleast_2d(np.asarray(dtheta, float).T).T
        phi, dphi = slow_sides(model, theta, phi, speed, dphi)
    v = np.full(theta.shape[1], -np.inf)
    with np.errstate(invalid="ignore", divide="ignore"):
        for c, cmax in ((phi - theta, lim["psi"]), (dphi, lim["dphi"])):
            finite = np.isfinite(cmax)
            if finite.any():
                v = np.maximum(v, np.max((np.abs(c[finite]) - cmax[finite, None]) / cmax[finite, None], axis=0))
        ranged = np.isfinite(lim["theta_lo"]) & np.isfinite(lim["theta_hi"])
        if ranged.any():
            lo, hi = lim["theta_lo"][ranged, None], lim["theta_hi"][ranged, None]
            th = theta[ranged]
            v = np.maximum(v, np.max(np.maximum(lo - th, th - hi) / (hi - lo), axis=0))
    return v


def max_violation(model, theta, phi, dphi, dtheta=None) -> float:
    """The largest violation over all samples, 0 if every limit is kept (the figure reports give)."""
    v = violation(model, theta, phi, dphi, dtheta)
    return max(float(v.max()), 0.0) if v.size else 0.0


def measurement_bounds(model) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi): the box of a plausible measured state (theta, phi, dtheta, dphi), 2 nq each (phi
    and dphi: the SEAs' motors)."""
    lim, mot = limit_arrays(model), model.motors
    lo = np.where(np.isfinite(lim["theta_lo"]), lim["theta_lo"] - ANGLE_MARGIN, -UNLIMITED_ANGLE)
    hi = np.where(np.isfinite(lim["theta_hi"]), lim["theta_hi"] + ANGLE_MARGIN, UNLIMITED_ANGLE)
    speed = np.where(np.isfinite(lim["dphi"]), SPEED_FACTOR * lim["dphi"], UNLIMITED_SPEED)
    return (np.concatenate([lo, lo[mot] - ANGLE_MARGIN, -speed, -speed[mot]]),
            np.concatenate([hi, hi[mot] + ANGLE_MARGIN, speed, speed[mot]]))


def torque_bounds(model) -> np.ndarray:
    """The largest plausible applied motor torque per joint (an observer's input)."""
    tau = limit_arrays(model)["tau"]
    return np.where(np.isfinite(tau), TORQUE_FACTOR * tau, UNLIMITED_TORQUE)
