"""Benchmark of the parametric C against the constant C (parameters as inputs, at what cost):
forward dynamics, its Jacobian, the RK4 step and its Jacobian, for the reference
arm (n = 3) and the Panda (n = 7), each library compiled for this processor at -O3, timed by the
C harness (ns per call; the median of 3 harness processes, each the median of 15 batches,
constant and parametric interleaved).

    python benchmarks/bench_parametric.py     # writes results/bench_parametric.{md,csv,png}

The parametric library takes the parameter vector p (inertias, springs, losses, gravity) as its
last input: one library serves every arm of the family, an identified or co-designed arm
without recompiling; `--parametric family` folds the parameters that are zero in the model.  Target: within 1.5x of the constant C.
"""
import subprocess
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from common import stamp, chain_arm, write_results  # noqa: E402
import rscasadi  # noqa: E402
from rscasadi.codegen import generate  # noqa: E402
from rscasadi.dynamics.arm import Arm  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
KINDS = ("constant", "all", "family")          # p: none, every parameter, the family's (zeros folded)
FUNCTIONS = ("forward_dynamics", "forward_dynamics_jacobian", "step", "step_jacobian")
ROUNDS = 3
TARGET = 1.5


def main():
    work = Path(tempfile.mkdtemp(prefix="rscasadi-bench-parametric-"))
    harness = work / "harness"
    subprocess.run(["cc", "-O2", "-std=c99", str(HERE / "harness.c"), "-ldl", "-o", str(harness)], check=True)
    arms = {3: chain_arm(3), 7: rscasadi.load(ROOT / "problems" / "panda_sea.toml")}
    libs = {}
    for n, arm in arms.items():
        for kind in KINDS:
            out = work / f"n{n}_{kind}"
            print(f"n = {n}: generating the {kind} C ...", flush=True)
            manifest = generate(arm, out, log=lambda m: None, native=True, parametric="none" if kind == "constant" else kind)
            libs[n, kind] = (out / manifest["library"], [f for f in FUNCTIONS if f in manifest["functions"]])
    runs = {key: [] for key in libs}
    for _ in range(ROUNDS):
        for key, (lib, names) in libs.items():
            run = subprocess.run([str(harness), str(lib)] + names, capture_output=True, text=True, check=True)
            runs[key].append({line.split()[0]: float(line.split()[1]) for line in run.stdout.splitlines()})
    ns = {key: {name: float(np.median([r[name] for r in rs])) for name in rs[0]} for key, rs in runs.items()}
    md = ["# Parametric C against constant C", "", stamp(), "",
          "`python benchmarks/bench_parametric.py`: ns per call in C (-O3, this processor), the median of "
          f"{ROUNDS} harness processes. The parametric functions take the model's parameter vector p last: "
          "*all* (`rscasadi codegen --parametric`) every parameter, for every arm with these joints; *family* "
          "(`--parametric family`) the parameters that are not zero in the model, for every arm "
          f"with these joints and the same zeros (balanced rotors, a level base, ...). Target: at most {TARGET}x the constant C.", "",
          "| n | function | constant (ns) | all (ns) | ratio | family (ns) | ratio | target (family) |",
          "|---|---|---|---|---|---|---|---|"]
    csv = ["n,function,constant_ns,all_ns,all_ratio,family_ns,family_ratio"]
    for n in arms:
        for name in libs[n, "constant"][1]:
            c, a, f = (ns[n, kind][name] for kind in KINDS)
            md.append(f"| {n} | {name} | {c:.0f} | {a:.0f} | {a / c:.2f} | {f:.0f} | {f / c:.2f} | "
                      f"{'met' if f / c <= TARGET else 'MISSED'} |")
            csv.append(f"{n},{name},{c},{a},{a / c},{f},{f / c}")
    md += ["", "Where the time goes: the constant C folds the model's numbers into the code, the parametric C "
           "cannot. Forward dynamics as SX instructions, and the parameters that are zero in the model "
           "(balanced rotors' centres, products of inertia, k3, ...), which the constant C drops:", "",
           "| n | forward dynamics instructions, constant | all | family | parameters | of them zero |",
           "|---|---|---|---|---|---|"]
    for n, arm in arms.items():
        names, values = arm.parameters()
        md.append(f"| {n} | {arm.forward_dynamics().n_instructions()} | {arm.forward_dynamics(parametric=True).n_instructions()} | "
                  f"{Arm.family(arm.model).forward_dynamics(parametric=True).n_instructions()} | {len(names)} | "
                  f"{int(np.sum(np.asarray(values) == 0))} |")
    fig, ax = plt.subplots(figsize=(7, 3.2))
    labels = [f"n={n} {name}" for n in arms for name in libs[n, "constant"][1]]
    y = np.arange(len(labels))
    for k, kind in enumerate(KINDS[1:]):
        ratios = [ns[n, kind][name] / ns[n, "constant"][name] for n in arms for name in libs[n, "constant"][1]]
        ax.barh(y + 0.4 * k, ratios, height=0.4, label=kind)
    ax.set_yticks(y + 0.2, labels)
    ax.axvline(TARGET, color="r", lw=1, label=f"target {TARGET}x")
    ax.set(xlabel="parametric / constant time per call")
    ax.legend()
    fig.tight_layout()
    write_results("bench_parametric", fig, "\n".join(csv) + "\n", "\n".join(md) + "\n")


if __name__ == "__main__":
    main()
