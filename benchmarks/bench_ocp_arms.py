"""Benchmark of the optimal-control layer on the arms users have: minimum time, rest to rest, for
the 7-joint Panda (problems/ocp_panda_min_time.toml) and the 6-joint UR5
(problems/ocp_ur5_min_time.toml), both 150 intervals of Radau degree 3, condensed, fatrop on both
cores.  Each solve runs in a fresh process: first with an empty compile cache (cold: everything
it needs generated and compiled, at the default -O1), then WARM times from the filled cache.

    python benchmarks/bench_ocp_arms.py     # writes results/bench_ocp_arms.{md,csv,png}

Targets: the first compile (setup, cold) under 30 s, the solve under 0.5 s.  Also one solve with
a busy process on one core (a pure-Python loop), as on a machine that does something else.
"""
import os
import subprocess
import sys
import tempfile

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from common import stamp, ROOT, solve_in_child, write_results  # noqa: E402

PROBLEMS = {"Panda (7 joints)": "ocp_panda_min_time.toml", "UR5 (6 joints)": "ocp_ur5_min_time.toml"}
WARM = 3
PROFILE = {"Hessian": ("eval_hess_time",), "Riccati (search direction)": ("compute_sd_time",),
           "Jacobian, gradient, constraints": ("eval_jac_time", "eval_grad_time", "eval_cv_time", "eval_obj_time")}
OWN = "fatrop's own work, one core"        # the solve less the evaluations: the Riccati recursion, line search, updates
SETUP_TARGET, SOLVE_TARGET = 30.0, 0.5


def profile(problem, cache) -> dict:
    """fatrop's own split of one solve (in this process, from the filled cache), in s."""
    import rscasadi.ocp.solving as solving
    from rscasadi.ocp import load_problem, solve_once
    holder, original = {}, solving.make_solver

    def spy(*args, **kw):
        holder["solver"], f = original(*args, **kw)
        return holder["solver"], f
    os.environ["RSCASADI_CACHE"], old = str(cache), os.environ.get("RSCASADI_CACHE")
    solving.make_solver = spy
    try:
        sol = solve_once(load_problem(problem), print_level=0, log=lambda m: None)
    finally:
        solving.make_solver = original
        os.environ.pop("RSCASADI_CACHE") if old is None else os.environ.update(RSCASADI_CACHE=old)
    fat = holder["solver"].stats()["fatrop"]
    split = {"solve": sol["solve_time_s"], **{k: sum(fat.get(key, 0.0) for key in keys) for k, keys in PROFILE.items()}}
    split[OWN] = split["solve"] - split["Hessian"] - split["Jacobian, gradient, constraints"]
    return split


def busy_solve(problem, cache) -> dict:
    """A solve from the filled cache while a pure-Python loop keeps one core busy."""
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        return solve_in_child(problem, cache)
    finally:
        busy.kill()
        busy.wait()


def main():
    rows = []
    for label, name in PROBLEMS.items():
        problem = ROOT / "problems" / name
        with tempfile.TemporaryDirectory() as cache:
            cold = solve_in_child(problem, cache)
            warm = [solve_in_child(problem, cache) for _ in range(WARM)]
            loaded = busy_solve(problem, cache)
            split = profile(problem, cache)
        solve = float(np.median([w["solve_first_s"] for w in warm]))
        rows.append(dict(label=label, problem=name, T=cold["T"], verified=cold["success"] and all(w["success"] for w in warm),
                         setup_cold=cold["setup_first_s"], wall_cold=cold["wall_s"], solve=solve,
                         setup_warm=float(np.median([w["setup_first_s"] for w in warm])),
                         iterations=cold["iterations_first"], rounds=cold["rounds"], threads=cold["threads"],
                         busy=loaded["solve_first_s"], split=split))
        r = rows[-1]
        print(f"{label}: T = {r['T']:.4f} s, first compile {r['setup_cold']:.1f} s, solve {solve:.3f} s "
              f"({r['iterations']} iterations)", flush=True)
    md = ["# Optimal control on 6 and 7 joints", "", stamp(), "",
          "`python benchmarks/bench_ocp_arms.py`: minimum time, rest to rest, 150 intervals of Radau degree 3, "
          "condensed, fatrop, the NLP's loops over the intervals on both cores; each solve in a fresh process. "
          "*First compile*: the setup of the first solve with an empty cache (generating and compiling the "
          "condensing kernel, the NLP and fatrop's driver at the default -O1); *solve*: fatrop's wall time, "
          f"the median of {WARM} solves from the filled cache.", "",
          "| arm | problem | T (s) | verified | first compile (s) | cold run, wall (s) | warm setup (s) | solve (s) | "
          "iterations | target | solve, one core busy (s) |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    csv = ["arm,problem,T_s,verified,setup_cold_s,wall_cold_s,setup_warm_s,solve_s,iterations,solve_one_core_busy_s"]
    for r in rows:
        met = r["setup_cold"] < SETUP_TARGET and r["solve"] < SOLVE_TARGET
        md.append(f"| {r['label']} | `{r['problem']}` | {r['T']:.4f} | {'yes' if r['verified'] else 'NO'} | "
                  f"{r['setup_cold']:.1f} | {r['wall_cold']:.0f} | {r['setup_warm']:.1f} | {r['solve']:.3f} | "
                  f"{r['iterations']} | {'met' if met else 'MISSED'} | {r['busy']:.3f} |")
        csv.append(f"{r['label']},{r['problem']},{r['T']},{r['verified']},{r['setup_cold']},{r['wall_cold']},"
                   f"{r['setup_warm']},{r['solve']},{r['iterations']},{r['busy']}")
    md += ["", f"Targets: first compile under {SETUP_TARGET:.0f} s, solve under {SOLVE_TARGET} s. *One core busy*: one "
           "solve from the filled cache while a pure-Python loop keeps one of the cores busy (the solve's loops "
           "still on both; GNU OpenMP's idle threads sleep after 10 000 spins, rscasadi.native.parallel).", "",
           "Where a solve's time goes: fatrop's own profile of one more solve in this process (s, wall, both "
           "cores). *Hessian*: the condensing kernel's exact Hessian (per collocation point the inverse "
           "dynamics' compiled curvature, then the chain rule's glue and Z' H Z); *Riccati*: fatrop's linear "
           "algebra; the rest: the collocation solves (Newton), the kernel's sensitivities and the Jacobians. "
           f"*{OWN}*: the solve less the evaluations (the Riccati recursion, the line search, the iterate's "
           "updates); the evaluations run on both cores, fatrop's own work on one, so a solve takes at least "
           "that long however fast the evaluations become.", "",
           "| arm | solve | " + " | ".join([*PROFILE, OWN]) + " |", "|---|---|" + "---|" * (len(PROFILE) + 1)]
    md += [f"| {r['label']} | {r['split']['solve']:.3f} | "
           + " | ".join(f"{r['split'][k]:.3f} ({r['split'][k] / r['split']['solve']:.0%})" for k in [*PROFILE, OWN]) + " |"
           for r in rows]
    fig, ax = plt.subplots(figsize=(7, 2.8))
    y = np.arange(len(rows))
    ax.barh(y + 0.2, [r["setup_cold"] for r in rows], height=0.4, label="first compile (s)")
    ax.barh(y - 0.2, [10 * r["solve"] for r in rows], height=0.4, label="solve (s) x 10")
    ax.axvline(SETUP_TARGET, color="C0", lw=1, ls="--")
    ax.axvline(10 * SOLVE_TARGET, color="C1", lw=1, ls="--")
    ax.set_yticks(y, [r["label"] for r in rows])
    ax.legend()
    fig.tight_layout()
    write_results("bench_ocp_arms", fig, "\n".join(csv) + "\n", "\n".join(md) + "\n")


if __name__ == "__main__":
    main()
