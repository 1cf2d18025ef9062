"""Closed-loop evidence for the interaction controllers, at 1 kHz through quantised encoders on the
complete model with contacts (`rscasadi.sim.contact`):

(a) `push`: a push of F at the frame; the steady displacement against F / K;
(b) `wall`: the target moved into a wall; the contact force against K d k_w / (K + k_w);
(c) `collision` and `collision_feedforward`: an obstacle nobody told the controller of, met during
    an impedance motion or a trajectory's feedforward; the momentum observer's flag delay and its
    torques against the contact's J^T f;
(d) each of (a), (b) with the controller designed on the DLR/Spong reduced model;
and the generated C's time per step.  `study` runs them all for one arm (`rscasadi controller
impedance MODEL --frame F --study`, benchmarks/bench_interaction.py)."""
from __future__ import annotations

from typing import Any

import numpy as np

from rscasadi.dynamics.arm import Arm
from rscasadi.dynamics.statics import rest_state
from rscasadi.interaction.generate import CompiledImpedance
from rscasadi.interaction.impedance import ImpedanceController
from rscasadi.interaction.observer import MomentumObserver
from rscasadi.native.controller import CODE_NAMES
from rscasadi.sim.contact import Contact, Push, World
from rscasadi.sim.loop import FeedforwardPD, contact_plant, run_loop
from rscasadi.errors import InvalidArgument

DT = 1e-3


def pose_of(arm: Arm, frame: str, theta) -> np.ndarray:
    """The frame's pose as the controller's reference: p (3), R (9, column-major)."""
    R, p = (np.array(v) for v in arm.frame_placement(frame)(np.asarray(theta, float)))
    return np.r_[p.ravel(), R.ravel("F")]


class _Impedance:
    """The impedance controller as the loop's controller, tracking reference(t) (12): the Python
    twin (ImpedanceController) or the generated C (CompiledImpedance: step returns its code)."""

    def __init__(self, ctrl, reference, stiffness, damping_ratio):
        self.ctrl, self.reference, self.stiffness, self.damping_ratio = ctrl, reference, stiffness, damping_ratio

    def init(self, meas) -> None:
        if self.ctrl.init(meas) != 0:                 # the C's init raises ControllerError itself
            raise InvalidArgument(f"impedance: the start state is outside the controller's box "
                                  f"({CODE_NAMES[self.ctrl.code]})")

    def step(self, k: int, meas) -> np.ndarray:
        out = self.ctrl.step(meas, self.reference(k * DT), self.stiffness, self.damping_ratio)
        tau, code = out if isinstance(out, tuple) else (out, self.ctrl.code)
        if code != 0:
            raise InvalidArgument(f"impedance: {CODE_NAMES[code]} at t = {k * DT:.3f} s (stiffness "
                                  f"{list(np.ravel(self.stiffness))}: TOO_STIFF is beyond what the springs allow "
                                  f"the passive design)")
        return tau


def impedance_loop(arm: Arm, frame: str, theta0, world: World, seconds: float, reference, stiffness,
                   damping_ratio, observer_gain: float | None = None, substeps: int = 8, plant=None,
                   compiled=None, **design) -> dict:
    """The arm at rest at theta0 under the Cartesian impedance controller (`design` keywords as
    `impedance_law`), the reference reference(t) (12), in `world` (rscasadi.sim.loop): per sample
    t, the frame's position p, the wrench at world.frames[0] (6), the deflections psi, the
    torques, the observer's link torques r and the true J^T f (when observer_gain is given).
    `plant`: another plant giving that wrench (rscasadi.export.mujoco.mujoco_plant with a world
    of its own), else rscasadi's contacts of `world`; `compiled`: the directory of the generated C
    controller (generate_impedance) to run instead of its Python twin."""
    n, samples = arm.n, int(round(seconds / DT))
    place, jac = arm.frame_placement(frame), arm.frame_jacobian(world.frames[0], "local_world_aligned")
    x0 = rest_state(arm, theta0)
    obs = MomentumObserver(arm, observer_gain, DT) if observer_gain else None
    if obs:
        obs.init(x0)
    seen: dict[str, list] = {"r": [], "true": []}

    def watch(k, t, x, meas, tau, wrench):
        if obs and 0 < k < samples:                 # the torque held over the sample before
            seen["r"].append(obs.step(meas, tau)[:n])
            seen["true"].append(np.array(jac(x[:n])).T @ wrench[:, 0])
    run = run_loop(arm, contact_plant(arm, world, DT, substeps) if plant is None else plant,
                   _Impedance(ImpedanceController(arm, frame, **design) if compiled is None else
                              CompiledImpedance(compiled), reference, stiffness, damping_ratio),
                   x0, samples, DT, watch=watch)
    x = run.x[:, 1:]
    rows = {"t": run.t[1:], "p": np.array(place.map(samples)(x[:n])[1]).T, "f": np.array([w[:, 0] for w in run.wrenches]),
            "psi": (x[n:2 * n] - x[:n]).T, "tau": run.tau.T}
    return rows | {k: np.array(v) for k, v in seen.items() if v}


def push(arm: Arm, frame: str, theta0, stiffness: float, force=(0.0, 0.0, -15.0), seconds: float = 2.5,
         rotational: float = 50.0, zeta: float = 0.7, **design) -> dict:
    """(a) The frame held at its start pose, pushed by `force` (N) from 0.3 s on: the steady
    displacement along the force against F / K, the overshoot, the largest |psi| against its limit."""
    F = np.asarray(force, float)
    ref = pose_of(arm, frame, theta0)
    run = impedance_loop(arm, frame, theta0, World(pushes=(Push(frame, np.r_[F, 0, 0, 0], 0.3, 1e9),)), seconds,
                         lambda t: ref, [stiffness] * 3 + [rotational] * 3, [zeta] * 6, **design)
    along = (run["p"] - ref[:3]) @ (F / np.linalg.norm(F))
    expected = np.linalg.norm(F) / stiffness
    psi_limit = np.array([jt.limits.get("psi", np.inf) for jt in arm.model.joints])
    return {"K": stiffness, "F": np.linalg.norm(F), "displacement": along[-1], "expected": expected,
            "error_percent": 100 * (along[-1] / expected - 1), "overshoot_percent": 100 * (along.max() / along[-1] - 1),
            "psi_of_limit": float(np.max(np.abs(run["psi"]) / psi_limit)), "trace": (run["t"], along)}


def frame_inertia(arm: Arm, frame: str, theta, direction) -> float:
    """The inertia (kg) the links show at the frame's origin along `direction`: 1 / (u^T J_v
    M_tt^-1 J_v^T u)."""
    n, theta = arm.n, np.asarray(theta, float)
    u = np.asarray(direction, float) / np.linalg.norm(direction)
    Jv = np.array(arm.frame_jacobian(frame, "local_world_aligned")(theta))[:3]
    M = np.array(arm.mass_matrix()(theta, theta))[:n, :n]
    return 1.0 / (u @ Jv @ np.linalg.solve(M, Jv.T) @ u)


def wall(arm: Arm, frame: str, theta0, stiffness: float, wall_stiffness: float, depth: float = 0.005,
         gap: float = 0.002, seconds: float = 2.0, wall_damping: float = 0.4, ramp: float = 0.5, rotational: float = 50.0, zeta: float = 0.7, **design) -> dict:
    """(b) A wall `gap` below the frame, its damping ratio `wall_damping` with the frame's
    inertia along its normal (restitution 0.25 at 0.4); the target moved in `ramp` s to `depth`
    inside it: the settled contact force against K d k_w / (K + k_w); after the first touch the
    time out of contact, the separations and the largest gap; the force's peak-to-peak over the
    last 0.2 s (chatter)."""
    ref0 = pose_of(arm, frame, theta0)
    c = 2 * wall_damping * np.sqrt(wall_stiffness * frame_inertia(arm, frame, theta0, [0.0, 0.0, 1.0]))
    surface = Contact(frame, k=wall_stiffness, c=c, mu=0.2, point=ref0[:3] - [0, 0, gap], normal=np.array([0.0, 0.0, 1.0]))

    def reference(t):
        s = min(t / ramp, 1.0)
        return ref0 - np.r_[0, 0, (3 * s ** 2 - 2 * s ** 3) * (gap + depth), np.zeros(9)]
    run = impedance_loop(arm, frame, theta0, World(contacts=(surface,)), seconds, reference,
                         [stiffness] * 3 + [rotational] * 3, [zeta] * 6, substeps=max(8, int(np.sqrt(wall_stiffness) / 40)),
                         **design)
    fz = run["f"][:, 2]
    touched = int(np.argmax(fz > 0))
    expected = stiffness * depth * wall_stiffness / (stiffness + wall_stiffness)
    last = run["t"] > run["t"][-1] - 0.2
    apart = fz[touched:] <= 0
    gap_after = run["p"][touched:, 2] - surface.point[2]
    return {"K": stiffness, "k_wall": wall_stiffness, "force": fz[last].mean(), "expected": expected,
            "error_percent": 100 * (fz[last].mean() / expected - 1), "lost_contact_ms": 1e3 * DT * int(np.sum(apart)),
            "bounces": int(np.sum(np.diff(apart.astype(int)) == 1)), "bounce_um": 1e6 * max(0.0, float(gap_after.max())),
            "chatter_percent": 100 * np.ptp(fz[last]) / expected, "trace": (run["t"], fz)}


def table_in_mujoco(arm: Arm, frame: str, theta0, stiffness: float, depth: float = 0.005, gap: float = 0.002,
                    seconds: float = 2.0, ramp: float = 0.5, half: float = 0.02, rotational: float = 50.0,
                    zeta: float = 0.7, observer_gain: float = 50.0, threshold: float = 0.5, compiled=None,
                    **design) -> dict:
    """(b) on MuJoCo's plant of the exported arm: a table (a box of half-width `half` m, MuJoCo's
    default contact) `gap` below the lowest point of the arm's capsules above it, the target moved
    in `ramp` s to `depth` below that touch: over the last 0.2 s the contact force MuJoCo reports
    against the stiffness the controller realises, K (p_z - p_ref,z) with p the frame where MuJoCo
    holds it, the force's peak-to-peak (chatter), and the momentum observer's link torques against
    MuJoCo's J^T f (their mean difference, per joint the largest); the observer's flag (a link
    torque above `threshold` N m) after MuJoCo's first contact, and its largest torque before.
    `compiled`: the generated C controller's directory (impedance_loop)."""
    from rscasadi.dynamics.kinematics import body_poses
    from rscasadi.export.mujoco import mujoco_plant
    from rscasadi.model.collision import capsules
    ref0 = pose_of(arm, frame, theta0)
    poses, low = body_poses(arm.model, np.asarray(theta0, float)), np.inf
    for c in capsules(arm.model):                   # the capsules' lowest point over the table
        R, o = (np.array(v) for v in poses[c.body])
        for s_ in np.linspace(0.0, 1.0, 101):
            q = R @ ((1 - s_) * c.a + s_ * c.b) + o.ravel()
            if np.all(np.abs(q[:2] - ref0[:2]) <= half):
                low = min(low, q[2] - c.radius)
    if not np.isfinite(low):
        raise InvalidArgument(f"table_in_mujoco: no capsule of {arm.model.path} is above {frame!r}: nothing to touch")
    top = low - gap
    table = (f'    <geom name="table" type="box" size="{half!r} {half!r} 0.01" '
             f'pos="{float(ref0[0])!r} {float(ref0[1])!r} {float(top) - 0.01!r}"/>')

    def reference(t):
        s_ = min(t / ramp, 1.0)
        return ref0 - np.r_[0, 0, (3 * s_ ** 2 - 2 * s_ ** 3) * (gap + depth), np.zeros(9)]
    run = impedance_loop(arm, frame, theta0, World(frames=[frame]), seconds, reference,
                         [stiffness] * 3 + [rotational] * 3, [zeta] * 6, observer_gain=observer_gain,
                         plant=mujoco_plant(arm, DT, world=table, frame=frame), compiled=compiled, **design)
    last = run["t"] > run["t"][-1] - 0.2
    fz = run["f"][:, 2]
    realised = stiffness * (run["p"][last, 2] - reference(seconds)[2])
    settled = np.arange(len(run["r"])) >= len(run["r"]) - 200           # the observer's last 0.2 s
    torque_error = np.abs((run["r"][settled] - run["true"][settled]).mean(axis=0))
    t, r, true = run["t"][:-1], run["r"], run["true"]               # r, true: at the start of samples 2..
    contact = t[int(np.argmax(np.abs(true).max(axis=1) > 0))]
    flag, false_alarm = _first_flags(t, np.abs(r).max(axis=1) > threshold, contact)
    return {"contact_s": float(contact), "flag_s": float(flag), "delay_ms": float(1e3 * (flag - contact)),
            "false_alarm_s": float(false_alarm), "free_max_Nm": float(np.abs(r[t < contact]).max()),
            "threshold_Nm": threshold,
            "K": stiffness, "force": float(fz[last].mean()), "expected": float(realised.mean()),
            "error_percent": float(100 * (fz[last].mean() / realised.mean() - 1)),
            "chatter_percent": float(100 * np.ptp(fz[last]) / abs(fz[last].mean())),
            "observer_error": float(torque_error.max()), "observer_torque": float(np.abs(run["true"][-1]).max()),
            "trace": (run["t"], fz)}


def push_in_mujoco(arm: Arm, frame: str, theta0, stiffness: float, force=(0.0, 0.0, -2.0), start: float = 0.2,
                   seconds: float = 1.2, rotational: float = 50.0, zeta: float = 0.7, observer_gain: float = 50.0,
                   compiled=None, **design) -> dict:
    """The impedance controller holding `frame` where it is at theta0, on MuJoCo's plant of the
    exported arm, pushed at the frame by `force` (N, world axes) from `start` s on: over the last
    0.2 s the frame's displacement against force / K (the stiffness the controller realises),
    and the momentum observer's link torques against J^T f of the push."""
    from rscasadi.export.mujoco import mujoco_plant
    ref0 = pose_of(arm, frame, theta0)
    wrench = np.r_[np.asarray(force, float), np.zeros(3)]
    run = impedance_loop(arm, frame, theta0, World(frames=[frame]), seconds, lambda t: ref0,
                         [stiffness] * 3 + [rotational] * 3, [zeta] * 6, observer_gain=observer_gain,
                         plant=mujoco_plant(arm, DT, frame=frame, push=lambda t: wrench * (t >= start - 1e-12)),
                         compiled=compiled, **design)
    last = run["t"] > run["t"][-1] - 0.2
    moved = run["p"][last].mean(axis=0) - ref0[:3]
    expected = np.asarray(force, float) / stiffness
    k = int(np.argmax(np.abs(expected)))
    settled = np.arange(len(run["r"])) >= len(run["r"]) - 200
    torque_error = np.abs((run["r"][settled] - run["true"][settled]).mean(axis=0))
    return {"K": stiffness, "force": list(map(float, force)), "displacement": moved.tolist(),
            "expected": expected.tolist(), "error_percent": float(100 * (moved[k] / expected[k] - 1)),
            "observer_error": float(torque_error.max()), "observer_torque": float(np.abs(run["true"][-1]).max())}


def _first_flags(t, flagged, contact: float) -> tuple[float, float]:
    """The first flag at or after the contact (NaN: never), and the first one before it (a false
    alarm; NaN: none)."""
    after, before = flagged & (t >= contact), flagged & (t < contact)
    return (float(t[np.argmax(after)]) if after.any() else np.nan,
            float(t[np.argmax(before)]) if before.any() else np.nan)


def collision(arm: Arm, frame: str, theta0, stiffness: float = 300.0, gap: float = 0.03, travel: float = 0.12,
              gain: float = 50.0, threshold: float = 1.0, seconds: float = 1.5, rotational: float = 50.0,
              zeta: float = 0.7, **design) -> dict:
    """(c) The target moved down by `travel` in 1 s through a table `gap` below the frame that
    the controller was not told of; the momentum observer (gain 1/s, fed the torque of the
    sample before): its largest link torque before the contact, the flag's delay (a link torque
    above `threshold` N m), its torques averaged from 0.1 s after the contact against J^T f."""
    ref0 = pose_of(arm, frame, theta0)
    table = Contact(frame, k=1e5, c=2 * 0.4 * np.sqrt(1e5), mu=0.2, point=ref0[:3] - [0, 0, gap], normal=np.array([0.0, 0.0, 1.0]))

    def reference(t):
        s = min(t / 1.0, 1.0)
        return ref0 - np.r_[0, 0, (3 * s ** 2 - 2 * s ** 3) * travel, np.zeros(9)]
    run = impedance_loop(arm, frame, theta0, World(contacts=(table,)), seconds, reference,
                         [stiffness] * 3 + [rotational] * 3, [zeta] * 6, observer_gain=gain, substeps=12, **design)
    t, r, true = run["t"][:-1], run["r"], run["true"]               # r, true: at the start of samples 2..
    contact = t[int(np.argmax(np.abs(true).max(axis=1) > 0))]
    flagged = np.abs(r).max(axis=1) > threshold
    flag, false_alarm = _first_flags(t, flagged, contact)
    late = t > contact + 0.1
    mean_r, mean_true = r[late].mean(0), true[late].mean(0)
    return {"contact_s": contact, "flag_s": flag, "delay_ms": 1e3 * (flag - contact), "false_alarm_s": false_alarm,
            "free_max_Nm": float(np.abs(r[t < contact]).max()), "threshold_Nm": threshold,
            "error_percent": 100 * np.linalg.norm(mean_r - mean_true) / np.linalg.norm(mean_true),
            "force_N": float(np.linalg.norm(run["f"][run["t"] > contact + 0.1, :3].mean(0)))}


def collision_feedforward(arm: Arm, frame: str, trajectory, gain: float = 50.0, threshold: float = 1.0,
                          wall_stiffness: float = 1e4, at: float = 0.2, seconds: float | None = None,
                          motor_hz: float = 4.0) -> dict:
    """(c) A feedforward motion (`rscasadi.sim.simulation.feedforward` of the trajectory, a motor
    PD of `motor_hz` around it, quantised encoders, `seconds` of it) into a wall nobody told the
    controller of: a plane across the frame's planned path where it is at `at` of the
    trajectory's duration, facing it.  The
    momentum observer (gain 1/s, fed the torque of the sample before): the largest link torque
    before the contact, the flag's delay (a link torque above `threshold` N m), its torques
    averaged over 0.1-0.3 s after the contact against J^T f."""
    from rscasadi.sim.simulation import feedforward, motor_pd_gains
    n = arm.n
    seconds = trajectory.duration if seconds is None else seconds
    t = np.arange(0.0, seconds + DT / 2, DT)
    ff = feedforward(arm, trajectory, t)
    place, jac = arm.frame_placement(frame), arm.frame_jacobian(frame, "local_world_aligned")
    k = int(round(at * trajectory.duration / DT))
    p_hit = np.array(place(ff["theta_d"][:, k])[1]).ravel()
    v_hit = (np.array(place(ff["theta_d"][:, k + 1])[1]) - np.array(place(ff["theta_d"][:, k - 1])[1])).ravel()
    plane = Contact(frame, k=wall_stiffness, c=2 * 0.4 * np.sqrt(wall_stiffness * 1.0), mu=0.2, point=p_hit,
                    normal=-v_hit / np.linalg.norm(v_hit))
    gains = (*motor_pd_gains(arm.model, motor_hz), arm.model.column("gear_ratio"))
    obs = MomentumObserver(arm, gain, DT, threshold)
    rows: list = []
    hit: list = []

    def watch(k, t, x, meas, tau, wrench):
        if k == 0:
            obs.init(meas)
            return
        f = wrench[:, 0]
        r = obs.step(meas, tau)[:n]                 # the torque held over the sample before
        if not hit and np.any(f):
            hit.append(t)
        rows.append(np.r_[t, r, np.array(jac(x[:n]))[:3].T @ f[:3], obs.collision])
    run_loop(arm, contact_plant(arm, World(contacts=(plane,)), DT, 8), FeedforwardPD(ff, gains), ff["x0"],
             len(t) - 1, DT, watch=watch)
    table, contact = np.array(rows), (hit[0] if hit else None)
    if contact is None:
        raise InvalidArgument(f"collision: the {frame!r} never reached the wall")
    flag, false_alarm = _first_flags(table[:, 0], table[:, -1] > 0, contact)
    data = table[:, :-1]
    window = (data[:, 0] > contact + 0.1) & (data[:, 0] < contact + 0.3)
    mean_r, mean_true = data[window, 1:n + 1].mean(0), data[window, n + 1:].mean(0)
    return {"contact_s": contact, "flag_s": flag, "delay_ms": 1e3 * (flag - contact), "false_alarm_s": false_alarm,
            "free_max_Nm": float(np.abs(data[data[:, 0] < contact, 1:n + 1]).max()), "threshold_Nm": threshold,
            "error_percent": 100 * np.linalg.norm(mean_r - mean_true) / np.linalg.norm(mean_true),
            "torque_Nm": float(np.linalg.norm(mean_true))}


def series_stiffness(arm: Arm, frame: str, theta0, stiffness: float, direction=(0.0, 0.0, -1.0)) -> float:
    """The stiffness along `direction` the classical design (no spring compensation) realises:
    1 / (1/K + u^T J C_s J^T u), C_s the springs' compliance."""
    u = np.asarray(direction, float) / np.linalg.norm(direction)
    J = np.array(arm.frame_jacobian(frame, "local_world_aligned")(np.asarray(theta0, float)))[:3]
    return 1.0 / (1.0 / stiffness + u @ J @ np.diag(1 / arm.model.column("k1")) @ J.T @ u)


def step_times(arm: Arm, frame: str, theta0, directory, samples: int = 2000, opt: str = "-O2", log=print) -> dict:
    """The generated C's time per step (impedance_step_seconds, observer_step_seconds), median and
    worst over `samples` states near rest at theta0, in microseconds."""
    from pathlib import Path
    from rscasadi.interaction.generate import (CompiledImpedance, CompiledObserver, generate_impedance,
                                               generate_observer)
    generate_impedance(arm, Path(directory) / "impedance", frame, opt=opt, log=log)
    generate_observer(arm, Path(directory) / "observer", 50.0, opt=opt, log=log)
    imp, obs = CompiledImpedance(Path(directory) / "impedance"), CompiledObserver(Path(directory) / "observer")
    rng = np.random.default_rng(1)
    x0, ref = rest_state(arm, theta0), pose_of(arm, frame, theta0)
    imp.init(x0)
    obs.init(x0)
    t_imp, t_obs, tau = [], [], np.zeros(arm.n)
    for _ in range(samples):
        x = x0 + rng.normal(0, 1e-3, x0.size)
        imp.step(x, ref, [1000.0] * 3 + [50.0] * 3, [0.7] * 6)
        t_imp.append(imp.seconds())
        obs.step(x, tau)
        t_obs.append(obs.seconds())
    us = lambda v: {"median_us": 1e6 * float(np.median(v)), "worst_us": 1e6 * float(np.max(v))}
    return {"impedance_step": us(t_imp), "observer_step": us(t_obs), "opt": opt}


def _passive_allows(arm: Arm, frame: str, theta0, stiffness: float, rotational: float) -> bool:
    """Whether the passive (motor) design's margin is positive at rest at theta0."""
    n, x = arm.n, rest_state(arm, theta0)
    law = ImpedanceController(arm, frame).law
    margin = law(x[:n], x[n:2 * n], x[2 * n:3 * n], x[3 * n:], pose_of(arm, frame, theta0),
                 [stiffness] * 3 + [rotational] * 3, [0.7] * 6)[3]
    return float(margin) > 0


def study(arm: Arm, frame: str, theta0, out, gain: float = 50.0, threshold: float = 1.0, trajectory=None,
          rotational: float = 50.0, short: bool = False, opt: str = "-O2", log=print) -> dict:
    """(a)-(d) and the C's time per step for one arm at theta0, written into `out` (study.json,
    study.md, study.png) whole or not at all.  The observer: `gain` (1/s) and `threshold` (N m);
    with a `trajectory` (rscasadi.sim.trajectory) (c) runs during its feedforward motion too.
    short: fewer and shorter cases (for tests)."""
    import tempfile
    from pathlib import Path
    from rscasadi.files import fresh_directory, write_json, write_text
    stiffnesses, walls = ((300.0, 2000.0), (1e5,)) if short else ((200.0, 1000.0, 2000.0), (1e4, 1e5, 1e6))
    seconds = 1.5 if short else 2.5
    result: dict[str, Any] = {"model": str(arm.model.path), "frame": frame, "theta0": list(map(float, theta0)),
              "rotational_stiffness": rotational, "push": [], "wall": [], "reduced": {}}
    traces: dict[str, dict] = {}
    with fresh_directory(Path(out)) as tmp:
        for K in stiffnesses:
            design = "motor" if _passive_allows(arm, frame, theta0, K, rotational) else "link"
            log(f"(a) push 15 N at K = {K:g} N/m ({design} design)")
            r = push(arm, frame, theta0, K, seconds=seconds, rotational=rotational, design=design)
            traces[f"push K={K:g} ({design})"] = r.pop("trace")
            result["push"].append({"design": design, **r})
        for kw in walls:
            log(f"(b) wall of {kw:g} N/m at K = 1000 N/m")
            r = wall(arm, frame, theta0, 1000.0, kw, seconds=seconds, rotational=rotational)
            traces[f"wall {kw:g} N/m"] = r.pop("trace")
            result["wall"].append(r)
        log(f"(c) a collision during a motion, the momentum observer at {gain:g} 1/s")
        result["collision"] = {"impedance motion": collision(arm, frame, theta0, gain=gain, threshold=threshold,
                                                             rotational=rotational)}
        if trajectory is not None:
            result["collision"]["feedforward motion"] = collision_feedforward(
                arm, frame, trajectory, gain=gain, threshold=threshold, seconds=1.0 if short else None)
        result["observer_gain"] = gain
        log("(d) the same controller designed on the reduced (DLR/Spong) model")
        for name, options in (("complete", {}), ("reduced", {"reduced": True})):
            p = push(arm, frame, theta0, 1000.0, seconds=seconds, rotational=rotational, **options)
            w = wall(arm, frame, theta0, 1000.0, walls[0], seconds=seconds, rotational=rotational, **options)
            result["reduced"][name] = {"push_error_percent": p["error_percent"], "push_overshoot_percent":
                                       p["overshoot_percent"], "wall_error_percent": w["error_percent"]}
        result["reduced"]["classical_series_stiffness_percent"] = \
            100 * (series_stiffness(arm, frame, theta0, 1000.0) / 1000.0 - 1)
        log("the generated C's time per step")
        with tempfile.TemporaryDirectory() as c_dir:
            result["timing"] = step_times(arm, frame, theta0, c_dir, samples=200 if short else 5000, opt=opt, log=log)
        write_json(tmp / "study.json", result, indent=2)
        write_text(tmp / "study.md", study_table(result))
        _plot(traces, tmp / "study.png")
    log(f"wrote {Path(out) / 'study.md'}, study.json and study.png")
    return result


def study_table(r: dict) -> str:
    """The study as Markdown tables."""
    from pathlib import Path
    from rscasadi.files import run_stamp
    lines = [f"# Interaction study: {Path(r['model']).name} at {r['frame']}", "", run_stamp(), "",
             "## (a) A 15 N push: displacement against F / K", "",
             "| K (N/m) | design | displacement (mm) | F / K (mm) | error | overshoot | max psi / limit |", "|---|---|---|---|---|---|---|"]
    lines += [f"| {p['K']:g} | {p['design']} | {1e3 * p['displacement']:.3f} | {1e3 * p['expected']:.3f} | "
              f"{p['error_percent']:+.2f} % | {p['overshoot_percent']:.0f} % | {p['psi_of_limit']:.2f} |" for p in r["push"]]
    lines += ["", "## (b) Pressing 5 mm into a wall at K = 1000 N/m", "",
              "| wall (N/m) | force (N) | K d k_w / (K + k_w) (N) | error | after the touch: apart, separations, "
              "largest gap | chatter (last 0.2 s) |", "|---|---|---|---|---|---|"]
    lines += [f"| {w['k_wall']:g} | {w['force']:.4f} | {w['expected']:.4f} | {w['error_percent']:+.3f} % | "
              f"{w['lost_contact_ms']:.0f} ms, {w['bounces']}, {w['bounce_um']:.1f} um | {w['chatter_percent']:.3f} % |"
              for w in r["wall"]]
    lines += ["", f"## (c) A collision during a motion (momentum observer, {r['observer_gain']:g} 1/s)", "",
              "| motion | contact at | flagged after | false alarm before it | largest residual before (N m) | "
              "threshold (N m) | torque error (averaged) |", "|---|---|---|---|---|---|---|"]
    lines += [f"| {name} | {c['contact_s']:.3f} s | "
              + ("never" if not np.isfinite(c["delay_ms"]) else f"{c['delay_ms']:.0f} ms") + " | "
              + ("none" if not np.isfinite(c.get("false_alarm_s", np.nan)) else f"at {c['false_alarm_s']:.3f} s") + " | "
              f"{c['free_max_Nm']:.2f} | {c['threshold_Nm']:g} | {c['error_percent']:.2f} % |" for name, c in r["collision"].items()]
    d = r["reduced"]
    lines += ["", "## (d) Designed on the complete or the reduced (DLR/Spong) model, K = 1000 N/m", "",
              "| design model | push error | push overshoot | wall error |", "|---|---|---|---|"]
    lines += [f"| {k} | {d[k]['push_error_percent']:+.4f} % | {d[k]['push_overshoot_percent']:.2f} % | "
              f"{d[k]['wall_error_percent']:+.4f} % |" for k in ("complete", "reduced")]
    lines += ["", f"Without the springs' compliance in the design (q_bar from gravity alone, the classical one) the "
              f"stiffness seen along the push would be {d['classical_series_stiffness_percent']:+.1f} % off.", "",
              "## The generated C, time per step", "", "| function | median (us) | worst (us) |", "|---|---|---|"]
    lines += [f"| {k} | {v['median_us']:.1f} | {v['worst_us']:.1f} |" for k, v in r["timing"].items() if isinstance(v, dict)]
    return "\n".join(lines) + f"\n\nCompiled at {r['timing']['opt']}.\n"


def _plot(traces: dict, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    for name, (t, y) in traces.items():
        (a if name.startswith("push") else b).plot(t, 1e3 * y if name.startswith("push") else y, label=name)
    a.set(xlabel="t (s)", ylabel="displacement along the push (mm)")
    b.set(xlabel="t (s)", ylabel="wall force (N)")
    a.legend(fontsize=7)
    b.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
