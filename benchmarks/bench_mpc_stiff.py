"""Benchmark: the MPC of an arm with stiff springs behind light links (ROS2) against RK4.

The Panda with its last link 50 times lighter (`LIGHT`): its wrist's spring mode is beyond what
RK4_MOST RK4 substeps of a 20 ms interval hold, so integrator = "auto" takes the L-stable ROS2
(codegen.rosenbrock: 2 steps of 10 ms per interval), stepped in the structured kernel
(templates/step_ros2.c).  Against it, the Panda itself on RK4 (problems/mpc_panda.toml: 3 steps
per interval), same problem otherwise, same horizon, same run:

1. N = 5 and 10 intervals of 20 ms, each generated and compiled from an empty cache with
   `rscasadi mpc`'s default flags (-O3, this processor): build seconds and C size;
2. each closed loop (1 s of problems/trajectory_panda.toml, quantised encoders, a 20 % heavier
   last link), its steps then timed in C along the loop's states (bench_mpc_horizon.timed: the
   best of 3 fresh processes' medians);
3. the light wrist at N = 5 built with -O2 for any processor, the flags `rscasadi mpc` used
   before -O3 and this processor became its default.

Targets (issue: stiff springs at full speed): build under 30 s, a ROS2 step within 1.5x of the
RK4 step at the same horizon.

    python benchmarks/bench_mpc_stiff.py       # writes results/bench_mpc_stiff.md (about 10 min)
"""
import dataclasses
import os
import tempfile
import time
from pathlib import Path

from bench_mpc_horizon import LIGHT, recorded, timed
from common import light_panda, stamp, RESULTS, ROOT  # noqa: E402
from rscasadi import load
from rscasadi.dynamics.arm import Arm
from rscasadi.mpc import closed_loop
from rscasadi.mpc.generate import generate_mpc
from rscasadi.mpc.problem import load_mpc_problem, with_integrator

HORIZONS = (5, 10)
BUILD_TARGET_S = 30.0
STEP_RATIO_TARGET = 1.5


def row(p, work: Path, label: str, opt: str = "-O3", native: bool = True, log=print) -> dict:
    """Generate `p` from an empty cache with these flags, run its closed loop (traced)."""
    out = work / label.replace(" ", "_").replace(",", "")
    os.environ["RSCASADI_CACHE"] = str(out.with_name(out.name + "_cache"))
    settled = with_integrator(p, Arm(load(p.model).model))
    t0 = time.perf_counter()
    generate_mpc(p, out, opt=opt, native=native, log=lambda m: None)
    built = time.perf_counter() - t0
    traces: dict = {}
    res = closed_loop(p, out, duration=1.0, log=lambda m: None, traces=traces)["MPC (C)"]
    r = {"label": label, "N": p.horizon, "integrator": f"{settled.integrator} x {settled.substeps}",
         "flags": opt + (", this processor" if native else ", any processor"), "build_s": built,
         "c_mb": sum(f.stat().st_size for f in out.glob("*.c")) / 1e6, "max_error": res["max_error"],
         **recorded(out, traces["MPC (C)"]["x"], traces["MPC (C)"]["reference"])}
    log(f"  {label}, N = {p.horizon}: {r['integrator']}, built in {built:.0f} s ({r['c_mb']:.1f} MB of C), "
        f"tracking {r['max_error']:.2e} rad")
    return r


def main():
    work = Path(tempfile.mkdtemp())
    base = load_mpc_problem(ROOT / "problems" / "mpc_panda.toml")
    light = dataclasses.replace(base, model=light_panda(work, LIGHT), substeps="auto", integrator="auto")
    rows = []
    for N in HORIZONS:
        print(f"N = {N} ...", flush=True)
        rows.append(row(dataclasses.replace(base, horizon=N), work, f"Panda N{N}"))
        rows.append(row(dataclasses.replace(light, horizon=N), work, f"light wrist N{N}"))
    print("the light wrist with -O2 for any processor ...", flush=True)
    rows.append(row(dataclasses.replace(light, horizon=5), work, "light wrist N5 O2", opt="-O2", native=False))
    timed(rows)
    md = ["# The MPC with stiff springs: ROS2 in the step kernel against RK4", "", stamp(), "",
          "`python benchmarks/bench_mpc_stiff.py`: `problems/mpc_panda.toml` (intervals of 20 ms, the real-time "
          "iteration) on the Panda as shipped (RK4) and with its last link "
          f"{1 / LIGHT:g} times lighter (integrator and substeps `auto`: ROS2), each generated and compiled from an "
          "empty cache; the steps timed in C along each 1 s closed loop's states (quantised encoders, a 20 % heavier "
          "last link), the best of 3 fresh processes' medians.", "",
          "| arm | N | integrator | flags | generate + compile, empty cache (s) | C (MB) | step median (us) | "
          "step 99.9 % (us) | tracking (rad) |", "|---|---|---|---|---|---|---|---|---|"]
    md += [f"| {r['label'].rsplit(' N', 1)[0]} | {r['N']} | {r['integrator']} | {r['flags']} | {r['build_s']:.0f} | "
           f"{r['c_mb']:.2f} | {r['step_us']:.0f} | {r['step_p999_us']:.0f} | {r['max_error']:.2e} |" for r in rows]
    by = {r["label"]: r for r in rows}
    md += ["", "## Targets", "", "| | measured | target | |", "|---|---|---|---|"]
    for N in HORIZONS:
        lw, pa = by[f"light wrist N{N}"], by[f"Panda N{N}"]
        ratio = lw["step_us"] / pa["step_us"]
        md.append(f"| light wrist, N = {N}: build from an empty cache | {lw['build_s']:.0f} s | < {BUILD_TARGET_S:.0f} s | "
                  + ("met |" if lw["build_s"] < BUILD_TARGET_S else f"missed by {lw['build_s'] / BUILD_TARGET_S:.2f}x |"))
        md.append(f"| light wrist (ROS2) / Panda (RK4) step, N = {N} | {ratio:.2f}x | <= {STEP_RATIO_TARGET}x | "
                  + ("met |" if ratio <= STEP_RATIO_TARGET else f"missed by {ratio / STEP_RATIO_TARGET:.2f}x |"))
    o2 = by["light wrist N5 O2"]
    md += ["", f"The default flags: the light wrist at N = 5 built with -O2 for any processor steps in "
               f"{o2['step_us']:.0f} us against {by['light wrist N5']['step_us']:.0f} us with -O3 for this processor "
               f"(built in {o2['build_s']:.0f} s against {by['light wrist N5']['build_s']:.0f} s)."]
    (RESULTS / "bench_mpc_stiff.md").write_text("\n".join(md) + "\n")
    print(f"wrote {RESULTS / 'bench_mpc_stiff.md'}: {len(rows)} controllers built, run and timed (timing only, "
          "no check of their results beyond finite tracking)")


if __name__ == "__main__":
    main()
