"""Benchmark: one millisecond of the arm simulated by MuJoCo (the exported complete model, RK4 at
1 ms: `mj_step` in C, 1000 steps a call) against rscasadi's generated C `step` (one RK4 step of the
complete model, from the C harness `benchmarks/harness.c`, -O3 native), for the reference arm and
the Panda, and the rigid-joint armature export for scale.

    python benchmarks/bench_mujoco.py     # writes results/bench_mujoco.{md,csv,png}
"""
import subprocess
import tempfile
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from common import stamp, write_results  # noqa: E402
import rscasadi  # noqa: E402
from rscasadi.codegen import generate  # noqa: E402
from rscasadi.dynamics.statics import rest_state  # noqa: E402
from rscasadi.export.mujoco import gear_map, mujoco_xml  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
ARMS = {"reference arm (n = 3)": "arm3.toml", "Panda (n = 7)": "panda_sea.toml"}
ROUNDS, STEPS = 15, 1000


def mujoco_us(arm, variant: str) -> float:
    """Median us per mj_step over ROUNDS calls of STEPS steps (nstep: the loop in C), from rest."""
    m = mujoco.MjModel.from_xml_string(mujoco_xml(arm.model, variant))
    d = mujoco.MjData(m)
    x = rest_state(arm, np.zeros(arm.n))
    if variant == "complete":
        T = gear_map(arm, m)
        d.qpos[:] = T @ x[:2 * arm.n]
    times = []
    for _ in range(ROUNDS):
        t0 = time.perf_counter()
        mujoco.mj_step(m, d, nstep=STEPS)
        times.append((time.perf_counter() - t0) / STEPS)
    return 1e6 * float(np.median(times))


def main():
    work = Path(tempfile.mkdtemp(prefix="rscasadi-bench-mujoco-"))
    harness = work / "harness"
    subprocess.run(["cc", "-O2", "-std=c99", str(HERE / "harness.c"), "-ldl", "-o", str(harness)], check=True)
    rows = []
    for label, model in ARMS.items():
        arm = rscasadi.load(ROOT / "problems" / model)
        out = work / model.removesuffix(".toml")
        manifest = generate(arm, out, log=lambda m: None, native=True)
        run = subprocess.run([str(harness), str(out / manifest["library"]), "step"], capture_output=True, text=True,
                             check=True)
        ours = float(run.stdout.split()[1]) / 1e3
        complete, armature = mujoco_us(arm, "complete"), mujoco_us(arm, "armature")
        rows.append((label, ours, complete, armature))
        print(f"{label}: rscasadi step (C, RK4) {ours:.2f} us, MuJoCo complete {complete:.2f} us, "
              f"MuJoCo armature {armature:.2f} us per 1 ms step", flush=True)
    md = "\n".join([
        "# One millisecond of the arm: MuJoCo against rscasadi's generated C", "", stamp(), "",
        "Measured by `python benchmarks/bench_mujoco.py`: MuJoCo's `mj_step` (RK4 at 1 ms, the settings",
        "under which the complete export follows the model), median of 15 calls of 1000 steps each (the loop",
        "in C); rscasadi's `step` (one RK4 step of the complete model, the generated C at -O3 -march=native)",
        "from the C harness. The armature export is the rigid-joint model MuJoCo users write, for scale.", "",
        "| arm | rscasadi step, C (us) | MuJoCo, complete export (us) | MuJoCo, armature export (us) |",
        "|---|---|---|---|"] + [f"| {r[0]} | {r[1]:.2f} | {r[2]:.2f} | {r[3]:.2f} |" for r in rows]) + "\n"
    csv = "arm,rscasadi_step_us,mujoco_complete_us,mujoco_armature_us\n" + "".join(
        f"{r[0]},{r[1]:.4f},{r[2]:.4f},{r[3]:.4f}\n" for r in rows)
    fig, ax = plt.subplots(figsize=(6, 3))
    for i, (name, values) in enumerate((("rscasadi C", [r[1] for r in rows]), ("MuJoCo complete", [r[2] for r in rows]),
                                        ("MuJoCo armature", [r[3] for r in rows]))):
        ax.bar(np.arange(len(rows)) + 0.27 * (i - 1), values, 0.27, label=name)
    ax.set_xticks(range(len(rows)), [r[0] for r in rows])
    ax.set_ylabel("us per 1 ms step")
    ax.legend()
    fig.tight_layout()
    write_results("bench_mujoco", fig, csv, md)


if __name__ == "__main__":
    main()
