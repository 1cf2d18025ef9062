"""Study: identification from logs the model cannot express exactly: the Panda's family with
unmodelled gear friction, a counterbalance spring and real sensors (offsets, latency,
quantisation, noise), link side and motor side, at 1 kHz and 100 Hz, against the model file and
an independent least-squares fit (rscasadi.studies.real_sensors; the fit needs Pinocchio:
`pip install -e ".[pin]"`).

    python benchmarks/real_sensors.py     # writes results/identification/real_sensors/ (about 5 min)
"""
from pathlib import Path

from rscasadi.studies.real_sensors import run

if __name__ == "__main__":
    run(Path(__file__).resolve().parents[1] / "results" / "identification" / "real_sensors")
