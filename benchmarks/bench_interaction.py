"""Benchmark of interaction control (issue: interaction control in C), in one run, for the
reference arm with a tool and the Panda with SEAs: (a) a 15 N push at K = 200-2000 N/m, (b)
pressing into walls of 1e4-1e6 N/m, (c) a collision during a motion and the momentum observer,
(d) the design on the reduced model beside the complete one, and the generated C's time per
step, each at 1 kHz through quantised encoders.

    python benchmarks/bench_interaction.py     # writes results/interaction/<model>/study.{md,json,png}

The same as `rscasadi controller impedance MODEL --frame F --study --theta ... --out DIR`.
"""
import sys

from common import ROOT  # noqa: F401  (puts the checkout on the path)

import rscasadi  # noqa: E402
from rscasadi.interaction.study import study  # noqa: E402
from rscasadi.sim.trajectory import load_trajectory  # noqa: E402

ARMS = [  # model, frame, configuration, trajectory, the observer's gain (1/s) and threshold (N m)
    ("arm3_tool", "tool", [0.0, 0.3, -0.5], "trajectory_arm3.toml", 50.0, 1.0),
    # the Panda's 19-bit link encoders through its larger inertias leave up to 3.9 N m of residual
    # in free motion at 100 1/s; at 50 1/s the estimate lags a contact that grows: 7 % against 3.5 %
    ("panda_sea", "panda_hand_tcp", [0.0, -0.3, 0.0, -2.0, 0.0, 1.7, 0.8], "trajectory_panda.toml", 100.0, 5.0),
]

if __name__ == "__main__":
    for name, frame, theta, trajectory, gain, threshold in ARMS:
        print(f"== {name}", flush=True)
        study(rscasadi.load(ROOT / "problems" / f"{name}.toml"), frame, theta, ROOT / "results" / "interaction" / name,
              gain=gain, threshold=threshold, trajectory=load_trajectory(ROOT / "problems" / trajectory),
              log=lambda msg: print(msg, flush=True))
    sys.exit(0)
