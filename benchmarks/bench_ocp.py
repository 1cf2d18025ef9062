"""Benchmark of the optimal-control layer (issues 5 and 10), in one run:

1. fatrop against IPOPT: problems (a) minimum time and (b) minimum effort, Radau degree 3,
   N = 100 and 200, condensed and lifted (explicit and implicit dynamics), compiled NLP; solve time (median of 5 at
   N = 100), iterations, and fatrop's own profile (time in its search direction = its linear
   algebra, against function evaluations), and IPOPT with fatrop's monotone barrier rule (where
   fatrop's extra iterations come from) and with its adaptive rule's other oracles (probing, LOQO);
2. the mesh-refinement history of problem (b) under the tightened rest tolerances;
3. co-design: problem (a) with the three SEA stiffnesses free, against the nominal arm;
(sweeps: benchmarks/bench_sweep.py)

    python benchmarks/bench_ocp.py       # writes results/bench_ocp.{md,csv,png}

fatrop's BLASFEO in the rows above: the CasADi wheel's with its 4x4 dgemm kernel compiled for this
processor (the default; rscasadi/ocp/fatrop/blasfeo.py).  A child process runs IPOPT and fatrop
(condensed, N = 100, round-robin within the child) on the wheel's kernels as shipped
(RSCASADI_BLASFEO=wheel); with RSCASADI_BLASFEO=/path/to/libblasfeo.so (an optimised BLASFEO,
docs/user-guide/model.md) a second child runs them on that one.
"""
import dataclasses
import json
import os
import subprocess
import sys
import time

# the fastest solves (the compile is cached); tests build at -O1
os.environ.setdefault("RSCASADI_NLP_OPT", "-O3")

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from common import stamp, ROOT, write_results  # noqa: E402
from rscasadi.native.parallel import available_cores  # noqa: E402
from rscasadi.ocp.fatrop.blasfeo import ENV as BLASFEO_ENV, WHEEL  # noqa: E402
import rscasadi.ocp.solving as solving  # noqa: E402
from rscasadi.ocp import load_problem, solve, solve_once  # noqa: E402

PROBLEMS = {"min_time": ROOT / "problems" / "ocp_min_time.toml", "min_effort": ROOT / "problems" / "ocp_min_effort.toml"}
TARGET = {"min_effort": 0.1, "min_time": 0.25}
QUIET = {"print_level": 0, "log": lambda m: None}


def timed(ps, repeats, options=None):
    """For each problem of `ps` (with its solver options, `options[i]`): the median solve time over
    `repeats` solves, its first solve's record and its solver's stats.  Round-robin (one solve of
    each per round): this VM's speed drifts within minutes, and the rows are compared with each other."""
    holder, out = {}, [dict(times=[]) for _ in ps]
    original = solving.make_solver

    def spy(*args, **kw):
        holder["solver"], f = original(*args, **kw)
        return holder["solver"], f
    solving.make_solver = spy
    options = options or [None] * len(ps)
    try:
        for _ in range(repeats):
            for p, o, opts in zip(ps, out, options):
                sol = solve_once(p, options=opts, **QUIET)
                o["times"].append(sol["solve_time_s"])
                o.setdefault("sol", sol)
                o.setdefault("stats", holder["solver"].stats())
    finally:
        solving.make_solver = original
    return [(float(np.median(o["times"])), o["sol"], o["stats"]) for o in out]


TRANSCRIPTIONS = (("condensed", "explicit"), ("lifted", "explicit"), ("lifted", "implicit"))
# fatrop: through its own C interface (the default), and through CasADi's plugin on the same NLP
SOLVERS = ("ipopt", "fatrop", "fatrop (CasADi plugin)", "ipopt (monotone barrier)", "ipopt (probing oracle)",
           "ipopt (LOQO oracle)")
CORES = available_cores()
# IPOPT with fatrop's barrier rule (Fiacco-McCormick, from fatrop's first mu): the evidence of where
# fatrop's extra iterations come from (fatrop 1.1.8 ships no adaptive barrier; docs/design/condensing.md)
MONOTONE = {"mu_strategy": "monotone", "mu_init": 1e-2}
# IPOPT's adaptive rule with its other two oracles (its default, "ipopt", asks the quality function,
# which needs an affine and a centring direction per iteration): which adaptive rule would save
# fatrop iterations, were one plugged into it
IPOPT_OPTIONS = {SOLVERS[3]: MONOTONE, SOLVERS[4]: {"mu_oracle": "probing"}, SOLVERS[5]: {"mu_oracle": "loqo"}}
# (solver, threads of the NLP's loops over the intervals): the condensed form on one thread and on
# every core, for both solvers (their NLP functions are the same library); the rest on every core
RUNS = {"condensed": [("ipopt", 1), ("ipopt", CORES), ("fatrop", 1), ("fatrop", CORES), (SOLVERS[2], CORES),
                      *((solver, 1) for solver in IPOPT_OPTIONS)],
        "lifted": [("ipopt", CORES), ("fatrop", CORES)]}


def configured(base, N, transcription, dynamics, runs):
    """The problems of `runs` ((solver, threads) rows) and their solver options, compiled (cached) first."""
    ps = [base.replace(intervals=N, dynamics=dynamics, solver=solver.split()[0], compiled=True,
                              condense=transcription == "condensed", threads=threads,
                              interface="casadi" if "plugin" in solver else "direct") for solver, threads in runs]
    for p in ps:
        solve_once(p, **QUIET)
    return ps, [IPOPT_OPTIONS.get(solver) for solver, _ in runs]


def blasfeo_rows():
    """(In the child, on RSCASADI_BLASFEO's library) condensed N = 100: IPOPT and fatrop, 1 and all cores."""
    runs = [run for run in RUNS["condensed"] if "plugin" not in run[0]]
    rows = []
    for name, path in PROBLEMS.items():
        ps, options = configured(load_problem(path), 100, "condensed", "explicit", runs)
        for (solver, _), (t, sol, _) in zip(runs, timed(ps, 5, options)):
            rows.append(dict(problem=name, solver=solver, threads=sol["threads"], status=sol["status"],
                             iterations=sol["iterations"], solve_s=t, objective=sol["objective"], blasfeo=sol["blasfeo"]))
    return rows


def blasfeo_section(path) -> list:
    """The child's rows on RSCASADI_BLASFEO=`path` as a markdown section (or how to get them)."""
    title = ("the CasADi wheel's BLASFEO as shipped (RSCASADI_BLASFEO=wheel: its GENERIC kernels, none tuned)"
             if path == WHEEL else "an optimised BLASFEO (RSCASADI_BLASFEO)")
    head = ["", f"## fatrop on {title}; N = 100, condensed", ""]
    if not path:
        return head + ["Not run: set RSCASADI_BLASFEO to a BLASFEO built for this CPU (docs/user-guide/model.md, "
                       "'fatrop's linear algebra')."]
    print(f"IPOPT and fatrop on {BLASFEO_ENV}={path} (a child process, ~2 min) ...", flush=True)
    run = subprocess.run([sys.executable, __file__, "--blasfeo-rows"], env={**os.environ, BLASFEO_ENV: path},
                         capture_output=True, text=True)
    if run.returncode != 0:
        raise RuntimeError(f"the BLASFEO rows failed ({BLASFEO_ENV}={path}):\n{run.stderr[-2000:]}")
    rows = json.loads(run.stdout.strip().splitlines()[-1])
    lib = next(r["blasfeo"] for r in rows if r["solver"] == "fatrop")
    md = head + [f"{BLASFEO_ENV}={path}: fatrop's calls reached {lib['library']} (built for '{lib['features']}'; "
                 f"tuned kernels: {lib['tuned_kernels']}); IPOPT and fatrop round-robin in one child process.", "",
                 "| problem | solver | threads | status | iterations | solve (s) | objective |", "|---|---|---|---|---|---|---|"]
    md += [f"| {r['problem']} | {r['solver']} | {r['threads']} | {r['status']} | {r['iterations']} | {r['solve_s']:.3f} | "
           f"{r['objective']:.8g} |" for r in rows]
    md.append("")
    for name in PROBLEMS:
        at = {(r["solver"], r["threads"]): r["solve_s"] for r in rows if r["problem"] == name}
        fat, ip = at[("fatrop", CORES)], at[("ipopt", CORES)]
        best = min(v for (solver, _), v in at.items() if solver.startswith("ipopt"))
        md.append(f"- {name}: fatrop {fat:.3f} s on {CORES} threads; IPOPT on the same threads {ip:.3f} s ({ip / fat:.2f}x), "
                  f"IPOPT's fastest {best:.3f} s ({best / fat:.2f}x); target 5x: " + ("met" if best >= 5 * fat else "MISSED")
                  + f"; on one thread each {at[('fatrop', 1)]:.3f} s against {at[('ipopt', 1)]:.3f} s "
                  f"({at[('ipopt', 1)] / at[('fatrop', 1)]:.2f}x)")
        print(md[-1], flush=True)
    return md


def solver_rows():
    rows = []
    for name, path in PROBLEMS.items():
        base = load_problem(path)
        for N in (100, 200):
            for transcription, dynamics in TRANSCRIPTIONS:
                runs = RUNS[transcription]
                ps, options = configured(base, N, transcription, dynamics, runs)
                for (solver, _), (t, sol, stats) in zip(runs, timed(ps, 5 if N == 100 else 1, options)):
                    fat = stats.get("fatrop", {})
                    la = fat.get("compute_sd_time", float("nan"))
                    evals = sum(fat.get(k, 0.0) for k in ("eval_hess_time", "eval_jac_time", "eval_cv_time",
                                                          "eval_grad_time", "eval_obj_time")) if fat else float("nan")
                    label = "condensed" if transcription == "condensed" else f"lifted, {dynamics}"
                    rows.append(dict(problem=name, N=N, transcription=label, dynamics=dynamics, solver=solver,
                                     threads=sol["threads"], status=sol["status"], iterations=sol["iterations"], solve_s=t,
                                     objective=sol["objective"], linear_algebra_s=la, evaluations_s=evals))
                    print(f"{name:10s} N={N:3d} {label:17s} {solver:22s} {sol['threads']} thr {sol['status']:16s} it {sol['iterations']:4d} "
                          f"solve {t:6.3f} s" + (f"  (fatrop: search direction {la:.3f} s, evaluations {evals:.3f} s)"
                                                  if fat else ""), flush=True)
    return rows


def main():
    user_blasfeo = os.environ.pop(BLASFEO_ENV, None)         # the main rows: the default (tuned kernel)
    if user_blasfeo == WHEEL:
        raise SystemExit(f"{BLASFEO_ENV}={WHEEL}: the benchmark runs the wheel's kernels in a child anyway; "
                         f"unset it, or give an optimised BLASFEO")
    rows = solver_rows()
    md = ["# Optimal control: fatrop against IPOPT, refinement, co-design", "", stamp(), "",
          f"`python benchmarks/bench_ocp.py` on this 2-core machine; Radau degree 3, compiled NLP and kernel "
          f"({os.environ['RSCASADI_NLP_OPT']}), exact",
          "Hessians, the same tolerance (1e-8) for both solvers; solve = wall time of the solver call, median",
          "of 5 at N = 100.  condensed: each interval's accelerations solved inside the NLP's functions (a C",
          "kernel; docs/design/condensing.md), the solver sees (x_k, tau_k); lifted: they are NLP variables.  fatrop's split:",
          "its search-direction time (its Riccati linear algebra) and its function evaluations.  fatrop: through",
          "its own C interface, stage by stage (same page), its solver built in the setup (once per",
          "layout of the bounds, as an nlpsol is built before its calls) and the pieces' derivatives placed",
          "unscattered; fatrop (CasADi plugin): casadi.nlpsol on the same",
          "compiled NLP (same iterates).  threads: the NLP's loops over the intervals (OpenMP; the same",
          "library and iterates for both solvers on any number of threads).  fatrop's BLASFEO: the CasADi wheel's",
          "(its GENERIC target) with its 4x4 dgemm kernel compiled for this processor (the default); the wheel's",
          "kernels as shipped, and an optimised BLASFEO if given, in their own sections below.", "",
          "| problem | N | transcription | solver | threads | status | iterations | solve (s) | fatrop search direction (s) | fatrop evaluations (s) |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    md += [f"| {r['problem']} | {r['N']} | {r['transcription']} | {r['solver']} | {r['threads']} | {r['status']} | {r['iterations']} | "
           f"{r['solve_s']:.3f} | {r['linear_algebra_s']:.3f} | {r['evaluations_s']:.3f} |" for r in rows]
    md += ["", "## Targets (N = 100)", ""]
    for name, limit in TARGET.items():
        at = {(r["transcription"], r["solver"], r["threads"]): r["solve_s"] for r in rows if r["problem"] == name and r["N"] == 100}
        fat, fat1, plug = at[("condensed", "fatrop", CORES)], at[("condensed", "fatrop", 1)], at[("condensed", SOLVERS[2], CORES)]
        ip, ip1 = at[("condensed", "ipopt", CORES)], at[("condensed", "ipopt", 1)]
        ip_best = min(v for (tr, solver, _), v in at.items() if solver.startswith("ipopt"))
        md.append(f"- {name}: fatrop (condensed, {CORES} threads) {fat:.3f} s: target < {limit:g} s "
                  + ("met" if fat < limit else "MISSED")
                  + f"; IPOPT on the same condensed NLP and threads {ip:.3f} s ({ip / fat:.2f}x), IPOPT's fastest "
                  f"{ip_best:.3f} s ({ip_best / fat:.2f}x); target 5x: " + ("met" if ip_best >= 5 * fat else "MISSED")
                  + f"; on one thread each: fatrop {fat1:.3f} s, IPOPT {ip1:.3f} s ({ip1 / fat1:.2f}x)"
                  + f"; fatrop through CasADi's plugin {plug:.3f} s ({ip / plug:.2f}x IPOPT)")
    md += ["", "## Why not 5x: iterations and time per iteration (N = 100, condensed, one thread)", "",
           "fatrop's barrier rule is monotone (Fiacco-McCormick); IPOPT's here is adaptive, its mu chosen each",
           "iteration by an oracle: by default the quality function (an affine and a centring direction, mu",
           "minimising a model of the KKT error), also run with Mehrotra's probing and LOQO's rule.  IPOPT with",
           "fatrop's rule (monotone, mu_init 1e-2) shows whether the rule alone explains the iteration counts.",
           "5x overall needs 5 x (fatrop's iterations / IPOPT's) per iteration.", ""]
    for name in PROBLEMS:
        one = {r["solver"]: r for r in rows if r["problem"] == name and r["N"] == 100
               and r["transcription"] == "condensed" and r["threads"] == 1}
        f, a, m = one["fatrop"], one["ipopt"], one[SOLVERS[3]]
        per = lambda r: r["solve_s"] / max(r["iterations"], 1)  # noqa: E731
        md.append(f"- {name}: fatrop {f['iterations']} iterations, {1e3 * per(f):.2f} ms each; IPOPT (adaptive, quality "
                  f"function) {a['iterations']}, {1e3 * per(a):.2f} ms each; IPOPT (monotone, as fatrop) {m['iterations']}, "
                  f"{1e3 * per(m):.2f} ms each (iterations {'equal to' if m['iterations'] == f['iterations'] else 'unlike'} "
                  f"fatrop's); IPOPT adaptive with probing {one[SOLVERS[4]]['iterations']}, with LOQO "
                  f"{one[SOLVERS[5]]['iterations']}.  Per iteration fatrop is {per(a) / per(f):.2f}x IPOPT; 5x overall "
                  f"would need {5 * f['iterations'] / a['iterations']:.2f}x")
    md += blasfeo_section(WHEEL) + blasfeo_section(user_blasfeo)
    md += ["", "## Implicit against explicit iterations", ""]
    for name in PROBLEMS:
        for N in (100, 200):
            it = {r["dynamics"]: r["iterations"] for r in rows if r["problem"] == name and r["N"] == N
                  and r["solver"] == "ipopt" and r["transcription"].startswith("lifted")}
            md.append(f"- {name}, N = {N}, IPOPT: explicit {it['explicit']}, implicit {it['implicit']} "
                      f"({it['implicit'] / it['explicit']:.2f}x; target <= 1.5x)")

    # 2. refinement history of problem (b)
    sol = solve(load_problem(PROBLEMS["min_effort"]), **QUIET)
    md += ["", "## Mesh refinement, problem (b) (rest tolerances 1e-4 rad, 1e-3 rad/s on the replay)", "",
           "| round | intervals | iterations | solve (s) | final angle error (rad) | final speed error (rad/s) | limit violation | passed |",
           "|---|---|---|---|---|---|---|---|"]
    md += [f"| {r['round']} | {r['intervals']} | {r['iterations']} | {r['solve_time_s']:.2f} | {r['final_angle_error']:.1e} | "
           f"{r['final_speed_error']:.1e} | {r['max_limit_violation']:.1e} | {r['passed']} |" for r in sol["rounds"]]
    print("refinement of (b):", [(r["intervals"], r["passed"]) for r in sol["rounds"]], flush=True)

    # 3. co-design
    cod = solve(load_problem(ROOT / "problems" / "ocp_min_time_codesign.toml"), **QUIET)
    nom = cod["nominal"]
    md += ["", "## Co-design: minimum time with the three SEA stiffnesses free (300-3000 N m/rad)", "",
           "| arm | " + " | ".join(cod["design"]) + " | minimum time (s) | verified |",
           "|---|" + "---|" * len(cod["design"]) + "---|---|",
           "| nominal | " + " | ".join(f"{v:.0f}" for v in nom["design"].values()) + f" | {nom['duration']:.4f} | {nom['success']} |",
           "| co-designed | " + " | ".join(f"{v:.0f}" for v in cod["design"].values()) + f" | {cod['t'][-1]:.4f} | {cod['success']} |"]
    print(f"co-design: T {nom['duration']:.4f} -> {cod['t'][-1]:.4f} s with {cod['design']}", flush=True)

    csv = "problem,N,transcription,solver,threads,status,iterations,solve_s,objective,fatrop_search_direction_s,fatrop_evaluations_s\n" + "".join(
        f"{r['problem']},{r['N']},{r['transcription'].replace(', ', ' ')},{r['solver']},{r['threads']},{r['status']},{r['iterations']},{r['solve_s']:.4f},"
        f"{r['objective']:.8g},{r['linear_algebra_s']:.4f},{r['evaluations_s']:.4f}\n" for r in rows)
    fig, ax = plt.subplots(figsize=(7, 4))
    for name in PROBLEMS:
        for solver in SOLVERS[:2]:
            for transcription, style in (("condensed", "o-"), ("lifted, explicit", "s--")):
                pts = [(r["N"], r["solve_s"]) for r in rows if r["problem"] == name and r["solver"] == solver
                       and r["transcription"] == transcription and r["threads"] == CORES]
                ax.loglog(*zip(*pts), style, label=f"{name}, {solver}, {transcription}")
    ax.set(xlabel="intervals N", ylabel="solve time (s)", title="Radau 3, compiled")
    ax.legend(fontsize=8)
    fig.tight_layout()
    write_results("bench_ocp", fig, csv, "\n".join(md) + "\n")


if __name__ == "__main__":
    if "--blasfeo-rows" in sys.argv:
        print(json.dumps(blasfeo_rows()))
        sys.exit(0)
    t0 = time.perf_counter()
    main()
    print(f"bench_ocp: {time.perf_counter() - t0:.0f} s")
