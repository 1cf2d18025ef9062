"""`rscasadi reproduce`: the main job.  The reference arm's report, the paper's figures, the seven
optimal-control problems, the identification demo and the closed-loop MPC studies, each part
checked; a summary of what each produced."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from rscasadi.dynamics.arm import load
from rscasadi.files import OutputError, check_writable, write_json, write_text
from rscasadi.model.modelfile import ModelFileError
from rscasadi.studies.model_report import model_report

PROBLEMS = Path(__file__).resolve().parents[2] / "problems"
REFERENCE = PROBLEMS / "arm3.toml"
TRAJECTORY = PROBLEMS / "trajectory_arm3.toml"
OCP_PROBLEMS = ("min_time", "min_effort", "tracking", "min_time_codesign", "min_time_gear_codesign", "panda_min_time",
                "reach_around")


class PartFailed(RuntimeError):
    """A part of the main job did not pass its own check."""


def run(out, log=print) -> list:
    """The main job into `out`: every part runs (those that need a failed one are skipped).
    Returns and prints a summary: (part, "ok" | "FAILED" | "skipped", what it produced or why)."""
    out = check_writable(out)
    summary = []

    def part(name, work, needs=()):
        missing = [n for n in needs if not any(s[0] == n and s[1] == "ok" for s in summary)]
        if missing:
            summary.append((name, "skipped", f"needs {', '.join(missing)}"))
            return
        try:
            summary.append((name, "ok", work()))
        except (PartFailed, ModelFileError, OutputError, ValueError, RuntimeError) as exc:
            log(f"rscasadi reproduce: {name} FAILED: {exc}")
            summary.append((name, "FAILED", str(exc)))

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
            if name in ("min_effort", "reach_around"):    # the motions to watch: view.html, and a GIF
                from rscasadi.view import scene_of, write_gif, write_html
                scene = scene_of(out / "ocp" / name / "solution.json")
                write_html(scene, out / "ocp" / name / "view.html")
                write_gif(scene, out / "ocp" / name / "view.gif")
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
        with tempfile.TemporaryDirectory() as build, fresh_directory(out / "mpc", "closed_loop.json") as tmp:
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

    part("model", model)
    part("paper", paper)
    for name in OCP_PROBLEMS:
        part(f"ocp {name}", ocp(name))
    part("identification", identification)
    part("mpc", mpc, needs=("identification",))
    log(f"\nrscasadi reproduce into {out}:")
    for name, state, what in summary:
        log(f"  {name:28s} {state:8s} {what}")
    return summary
