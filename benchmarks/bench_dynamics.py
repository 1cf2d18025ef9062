"""Benchmark of the symbolic dynamics: time per call in-process (casadi.Function
from Python) and of the numerical core, for n = 3 (reference arm), 6, 12, 24; symbolic
size (n_instructions) of the recursive forward dynamics against the mass-matrix route.

    python benchmarks/bench_dynamics.py      # writes results/bench_dynamics.{md,csv,png}
"""
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from common import stamp, chain_arm, mass_matrix_forward_dynamics, per_call, write_results  # noqa: E402
from rscasadi.reference.numeric import Numeric  # noqa: E402

SIZES = (3, 6, 12, 24)
FUNCTIONS = ("forward_dynamics", "inverse_dynamics", "reduced_forward_dynamics", "reduced_inverse_dynamics",
             "joint_forward_dynamics", "arm_forward_dynamics", "energy")


def main():
    rows, sizes = [], {"recursive": [], "mass_matrix": []}
    for n in SIZES:
        arm, rng = chain_arm(n), np.random.default_rng(n)
        x = [rng.uniform(-1, 1, n) for _ in range(4)]
        extra = {"forward_dynamics": [rng.normal(size=n)], "reduced_forward_dynamics": [rng.normal(size=n)],
                 "inverse_dynamics": [rng.normal(size=n)] * 2, "reduced_inverse_dynamics": [rng.normal(size=n)] * 2,
                 "joint_forward_dynamics": [rng.normal(size=n)] * 2, "arm_forward_dynamics": [rng.normal(size=n)] * 2,
                 "energy": []}
        num = Numeric(arm.model)
        numeric = {"forward_dynamics": num.forward_dynamics, "inverse_dynamics": num.inverse_dynamics,
                   "joint_forward_dynamics": num.joint_forward_dynamics,
                   "arm_forward_dynamics": num.arm_forward_dynamics, "energy": num.energy}
        for name in FUNCTIONS:
            f = getattr(arm, name)()
            t_num = per_call(numeric[name], *x, *extra[name]) if name in numeric else float("nan")
            rows.append((n, name, f.n_instructions(), per_call(f, *x, *extra[name]) * 1e6, t_num * 1e6))
            print(f"n={n:2d} {name:26s} n_instructions={rows[-1][2]:7d}  casadi {rows[-1][3]:8.1f} us"
                  f"  numeric {rows[-1][4]:8.1f} us", flush=True)
        sizes["recursive"].append(arm.forward_dynamics().n_instructions())
        sizes["mass_matrix"].append(mass_matrix_forward_dynamics(arm).n_instructions())
        print(f"n={n:2d} forward dynamics n_instructions: recursive {sizes['recursive'][-1]}, "
              f"mass matrix + solve {sizes['mass_matrix'][-1]}", flush=True)

    csv = "n,function,n_instructions,casadi_us,numeric_us\n" + "".join(
        f"{n},{name},{ni},{tc:.2f},{tn:.2f}\n" for n, name, ni, tc, tn in rows)
    md = ["# Symbolic dynamics: time per call in-process and symbolic size", "", stamp(), "",
          "Measured by `python benchmarks/bench_dynamics.py` (median of 5 batches, 2-core machine).",
          "casadi = the SX Function called from Python (dominated by call overhead);",
          "numeric = the numpy numerical core (`rscasadi.reference.numeric`).", "",
          "| n | function | n_instructions | casadi (us) | numeric core (us) |", "|---|---|---|---|---|"]
    md += [f"| {n} | {name} | {ni} | {tc:.1f} | {tn:.1f} |" for n, name, ni, tc, tn in rows]
    md += ["", "## Forward dynamics size against n", "", "| n | recursive O(n) sweep | mass matrix + solve |",
           "|---|---|---|"]
    md += [f"| {n} | {r} | {m} |" for n, r, m in zip(SIZES, sizes["recursive"], sizes["mass_matrix"])]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].loglog(SIZES, sizes["recursive"], "o-", label="recursive (one O(n) sweep)")
    ax[0].loglog(SIZES, sizes["mass_matrix"], "s-", label="mass matrix + symbolic solve")
    ax[0].loglog(SIZES, np.array(SIZES) * sizes["recursive"][-1] / SIZES[-1], "k:", label="~ n")
    ax[0].set(xlabel="joints n", ylabel="n_instructions", title="forward dynamics size")
    ax[0].legend()
    for name in ("forward_dynamics", "inverse_dynamics"):
        ax[1].loglog(SIZES, [r[3] for r in rows if r[1] == name], "o-", label=f"{name} (casadi)")
        ax[1].loglog(SIZES, [r[4] for r in rows if r[1] == name], "s--", label=f"{name} (numeric core)")
    ax[1].set(xlabel="joints n", ylabel="us per call", title="time per call, in-process")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    write_results("bench_dynamics", fig, csv, "\n".join(md) + "\n")


if __name__ == "__main__":
    main()
