"""One closed loop: a plant, its sensors and a controller at a fixed sample time, and the figures
every study reports of it.

Every closed-loop result (the MPC's studies, the impedance and observer studies) is a run of
`run_loop`. Per sample k, t_k = k dt:

    meas_k         = sensors(x_k)                        quantised encoders, speeds by differences
    watch(k, ...)                                        observers and metrics see the sample
    tau_k          = clamp(controller.step(k, meas_k))   within the motor torque limits
    x_k+1, w_k+1   = plant(x_k, tau_k, t_k)              the torque held over the sample

A controller is anything with `init(meas_0)` and `step(k, meas_k) -> tau_k` (Python, or generated
C behind a ctypes wrapper); one that times itself sets `seconds` after each step.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Protocol

import casadi as ca
import numpy as np

from rscasadi.dynamics.arm import Arm
from rscasadi.errors import InvalidArgument
from rscasadi.model.limits import limit_arrays, violation
from rscasadi.sim.sensors import quanta


class Controller(Protocol):
    """What the loop drives: `init` with the first measurement, then one torque per sample."""

    def init(self, meas: np.ndarray) -> None: ...

    def step(self, k: int, meas: np.ndarray) -> np.ndarray: ...


class Encoders:
    """The absolute link and motor encoders of `arm` (rscasadi.sim.sensors' counts), quantised,
    their speeds by backward differences over `dt` (the true speeds at the first sample);
    `exact`: the state itself.  Returns (theta, phi, dtheta, dphi) as the controllers read them."""

    def __init__(self, arm: Arm, dt: float, exact: bool = False):
        self.n, self.nq, self.dt, self.exact, self.prev = arm.n, arm.nq, dt, exact, None
        self.q_link, self.q_motor = quanta(arm.model.column("gear_ratio")[arm.model.motors])

    def __call__(self, x) -> np.ndarray:
        n, nq = self.n, self.nq
        q = np.r_[np.round(x[:n] / self.q_link) * self.q_link, np.round(x[n:nq] / self.q_motor) * self.q_motor]
        speeds = (q - self.prev) / self.dt if self.prev is not None else x[nq:]
        self.prev = q
        return np.asarray(x, float).copy() if self.exact else np.r_[q, speeds]


def rk4_plant(arm: Arm, dt: float, substeps: int = 4) -> Callable:
    """(x, tau, t) -> (x after dt, no wrench): `substeps` RK4 steps of the arm's complete model."""
    from rscasadi.codegen import rk4
    nq, fd = arm.nq, arm.forward_dynamics()
    xs, us = ca.SX.sym("x", 2 * nq), ca.SX.sym("u", arm.u)
    z = xs
    for _ in range(substeps):
        z = rk4(lambda v: ca.vertcat(v[nq:], *fd(*arm.split_state(v), us)), z, dt / substeps)[0]
    advance = ca.Function("advance", [xs, us], [z])
    return lambda x, tau, t: (np.array(advance(x, tau)).ravel(), None)


def contact_plant(arm: Arm, world, dt: float, substeps: int = 8) -> Callable:
    """(x, tau, t) -> (x after dt, the wrenches at world.frames): the arm under `world`'s contacts
    and pushes (rscasadi.sim.contact)."""
    from rscasadi.sim.contact import plant_with_contacts
    advance = plant_with_contacts(arm, world, dt, substeps)

    def plant(x, tau, t):
        x_next, W = advance(x, tau, t)
        return np.array(x_next).ravel(), np.array(W)
    return plant


@dataclass
class Run:
    """A closed loop's record: t (K + 1), the states x (2 nq x K + 1), the torques tau (u x K),
    the measurements meas (2 nq x K), the controller's own step times (s; empty if it does not
    time itself) and the plant's wrenches after each sample (None for a plant without contacts)."""
    t: np.ndarray
    x: np.ndarray
    tau: np.ndarray
    meas: np.ndarray
    seconds: np.ndarray
    wrenches: list = field(default_factory=list)


def run_loop(arm: Arm, plant: Callable, controller: Controller, x0, samples: int, dt: float,
             sensors: Callable | None = None, watch: Callable | None = None, log=None) -> Run:
    """`samples` samples of the loop above from the state x0 of `arm` (the plant's model: its
    motor torque limits clamp the controller's output).  `sensors` default: Encoders(arm, dt).
    `watch(k, t_k, x_k, meas_k, tau_before, wrench_k)` is called at every sample and once after the
    last (k = samples, without a control step); `log`, if given, hears the progress every 500."""
    if samples < 1 or not dt > 0:
        raise InvalidArgument(f"run_loop: samples must be >= 1 and dt > 0 (got {samples}, {dt})")
    sensors = Encoders(arm, dt) if sensors is None else sensors
    limit = limit_arrays(arm.model)["tau"][arm.model.actuated]
    x, tau, wrench = np.asarray(x0, float).copy(), None, None
    xs, taus, measured, seconds, wrenches = [x], [], [], [], []
    meas = sensors(x)
    controller.init(meas)
    for k in range(samples):
        if k:
            meas = sensors(x)
        if watch is not None:
            watch(k, k * dt, x, meas, tau, wrench)
        tau = np.clip(np.asarray(controller.step(k, meas), float).ravel(), -limit, limit)
        spent = getattr(controller, "seconds", None)
        if spent is not None:
            seconds.append(spent)
        x, wrench = plant(x, tau, k * dt)
        xs.append(x)
        taus.append(tau)
        measured.append(meas)
        if wrench is not None:
            wrenches.append(wrench)
        if log is not None and (k + 1) % 500 == 0:
            log(f"  {(k + 1) * dt:.2f} of {samples * dt:.2f} s")
    if watch is not None:
        watch(samples, samples * dt, x, sensors(x), tau, wrench)
    return Run(np.arange(samples + 1) * dt, np.array(xs).T, np.array(taus).T, np.array(measured).T,
               np.array(seconds), wrenches)


# ------------------------------------------------------------------ controllers of any arm

class FeedforwardPD:
    """Feedforward torques `ff["tau"][:, k]` (rscasadi.sim.simulation.feedforward), with `gains`
    = (kp, kd, gear_ratio) a motor-position PD around its rotor motion, divided by the gear ratio
    at the motor; gains=None: the feedforward alone."""

    def __init__(self, ff: dict, gains: tuple | None = None):
        self.ff, self.gains = ff, gains

    def init(self, meas) -> None:
        self.n = len(meas) // 4

    def step(self, k: int, meas) -> np.ndarray:
        ff, n = self.ff, self.n
        tau = ff["tau"][:, k].copy()
        if self.gains is not None:
            kp, kd, mu = self.gains
            tau -= (kp * (ff["phi"][:, k] - meas[n:2 * n]) + kd * (ff["dphi"][:, k] - meas[3 * n:])) / mu
        return tau


# ------------------------------------------------------------------ what every study reports

def tracking(t, error) -> dict:
    """The largest error (and when, s) and its RMS over the samples of `error` at times `t`."""
    e = np.asarray(error, float)
    return {"max_error": float(e.max()), "max_error_at_s": float(np.asarray(t)[int(np.argmax(e))]),
            "rms_error": float(np.sqrt(np.mean(e ** 2)))}


def limit_violation(arm: Arm, run: Run) -> float:
    """The largest limit violation over the run's samples after the start (fraction beyond the
    limit; 0 within every limit): deflections, slow-side speeds, link angles (rscasadi.model.limits)."""
    n, nq, x = arm.n, arm.nq, run.x[:, 1:]
    v = violation(arm.model, x[:n], x[n:nq], x[nq + n:], x[nq:nq + n])
    return max(float(v.max()), 0.0) if v.size else 0.0


def step_times(run: Run) -> dict:
    """The controller's median and worst time per step (s), if it timed itself."""
    if not run.seconds.size:
        return {}
    return {"step_median_s": float(np.median(run.seconds)), "step_worst_s": float(np.max(run.seconds))}
