"""Synthetic logs: a *different* arm than the nominal one, driven along a trajectory by a
feedback controller, measured by realistic sensors.  For honest tests of the identification.

The true arm is the nominal one with every physical parameter perturbed by 10-40 % (masses,
centres of mass, inertias, springs, dampers, gear losses), a cubic spring term and Coulomb
loss added.  Control at 1 kHz: the nominal model's feedforward (the paper's pipeline) plus a
motor-side PD on the measured slow-side angle.  Sensors: link encoder 2^19 counts/turn, motor
encoder 2^17 counts/turn before the gear, motor-torque noise 0.5 % of its limit.  The loop is
rscasadi.sim.loop's (RK4 at 4 substeps per sample, or MuJoCo's plant of the exported arm).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from rscasadi.sim.loop import Encoders, FeedforwardPD, rk4_plant, run_loop
from rscasadi.sim.simulation import feedforward, motor_pd_gains
from rscasadi.dynamics.arm import Arm
from rscasadi.dynamics.statics import spring_torque
from rscasadi.model.modelfile import Body, inertia_problem
from rscasadi.identification.logs import Log
from rscasadi.errors import Failed, InvalidArgument



def _factor(rng, lo=0.1, hi=0.4):
    return 1.0 + rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi)


def _perturbed_body(body: Body, rng, balanced: bool) -> Body:
    for _ in range(100):
        m = body.mass * _factor(rng)
        if balanced:
            com = body.com * np.array([0.0, 0.0, 1.0])
            s = _factor(rng)
            I = np.diag([body.inertia[0, 0] * s, body.inertia[0, 0] * s, body.inertia[2, 2] * _factor(rng)])
        else:
            scale = max(np.linalg.norm(body.com), 0.02)
            com = body.com + rng.choice([-1.0, 1.0], 3) * rng.uniform(0.1, 0.4, 3) * scale
            I = body.inertia * np.outer(*(2 * [np.sqrt([_factor(rng) for _ in range(3)])]))
        if inertia_problem(I) is None:
            return Body(m, com, I)
    raise Failed("could not perturb a body into a physical one")


def perturbed_arm(arm: Arm, rng, k3_fraction: float = 0.2, coulomb: float = 0.5) -> Arm:
    """A different arm with the same joints: every physical parameter off by 10-40 %, plus a
    cubic spring (k3 psi^3 = k3_fraction k1 psi at psi = limit/2) and Coulomb loss c."""
    joints = []
    for jt in arm.model.joints:
        psi_ref = jt.limits.get("psi", 0.1) / 2
        joints.append(dataclasses.replace(
            jt, link=_perturbed_body(jt.link, rng, False),
            slow_rotor=_perturbed_body(jt.slow_rotor, rng, jt.slow_rotor.balanced),
            fast_rotor=_perturbed_body(jt.fast_rotor, rng, jt.fast_rotor.balanced),
            k1=jt.k1 * _factor(rng), d=jt.d * _factor(rng), b=jt.b * _factor(rng),
            k3=jt.k1 * k3_fraction / psi_ref ** 2 * _factor(rng), c=coulomb * _factor(rng)))
    return Arm(dataclasses.replace(arm.model, joints=tuple(joints), name=arm.model.name + "-true",
                                   path=arm.model.path + " (perturbed)"))


SENSOR_NOISE = {"T": 0.005, "dtheta": 1e-3, "dphi": 1e-3}   # a torque sensor: of the largest |T|; speeds: rad/s


def record(true_arm: Arm, nominal_arm: Arm, trajectory, rate: float = 1000.0, rng=None,
           torque_noise: float = 0.005, substeps: int = 4, ff_step: float = 0.002, plant=None,
           columns=("theta", "phi", "tau"), every: int = 1, offsets: dict | None = None,
           delays: dict | None = None) -> tuple[Log, dict]:
    """Drive the true arm along `trajectory` (nominal feedforward + motor-side PD) and log what its
    sensors see: the one closed loop (rscasadi.sim.loop) on `plant` (default: `substeps` RK4 steps
    of the true arm's complete model per sample; e.g. rscasadi.export.mujoco.mujoco_plant(true_arm,
    dt)), quantised encoders, the applied torques (within the limits) logged with noise of
    `torque_noise` times each limit.  `columns`: the groups logged (rscasadi.identification.logs:
    T the true spring torque with noise of SENSOR_NOISE["T"] of its largest magnitude, speeds the
    true ones with SENSOR_NOISE's noise); `every`: one logged sample per `every` control steps;
    `offsets` {group: per-joint values} added to what a sensor reads (a torque sensor's zero);
    `delays` {group: seconds} by which a sensor's samples lag (its latency, whole control steps).
    Returns the log and the true state history {t, x, tau_applied}."""
    rng = np.random.default_rng(0) if rng is None else rng
    n, dt = true_arm.n, 1.0 / rate
    N = int(round(trajectory.duration * rate)) + 1
    t = np.arange(N) * dt
    t_ff = np.arange(int(np.ceil(trajectory.duration / ff_step)) + 1) * ff_step
    ff = feedforward(nominal_arm, trajectory, t_ff)
    interp = lambda Y: np.vstack([np.interp(t, t_ff, row) for row in Y])
    reference = {"tau": interp(ff["tau"]), "phi": interp(ff["phi"]), "dphi": interp(ff["dphi"])}
    kp, kd = motor_pd_gains(nominal_arm.model)                       # a 4 Hz motor-position loop
    controller = FeedforwardPD(reference, (kp, kd, nominal_arm.model.column("gear_ratio")))
    plant = rk4_plant(true_arm, dt, substeps) if plant is None else plant
    x0 = np.asarray(ff["x0"], float)                                 # nominal static equilibrium
    run = run_loop(true_arm, plant, controller, x0, N, dt, sensors=Encoders(true_arm, dt))
    limits = np.array([jt.limits.get("tau", np.max(np.abs(run.tau), initial=1.0)) for jt in true_arm.model.joints])
    tau_logged = run.tau + rng.normal(0, 1, run.tau.shape) * (torque_noise * limits)[:, None]
    x = run.x[:, :N]
    T = spring_torque(true_arm.model, x[:n], x[n:2 * n], x[2 * n:3 * n], x[3 * n:])
    noisy = lambda v, s: v + rng.normal(0, 1, v.shape) * s
    measured = {"theta": run.meas[:n], "phi": run.meas[n:2 * n], "tau": tau_logged,
                "T": noisy(T, SENSOR_NOISE["T"] * np.max(np.abs(T), axis=1, keepdims=True)),
                "dtheta": noisy(x[2 * n:3 * n], SENSOR_NOISE["dtheta"]), "dphi": noisy(x[3 * n:], SENSOR_NOISE["dphi"])}
    if "i" in columns:               # motor currents: tau / kt, the true motors' (simulate checks kt is given)
        motors = true_arm if all(jt.torque_constant for jt in true_arm.model.joints) else nominal_arm
        measured["i"] = tau_logged / np.array([jt.torque_constant for jt in motors.model.joints])[:, None]
    for g, value in (offsets or {}).items():
        measured[g] = measured[g] + np.asarray(value, float)[:, None]
    for g, lag in (delays or {}).items():
        k = int(round(lag / dt))
        measured[g] = np.hstack([np.repeat(measured[g][:, :1], k, axis=1), measured[g][:, :measured[g].shape[1] - k]])
    pick = slice(None, None, every)
    log = Log("<synthetic>", t[pick], **{g: measured[g][:, pick] for g in columns})
    return log, {"t": t, "x": x, "tau": run.tau}


def simulate_log(model, trajectory, out, rate: float = 1000.0, noise: float = 0.005, perturb: int | None = None,
                 true_model=None, simulator: str = "rscasadi", columns="theta,phi,tau", log_rate: float | None = None,
                 log=print) -> Path:
    """`rscasadi simulate`: the log (docs/user-guide/logs.md's format) that the arm of
    `model`, or with `perturb` (a seed) a different arm of its family (every parameter off by
    10-40 %, a cubic spring and Coulomb loss added: perturbed_arm), records along `trajectory`
    (a trajectory file: rscasadi excite's, or a start-amplitude file) under the nominal
    feedforward and a motor-side PD, with torque noise of `noise` times each torque limit; the
    true arm's model file into `true_model` if given.  `simulator` "mujoco": the true arm
    exported to MuJoCo (rscasadi.export.mujoco) is the plant, at its 1 ms RK4 step; a perturbed
    arm then keeps linear springs and no Coulomb loss (what MJCF holds).  `columns`: the sensors
    logged (comma-separated groups, checked as a log's header is); `log_rate`: the log's sample
    rate, a divisor of the loop's `rate`."""
    import time
    from rscasadi.dynamics.arm import load
    from rscasadi.files import check_output_file, write_text
    from rscasadi.identification.logs import write_log
    from rscasadi.model.modelfile import document, to_toml
    from rscasadi.sim.trajectory import load_trajectory
    out = Path(out)
    for target in [out] + ([Path(true_model)] if true_model else []):
        check_output_file(target)
    if not (rate > 0 and np.isfinite(rate)) or not (noise >= 0 and np.isfinite(noise)):
        raise InvalidArgument(f"simulate: --rate {rate!r} must be > 0 and --noise {noise!r} >= 0")
    nominal = load(model)
    traj = load_trajectory(trajectory)
    if traj.n != nominal.n:
        raise InvalidArgument(f"{trajectory}: {traj.n} joints, the model {model} has {nominal.n}")
    groups = tuple(g.strip() for g in str(columns).split(",") if g.strip())
    from rscasadi.identification.logs import LogError, column_groups
    try:
        column_groups("simulate --columns", ["t"] + [f"{g}_{j}" for g in groups for j in range(1, nominal.n + 1)],
                   nominal.n)
    except LogError as exc:
        raise InvalidArgument(str(exc).replace("header: ", "")) from None
    lacking = [jt.name for jt in nominal.model.joints if jt.torque_constant is None]
    if "i" in groups and lacking:
        raise InvalidArgument(f"simulate --columns: motor currents (i) need each joint's torque_constant in {model}: "
                              f"none for {', '.join(lacking)}")
    every = int(round(rate / log_rate)) if log_rate else 1
    if log_rate and (every < 1 or abs(every * log_rate - rate) > 1e-9 * rate):
        raise InvalidArgument(f"simulate: --log-rate {log_rate:g} must divide --rate {rate:g}")
    if simulator not in ("rscasadi", "mujoco"):
        raise InvalidArgument(f"simulate: --simulator must be rscasadi or mujoco, got {simulator!r}")
    rng = np.random.default_rng(0 if perturb is None else perturb)
    mujoco = simulator == "mujoco"
    true = nominal if perturb is None else perturbed_arm(nominal, rng, *((0.0, 0.0) if mujoco else ()))
    plant = None
    if mujoco:
        from rscasadi.export.mujoco import mujoco_plant
        plant = mujoco_plant(true, 1.0 / rate)                    # refuses what MJCF cannot hold, by name
    log(f"simulating {true.model.name} along {Path(trajectory).name}: {traj.duration:g} s at {rate:g} Hz "
        f"({'MuJoCo, the arm exported' if mujoco else 'the complete model, RK4'}) ...")
    t0 = time.perf_counter()
    lg, _ = record(true, nominal, traj, rate=rate, rng=rng, torque_noise=noise, plant=plant, columns=groups,
                   every=every)
    write_log(out, lg)
    if true_model:
        write_text(true_model, f"# the arm that recorded {out.name} (rscasadi simulate --perturb {perturb})\n"
                   + to_toml(document(true.model)))
    log(f"wrote {out} ({lg.t.size} samples, {time.perf_counter() - t0:.1f} s)"
        + (f" and {true_model}" if true_model else ""))
    return out
