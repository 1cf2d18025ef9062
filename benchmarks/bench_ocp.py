"""Benchmark of the optimal-control problems (issue 5): solve time and iterations for N = 50,
100, 200 intervals (Radau, degree 3), explicit against implicit dynamics, compiled NLP against
CasADi's virtual machine, for problems (a) minimum time and (b) minimum effort.  The compiled
N = 100 cases are timed as the median of 5 solves (the compile itself, cached, is reported apart).

    python benchmarks/bench_ocp.py       # writes results/bench_ocp.{md,csv,png}
"""
import dataclasses
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from common import ROOT, write_results  # noqa: E402
from rscasadi.control.ocp import load_problem, solve, verify  # noqa: E402

PROBLEMS = {"min_time": ROOT / "problems" / "ocp_min_time.toml", "min_effort": ROOT / "problems" / "ocp_min_effort.toml"}
TARGET = {"min_effort": 1.0, "min_time": 3.0}


def main():
    rows = []
    for name, path in PROBLEMS.items():
        base = load_problem(path)
        for N in (50, 100, 200):
            for dynamics in ("explicit", "implicit"):
                for compiled in (True, False):
                    p = dataclasses.replace(base, intervals=N, dynamics=dynamics, compiled=compiled)
                    t0 = time.perf_counter()
                    sol = solve(p, print_level=0, log=lambda m: None)
                    first = time.perf_counter() - t0
                    repeats = 5 if (compiled and N == 100) else 1
                    times = [sol["solve_time_s"]] + [solve(p, print_level=0, log=lambda m: None)["solve_time_s"]
                                                     for _ in range(repeats - 1)]
                    rep = verify(sol)
                    rows.append((name, N, dynamics, compiled, sol["status"], sol["iterations"], float(np.median(times)),
                                 first - sol["solve_time_s"], max(rep["final_angle_error"], rep["final_speed_error"]),
                                 rep["max_limit_violation"]))
                    print(f"{name:10s} N={N:3d} {dynamics:8s} {'compiled' if compiled else 'VM':8s} "
                          f"{sol['status']:22s} it {sol['iterations']:4d}  solve {rows[-1][6]:7.2f} s "
                          f"(median of {repeats})  setup {rows[-1][7]:6.1f} s  final-state error {rows[-1][8]:.1e} (rad, rad/s)",
                          flush=True)
    panda = load_problem(ROOT / "problems" / "ocp_panda_min_time.toml")
    sol = solve(panda, print_level=0, log=lambda m: None)
    rep = verify(sol)
    rows.append(("panda_min_time (7 joints)", panda.intervals, panda.dynamics, panda.compiled, sol["status"],
                 sol["iterations"], sol["solve_time_s"], sol["setup_time_s"],
                 max(rep["final_angle_error"], rep["final_speed_error"]), rep["max_limit_violation"]))
    print(f"Panda minimum time N={panda.intervals}: {sol['status']} it {sol['iterations']} solve "
          f"{sol['solve_time_s']:.1f} s, T = {sol['t'][-1]:.3f} s, limit violation {rep['max_limit_violation']:.1e}",
          flush=True)
    checks = []
    for name, limit in TARGET.items():
        r = next(r for r in rows if r[0] == name and r[1] == 100 and r[2] == "explicit" and r[3])
        checks.append(f"{name}, N = 100, Radau 3, compiled, explicit: {r[6]:.2f} s (target < {limit:g} s): "
                      + ("met" if r[6] < limit else "MISSED"))
    for c in checks:
        print(c)
    csv = "problem,N,dynamics,compiled,status,iterations,solve_s,setup_s,final_state_error,max_limit_violation\n" + "".join(
        f"{a},{b},{c},{d},{e},{f},{g:.3f},{h:.1f},{i:.3e},{j:.3e}\n" for a, b, c, d, e, f, g, h, i, j in rows)
    md = ["# Optimal control: solve time and iterations", "",
          "`python benchmarks/bench_ocp.py`, Radau degree 3, IPOPT (MUMPS), exact Hessians, 2-core machine.",
          "solve = IPOPT wall time (median of 5 for compiled N = 100); setup = building the NLP and, for",
          "compiled, generating and compiling its C (-O1) the first time (cached afterwards).", "",
          "| problem | N | dynamics | NLP | status | iterations | solve (s) | setup (s) | final-state error | limit violation |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    md += [f"| {a} | {b} | {c} | {'compiled' if d else 'CasADi VM'} | {e} | {f} | {g:.2f} | {h:.1f} | {i:.1e} | {j:.1e} |"
           for a, b, c, d, e, f, g, h, i, j in rows]
    md += ["", "## Targets", ""] + [f"- {c}" for c in checks]
    fig, ax = plt.subplots(figsize=(7, 4))
    for name in PROBLEMS:                                 # the Panda's single row is in the table only
        for dyn in ("explicit", "implicit"):
            pts = [(r[1], r[6]) for r in rows if r[0] == name and r[2] == dyn and r[3]]
            ax.loglog(*zip(*pts), "o-", label=f"{name}, {dyn}, compiled")
    ax.set(xlabel="intervals N", ylabel="IPOPT wall time (s)", title="direct collocation, Radau 3")
    ax.legend(fontsize=8)
    fig.tight_layout()
    write_results("bench_ocp", fig, csv, "\n".join(md) + "\n")


if __name__ == "__main__":
    main()
