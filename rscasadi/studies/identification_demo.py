"""The identification workflow end to end on a synthetic robot (part of `rscasadi reproduce`):
`excite`, "run it on the robot" (a perturbed arm simulated with realistic sensors), `identify`,
the table of recovered parameters against the truth, the reduced-model ablation, and the
paper's feedforward loop closed with the identified models.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from rscasadi.ocp import rest_state
from rscasadi.sim.simulation import feedforward, simulate
from rscasadi.sim.trajectory import load_trajectory
from rscasadi.dynamics.arm import Arm, load
from rscasadi.files import CheckError, fresh_directory, showing_final_paths, write_json
from rscasadi.model.parameters import n_linear
from rscasadi.identification import excitation, identify as ident_mod
from rscasadi.identification.logs import read_log, write_log
from rscasadi.identification.synthetic import perturbed_arm, record

SEED = 20261122
HELD_OUT_LIMIT = 0.05   # the identified model predicts every held-out motor torque within 5 % RMS


def recovered_table(ident, arm: Arm, true_arm: Arm) -> list[dict]:
    """k1, k3, d, b, c of every joint and each joint's reflected rotor inertia (and mu^2 Izz of its
    fast rotor where that is identifiable alone) against the truth, in standard deviations."""
    u = ident.unknowns
    th_true = u.from_p(true_arm.parameters()[1][:n_linear(arm.model)])
    out = []
    for j, jt in enumerate(arm.model.joints):
        quantities = [(f"{jt.name}.{a}", np.eye(len(u.names))[u.names.index(f"{jt.name}.{a}")])
                      for a in ("sea.k1", "sea.k3", "sea.d", "gear_loss.b", "gear_loss.c")]
        quantities.append((f"{jt.name}.B (= Izz_S + mu^2 Izz_F)", ident_mod.reflected_inertia(u, arm.model, j)))
        c = np.zeros(len(u.names))
        c[u.names.index(f"{jt.name}.fast_rotor.Izz")] = jt.gear_ratio ** 2
        quantities.append((f"{jt.name}.mu^2 Izz_F", c))
        for name, c in quantities:
            est, std = ident.combination(c)
            truth = float(c @ th_true)
            out.append({"quantity": name, "nominal": float(c @ ident.th_nominal), "true": truth, "estimate": est,
                        "std": std, "z": None if not std else (est - truth) / std})
    return out


def model_errors(arm: Arm, true_arm: Arm, ident, ident_red, val_log) -> dict:
    """Noise-free model error on the held-out motion: each identified model's motor torques
    against the true arm's, on the same filtered signals, relative to the true torques' RMS."""
    u = ident.unknowns
    sig = ident_mod.prepare(val_log, ident.cutoff_hz, arm=arm)
    th_true = u.from_p(true_arm.parameters()[1][:n_linear(arm.model)])
    complete, reduced = ident_mod.rows(arm, sig, u), ident_mod.rows(arm, sig, u, reduced=True)
    out = {}
    for b, label in enumerate(complete.labels):
        if not label.startswith("tau"):
            continue
        sel = complete.block == b
        truth = complete.A[sel] @ th_true
        rms = np.sqrt(np.mean(truth ** 2))
        out[label] = {"complete": float(np.sqrt(np.mean((complete.A[sel] @ ident.th - truth) ** 2)) / rms),
                      "reduced": float(np.sqrt(np.mean((reduced.A[sel] @ ident_red.th - truth) ** 2)) / rms)}
    return out


def paper_loop(true_arm: Arm, models: dict, traj, t) -> dict:
    """Feedforward from each model along the paper's trajectory, open loop on the true arm,
    which starts at rest in its own static equilibrium."""
    x0 = rest_state(true_arm, traj(np.array([0.0]))[0][:, 0])
    out = {}
    for name, (arm, reduced) in models.items():
        ff = feedforward(arm, traj, t, reduced=reduced)
        sim = simulate(true_arm, x0, t, ff["tau"], method="cvodes", tol=1e-9)
        e = sim["theta"] - ff["theta_d"]
        out[name] = {"max_error": np.max(np.abs(e), axis=1).tolist(), "rms_error": np.sqrt(np.mean(e ** 2, axis=1)).tolist(),
                     "error": e}
    return out


def _md_table(rows: list[dict]) -> str:
    lines = ["| quantity | nominal (model file) | true | identified | std | (identified - true) / std |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        z = "not identifiable alone" if r["z"] is None else f"{r['z']:+.2f}"
        std = "" if r["std"] is None else f"{r['std']:.3g}"
        lines.append(f"| {r['quantity']} | {r['nominal']:.5g} | {r['true']:.5g} | {r['estimate']:.5g} | {std} | {z} |")
    return "\n".join(lines) + "\n"


def true_arm_of(arm: Arm) -> Arm:
    """The demo's 'real' arm for this model: the first draw of its seeded generator (as in run)."""
    return perturbed_arm(arm, np.random.default_rng(SEED))


def check(summary: dict) -> None:
    """The demo's own check: every figure finite and the held-out torques predicted within
    HELD_OUT_LIMIT by the identified complete model."""
    worst = max(v["relative"] for v in summary["validation"]["prediction"].values())
    loop = [v for r in summary["paper_loop"].values() for v in r["max_error"]]
    if not (np.isfinite(worst) and np.all(np.isfinite(loop))):
        raise CheckError("the identification demo produced a figure that is not finite")
    if worst > HELD_OUT_LIMIT:
        raise CheckError(f"the identified model predicts the held-out motor torques only within {100 * worst:.2f} % "
                         f"RMS (at most {100 * HELD_OUT_LIMIT:g} % expected)")


def run(model_file, out, log=print) -> dict:
    """The identification demo into out: excitation, logs of a perturbed arm, the fit, held-out validation."""
    t0 = time.perf_counter()
    stamp = lambda: f"[{time.perf_counter() - t0:5.1f} s]"
    arm = load(model_file)
    rng = np.random.default_rng(SEED)
    true_arm = perturbed_arm(arm, rng)                  # = true_arm_of(arm); rng goes on to the logs' noise
    with fresh_directory(out) as tmp:
        log = showing_final_paths(log, tmp, Path(out))
        log(f"{stamp()} 1. rscasadi excite: identification and validation trajectories")
        designed = excitation.run(model_file, tmp / "excitation", period=10.0, harmonics=5, log=log)
        excitation.run(model_file, tmp / "validation_trajectory", period=8.0, harmonics=4, log=log)
        log(f"{stamp()} 2. 'run it on the robot': a perturbed arm, feedforward + motor PD, quantised encoders")
        (tmp / "logs").mkdir()
        for name, folder in (("identification", "excitation"), ("validation", "validation_trajectory")):
            lg, _ = record(true_arm, arm, load_trajectory(tmp / folder / "trajectory.toml"), rng=rng)
            write_log(tmp / "logs" / f"{name}.csv", lg)
        log(f"{stamp()} 3. rscasadi identify (complete model, then the DLR reduced model as an ablation)")
        logs = [tmp / "logs" / "identification.csv"]
        val = tmp / "logs" / "validation.csv"
        rep, ident = ident_mod.run(model_file, logs, tmp / "identified", validate=val, log=log)
        rep_red, ident_red = ident_mod.run(model_file, logs, tmp / "identified_reduced", validate=val, reduced=True,
                                           log=log)
        log(f"{stamp()} 4. recovered parameters against the truth")
        table = recovered_table(ident, arm, true_arm)
        (tmp / "recovered.md").write_text("# Recovered parameters of the synthetic arm\n\n" + _md_table(table))
        model_error = model_errors(arm, true_arm, ident, ident_red, read_log(val, arm.n))
        log(f"{stamp()} 5. the paper's loop closed: feedforward from each model on the true arm")
        traj = load_trajectory(Path(__file__).resolve().parents[2] / "problems" / "trajectory_arm3.toml")
        t = np.linspace(0, traj.duration, int(round(traj.duration * 500)) + 1)
        identified = Arm(ident.model)
        loop = paper_loop(true_arm, {"true arm (ideal)": (true_arm, False),
                                     "identified, rotor-separated": (identified, False),
                                     "identified, DLR/Spong feedforward": (identified, True),
                                     "nominal model file": (arm, False)}, traj, t)
        _loop_outputs(tmp, loop, t)
        summary = {"model": Path(model_file).name, "seed": SEED, "recovered": table, "model_error": model_error,
                   "excitation_condition_number": designed["condition_number"],
                   "validation": rep["validation"], "validation_reduced": rep_red["validation"],
                   "paper_loop": {k: {m: v[m] for m in ("max_error", "rms_error")} for k, v in loop.items()}}
        check(summary)
        write_json(tmp / "summary.json", summary, indent=2)
    log(f"{stamp()} wrote {out}")
    return summary


def _loop_outputs(tmp: Path, loop: dict, t):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    lines = ["| feedforward from | max error per joint (mrad) | RMS error per joint (mrad) |", "|---|---|---|"]
    for name, r in loop.items():
        lines.append(f"| {name} | {', '.join(f'{1e3 * v:.3g}' for v in r['max_error'])} | "
                     f"{', '.join(f'{1e3 * v:.3g}' for v in r['rms_error'])} |")
    (tmp / "paper_loop.md").write_text("# The paper's trajectory, open loop on the true (synthetic) arm\n\n"
                                       + "\n".join(lines) + "\n")
    n = next(iter(loop.values()))["error"].shape[0]
    fig, axes = plt.subplots(n, 1, figsize=(8, 2.2 * n), sharex=True)
    for j in range(n):
        for name, r in loop.items():
            axes[j].plot(t, 1e3 * r["error"][j], label=name)
        axes[j].set_ylabel(f"joint {j + 1} error (mrad)")
    axes[0].legend(fontsize=7)
    axes[-1].set_xlabel("t (s)")
    fig.tight_layout()
    fig.savefig(tmp / "paper_loop.png", dpi=110)
    plt.close(fig)
