"""Benchmark of `rscasadi sweep`: points per second on a local Dask cluster of 1 and 2
workers, for the 12 minimum-time problems of problems/sweep_spring_stiffness.toml.  The shared
NLP is compiled before the clock starts (and cached); the 2-worker run's table and figure are
kept in results/sweep/.

    python benchmarks/bench_sweep.py     # writes results/bench_sweep.md and results/sweep/
"""
import shutil
import tempfile
from pathlib import Path

from common import stamp, RESULTS, ROOT  # noqa: E402
from rscasadi.ocp.sweep import run  # noqa: E402


def main():
    sweep_file = ROOT / "problems" / "sweep_spring_stiffness.toml"
    rates = {}
    for workers in (1, 2):
        tmp = Path(tempfile.mkdtemp())
        res = run(sweep_file, tmp / "s", workers=workers, log=lambda m: None)
        rates[workers] = res["points_per_second"]
        print(f"sweep with {workers} worker(s): {rates[workers]:.2f} points/s, {res['solved']} of "
              f"{len(res['rows'])} solved", flush=True)
        if workers == 2:
            shutil.rmtree(RESULTS / "sweep", ignore_errors=True)
            shutil.copytree(tmp / "s", RESULTS / "sweep")
        shutil.rmtree(tmp, ignore_errors=True)
    md = ["# Sweeps on Dask", "", stamp(), "", "`python benchmarks/bench_sweep.py`: the 12 minimum-time problems of",
          "`problems/sweep_spring_stiffness.toml` (elbow x shoulder-pitch spring stiffness), one compiled",
          "NLP shared by all points (compiled before the clock starts), a local cluster on this 2-core machine.", "",
          "| workers | points per second |", "|---|---|"] + [f"| {w} | {r:.2f} |" for w, r in rates.items()]
    md += ["", "Table and figure of the 2-worker run: results/sweep/sweep.csv, results/sweep/sweep.png."]
    (RESULTS / "bench_sweep.md").write_text("\n".join(md) + "\n")
    print(f"wrote {RESULTS / 'bench_sweep.md'}")


if __name__ == "__main__":
    main()
