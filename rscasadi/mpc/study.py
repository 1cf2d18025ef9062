"""The closed-loop evidence: the C MPC, feedforward alone and feedforward + PD on a plant that is
not the controllers' model, at 1 kHz with quantised encoders."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from rscasadi.dynamics.arm import Arm, load
from rscasadi.mpc.compiled import CODES, CompiledMPC
from rscasadi.sim.loop import Controller, Encoders, FeedforwardPD, limit_violation, rk4_plant, run_loop, step_times, tracking
from rscasadi.mpc.generate import generate_mpc
from rscasadi.mpc.problem import MPCProblem, mpc_problem
from rscasadi.errors import Failed, InvalidArgument


def heavier_tip(arm: Arm, factor: float = 1.2) -> Arm:
    """The same arm with its last link's mass (and inertia) scaled: the plant of the mismatch study."""
    import dataclasses
    from rscasadi.model.modelfile import Body
    last = arm.model.joints[-1]
    link = Body(last.link.mass * factor, last.link.com, last.link.inertia * factor)
    joints = arm.model.joints[:-1] + (dataclasses.replace(last, link=link),)
    return Arm(dataclasses.replace(arm.model, joints=joints, name=arm.model.name + f"-tip-x{factor:g}"))


class _MPC:
    """The generated C MPC as the loop's controller: `reference(k)` gives the columns of the
    horizon at sample k; `target`, if given, drives it with mpc_step_to instead."""

    def __init__(self, mpc: CompiledMPC, reference=None, target=None):
        self.mpc, self.reference, self.target, self.seconds = mpc, reference, target, None

    def init(self, meas) -> None:
        self.mpc.init(meas)                       # ControllerError if C refuses the state

    def step(self, k: int, meas) -> np.ndarray:
        if self.target is not None:
            tau, self.seconds, flag = self.mpc.step_to(meas, self.target)
        else:
            tau, self.seconds, flag = self.mpc.step(meas, self.reference(k))
        if flag != 0:
            raise Failed(f"mpc_step{'_to' if self.target is not None else ''} returned {CODES.get(flag, flag)} "
                         f"at sample {k}")
        return tau


def reach_pose(problem, mpc_dir, theta_target, seconds: float = 1.0, plant: Arm | None = None, start=None) -> dict:
    """From rest at theta = 0 (or `start`) to a target pose with the C MPC's mpc_step_to, on the problem's arm
    (or `plant`), exact measurements: final angle error and speed, largest limit violation
    (fraction of the limit beyond it), the torques and the time per step."""
    from rscasadi.dynamics.statics import rest_state
    p = mpc_problem(problem)
    arm = load(p.model) if plant is None else plant
    n, dt, target = arm.n, p.sample_time, np.asarray(theta_target, float)
    x0 = rest_state(arm, np.zeros(n) if start is None else np.asarray(start, float))
    run = run_loop(arm, rk4_plant(arm, dt), _MPC(CompiledMPC(mpc_dir), target=target), x0,
                   int(round(seconds / dt)), dt, sensors=Encoders(arm, dt, exact=True))
    x = run.x[:, -1]
    return {"final_angle_error": float(np.max(np.abs(x[:n] - target))), "final_speed": float(np.max(np.abs(x[arm.nq:]))),
            "max_limit_violation": limit_violation(arm, run), "tau": run.tau.T, **step_times(run)}


def closed_loop(problem, mpc_dir, duration: float | None = None, tip_factor: float = 1.2,
                log=print, model=None, plant: Arm | None = None, quantised: bool = True,
                traces: dict | None = None, simulator=rk4_plant) -> dict:
    """Controllers from one model (the problem's, or the model file `model`, e.g. an identified
    one; the C MPC in `mpc_dir` must be generated from it) on a plant that differs (`plant`, by
    default the model with a heavier tip), at 1 kHz, encoders quantised (speeds by backward
    differences; `quantised=False`: the exact state): feedforward alone, feedforward +
    motor-side PD, the C MPC.  `problem`: an `MPCProblem` or the path of its file.  Returns per
    controller the tracking error (max, RMS), the largest limit violation and, for the MPC, its
    time per step (measured in C); `traces`, if given, receives per controller the time, the error
    and the plant's state over time and (MPC) the step times and references, for `plot_closed_loop`
    and the benchmarks.  `simulator(plant, dt)` makes the
    plant's step (rscasadi.sim.loop.rk4_plant; rscasadi.export.mujoco.mujoco_plant: MuJoCo's)."""
    from rscasadi.sim.simulation import feedforward, motor_pd_gains
    from rscasadi.sim.trajectory import load_trajectory
    p = mpc_problem(problem)
    nominal = load(p.model if model is None else model)
    plant = heavier_tip(nominal, tip_factor) if plant is None else plant
    traj = load_trajectory(p.trajectory)
    n, dt = nominal.n, p.sample_time
    K = int(round((traj.duration if duration is None else duration) / dt))
    t = np.arange(K + 1) * dt
    ff = feedforward(nominal, traj, t)
    advance = simulator(plant, dt)
    offsets = p.interval * np.arange(1, p.horizon + 1)

    def horizon(k):
        q, dq = traj(np.minimum(t[k] + offsets, traj.duration))[:2]
        return np.vstack([q, dq])
    pd = (*motor_pd_gains(nominal.model), nominal.model.column("gear_ratio"))
    controllers: dict[str, Controller] = {"feedforward": FeedforwardPD(ff), "feedforward + PD": FeedforwardPD(ff, pd),
                                          "MPC (C)": _MPC(CompiledMPC(mpc_dir), horizon)}
    results: dict[str, dict] = {}
    for name, controller in controllers.items():
        run = run_loop(plant, advance, controller, ff["x0"], K, dt, sensors=Encoders(plant, dt, exact=not quantised))
        e = np.max(np.abs(run.x[:n, 1:] - ff["theta_d"][:, 1:K + 1]), axis=0)
        if traces is not None:
            traces[name] = {"t": t[1:K + 1], "error": e, "step_s": run.seconds, "x": run.x[:, :K].T}
            if name == "MPC (C)":
                traces[name]["reference"] = np.array([horizon(k) for k in range(K)])
        results[name] = {**tracking(t[1:], e), "max_limit_violation": limit_violation(plant, run), **step_times(run)}
        if name == "MPC (C)":                           # its motion, every 10 ms, for rscasadi view
            every = max(1, int(round(0.01 / dt)))
            results[name].update(model=str(p.model if model is None else model), t=t[::every].tolist(),
                                 theta=run.x[:n, ::every].tolist())
        r = results[name]
        log(f"{name:18s} max error {r['max_error']:.2e} rad, RMS {r['rms_error']:.2e} rad, "
            f"limit violation {r['max_limit_violation']:.1e}"
            + (f", step median {r['step_median_s'] * 1e6:.0f} us, worst {r['step_worst_s'] * 1e6:.0f} us"
               if run.seconds.size else ""))
    return results


class FrameReference:
    """Where the controller's frames should be over time, for the task-space study: the problem's
    `[path]` at its speed (one frame, from rest at theta_start; the rotation held at the start's),
    or the frames' motion in an optimal-control `solution` (its link angles and speeds interpolated
    between the nodes).  `columns(times)` gives the MPC's reference columns, a block per frame."""

    def __init__(self, p: MPCProblem, arm: Arm, samples: int = 2000):
        self.p, self.arm = p, arm
        if p.tool_path is not None:
            self.theta_start, self.duration = np.asarray(p.theta_start, float), p.tool_path.duration
            self.R0 = np.array(arm.frame_placement(p.frames[0])(self.theta_start)[0])
            return
        import json
        sol = json.loads(Path(p.solution).read_text())
        t = np.asarray(sol["t"], float)
        theta, dtheta = np.asarray(sol["theta"], float), np.asarray(sol["dtheta"], float)
        self.theta_start, self.duration = theta[:, 0], float(t[-1])
        self.tt = np.linspace(0.0, t[-1], samples)
        th = np.vstack([np.interp(self.tt, t, row) for row in theta])
        dth = np.vstack([np.interp(self.tt, t, row) for row in dtheta])
        from rscasadi.task.toolpath import ToolPath
        self.P, self.V, self.R, self.curves = [], [], [], []       # per frame
        for frame in p.frames:
            R, P = arm.frame_placement(frame).map(samples)(th)
            J = np.array(arm.frame_jacobian(frame, "local_world_aligned").map(samples)(th)).reshape(
                6, samples, arm.n, order="F")
            self.P.append(np.array(P).T)
            self.V.append(np.einsum("ksj,js->sk", J[:3], dth))
            self.R.append(np.array(R).reshape(3, samples, 3, order="F").transpose(1, 0, 2))   # R[s] (3 x 3)
            self.curves.append(ToolPath(frame, self.P[-1]))              # the frame's curve, for distances

    def position(self, t) -> np.ndarray:
        """The frames' reference positions at the times t (frames x len(t) x 3)."""
        if self.p.tool_path is not None:
            return self.p.tool_path(t)[None]
        return np.stack([np.column_stack([np.interp(t, self.tt, P[:, i]) for i in range(3)]) for P in self.P])

    def columns(self, times) -> np.ndarray:
        """The reference columns at `times`: per frame p, v (central differences of a path's
        timing law, 0.1 ms) and, with orientation, vec(R)."""
        times = np.atleast_1d(np.asarray(times, float))
        position = self.position(times)
        if self.p.tool_path is not None:
            eps = 1e-4
            vs = [(self.position(times + eps)[0] - self.position(times - eps)[0]) / (2 * eps)]
            Rs = [np.repeat(self.R0.ravel("F")[None, :], len(times), axis=0)]
        else:
            vs = [np.column_stack([np.interp(times, self.tt, V[:, i]) for i in range(3)]) for V in self.V]
            Rs = [np.column_stack([np.interp(times, self.tt, R[:, i % 3, i // 3]) for i in range(9)]) for R in self.R]
        return np.vstack([block for P, v, R in zip(position, vs, Rs)
                          for block in [P.T, v.T] + ([R.T] if self.p.orientation else [])])

    def distance(self, points) -> float:
        """How far the frames (`points`, frames x 3) are from their reference curves: the largest."""
        curves = [self.p.tool_path] if self.p.tool_path is not None else self.curves
        return max(float(c.distance(np.asarray(q)[None, :])[0]) for c, q in zip(curves, np.atleast_2d(points)))


def task_closed_loop(problem, mpc_dir, plant_mass: float | None = None, told: bool = False, settle: float = 0.2,
                     quantised: bool = True, log=print, label: str | None = None, traces: dict | None = None) -> dict:
    """The task-space MPC (its problem's `[path]` from rest at theta_start, or the frames' motion in
    its `solution`) on the arm holding a payload of `plant_mass` kg (None: the problem's), at the
    problem's sample rate with quantised encoders: `told`, the controller is given that mass
    (mpc_set_payload_mass), else it keeps the problem's.  The arm holds the start for `settle` s,
    then the reference runs and the arm holds its end for 0.2 s.  Returns the frames' largest and
    RMS distance from the reference point of its time (the farthest frame's at each sample), the
    largest distance from a reference curve, the final error, the largest limit violation, the smallest clearance to the obstacles
    (exact) and the time per step in C; `trace` every 10 ms (the error, the step time); `label`
    names the case in the log line; `traces`, if given, receives the plant's state "x" and the
    reference's columns "reference" at every sample (for the benchmarks)."""
    from rscasadi.dynamics.collision import exact_clearance
    from rscasadi.dynamics.statics import rest_state
    from rscasadi.model.frames import holding
    from rscasadi.mpc.problem import mpc_model
    p = mpc_problem(problem)
    if not p.task_space or (p.tool_path is None and p.solution is None):
        raise InvalidArgument(f"{p.path}: task_closed_loop needs a frame, and a [path] or a solution")
    model = mpc_model(p)
    plant = Arm(model if plant_mass is None else holding(model, mass=plant_mass))
    reference = FrameReference(p, plant)
    dt, n = p.sample_time, plant.n
    places = [plant.frame_placement(f) for f in p.frames]
    clearance = exact_clearance(plant.model, p.obstacles) if p.obstacles else None
    mpc = CompiledMPC(mpc_dir)
    K = int(round((settle + reference.duration + 0.2) / dt))
    offsets = p.interval * np.arange(1, p.horizon + 1)
    clock = lambda k: k * dt - settle                      # the reference's clock (< 0: holding its start)
    errors, off_path, gaps = [], [], []

    def watch(k, t, x, meas, tau, wrench):
        if k == 0:
            if told and mpc.set_payload_mass(plant.model.payload.body.mass) != 0:
                raise InvalidArgument(f"{p.path}: the controller's model holds no payload to be told of")
            return
        where = np.array([np.array(place(x[:n])[1]).ravel() for place in places])
        goal = reference.position(np.clip([clock(k)], 0.0, reference.duration))[:, 0]
        errors.append(float(np.max(np.linalg.norm(where - goal, axis=1))))
        off_path.append(reference.distance(where))
        gaps.append(float(clearance(x[:n])) if clearance is not None else np.inf)

    controller = _MPC(mpc, lambda k: reference.columns(np.clip(clock(k) + offsets, 0.0, reference.duration)))
    run = run_loop(plant, rk4_plant(plant, dt), controller, rest_state(plant, reference.theta_start), K, dt,
                   sensors=Encoders(plant, dt, exact=not quantised), watch=watch, log=log)
    if traces is not None:
        traces.update(x=run.x[:, :K].T, reference=np.array([controller.reference(k) for k in range(K)]))
    every = max(1, int(round(0.01 / dt)))
    times, violation, thetas = run.seconds, limit_violation(plant, run), run.x[:n, ::every].T
    gap = min(gaps) if clearance is not None else np.inf
    gap_at = clock(1 + int(np.argmin(gaps))) if clearance is not None else None
    e = np.array(errors)
    res = {"plant_mass": float(plant.model.payload.body.mass) if plant.model.payload else 0.0,
           "told": told, "max_error": float(e.max()), "rms_error": float(np.sqrt(np.mean(e ** 2))),
           "max_path_distance": float(np.max(off_path)), "final_error": float(e[-1]),
           "max_limit_violation": max(violation, 0.0), "min_clearance": None if clearance is None else gap,
           "min_clearance_at_s": gap_at,
           "step_median_s": float(np.median(times)), "step_worst_s": float(np.max(times)),
           "model": str(p.model), "t": (np.arange(len(thetas)) * every * dt).tolist(), "theta": np.array(thetas).T.tolist(),
           "trace": {"t": ((np.arange(len(e)) + 1) * dt - settle)[every - 1::every].tolist(),
                     "error": e[every - 1::every].tolist(), "step_s": np.asarray(times)[every - 1::every].tolist()}}
    if label is None:
        label = f"payload {res['plant_mass']:.2f} kg, {'told' if told else 'not told'}"
    log(f"{label}: {'the frame' if len(p.frames) == 1 else 'the frames'} within "
        f"{res['max_error'] * 1e3:.2f} mm of its reference (RMS {res['rms_error'] * 1e3:.2f} mm), "
        f"{res['max_path_distance'] * 1e3:.2f} mm of its curve, {res['final_error'] * 1e3:.2f} mm at the end, "
        f"limit violation {res['max_limit_violation']:.1e}"
        + (f", clearance >= {gap * 1e3:.1f} mm (at {gap_at:.3f} s)" if clearance is not None else "")
        + f"; step median {res['step_median_s'] * 1e6:.0f} us")
    return res


def task_study(problem, mpc_dir, plant_mass: float | None = None, log=print) -> dict:
    """The task-space closed loop (task_closed_loop) three times: the arm holding the problem's
    payload; holding `plant_mass` kg (default: the solution's payload, else ten times the
    problem's) that the controller is not told; and the same, told (mpc_set_payload_mass).
    The C MPC must be in `mpc_dir`."""
    import json
    from rscasadi.mpc.problem import mpc_model
    p = mpc_problem(problem)
    model = mpc_model(p)
    if model.payload is None:
        raise InvalidArgument(f"{p.path}: the task-space study changes the payload: give the problem a payload")
    if plant_mass is None and p.solution is not None:
        held = json.loads(Path(p.solution).read_text()).get("payload") or {}
        plant_mass = held.get("mass")
    plant_mass = 10 * model.payload.body.mass if plant_mass is None else plant_mass
    out = {"path": None if p.tool_path is None else p.tool_path.to_dict(),
           "obstacles": [o.to_dict() for o in p.obstacles]}
    from rscasadi.model.frames import holding, payload_document
    modelled = model.payload.body.mass
    cases: list[tuple[str, float | None, bool, str]] = [
        ("as_modelled", None, False, f"as modelled (payload {modelled:.2f} kg)")]
    if abs(plant_mass - modelled) > 1e-9 * max(1.0, modelled):
        cases += [("untold_payload", plant_mass, False, f"payload {plant_mass:.2f} kg, not told"),
                  ("told_payload", plant_mass, True, f"payload {plant_mass:.2f} kg, told")]
    else:
        log(f"the plant's payload ({plant_mass:.2f} kg) is the modelled one: the untold and told cases would "
            "repeat the first; give another mass (rscasadi mpc --plant-payload) to see one the model lacks")
    for case, mass, told, label in cases:
        run = task_closed_loop(p, mpc_dir, mass, told, log=log, label=label)
        run["payload"] = payload_document(holding(model, mass=run["plant_mass"]))
        run["label"] = label
        out[case] = {"MPC (C)": run}
    return out


def plot_task_study(res: dict, path: Path):
    """The task-space study's cases: the frame's distance from its reference over time, and the C
    MPC's time per step against the sample time's budget of 1 ms."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    runs = {k: v["MPC (C)"] for k, v in res.items() if isinstance(v, dict) and "MPC (C)" in v}
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    for case, run in runs.items():
        tr = run["trace"]
        axes[0].plot(tr["t"], 1e3 * np.asarray(tr["error"]), lw=1, label=run.get("label", case))
        axes[1].plot(tr["t"], 1e6 * np.asarray(tr["step_s"]), ".", ms=2, label=run.get("label", case))
    axes[0].axvline(0.0, color="0.6", lw=0.8)
    axes[0].set(xlabel="t (s; the reference starts at 0)", ylabel="frame's distance from its reference (mm)",
                title="task-space MPC, quantised encoders")
    axes[1].axhline(1000.0, color="r", lw=1, label="1 ms (1 kHz)")
    axes[1].set(xlabel="t (s)", ylabel="mpc_step in C (us)", title="time per step (every 10th)")
    for ax in axes:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def study(problem, build, identified_model=None, true_arm: Arm | None = None, log=print,
          figure: Path | None = None) -> dict:
    """The closed-loop evidence, whole trajectory: the problem's model against a 20 % heavier tip;
    if given, the identified model's controllers (MPC generated into `build`) against the true arm
    that produced the identification logs.  `figure`: where to draw them (plot_closed_loop)."""
    build = Path(build)
    res: dict = {}
    traces: dict = {}
    log("closed loop: the model's controllers on a plant with a 20 % heavier tip, quantised encoders")
    generate_mpc(problem, build / "mpc", log=log)
    res["heavier_tip"] = closed_loop(problem, build / "mpc", log=log, traces=traces.setdefault("heavier_tip", {}))
    if identified_model is not None:
        log("closed loop: the identified model's controllers on the true arm, quantised encoders")
        generate_mpc(problem, build / "mpc_identified", log=log, model=identified_model)
        res["identified_on_true_arm"] = closed_loop(problem, build / "mpc_identified", log=log,
                                                    model=identified_model, plant=true_arm,
                                                    traces=traces.setdefault("identified_on_true_arm", {}))
    if figure is not None:
        plot_closed_loop(traces, figure)
        log(f"wrote {figure}")
    return res


CASES = {"heavier_tip": "controllers' model, plant with a 20 % heavier tip",
         "identified_on_true_arm": "identified model, true arm"}


def plot_closed_loop(traces: dict, path: Path):
    """Per case (a column): the tracking error of each controller over time (log scale), and the
    C MPC's time per step against the 1 ms budget of 1 kHz."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(2, len(traces), figsize=(6 * len(traces), 6.5), squeeze=False)
    for col, (case, ctrl) in enumerate(traces.items()):
        ax = axes[0, col]
        for name, tr in ctrl.items():
            ax.semilogy(tr["t"], np.maximum(tr["error"], 1e-9), label=name, lw=1)
        ax.set(title=CASES.get(case, case), xlabel="t (s)", ylabel="max |theta - theta_d| (rad)")
        ax.legend(fontsize=8)
        ax = axes[1, col]
        steps = ctrl["MPC (C)"]["step_s"] * 1e6
        ax.plot(ctrl["MPC (C)"]["t"], steps, ".", ms=1.5)
        ax.axhline(1000.0, color="r", lw=1, label="1 ms (1 kHz)")
        ax.set(xlabel="t (s)", ylabel="mpc_step in C (us)", ylim=(0, max(1100.0, steps.max() * 1.05)),
               title=f"median {np.median(steps):.0f} us, worst {steps.max():.0f} us")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
