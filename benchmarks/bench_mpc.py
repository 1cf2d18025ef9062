"""Benchmark of the generated NMPC (issue 11): the closed-loop study over the whole trajectory
(plant with a 20 % heavier tip, quantised encoders; feedforward, feedforward + PD, the C MPC) and
the example C program's own timing of every mpc_step (clock_gettime, in C).

    python benchmarks/bench_mpc.py       # writes results/bench_mpc.md and results/mpc/closed_loop.json
"""
import json
import subprocess
import tempfile
from pathlib import Path

from common import RESULTS, ROOT  # noqa: E402
from rscasadi.codegen import generate  # noqa: E402
from rscasadi.control.mpc import closed_loop, generate_mpc, load_mpc_problem  # noqa: E402

PROBLEM = ROOT / "problems" / "mpc_arm3.toml"


def main():
    work = Path(tempfile.mkdtemp())
    generate(ROOT / "problems" / "arm3.toml", work / "arm3", log=lambda m: None)
    generate_mpc(PROBLEM, work / "mpc", log=print)
    res = closed_loop(PROBLEM, work / "mpc", log=print)
    exe = work / "mpc_example"
    subprocess.run(["cc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-O2", f"-I{work / 'arm3'}", f"-I{work / 'mpc'}",
                    str(ROOT / "examples" / "mpc.c"), f"-L{work / 'arm3'}", f"-L{work / 'mpc'}", "-lrscasadi_arm",
                    "-lrscasadi_mpc", f"-Wl,-rpath,{work / 'arm3'}", f"-Wl,-rpath,{work / 'mpc'}", "-lm", "-o", str(exe)],
                   check=True)
    p = load_mpc_problem(PROBLEM)
    line = subprocess.run([str(exe), str(p.interval), "2.5"], capture_output=True, text=True,
                          check=True).stdout.splitlines()[-1]
    print("example:", line)
    (RESULTS / "mpc").mkdir(parents=True, exist_ok=True)
    (RESULTS / "mpc" / "closed_loop.json").write_text(json.dumps(res, indent=1) + "\n")
    pd, mpc = res["feedforward + PD"], res["MPC (C)"]
    md = ["# Nonlinear MPC in C", "",
          f"`python benchmarks/bench_mpc.py`: `problems/mpc_arm3.toml` (real-time iteration, N = {p.horizon} "
          f"intervals of {p.interval * 1e3:g} ms, {p.substeps} RK4 steps each, {p.newton_iterations} projected-Newton "
          "iterations), the paper's trajectory (2 s), 1 kHz, on a plant whose last link is 20 % heavier, link and motor "
          "encoders quantised (2^19 and 2^17 counts per turn), speeds by backward differences.", "",
          "| controller | max error (rad) | RMS error (rad) | limit violation | step time median / worst (us) |",
          "|---|---|---|---|---|"]
    for name, r in res.items():
        times = (f"{r['step_median_s'] * 1e6:.0f} / {r['step_worst_s'] * 1e6:.0f} (from Python, ctypes)"
                 if "step_median_s" in r else "")
        md.append(f"| {name} | {r['max_error']:.2e} | {r['rms_error']:.2e} | {r['max_limit_violation']:.1e} | {times} |")
    md += ["", f"MPC against feedforward + PD: {pd['max_error'] / mpc['max_error']:.1f}x smaller max error "
               "(target >= 10x).", "",
           "The example C program (`examples/mpc.c`, nominal plant, 0.5 s settling then the motion), timing every "
           "mpc_step in C:", "", "    " + line]
    (RESULTS / "bench_mpc.md").write_text("\n".join(md) + "\n")
    print(f"wrote {RESULTS / 'bench_mpc.md'}")


if __name__ == "__main__":
    main()
