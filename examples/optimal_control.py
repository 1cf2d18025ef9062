"""Optimal control stated in Python: a minimum-effort motion of the reference arm between two
rest poses, solved with fatrop, replayed on the complete model, plotted and written.

    python examples/optimal_control.py [--out DIR] [--intervals 60]   # docs/tutorials/ocp.md
"""
import argparse
from pathlib import Path

from rscasadi.ocp import Problem, SolverOptions, Task, TranscriptionOptions, Verification, solve

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/optimal_control", help="where solution.json and the plots go")
    parser.add_argument("--intervals", type=int, default=60, help="collocation intervals of the first mesh")
    args = parser.parse_args(argv)
    problem = Problem(
        Task(ROOT / "problems" / "arm3.toml", "min_effort", duration=1.5,
             theta_start=[0.0, 0.3, -0.5], theta_end=[0.8, 0.9, -1.2]),       # at rest at both ends
        TranscriptionOptions(method="radau", degree=3, intervals=args.intervals),
        SolverOptions(name="fatrop"),
        Verification(final_angle_tol=1e-4, rounds=4))
    sol = solve(problem, print_level=0)           # transcribe, solve, replay, refine where it misses
    print(f"{sol.status}: objective {sol.objective:.6g}, {sol['intervals']} intervals, "
          f"verified {sol['verification']['passed']}")
    replay = sol.verify()                         # the torques on the complete model (CVODES)
    print(f"replay: final angle error {replay['final_angle_error']:.1e} rad, "
          f"largest limit violation {replay['max_limit_violation']:.1e}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sol.to_json(out / "solution.json")
    sol.plot(out)
    print(f"wrote {out / 'solution.json'}, solution.png, solution.pdf")
    return sol


if __name__ == "__main__":
    main()
