"""`rscasadi reproduce`: the main job.  The reference arm's report, the paper's figures, the
optimal-control problems, the identification demo, the closed-loop MPC studies and the
interaction studies, each part checked; a summary of what each produced."""
from __future__ import annotations

import functools
import time
from typing import Callable
from pathlib import Path

import numpy as np

from rscasadi.dynamics.arm import Arm, load
from rscasadi.errors import Error
from rscasadi.files import OutputError, check_writable, run_stamp, write_json, write_text
from rscasadi.model.modelfile import ModelFileError
from rscasadi.studies.model_report import model_report

PROBLEMS = Path(__file__).resolve().parents[2] / "problems"
REFERENCE = PROBLEMS / "arm3.toml"
TRAJECTORY = PROBLEMS / "trajectory_arm3.toml"
OCP_PROBLEMS = ("min_time", "min_effort", "tracking", "min_time_codesign", "min_time_gear_codesign", "panda_min_time",
                "ur5_min_time", "reach_around", "tool_circle")
WATCHED = ("min_effort", "reach_around", "tool_circle", "panda_shelf")      # view.html and view.gif
INTERACTION_ARMS = {  # model: frame, configuration, trajectory, the observer's gain (1/s) and threshold (N m)
    "arm3_tool": ("tool", [0.0, 0.3, -0.5], "trajectory_arm3.toml", 50.0, 1.0),
    # the Panda's 19-bit link encoders through its larger inertias leave up to 3.9 N m of residual
    # in free motion at 100 1/s; at 50 1/s the estimate lags a contact that grows: 7 % against 3.5 %
    "panda_sea": ("panda_hand_tcp", [0.0, -0.3, 0.0, -2.0, 0.0, 1.7, 0.8], "trajectory_panda.toml", 100.0, 5.0),
}


def interaction_study(name: str, out: Path, log=print) -> str:
    """The interaction study (rscasadi.interaction.study) of INTERACTION_ARMS[name] into out/name,
    checked: F / K and the wall's force within 5 %, collisions flagged within 10 ms, no false flag,
    the torques within 5 %."""
    from rscasadi.interaction.study import study
    from rscasadi.sim.trajectory import load_trajectory
    frame, theta, trajectory, gain, threshold = INTERACTION_ARMS[name]
    r = study(load(PROBLEMS / f"{name}.toml"), frame, theta, out / name, gain=gain, threshold=threshold,
              trajectory=load_trajectory(PROBLEMS / trajectory), log=log)
    bad = [f"push at K = {p['K']:g}" for p in r["push"] if not abs(p["error_percent"]) < 5]
    bad += [f"wall of {w['k_wall']:g} N/m" for w in r["wall"] if not abs(w["error_percent"]) < 5]
    bad += [f"collision in the {k}" for k, c in r["collision"].items()
            if not (0 <= c["delay_ms"] <= 10 and c["free_max_Nm"] < threshold and c["error_percent"] < 5)]
    if bad:
        raise PartFailed("outside its targets: " + ", ".join(bad))
    worst = max(abs(p["error_percent"]) for p in r["push"])
    return (f"{out / name}/: F / K within {worst:.2f} %, collisions flagged after "
            f"{max(c['delay_ms'] for c in r['collision'].values()):.0f} ms at most")


class PartFailed(Error, RuntimeError):
    """A part of the main job did not pass its own check."""


def _watch(directory: Path):
    """The motion of directory/solution.json to watch: view.html, and view.gif for documents."""
    from rscasadi.view import scene_of, write_gif, write_html
    scene = scene_of(directory / "solution.json")
    write_html(scene, directory / "view.html")
    write_gif(scene, directory / "view.gif")


def shelf_comparison(out: Path, log=print) -> str:
    """The shelf task with its 2 kg part and without it: one NLP, the part's inertial
    parameters set (the model's) or zero."""
    from rscasadi.task.objects import holding_payload
    from rscasadi.model.modelfile import read
    from rscasadi.model.parameters import value
    from rscasadi.ocp import load_problem
    from rscasadi.ocp import run as run_ocp
    problem = load_problem(PROBLEMS / "ocp_panda_shelf.toml")
    held = holding_payload(read(problem.task.model), problem.task.payload, problem.path)
    names = [k for k in Arm(held).parameters()[0] if k.startswith("payload.")]
    times = {}
    for case, values in (("panda_shelf", {k: value(held, k) for k in names}),
                         ("panda_shelf_empty", {k: 0.0 for k in names})):
        sol = run_ocp(problem.replace(parameters=values), out / "ocp" / case, log=log, print_level=0)
        if not sol["success"]:
            raise PartFailed(f"{case}: not solved and verified ({sol['status']})")
        times[case] = sol["t"][-1]
    _watch(out / "ocp" / "panda_shelf")
    write_json(out / "ocp" / "panda_shelf" / "comparison.json",
               {"with_part_s": times["panda_shelf"], "without_part_s": times["panda_shelf_empty"],
                "slower": times["panda_shelf"] / times["panda_shelf_empty"] - 1})
    return (f"{out / 'ocp' / 'panda_shelf'}/: {times['panda_shelf']:.3f} s with the 2 kg part, "
            f"{times['panda_shelf_empty']:.3f} s without, verified")


def run(out, log=print) -> list:
    """The main job into `out`: every part runs (those that need a failed one are skipped).
    Returns and prints a summary: (part, "ok" | "FAILED" | "skipped", what it produced or why),
    and writes it with each part's wall time, the date, machine and commit to `out/summary.json`."""
    out = check_writable(out)
    summary: list[tuple[str, str, str]] = []
    seconds: dict[str, float] = {}

    began, parts = time.perf_counter(), 0                       # parts: set below, before the first runs

    def part(name, work, needs=()):
        missing = [n for n in needs if not any(s[0] == n and s[1] == "ok" for s in summary)]
        if missing:
            summary.append((name, "skipped", f"needs {', '.join(missing)}"))
            return
        elapsed = time.perf_counter() - began
        log(f"\nrscasadi reproduce: part {len(summary) + 1} of {parts}, {name} "
            f"({elapsed // 60:.0f} min {elapsed % 60:.0f} s in)")
        start = time.perf_counter()
        try:
            summary.append((name, "ok", work()))
        except (PartFailed, ModelFileError, OutputError, ValueError, RuntimeError) as exc:
            log(f"rscasadi reproduce: {name} FAILED: {exc}")
            summary.append((name, "FAILED", str(exc)))
        seconds[name] = time.perf_counter() - start

    def model():
        (out / "model.md").parent.mkdir(parents=True, exist_ok=True)
        write_text(out / "model.md", model_report(REFERENCE))
        return f"{out / 'model.md'}"

    def paper():
        from rscasadi.studies.paper import run
        res = run(TRAJECTORY, out / "paper", log=log, ocp_problem=PROBLEMS / "ocp_tracking.toml")
        worst = max(res["rotor_separated"]["max_error"])
        if not np.isfinite(worst):
            raise PartFailed("the rotor-separated feedforward's tracking error is not finite")
        return f"{out / 'paper'}/: rotor-separated feedforward max error {worst:.2e} rad"

    def ocp(name):
        def work():
            from rscasadi.ocp import run as run_ocp
            sol = run_ocp(PROBLEMS / f"ocp_{name}.toml", out / "ocp" / name, log=log, print_level=0)
            if not sol["success"]:
                raise PartFailed(f"not solved and verified ({sol['status']})")
            _watch(out / "ocp" / name) if name in WATCHED else None
            return f"{out / 'ocp' / name}/: objective {sol['objective']:.6g}, verified"
        return work

    def identification():
        from rscasadi.studies.identification_demo import run as run_identification
        res = run_identification(REFERENCE, out / "identification", log=log)
        worst = max(v["relative"] for v in res["validation"]["prediction"].values())
        return (f"{out / 'identification'}/: excitation condition number {res['excitation_condition_number']:.3g}, "
                f"held-out motor torques within {100 * worst:.2f} % RMS")

    def mpc():
        import tempfile
        from rscasadi.mpc import study
        from rscasadi.files import fresh_directory, showing_final_paths
        from rscasadi.studies.identification_demo import true_arm_of
        with tempfile.TemporaryDirectory() as build, fresh_directory(out / "mpc") as tmp:
            shown = showing_final_paths(showing_final_paths(log, tmp, out / "mpc"), build, "(a temporary build)")
            shown("MPC: generating the C controllers and running the closed-loop studies ...")
            res = study(PROBLEMS / "mpc_arm3.toml", build, log=shown, true_arm=true_arm_of(load(REFERENCE)),
                        identified_model=out / "identification" / "identified" / "model.toml",
                        figure=tmp / "closed_loop.png")
            write_json(tmp / "closed_loop.json", res)
        worst = max(c["MPC (C)"]["max_error"] for c in res.values())
        if not np.isfinite(worst):
            raise PartFailed("the closed-loop MPC's tracking error is not finite")
        return f"{out / 'mpc'}/: closed-loop MPC max tracking error {worst:.2e} rad"

    def mujoco():
        from rscasadi.studies.mujoco_twin import run as run_mujoco
        res = run_mujoco(out / "mujoco", out / "identification" / "excitation" / "trajectory.toml", log=log)
        return (f"{out / 'mujoco'}/: MuJoCo's complete export within "
                f"{max(r['complete'] for r in res['exports'].values()):.1e} rad of the model, "
                f"the impedance's contact force within {max(abs(r['error_percent']) for r in res['impedance']):.2f} %")

    def floating():
        from rscasadi.studies.rotor_spin import report, study
        r = study(PROBLEMS / "anymal_c_sea.toml", log=log)
        (out / "floating").mkdir(parents=True, exist_ok=True)
        write_json(out / "floating" / "rotor_spin.json", {"run": run_stamp(), **r})
        write_text(out / "floating" / "rotor_spin.md", report(r, run_stamp()))
        held = max(r["angular_momentum_at_end_Nms"][k] for k in ("complete", "rigid"))
        if not held < 1e-6 or not r["rigid_vs_armature_deg"] > 0.01:
            raise PartFailed(f"momentum not conserved ({held:.2e} N m s) or no spin effect")
        return (f"{out / 'floating'}/rotor_spin.md: in flight the armature model's base ends "
                f"{r['rigid_vs_armature_deg']:.2f} deg from the rotors-as-bodies model's")

    def mpc_task(name, problem, limits_kept=True):
        def work():
            import dataclasses
            import tempfile
            from rscasadi.mpc import generate_mpc, plot_task_study, task_study
            from rscasadi.mpc.problem import load_mpc_problem
            from rscasadi.files import fresh_directory
            p = load_mpc_problem(PROBLEMS / problem)
            if p.solution is not None:                       # the reference this run has just solved
                p = dataclasses.replace(p, solution=out / p.solution.relative_to(PROBLEMS.parent / "results"))
            with tempfile.TemporaryDirectory() as build, fresh_directory(out / name) as tmp:
                generate_mpc(p, build, log=log)
                res = task_study(p, build, log=log)
                write_json(tmp / "closed_loop.json", res)
                plot_task_study(res, tmp / "closed_loop.png")
            runs = {k: v["MPC (C)"] for k, v in res.items() if isinstance(v, dict) and "MPC (C)" in v}
            if any((limits_kept and r["max_limit_violation"] > 0) or (r["min_clearance"] or 0.0) < 0
                   or not np.isfinite(r["max_error"])
                   for r in runs.values()):
                raise PartFailed("the task-space MPC broke a limit or an obstacle's margin")
            line = f"{out / name}/: reference within {1e3 * max(r['max_error'] for r in runs.values()):.1f} mm"
            if "untold_payload" in runs:
                line += (f"; at the end, the payload untold {1e3 * runs['untold_payload']['final_error']:.2f} mm, "
                         f"told {1e3 * runs['told_payload']['final_error']:.2f} mm")
            return line
        return work

    schedule: list[tuple[str, Callable[[], str], tuple[str, ...]]] = [("model", model, ()), ("paper", paper, ())]
    schedule += [(f"ocp {name}", ocp(name), ()) for name in OCP_PROBLEMS]
    schedule += [("ocp panda_shelf", lambda: shelf_comparison(out, log), ()),
                 ("identification", identification, ()),
                 ("mpc", mpc, ("identification",)),
                 ("mpc task space", mpc_task("mpc_tool", "mpc_arm3_tool.toml"), ()),
                 # the minimum-time reference rides the speed limits: the soft limits give a few per cent
                 ("mpc panda shelf", mpc_task("mpc_panda_shelf", "mpc_panda_shelf.toml", limits_kept=False),
                  ("ocp panda_shelf",))]
    schedule += [(f"interaction {name}", functools.partial(interaction_study, name, out / "interaction", log), ())
                 for name in INTERACTION_ARMS]
    schedule += [("mujoco", mujoco, ("identification",)), ("floating rotor spin", floating, ())]
    parts = len(schedule)
    for name, work, needs in schedule:
        part(name, work, needs)
    write_json(out / "summary.json", {
        "run": run_stamp(), "seconds": sum(seconds.values()),
        "parts": [{"part": name, "status": state, "produced": what, "seconds": seconds.get(name, 0.0)}
                  for name, state, what in summary]})
    log(f"\nrscasadi reproduce into {out}:")
    for name, state, what in summary:
        log(f"  {name:28s} {state:8s} {seconds.get(name, 0.0):6.0f} s  {what}")
    return summary
