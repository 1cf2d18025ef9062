"""Benchmark: the Panda's joint-space MPC over the horizon, both QPs, and a light wrist.

1. N = 5, 10, 20, 40 intervals of 10 ms (2 RK4 steps each), the condensed QP (straight-line C,
   its size growing as N^2: generated up to N = 20) and the Riccati recursion (HPIPM, partially
   condensed into blocks of about 4 intervals): the time to generate and compile, the C's size,
   the median step and feedback (mpc_prepare before the sample, mpc_feedback from it: the
   latency) timed in C along the 1000 samples of the closed loop's own states, and the closed loop's
   tracking of problems/trajectory_panda.toml (1 s, 20 % heavier last link);
2. the task-space MPC of problems/mpc_panda_shelf.toml (N = 10, position and rotation, the ball
   and the table), its phases timed along its closed loop on the shelf motion (as modelled);
   At N = 10 and 20 and in task space the Riccati controller is also run with threads = 2 (its
   preparation's loops over the intervals on both cores, OpenMP);
3. a second 7-joint arm, Baxter's left arm from its whole-robot URDF (common.baxter_model), on a
   motion of the Panda's form within its ranges (common.baxter_trajectory): problems/mpc_panda.toml's
   settings with N = 10 and 20 intervals of 10 ms and substeps = auto, the Riccati QP, timed as
   the Panda's;
4. the Panda with a last link 50 times lighter, problems/mpc_panda.toml's settings untouched:
   integrator = auto takes ROS2 (RK4 would need more substeps than it allows), every step finite.

With RSCASADI_BENCH_BLASFEO=/path/to/libblasfeo.so (a BLASFEO built for this CPU, e.g.
`git clone https://github.com/giaf/blasfeo && make -C blasfeo shared_library TARGET=X64_INTEL_HASWELL`)
the Riccati rows at N = 10 and 20 (both arms) and the task-space row are also run linked to it
(RSCASADI_BLASFEO, rscasadi.mpc.generate.riccati_blasfeo); without it, the CasADi wheel's BLASFEO
with the controller's vector kernels only.

    python benchmarks/bench_mpc_horizon.py      # writes results/bench_mpc_horizon.md (about 35 min,
                                                # every build from an empty cache)
"""
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from common import baxter_trajectory, light_panda, stamp, RESULTS, ROOT  # noqa: E402
from rscasadi.mpc import closed_loop, generate_mpc, load_mpc_problem, task_closed_loop  # noqa: E402
from rscasadi.mpc.problem import with_integrator  # noqa: E402
from rscasadi.dynamics.arm import Arm, load  # noqa: E402
from rscasadi.sim.loop import rk4_plant  # noqa: E402

PROBLEM = ROOT / "problems" / "mpc_panda.toml"
HORIZONS = (5, 10, 20, 40)
CONDENSED_UP_TO = 20          # its C at 40 intervals would be ~4x that at 20
LIGHT = 0.02                  # the light wrist: the last link's mass and inertia times this


_PHASES = """
import ctypes, json, os, sys
import numpy as np
try:                       # a real-time loop's scheduling where this user may set it: FIFO, memory locked
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
    rt = ctypes.CDLL(None).mlockall(3) == 0          # MCL_CURRENT | MCL_FUTURE
except (OSError, AttributeError):
    rt = False
from rscasadi.mpc import CompiledMPC
d = sys.argv[1]
states, references = np.load(d + "/states.npy"), np.load(d + "/references.npy")
c = CompiledMPC(d)
c.init(states[0])
step, feedback = [], []
for x, ref in zip(states, references):
    step.append(c.step(x, ref)[1])
c.init(states[0])
for x, ref in zip(states, references):
    c.prepare(ref)
    feedback.append(c.feedback(x)[1])
q = lambda v, pct: float(np.percentile(v, pct)) * 1e6
print(json.dumps({"step_us": q(step, 50), "step_p999_us": q(step, 99.9), "feedback_us": q(feedback, 50), "rt": rt}))
"""


RUNS = 3                      # rounds of timing processes; each controller's best median is reported


def phases_once(directory: Path) -> dict:
    """mpc_step, mpc_prepare + mpc_feedback timed in C along the states and references saved in
    `directory`, in a fresh process: the BLASFEO a controller links binds there (a process binds
    HPIPM's calls once, to the first BLASFEO it loads), and nothing else of this run runs beside
    it; under SCHED_FIFO with its memory locked where permitted (rt: whether it was)."""
    return json.loads(subprocess.run([sys.executable, "-c", _PHASES, str(directory)], capture_output=True, text=True,
                                     check=True, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"}
                                     ).stdout.strip().splitlines()[-1])


def timed(rows: list, log=print) -> list:
    """Each row's phases: RUNS rounds over all rows, so a controller's processes fall minutes
    apart (this VM's neighbours slow it for minutes at a time: single medians moved by up to
    40 %, the unchanged feedback by 1.75x within one run), and the best of its medians."""
    runs: list = [[] for _ in rows]
    for k in range(RUNS):
        log(f"timing, round {k + 1} of {RUNS} ({len(rows)} controllers) ...")
        for row, got in zip(rows, runs):
            got.append(phases_once(Path(row["_dir"])))
    for row, got in zip(rows, runs):
        row.pop("_dir", None)
        row.update({key: min(r[key] for r in got) for key in got[0] if key != "rt"}, rt=all(r["rt"] for r in got))
    return rows


def recorded(directory: Path, states: np.ndarray, references: np.ndarray) -> dict:
    """The closed loop's states and references kept beside the controller, for `timed`."""
    np.save(directory / "states.npy", states)
    np.save(directory / "references.npy", references)
    return {"_dir": str(directory)}


def generated(p, out: Path, blasfeo: str = "") -> float:
    """Generate and compile at -O3 for this CPU, linked to `blasfeo` ("" the default); seconds."""
    os.environ.pop("RSCASADI_BLASFEO", None)
    if blasfeo:
        os.environ["RSCASADI_BLASFEO"] = blasfeo
    t0 = time.perf_counter()
    try:
        generate_mpc(p, out, opt="-O3", native=True, log=lambda m: None)
    finally:
        os.environ.pop("RSCASADI_BLASFEO", None)
    return time.perf_counter() - t0


def case(p, work: Path, log=print, blasfeo: str = "", arm: str = "panda") -> dict:
    """Generate, run the closed loop (1 s, traced), then time the phases along its states."""
    out = work / f"{arm}_{p.qp}_{p.horizon}_t{p.threads}{'_blasfeo' if blasfeo else ''}"
    built = generated(p, out, blasfeo)
    traces: dict = {}
    res = closed_loop(p, out, duration=1.0, log=lambda m: None, traces=traces)["MPC (C)"]
    states, refs = traces["MPC (C)"]["x"], traces["MPC (C)"]["reference"]
    row = {"qp": p.qp, "N": p.horizon, "threads": p.threads, "build_s": built, "c_mb": sum(f.stat().st_size for f in out.glob("*.c")) / 1e6,
           "max_error": res["max_error"], "blasfeo": blasfeo, **recorded(out, states, refs)}
    log(f"  {arm}: {p.qp} N = {p.horizon}, {p.threads} thread(s){' (BLASFEO for this CPU)' if blasfeo else ''}: built in {built:.0f} s "
        f"({row['c_mb']:.1f} MB of C), tracking {row['max_error']:.2e} rad")
    return row


def task_space(work: Path, log=print, blasfeo: str = "", threads: int = 1) -> dict:
    """problems/mpc_panda_shelf.toml generated as the benchmark builds, its closed loop on the
    shelf motion as modelled, then its phases timed along the loop's states and references."""
    p = dataclasses.replace(load_mpc_problem(ROOT / "problems" / "mpc_panda_shelf.toml"), threads=threads)
    if not Path(p.solution).exists():
        raise SystemExit(f"{p.solution} missing: run `rscasadi reproduce` first (the shelf motion)")
    out = work / f"task_t{threads}{'_blasfeo' if blasfeo else ''}"
    built = generated(p, out, blasfeo)
    traces: dict = {}
    res = task_closed_loop(p, out, log=lambda m: None, traces=traces)
    row = {"N": p.horizon, "threads": threads, "build_s": built, "max_error": res["max_error"], "blasfeo": blasfeo,
           "qp": json.loads((out / "manifest.json").read_text())["qp"], **recorded(out, traces["x"], traces["reference"])}
    log(f"  task space N = {p.horizon}, {threads} thread(s){' (BLASFEO for this CPU)' if blasfeo else ''}: "
        f"the hand within {row['max_error'] * 1e3:.1f} mm")
    return row


def second_arm(work: Path, tuned: str, log=print) -> tuple[list, object]:
    """Baxter's left arm (module docstring, 3.): the Riccati controller at N = 10 and 20 on one
    thread, and on two linked to the CPU's BLASFEO where given; the rows and the settled problem."""
    model = baxter_trajectory(work)
    p = dataclasses.replace(load_mpc_problem(PROBLEM), model=model.with_name("baxter_sea.toml"), trajectory=model,
                            interval=0.01, substeps="auto", qp="riccati")
    settled = with_integrator(p, Arm(load(p.model).model))
    rows = []
    for N in (10, 20):
        log(f"Baxter's left arm, N = {N} ...")
        rows.append(case(dataclasses.replace(p, horizon=N), work, log, arm="baxter"))
        if tuned:
            rows.append(case(dataclasses.replace(p, horizon=N, threads=2), work, log, blasfeo=tuned, arm="baxter"))
    return rows, settled


def light_wrist(work: Path, log=print) -> dict:
    p = dataclasses.replace(load_mpc_problem(PROBLEM), model=light_panda(work, LIGHT))
    settled = with_integrator(p, Arm(load(p.model).model))
    generate_mpc(p, work / "light", opt="-O3", native=True, log=lambda m: None)
    res = closed_loop(p, work / "light", duration=1.0, log=lambda m: None, simulator=lambda pl, dt: rk4_plant(pl, dt, 10))
    mpc, pd = res["MPC (C)"], res["feedforward + PD"]
    row = {"integrator": settled.integrator, "substeps": settled.substeps, "max_error": mpc["max_error"],
           "pd_error": pd["max_error"], "step_us": mpc["step_median_s"] * 1e6}
    log(f"  light wrist: {row['integrator']} x {row['substeps']}, tracking {row['max_error']:.2e} rad "
        f"(PD {row['pd_error']:.2e}), step {row['step_us']:.0f} us")
    return row


def main():
    work = Path(tempfile.mkdtemp())
    os.environ["RSCASADI_CACHE"] = str(work / "cache")      # every build timed from an empty cache
    base = dataclasses.replace(load_mpc_problem(PROBLEM), interval=0.01, substeps=2)
    rows = []
    tuned = os.environ.get("RSCASADI_BENCH_BLASFEO", "")
    for N in HORIZONS:
        for qp in ("condensed", "riccati"):
            if qp == "condensed" and N > CONDENSED_UP_TO:
                continue
            print(f"N = {N}, {qp} ...", flush=True)
            rows.append(case(dataclasses.replace(base, horizon=N, qp=qp), work))
            if qp == "riccati" and N in (10, 20):
                rows.append(case(dataclasses.replace(base, horizon=N, qp=qp, threads=2), work))
                if tuned:
                    rows += [case(dataclasses.replace(base, horizon=N, qp=qp, threads=t), work, blasfeo=tuned)
                             for t in (1, 2)]
    print("task space ...", flush=True)
    tasks = [task_space(work, blasfeo=b, threads=t) for b in [""] + ([tuned] if tuned else []) for t in (1, 2)]
    baxter, settled = second_arm(work, tuned)
    light = light_wrist(work)
    label = lambda r: (r["qp"] + (f", {r['threads']} threads" if r["threads"] > 1 else "")
                       + (", BLASFEO for this CPU" if r["blasfeo"] else ""))
    timed(rows + tasks + baxter)
    for r in rows + tasks + baxter:
        print(f"  {label(r)}{'' if r in rows else ', task space'}, N = {r['N']}: step {r['step_us']:.0f} us, "
              f"feedback {r['feedback_us']:.0f} us", flush=True)
    md = ["# The Panda's MPC over the horizon", "", stamp(), "",
          "`python benchmarks/bench_mpc_horizon.py`: `problems/mpc_panda.toml` with N intervals of 10 ms (2 RK4 "
          "steps each), the real-time iteration, 10 interior-point iterations of either QP, `--opt=-O3 --native`; "
          "times in C, medians over the 1000 samples of a 1 s closed loop's states (quantised encoders, a 20 % "
          "heavier last link), each the best of 3 fresh processes' medians (three rounds over all the controllers, minutes apart), the step's 99.9th percentile, and the feedback alone (mpc_feedback after "
          "mpc_prepare: the measurement-to-torque latency). The timing processes ran "
          + ("under SCHED_FIFO (priority 50) with their memory locked" if all(r["rt"] for r in rows + tasks + baxter) else
             "under the default scheduler (SCHED_FIFO and mlockall not permitted here)") + ".", "",
          "| QP | N | generate + compile, empty cache (s) | C (MB) | step median (us) | step 99.9 % (us) | feedback (us) | "
          "tracking (rad) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {label(r)} | {r['N']} | {r['build_s']:.0f} | {r['c_mb']:.1f} | {r['step_us']:.0f} | "
                  f"{r['step_p999_us']:.0f} | {r['feedback_us']:.0f} | {r['max_error']:.2e} |")
    by = {(r["qp"], r["N"]): r for r in rows if not r["blasfeo"] and r["threads"] == 1}
    ratio = lambda qp, a, b: by[(qp, b)]["step_us"] / by[(qp, a)]["step_us"]
    md += ["", f"Step growth from N = 10 to 20: condensed {ratio('condensed', 10, 20):.1f}x, Riccati "
               f"{ratio('riccati', 10, 20):.1f}x; Riccati from 20 to 40: {ratio('riccati', 20, 40):.1f}x. "
               f"The condensed QP is not generated beyond N = {CONDENSED_UP_TO} (its C grows as N^2). The Riccati "
               "controller's BLASFEO: the CasADi wheel's (its GENERIC target) with BLASFEO's 4x4 product and matrix-vector "
               "kernels in vector C in the controller's library, or one built for this CPU where the row says so.", "",
           "## Task space", "",
           "`problems/mpc_panda_shelf.toml`: the hand's position, velocity and rotation along the shelf motion, the "
           "ball and the table as soft constraints, N = 10 intervals of 10 ms; phases timed along its closed loop "
           "(as modelled, 1 kHz, quantised encoders).", "",
           "| QP | step median (us) | step 99.9 % (us) | feedback (us) | the hand within (mm) |", "|---|---|---|---|---|"]
    md += [f"| {label(r)} | {r['step_us']:.0f} | {r['step_p999_us']:.0f} | {r['feedback_us']:.0f} | "
           f"{r['max_error'] * 1e3:.1f} |" for r in tasks]
    md += ["", "## A second 7-joint arm: Baxter's left arm", "",
           "Baxter's left arm from its whole-robot URDF (`tests/data/baxter_description`) with an FS-SEA in every "
           "joint (`benchmarks/common.py`, as in `bench_tasks.md`), `problems/mpc_panda.toml`'s settings with N "
           f"intervals of 10 ms and substeps = auto ({settled.integrator} x {settled.substeps} per interval), on a "
           "motion of the Panda's form from Baxter's neutral pose (the hand sweeps about 0.4 m; a 20 % heavier last "
           "link), timed as above.", "",
           "| arm | QP | N | generate + compile, empty cache (s) | step median (us) | step 99.9 % (us) | feedback (us) | "
           "tracking (rad) |", "|---|---|---|---|---|---|---|---|"]
    md += [f"| Baxter's left arm | {label(r)} | {r['N']} | {r['build_s']:.0f} | {r['step_us']:.0f} | "
           f"{r['step_p999_us']:.0f} | {r['feedback_us']:.0f} | {r['max_error']:.2e} |" for r in baxter]
    best = lambda key, N: min(r[key] for r in rows if r["qp"] == "riccati" and r["N"] == N)
    targets = [("joint space, N = 10, step", best("step_us", 10), 400), ("joint space, N = 10, feedback",
               best("feedback_us", 10), 100), ("joint space, N = 20, step", best("step_us", 20), 800),
               ("task space, N = 10, step", min(r["step_us"] for r in tasks), 600)]
    fastest = lambda N: min((r for r in baxter if r["N"] == N), key=lambda r: r["step_us"])
    targets += [("Baxter's left arm, joint space, N = 10, step", fastest(10)["step_us"], 400),
                ("Baxter's left arm, joint space, N = 10, feedback", fastest(10)["feedback_us"], 100),
                ("Baxter's left arm, joint space, N = 20, step", fastest(20)["step_us"], 800)]
    md += ["", "## Targets (medians, the best row of this run: BLASFEO, threads)", "", "| | measured (us) | target (us) | |",
           "|---|---|---|---|"]
    md += [f"| {what} | {v:.0f} | < {goal} | {'met' if v < goal else f'missed by {v / goal:.2f}x'} |"
           for what, v, goal in targets]
    md += ["", "## A light wrist", "",
           f"The Panda with its last link {1 / LIGHT:g} times lighter, `problems/mpc_panda.toml`'s settings: the "
           f"integrator `auto` took {light['integrator']} with {light['substeps']} substeps per 20 ms interval; every "
           f"step finite, tracking to {light['max_error']:.2e} rad (feedforward + PD: {light['pd_error']:.2e}), "
           f"step median {light['step_us']:.0f} us in the closed loop."]
    (RESULTS / "bench_mpc_horizon.md").write_text("\n".join(md) + "\n")
    print(f"wrote {RESULTS / 'bench_mpc_horizon.md'}")


if __name__ == "__main__":
    main()
