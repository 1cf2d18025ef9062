"""`rscasadi paper`: the paper's simulation (section IV, Figs. 5-11) rebuilt, plus the cascade's
accuracy and a sweep of what makes rotor separation matter.

Feedforward torques from (a) the rotor-separated (complete) model and (b) the DLR/Spong
reduced model are applied open loop to the complete model; the tracking errors are compared.
Everything is written to a temporary directory and moved into place at the end, so a failed
run leaves no half-written results.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from rscasadi.dynamics.arm import Arm, load  # noqa: E402
from rscasadi.files import fresh_directory, write_json  # noqa: E402
from rscasadi.sim.simulation import cascade_simulate, feedforward, simulate, simulate_held  # noqa: E402
from rscasadi.sim.trajectory import Trajectory, load_trajectory  # noqa: E402
from rscasadi.errors import Failed, InvalidArgument

METHODS = {"rotor_separated": False, "dlr": True}       # name -> reduced model for the feedforward
LABELS = {"rotor_separated": "rotor-separated (this paper)", "dlr": "DLR / Spong reduced",
          "ocp_tracking": "tracking OCP (complete model)"}


def tracking(arm: Arm, traj: Trajectory, t, reduced: bool) -> tuple[dict, dict]:
    """Feedforward from one model, applied open loop to the complete model."""
    ff = feedforward(arm, traj, t, reduced=reduced)
    sim = simulate(arm, ff["x0"], t, ff["tau"], method="cvodes", tol=1e-10)
    return ff, sim


def errors(sim, theta_d) -> dict:
    """Per joint the largest and the RMS tracking error of a simulation (rad)."""
    e = sim["theta"] - theta_d
    return {"max_error": np.max(np.abs(e), axis=1).tolist(), "rms_error": np.sqrt(np.mean(e ** 2, axis=1)).tolist()}


def _save(fig, out: Path, stem: str):
    for ext in ("png", "pdf"):
        fig.savefig(out / f"{stem}.{ext}", dpi=130)
    plt.close(fig)


def figures(out: Path, arm: Arm, t, theta_d, sims: dict):
    """The paper's figures 5-11: the expected motion and each joint's tracking under each feedforward."""
    names = [jt.name for jt in arm.model.joints]
    fig, ax = plt.subplots(figsize=(7, 4))
    for j, name in enumerate(names):
        ax.plot(t, theta_d[j], label=f"joint {j + 1} ({name})")
    ax.set(xlabel="t (s)", ylabel="theta_d (rad)", title="Fig. 5: expected trajectories of the joints")
    ax.legend()
    _save(fig, out, "fig05_expected_trajectories")
    for j, name in enumerate(names):                      # Figs. 6-8: actual against expected
        fig, ax = plt.subplots(figsize=(7, 4))
        ax.plot(t, theta_d[j], "k-", lw=2.5, alpha=0.35, label="expected")
        for m, sim in sims.items():
            ax.plot(t, sim["theta"][j], {"dlr": "--", "ocp_tracking": ":"}.get(m, "-"), label=LABELS[m])
        ax.set(xlabel="t (s)", ylabel="theta (rad)", title=f"Fig. {6 + j}: joint {j + 1} ({name}), actual vs expected")
        ax.legend()
        _save(fig, out, f"fig{6 + j:02d}_joint{j + 1}_trajectory")
    for j, name in enumerate(names):                      # Figs. 9-11: tracking errors
        fig, ax = plt.subplots(figsize=(7, 4))
        for m, sim in sims.items():
            ax.plot(t, sim["theta"][j] - theta_d[j], {"dlr": "--", "ocp_tracking": ":"}.get(m, "-"), label=LABELS[m])
        ax.set(xlabel="t (s)", ylabel="theta - theta_d (rad)", title=f"Fig. {9 + j}: tracking error of joint {j + 1} ({name})")
        ax.legend()
        _save(fig, out, f"fig{9 + j:02d}_joint{j + 1}_error")


def tables(out: Path, model_file: str, results: dict, n: int):
    """tracking.json, .csv and .md: the errors of each feedforward method per joint."""
    write_json(out / "tracking.json", {"model": model_file, "methods": results}, indent=2)
    rows = ["method,joint,max_error_rad,rms_error_rad"]
    md = ["| method | joint | max error (rad) | RMS error (rad) |", "|---|---|---|---|"]
    for m, r in results.items():
        for j in range(n):
            rows.append(f"{m},{j + 1},{r['max_error'][j]:.6e},{r['rms_error'][j]:.6e}")
            md.append(f"| {LABELS[m]} | {j + 1} | {r['max_error'][j]:.3e} | {r['rms_error'][j]:.3e} |")
    (out / "tracking.csv").write_text("\n".join(rows) + "\n")
    (out / "tracking.md").write_text("\n".join(md) + "\n")


def cascade_study(out: Path, arm: Arm, traj: Trajectory, log):
    """Distance of the paper's cascade (ABM4 PECE) from the exact simulation, against step size."""
    t = np.linspace(0.0, 0.5, 126)                         # 4 ms samples of the torque
    ff = feedforward(arm, traj, t)
    exact = simulate(arm, ff["x0"], t, ff["tau"], method="cvodes", tol=1e-12)
    rows = []
    for h in (4e-3, 2e-3, 1e-3, 5e-4, 2.5e-4):
        cs = cascade_simulate(arm, ff["x0"], t, ff["tau"], h)
        rows.append((h, float(np.max(np.abs(cs["theta"] - exact["theta"]))),
                     float(np.max(np.abs(cs["phi"] - exact["phi"])))))
        log(f"  cascade h = {h * 1e3:.2f} ms: max |theta - exact| = {rows[-1][1]:.2e} rad")
    (out / "cascade_convergence.csv").write_text(
        "h_s,max_theta_error_rad,max_phi_error_rad\n" + "".join(f"{h},{a:.6e},{b:.6e}\n" for h, a, b in rows))
    fig, ax = plt.subplots(figsize=(6, 4))
    hs = np.array([r[0] for r in rows])
    ax.loglog(hs * 1e3, [r[1] for r in rows], "o-", label="max |theta - exact|")
    ax.loglog(hs * 1e3, rows[-1][1] * (hs / hs[-1]) ** 2, "k:", label="~ h^2")
    ax.set(xlabel="step h (ms)", ylabel="rad", title="paper's cascade (ABM4 PECE) vs exact simulation, 0.5 s")
    ax.legend()
    _save(fig, out, "cascade_convergence")
    return rows


def _variant(arm: Arm, name: str, **change) -> Arm:
    """The arm with every joint changed by `change`: gear scale, fast-rotor inertia scale, tilt."""
    joints = []
    for j, jt in enumerate(arm.model.joints):
        new = {}
        if "gear" in change:
            new["gear_ratio"] = jt.gear_ratio * change["gear"]
        if "fast_inertia" in change:
            fr = jt.fast_rotor
            new["fast_rotor"] = dataclasses.replace(fr, inertia=fr.inertia * change["fast_inertia"])
        if "tilt" in change and j > 0:                     # axes neither parallel nor perpendicular
            new["origin_rpy"] = jt.origin_rpy + np.array([0.0, change["tilt"], 0.0])
        joints.append(dataclasses.replace(jt, **new))
    return Arm(dataclasses.replace(arm.model, joints=tuple(joints), name=name))


def sweep(out: Path, arm: Arm, traj: Trajectory, log):
    """DLR feedforward tracking error against what drives the rotor coupling."""
    t_of = lambda period: np.linspace(0.0, period, int(round(period / 2e-3)) + 1)
    cases = {
        "gear ratio scale": [(s, _variant(arm, f"gear x{s}", gear=s), traj) for s in (0.5, 1, 2, 4)],
        "fast-rotor inertia scale": [(s, _variant(arm, f"Izz(F) x{s}", fast_inertia=s), traj) for s in (0.5, 1, 2, 4)],
        "motion speed (1 / period, 1/s)": [
            (1 / p, arm, dataclasses.replace(traj, period=p, duration=p)) for p in (4.0, 2.0, 1.0, 0.5)],
        "axis tilt (rad)": [(a, _variant(arm, f"tilt {a}", tilt=a), traj) for a in (0.0, 0.2, 0.4, 0.8)],
    }
    result: dict = {}
    for what, points in cases.items():
        result[what] = []
        for value, variant, tr in points:
            t = t_of(tr.period)
            runs = {m: tracking(variant, tr, t, red) for m, red in METHODS.items()}
            e = {m: errors(sim, tr(t)[0])["max_error"] for m, (_, sim) in runs.items()}
            tau_c, tau_r = runs["rotor_separated"][0]["tau"], runs["dlr"][0]["tau"]
            dtau = float(np.max(np.abs(tau_r - tau_c)) / np.max(np.abs(tau_c)))   # drift-free measure
            result[what].append({"value": value, **e, "torque_difference": dtau})
            log(f"  {what} = {value:g}: max tracking error DLR {max(e['dlr']):.2e} rad, "
                f"rotor-separated {max(e['rotor_separated']):.2e} rad; DLR torque off by {100 * dtau:.2f} %")
    write_json(out / "sweep.json", result, indent=2)
    fig, axes = plt.subplots(2, 4, figsize=(15, 7), sharey="row")
    for k, (what, pts) in enumerate(result.items()):
        x = [p["value"] for p in pts]
        for m in METHODS:
            axes[0, k].semilogy(x, [max(p[m]) for p in pts], "o-" if m == "dlr" else "s--", label=LABELS[m])
        axes[1, k].plot(x, [100 * p["torque_difference"] for p in pts], "o-", color="C1")
        axes[0, k].set(title=what)
        axes[1, k].set(xlabel=what)
    axes[0, 0].set_ylabel("max tracking error, open loop (rad)")
    axes[1, 0].set_ylabel("max |tau_DLR - tau_RS| / max |tau_RS| (%)")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    _save(fig, out, "sweep_dlr_error")
    return result


def ocp_method(problem_file, arm: Arm, t, log):
    """(c): the torques of the tracking OCP (piecewise constant), replayed on the complete model
    at the paper's sample times."""
    from rscasadi.ocp import load_problem, solve
    sol = solve(load_problem(problem_file), print_level=0, log=log)
    if not sol["success"]:
        raise Failed(f"the tracking OCP {problem_file} failed: {sol['status']}")
    t_ocp, tau = np.asarray(sol["t"]), np.asarray(sol["tau"])
    substeps = int(round((t_ocp[1] - t_ocp[0]) / (t[1] - t[0])))
    x0 = np.concatenate([np.asarray(sol[k])[:, 0] for k in ("theta", "phi", "dtheta", "dphi")])
    full = simulate_held(arm, x0, t_ocp, tau, substeps)
    if len(full["t"]) < len(t) or not np.allclose(full["t"][:len(t)], t, rtol=0, atol=1e-9):
        raise InvalidArgument(f"the tracking OCP's grid ({t_ocp[1] - t_ocp[0]} s steps up to {t_ocp[-1]} s) "
                         f"does not contain the paper's sample times")
    sim = {k: (v[..., :len(t)] if isinstance(v, np.ndarray) and v.shape[-1] == len(full["t"]) else v)
           for k, v in full.items()}
    return {"t": t_ocp.tolist(), "tau": tau.tolist(), "interpolation": "constant"}, sim


def run(trajectory_file, out, duration: float | None = None, sweeps: bool = True, log=print,
        ocp_problem=None) -> dict:
    """The paper's simulation into out: each feedforward method on the complete model, its
    figures and tables, and (with sweeps) where rotor separation matters."""
    t0 = time.perf_counter()
    traj = load_trajectory(trajectory_file)
    arm = load(traj.model_path)
    duration = duration or traj.duration
    t = np.linspace(0.0, duration, int(round(duration * 1000)) + 1)      # 1 kHz torque samples
    with fresh_directory(out) as tmp:
        log(f"[{time.perf_counter() - t0:5.1f} s] feedforward and open-loop simulation ({len(t)} samples)")
        ffs, sims, results = {}, {}, {}
        for m, red in METHODS.items():
            ffs[m], sims[m] = tracking(arm, traj, t, red)
            results[m] = errors(sims[m], ffs[m]["theta_d"])
            log(f"  {LABELS[m]}: max error per joint {np.round(results[m]['max_error'], 7).tolist()} rad")
        theta_d = ffs["rotor_separated"]["theta_d"]
        tau_ocp = None
        if ocp_problem is not None:
            log(f"[{time.perf_counter() - t0:5.1f} s] (c) the tracking OCP's torques ({ocp_problem})")
            tau_ocp, sims["ocp_tracking"] = ocp_method(ocp_problem, arm, t, log)
            results["ocp_tracking"] = errors(sims["ocp_tracking"], theta_d)
            log(f"  {LABELS['ocp_tracking']}: max error per joint "
                f"{np.round(results['ocp_tracking']['max_error'], 7).tolist()} rad")
        tables(tmp, str(traj.model_path), results, arm.n)
        x0 = ffs["rotor_separated"]["x0"]
        n = arm.n
        write_json(tmp / "feedforward.json", {
            "t": t.tolist(), "theta_d": theta_d.tolist(),
            "initial_state": {k: x0[i * n:(i + 1) * n].tolist() for i, k in enumerate(("theta", "phi", "dtheta", "dphi"))},
            "tau": {m: ffs[m]["tau"].tolist() for m in METHODS}, "tau_interpolation": "linear",
            **({"tau_ocp_tracking": tau_ocp} if tau_ocp else {})}, indent=None)
        log(f"[{time.perf_counter() - t0:5.1f} s] figures 5-11")
        figures(tmp, arm, t, theta_d, sims)
        log(f"[{time.perf_counter() - t0:5.1f} s] the paper's cascade against the exact simulation")
        cascade_study(tmp, arm, traj, log)
        if sweeps:
            log(f"[{time.perf_counter() - t0:5.1f} s] when does rotor separation matter? (sweeps)")
            sweep(tmp, arm, traj, log)
    log(f"[{time.perf_counter() - t0:5.1f} s] wrote {out}")
    return results
