"""Benchmark of tasks in space, in one run:

1. the Panda's shelf task (problems/ocp_panda_shelf.toml: 2 kg, minimum time, a pose goal,
   around a ball above the table) as `rscasadi ocp` solves it: cold (an empty compile cache:
   everything it needs compiled), warm with --cold (the cache that first solve filled) and warm
   from the verified solution the earlier runs kept: the time to the first solve's start
   (compiling or finding the condensing kernel), the first round's solve, and the whole solve
   with its mesh refinements;
   the same kind of task on a second 7-joint arm, Baxter's left arm from its whole-robot URDF
   (tests/data/baxter_description, as example-robot-data ships it) with an FS-SEA table, a 1 kg
   part, a ball and a table, cold and warm;
2. warm solves of the 3-joint tasks: the reach around a ball (ocp_reach_around.toml) and the
   minimum time once round a circle (ocp_tool_circle.toml);
3. the task-space MPC (problems/mpc_arm3_tool.toml): its step time in C in the closed loop.

    python benchmarks/bench_tasks.py       # writes results/bench_tasks.{md,csv,png}

Each solve runs in a child process (a fresh interpreter, as a user's first command would).
"""
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from common import baxter_model, stamp, ROOT, solve_in_child, write_results  # noqa: E402


def baxter_task(directory: Path) -> Path:
    """Baxter's left arm (common.baxter_model) moving a 1 kg part from its neutral pose to a pose
    0.4 m away, the gripper pointing down, over a ball and above a table: the model and problem
    files, written into `directory`; the problem's path."""
    baxter_model(directory)
    (directory / "ocp_baxter_shelf.toml").write_text(BAXTER_TASK)
    return directory / "ocp_baxter_shelf.toml"


BAXTER_TASK = """model = "baxter_sea.toml"
objective = "min_time"
theta_start = [0.0, -0.55, 0.0, 0.75, 0.0, 1.26, 0.0]   # Baxter's neutral pose
duration = 1.5
max_duration = 6.0
effort_weight = 1e-3
payload = { frame = "left_gripper", mass = 1.0, com = [0.0, 0.0, 0.03], inertia = [1.5e-3, 1.5e-3, 1e-3, 0.0, 0.0, 0.0] }

[goal]
frame = "left_gripper"
position = [0.80, 0.45, 0.06]
rpy = [3.141592653589793, 0.0, -2.356194490192345]   # pointing down, turned as at the start
tolerance = { position = 1e-3, angle = 1e-2 }

[[obstacles]]
sphere = { center = [0.73, 0.64, 0.10], radius = 0.08 }
[[obstacles]]
box = { center = [0.75, 0.6, -0.06], size = [0.8, 1.0, 0.04] }

[transcription]
method = "radau"
degree = 3
intervals = 100
dynamics = "implicit"
compiled = true
limit_margin = 0.003    # 0.1 % left the replay 0.1 % over a limit after three refinements

[refinement]
rounds = 3

[solver]
threads = 0
"""


def main():
    shelf = ROOT / "problems" / "ocp_panda_shelf.toml"
    rows = []
    with tempfile.TemporaryDirectory() as cache:            # empty, then filled by that first solve
        rows.append(("Panda shelf task, cold cache", solve_in_child(shelf, cache, "command")))
        rows.append(("Panda shelf task, warm cache, --cold", solve_in_child(shelf, cache, "command")))
        rows.append(("Panda shelf task, warm cache, its solution kept", solve_in_child(shelf, cache, "reuse")))
    with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as files:
        baxter = baxter_task(Path(files))
        rows.append(("Baxter left arm task, cold cache", solve_in_child(baxter, cache, "command")))
        rows.append(("Baxter left arm task, warm cache, --cold", solve_in_child(baxter, cache, "command")))
        rows.append(("Baxter left arm task, warm cache, its solution kept", solve_in_child(baxter, cache, "reuse")))
    for name in ("reach_around", "tool_circle"):
        solve_in_child(ROOT / "problems" / f"ocp_{name}.toml")                  # fill the cache
        rows.append((f"{name} (3 joints), warm cache", solve_in_child(ROOT / "problems" / f"ocp_{name}.toml")))
    from rscasadi.mpc import generate_mpc, task_closed_loop
    with tempfile.TemporaryDirectory() as build:
        generate_mpc(ROOT / "problems" / "mpc_arm3_tool.toml", build, log=lambda m: None)
        loop = task_closed_loop(ROOT / "problems" / "mpc_arm3_tool.toml", build, log=print)
    md = ["# Tasks in space", "", stamp(), "",
          "`python benchmarks/bench_tasks.py`: each optimal-control problem solved in a fresh process (the 7-joint "
          "tasks as `rscasadi ocp` solves them, with `--cold` or starting from the verified solution an earlier run "
          "kept for the same problem; the 3-joint ones by `rscasadi.ocp.solve`), fatrop (IPOPT where fatrop fails), "
          "with mesh refinement until the replay on the complete model passes. *Setup* is the time before a round's solve starts: transcribing, generating and compiling "
          "(or finding in the cache) the condensing kernel and the NLP's end pieces; *wall* the child from "
          "importing rscasadi to the verified answer, replays included (no plots).", "",
          "| problem | T (s) | verified | first round: setup (s) | solve (s) | iterations | rounds | all rounds: setup (s) | solve (s) | wall (s) |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    csv = ["problem,T_s,success,setup_first_s,solve_first_s,iterations_first,rounds,setup_all_s,solve_all_s,wall_s"]
    for name, r in rows:
        md.append(f"| {name} | {r['T']:.4f} | {'yes' if r['success'] else 'NO'} | {r['setup_first_s']:.1f} | "
                  f"{r['solve_first_s']:.2f} | {r['iterations_first']} | {r['rounds']} | {r['setup_all_s']:.1f} | "
                  f"{r['solve_all_s']:.2f} | {r['wall_s']:.0f} |")
        csv.append(f"\"{name}\",{r['T']},{r['success']},{r['setup_first_s']},{r['solve_first_s']},{r['iterations_first']},"
                   f"{r['rounds']},{r['setup_all_s']},{r['solve_all_s']},{r['wall_s']}")
    verdict = lambda v, goal: "met" if v < goal else f"missed by {v / goal:.2f}x"     # noqa: E731
    md += ["", "Targets for the 7-joint obstacle tasks: the verified answer from an empty cache in under 90 s and "
           "from a filled one in under 10 s (the same problem again: its solution kept).", ""]
    for arm, (cold, warm, kept) in (("Panda", [r for _, r in rows[0:3]]), ("Baxter", [r for _, r in rows[3:6]])):
        md.append(f"- {arm}: the same problem again, {kept['wall_s']:.1f} s ({verdict(kept['wall_s'], 10)}, "
                  f"{'verified' if kept['success'] else 'NOT verified'}, {kept['rounds']} round(s) where --cold took "
                  f"{warm['rounds']}).")
        md.append(f"- {arm}: cold {cold['wall_s']:.0f} s ({verdict(cold['wall_s'], 90)}), warm --cold {warm['wall_s']:.0f} s "
                  f"({verdict(warm['wall_s'], 10)}, {'verified' if warm['success'] else 'NOT verified'}). Warm: "
                  f"{warm['solve_all_s']:.1f} s in the solver over {warm['rounds']} rounds ({warm['iterations_first']} "
                  f"iterations in the first, {warm['solver']} at the end), {warm['setup_all_s']:.1f} s of setup, the "
                  f"rest the replays on the complete model (CVODES), the choice of refined meshes and the imports; cold "
                  f"adds {cold['setup_first_s']:.0f} s before the first solve, almost all of it the condensing "
                  "kernel's C (at -O1).")
    md += ["", "A refinement round compiles nothing and builds nothing symbolic: the kernel is found by the stage's "
           "key and fatrop's driver evaluates it on any mesh. The problems hold a fraction of each limit in reserve "
           "at the collocation points (`limit_margin`: the Panda 0.1 %, Baxter 0.3 %): the replay between them keeps "
           "the limits after fewer refinements (the Panda: one instead of three, T 0.11 % longer; Baxter: one "
           "instead of three, T 0.05 % longer).", "",
           f"Task-space MPC (`problems/mpc_arm3_tool.toml`, 3 joints, N = 10, 5 RK4 substeps, soft obstacle): "
           f"`mpc_step` in C median {loop['step_median_s'] * 1e6:.0f} us, worst {loop['step_worst_s'] * 1e6:.0f} us over "
           f"the closed loop (1 kHz, -O2)."]
    fig, ax = plt.subplots(figsize=(8, 3.5))
    names = [n for n, _ in rows]
    ax.barh(names, [r["setup_all_s"] for _, r in rows], label="setup (compile or cache)")
    ax.barh(names, [r["solve_all_s"] for _, r in rows], left=[r["setup_all_s"] for _, r in rows], label="solve")
    ax.set(xlabel="s (all rounds)")
    ax.legend()
    fig.tight_layout()
    write_results("bench_tasks", fig, "\n".join(csv) + "\n", "\n".join(md) + "\n")


if __name__ == "__main__":
    main()
