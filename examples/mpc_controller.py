"""Nonlinear MPC in C: the controller generated for the reference arm, then run at 1 kHz from
Python on a plant with a 20 % heavier tip, against feedforward alone and feedforward + PD.

    python examples/mpc_controller.py [--out DIR] [--seconds 2]   # docs/tutorials/mpc.md
"""
import argparse
from pathlib import Path

from rscasadi.mpc import closed_loop, generate_mpc

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/mpc", help="where the controller's C and library go")
    parser.add_argument("--seconds", type=float, default=2.0, help="closed-loop duration")
    parser.add_argument("--opt", default="-O2", help="the C compiler's optimisation flag")
    args = parser.parse_args(argv)
    problem = ROOT / "problems" / "mpc_arm3.toml"
    generate_mpc(problem, args.out, opt=args.opt)        # mpc_rti.c, rscasadi_mpc.{c,h}, the .so
    res = closed_loop(problem, args.out, duration=args.seconds)    # prints one line per controller
    return res


if __name__ == "__main__":
    main()
