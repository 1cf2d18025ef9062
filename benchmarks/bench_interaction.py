"""Benchmark of interaction control (issue: interaction control in C), in one run, for the
reference arm with a tool and the Panda with SEAs: (a) a 15 N push at K = 200-2000 N/m, (b)
pressing into walls of 1e4-1e6 N/m, (c) a collision during a motion and the momentum observer,
(d) the design on the reduced model beside the complete one, and the generated C's time per
step, each at 1 kHz through quantised encoders.

    python benchmarks/bench_interaction.py     # writes results/interaction/<model>/study.{md,json,png}

The same as `rscasadi controller impedance MODEL --frame F --study --theta ... --out DIR` with
the settings of rscasadi.studies.reproduce.INTERACTION_ARMS, and as the main job's interaction
parts.
"""
import sys

from common import ROOT  # noqa: F401  (puts the checkout on the path)

from rscasadi.studies.reproduce import INTERACTION_ARMS, interaction_study  # noqa: E402

if __name__ == "__main__":
    for name in INTERACTION_ARMS:
        print(f"== {name}", flush=True)
        print(interaction_study(name, ROOT / "results" / "interaction", log=lambda msg: print(msg, flush=True)))
    sys.exit(0)
