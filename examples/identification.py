"""Identification: an excitation trajectory designed for the reference arm, "run on the robot"
(here a different arm, every parameter off by 10-40 %, simulated with realistic sensors), the
model identified from its log and checked on a held-out log.

    python examples/identification.py [--out DIR] [--period 10] [--harmonics 5]   # docs/tutorials/identification.md
On your robot: run excite/trajectory.toml, log t, theta_j, phi_j, tau_j at 1 kHz
(docs/user-guide/logs.md), and give the log to identify.run (or `rscasadi identify`).
"""
import argparse
from pathlib import Path

import numpy as np

import rscasadi
from rscasadi.identification import excitation, identify
from rscasadi.identification.logs import write_log
from rscasadi.identification.synthetic import perturbed_arm, record
from rscasadi.sim.trajectory import load_trajectory

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/identification", help="where the design, logs and model go")
    parser.add_argument("--period", type=float, default=10.0, help="excitation period (s)")
    parser.add_argument("--harmonics", type=int, default=5, help="Fourier harmonics per joint")
    args = parser.parse_args(argv)
    model = ROOT / "problems" / "arm3.toml"
    out = Path(args.out)
    excitation.run(model, out / "excite", period=args.period, harmonics=args.harmonics)   # checked design

    nominal = rscasadi.load(model)
    robot = perturbed_arm(nominal, np.random.default_rng(7))             # the arm you do not know
    logs = {}
    for name, trajectory in (("training", out / "excite" / "trajectory.toml"),
                             ("held_out", ROOT / "problems" / "trajectory_arm3.toml")):
        log, _ = record(robot, nominal, load_trajectory(trajectory), rng=np.random.default_rng(8))
        logs[name] = out / f"{name}.csv"
        write_log(logs[name], log)
    report, _ = identify.run(model, [logs["training"]], out / "identified", validate=logs["held_out"])
    worst = max(v["relative"] for v in report["validation"]["prediction"].values())
    print(f"held-out motor torques predicted within {100 * worst:.2f} % RMS; "
          f"the identified model: {out / 'identified' / 'model.toml'}")
    return worst


if __name__ == "__main__":
    main()
