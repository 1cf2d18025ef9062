"""The arm in MuJoCo (part of `rscasadi reproduce`, into results/mujoco/): the exported files, how
far each export's motion is from rscasadi's complete model, the impedance controller and the
momentum observer against a MuJoCo table, the generated C MPC driving the MuJoCo arm, and
identification from logs MuJoCo recorded.

Every figure is MuJoCo's physics (the `mujoco` package) against rscasadi's, run now.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from rscasadi.dynamics.arm import load
from rscasadi.export.mujoco import VARIANTS, compare_variants, mujoco_xml
from rscasadi.files import CheckError, fresh_directory, showing_final_paths, write_json, write_text
from rscasadi.sim.trajectory import load_trajectory

PROBLEMS = Path(__file__).resolve().parents[2] / "problems"
ARMS = {"arm3": ("arm3.toml", "trajectory_arm3.toml"), "panda": ("panda_sea.toml", "trajectory_panda.toml")}
STIFFNESSES = (300.0, 1000.0)                      # N/m: the impedance against the table
TOOL_START = [0.0, 0.3, -0.5]


def exports(tmp: Path, log) -> dict:
    """Each arm's three exports written, and their motion against rscasadi's replay."""
    out = {}
    for name, (model, trajectory) in ARMS.items():
        arm = load(PROBLEMS / model)
        (tmp / name).mkdir()
        for variant in VARIANTS:
            write_text(tmp / name / f"{variant}.xml", mujoco_xml(arm.model, variant))
        out[name] = compare_variants(arm, load_trajectory(PROBLEMS / trajectory))
        log(f"  {name}: the feedforward run in MuJoCo, off rscasadi's replay by: complete {out[name]['complete']:.1e}, "
            f"reduced {out[name]['reduced']:.1e}, armature {out[name]['armature']:.1e} rad")
    return out


def impedance(log) -> tuple[list, list]:
    """The generated C impedance controller on arm3's tool pressed 5 mm into a MuJoCo table, and
    holding it against a 2 N push (MuJoCo's applied force)."""
    import tempfile
    from rscasadi.interaction.generate import generate_impedance
    from rscasadi.interaction.study import push_in_mujoco, table_in_mujoco
    arm, rows = load(PROBLEMS / "arm3_tool.toml"), []
    with tempfile.TemporaryDirectory() as build:
        generate_impedance(arm, Path(build) / "impedance", "tool", log=log)
        runs = [table_in_mujoco(arm, "tool", TOOL_START, K, compiled=Path(build) / "impedance") for K in STIFFNESSES]
        pushes = [push_in_mujoco(arm, "tool", TOOL_START, K, compiled=Path(build) / "impedance") for K in STIFFNESSES]
    for r in pushes:
        log(f"  impedance K = {r['K']:g} N/m pushed with 2 N in MuJoCo: moved {1e3 * r['displacement'][2]:.3f} mm, "
            f"F / K {1e3 * r['expected'][2]:.3f} mm ({r['error_percent']:+.3f} %), observer off by "
            f"{r['observer_error']:.1e} N m")
    for r in runs:
        rows.append({k: v for k, v in r.items() if k != "trace"} | {"trace": [list(map(float, v)) for v in r["trace"]]})
        log(f"  impedance K = {r['K']:g} N/m on a MuJoCo table: force {r['force']:.3f} N, K x distance {r['expected']:.3f} N "
            f"({r['error_percent']:+.2f} %), chatter {r['chatter_percent']:.3f} %, observer off by {r['observer_error']:.1e} N m")
    return rows, pushes


def mpc(log) -> dict:
    """The generated C MPC of problems/mpc_arm3.toml (and feedforward + motor PD) on a plant with a
    20 % heavier last link, once simulated by rscasadi (RK4) and once by MuJoCo (the plant
    exported, RK4 at 1 ms): the same controllers, two physics engines."""
    import tempfile
    from rscasadi.export.mujoco import mujoco_plant
    from rscasadi.mpc.generate import generate_mpc
    from rscasadi.mpc.study import closed_loop
    from rscasadi.sim.loop import rk4_plant
    out = {}
    with tempfile.TemporaryDirectory() as build:
        generate_mpc(PROBLEMS / "mpc_arm3.toml", Path(build) / "mpc", log=lambda m: None)
        for engine, simulator in (("rscasadi", rk4_plant), ("mujoco", mujoco_plant)):
            res = closed_loop(PROBLEMS / "mpc_arm3.toml", Path(build) / "mpc", simulator=simulator, log=lambda m: None)
            out[engine] = {name: {k: r[k] for k in ("max_error", "rms_error", "max_limit_violation")}
                           for name, r in res.items()}
            log(f"  C MPC on the heavier-tip arm simulated by {engine}: max error "
                f"{out[engine]['MPC (C)']['max_error']:.2e} rad (feedforward + PD: "
                f"{out[engine]['feedforward + PD']['max_error']:.2e})")
    return out


def identification(tmp: Path, excitation_trajectory: Path, log) -> dict:
    """A perturbed arm3 exported, its logs recorded by MuJoCo, identified on the nominal model."""
    import json
    from rscasadi.identification.identify import run as identify
    from rscasadi.identification.synthetic import simulate_log
    logs: dict = {}
    (tmp / "logs").mkdir()
    for name, traj in (("identification", excitation_trajectory), ("validation", PROBLEMS / "trajectory_arm3.toml")):
        logs[name] = simulate_log(PROBLEMS / "arm3.toml", traj, tmp / "logs" / f"{name}.csv", perturb=4,
                                  simulator="mujoco", true_model=tmp / "logs" / "true.toml", log=log)
    identify(PROBLEMS / "arm3.toml", [logs["identification"]], tmp / "identified", validate=logs["validation"], log=log)
    from rscasadi.identification import identify as ident
    from rscasadi.identification.logs import read_log
    from rscasadi.model.parameters import n_linear
    report = json.loads((tmp / "identified" / "report.json").read_text())
    found, true = load(tmp / "identified" / "model.toml"), load(tmp / "logs" / "true.toml")
    k1 = [abs(a.k1 / b.k1 - 1) for a, b in zip(found.model.joints, true.model.joints)]
    arm = load(PROBLEMS / "arm3.toml")                  # the exported arm's own prediction: the sensors' floor
    u = ident.Unknowns.of(arm.model)
    rows = ident.rows(arm, ident.prepare(read_log(logs["validation"], arm.n), report["cutoff_hz"], arm=arm), u)
    floor = ident.predict(rows, u.from_p(true.parameters()[1][:n_linear(arm.model)]))
    return {"k1_relative_error": k1, "held_out": {k: v["relative"] for k, v in report["validation"]["prediction"].items()},
            "held_out_floor": {k: v["relative"] for k, v in floor.items()}}


def table(summary: dict) -> str:
    """summary.md: the figures as tables."""
    lines = ["# The arm in MuJoCo", "", summary["run"], "",
             "| arm | complete (rad) | reduced (rad) | armature (rad) |", "|---|---|---|---|"]
    lines += [f"| {name} | {r['complete']:.2e} | {r['reduced']:.2e} | {r['armature']:.2e} |"
              for name, r in summary["exports"].items()]
    lines += ["", "Largest link-angle difference from rscasadi's CVODES replay, the feedforward torques of the arm's",
              "2 s trajectory held over each 1 ms MuJoCo step, open loop.", "",
              "| K (N/m) | contact force (N) | K x distance (N) | error | peak-to-peak | observer error (N m) "
              "| flagged after (ms) |",
              "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['K']:g} | {r['force']:.4f} | {r['expected']:.4f} | {r['error_percent']:+.3f} % | "
              f"{r['chatter_percent']:.3f} % | {r['observer_error']:.1e} | {r['delay_ms']:.0f} |"
              for r in summary["impedance"]]
    lines += ["", "The generated C impedance controller's target 5 mm into a MuJoCo table under the tool; the observer's flag: "
                  "a link torque above 0.5 N m (before the contact its largest was "
              f"{max(r['free_max_Nm'] for r in summary['impedance']):.2f} N m)."]
    if summary.get("push"):
        lines += ["", "| K (N/m) | push (N) | moved (mm) | F / K (mm) | error | observer error (N m) |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {r['K']:g} | {r['force'][2]:g} | {1e3 * r['displacement'][2]:.4f} | {1e3 * r['expected'][2]:.4f} | "
                  f"{r['error_percent']:+.3f} % | {r['observer_error']:.1e} |" for r in summary["push"]]
        lines += ["", "The same controller holding the tool where it is, pushed down at the tool in MuJoCo (mj_applyFT) "
                      "from 0.2 s: its displacement over the last 0.2 s of 1.2 s."]
    if summary.get("mpc"):
        lines += ["", "| controller | max error, rscasadi plant (rad) | max error, MuJoCo plant (rad) | "
                      "RMS, rscasadi | RMS, MuJoCo |", "|---|---|---|---|---|"]
        ours, theirs = summary["mpc"]["rscasadi"], summary["mpc"]["mujoco"]
        lines += [f"| {name} | {ours[name]['max_error']:.3e} | {theirs[name]['max_error']:.3e} | "
                  f"{ours[name]['rms_error']:.3e} | {theirs[name]['rms_error']:.3e} |" for name in ours]
        lines += ["", "problems/mpc_arm3.toml's controllers (the C MPC generated from it, its feedforward, feedforward "
                      "+ motor PD) at 1 kHz with quantised encoders on the arm with a 20 % heavier last link, simulated "
                      "by rscasadi's RK4 and by MuJoCo (the plant exported)."]
    if summary.get("identification"):
        ident = summary["identification"]
        excess = max(np.sqrt(max(ident["held_out"][k] ** 2 - ident["held_out_floor"][k] ** 2, 0.0))
                     for k in ident["held_out"])
        lines += ["", f"Identified from MuJoCo's logs: k1 within {100 * max(ident['k1_relative_error']):.3f} % of the "
                      f"exported arm's; held-out motor torques within {100 * max(ident['held_out'].values()):.2f} % RMS "
                      f"of the noisy log, where the exported arm itself predicts "
                      f"{100 * max(ident['held_out_floor'].values()):.2f} % (sensor noise and quantisation): "
                      f"{100 * excess:.2f} % beyond that floor."]
    return "\n".join(lines) + "\n"


def plot(rows: list, path: Path):
    """impedance.png: the contact force MuJoCo reports over time, per stiffness."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 3))
    for r in rows:
        ax.plot(r["trace"][0], r["trace"][1], label=f"K = {r['K']:g} N/m")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("MuJoCo contact force (N)")
    ax.set_title("Impedance control pressing a MuJoCo table")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run(out, excitation_trajectory=None, log=print) -> dict:
    """Everything above into `out` (whole or not at all); identification only with an excitation
    trajectory (results/identification/excitation/trajectory.toml)."""
    from rscasadi.files import run_stamp
    t0 = time.perf_counter()
    with fresh_directory(out) as tmp:
        log = showing_final_paths(log, tmp, Path(out))
        log("MuJoCo: the exports against rscasadi's replay ...")
        summary: dict = {"run": run_stamp(), "exports": exports(tmp, log)}
        log("MuJoCo: impedance control and the observer against a table ...")
        summary["impedance"], summary["push"] = impedance(log)
        log("MuJoCo: the C MPC driving the MuJoCo arm ...")
        summary["mpc"] = mpc(log)
        if excitation_trajectory is not None:
            log("MuJoCo: identification from MuJoCo's logs ...")
            summary["identification"] = identification(tmp, Path(excitation_trajectory), log)
        plot(summary["impedance"], tmp / "impedance.png")
        for r in summary["impedance"]:
            r.pop("trace")
        write_json(tmp / "summary.json", summary, indent=2)
        write_text(tmp / "summary.md", table(summary))
        worst = max(r["complete"] for r in summary["exports"].values())
        if not worst < 2e-5:
            raise CheckError(f"MuJoCo's complete export left rscasadi's replay by {worst:.2e} rad (2e-5 expected)")
    log(f"wrote {out} in {time.perf_counter() - t0:.0f} s")
    return summary
