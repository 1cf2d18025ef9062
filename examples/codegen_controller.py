"""Generate C for a controller: the reference arm's functions as C99 and one shared library,
loaded back and checked against the symbolic model, then the 1 kHz feedforward controller of
examples/controller.c compiled against it and run.

    python examples/codegen_controller.py [--out DIR] [--opt -O2] [--seconds 2]   # docs/tutorials/codegen.md
"""
import argparse
import subprocess
from pathlib import Path

import numpy as np

import rscasadi
from rscasadi.codegen import generate, load_compiled
from rscasadi.native.build import compiler

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/codegen", help="where the C, header and library go")
    parser.add_argument("--opt", default="-O2", help="the C compiler's optimisation flag")
    parser.add_argument("--seconds", default="2", help="how long the controller runs")
    args = parser.parse_args(argv)
    model = ROOT / "problems" / "arm3.toml"
    out = Path(args.out)
    generate(model, out / "arm3", opt=args.opt)                 # sources, rscasadi_arm.h, the .so, manifest.json

    # the compiled library against the symbolic model, at a random state
    arm, lib = rscasadi.load(model), load_compiled(out / "arm3")
    rng = np.random.default_rng(1)
    x = [rng.uniform(-1, 1, arm.n) for _ in range(4)] + [rng.uniform(-0.2, 0.2, arm.n)]
    c = np.array(lib["forward_dynamics"](*x)[0]).ravel()
    s = np.array(arm.forward_dynamics()(*x)[0]).ravel()
    print(f"forward dynamics, C against CasADi: {np.max(np.abs(c - s)):.1e}")

    # a C program on the library: examples/controller.c (n and the springs from the header)
    exe = out / "controller"
    subprocess.run([*compiler(), "-std=c99", "-O2", f"-I{out / 'arm3'}", str(ROOT / "examples" / "controller.c"),
                    f"-L{out / 'arm3'}", "-lrscasadi_arm", f"-Wl,-rpath,{(out / 'arm3').resolve()}", "-lm",
                    "-o", str(exe)], check=True)
    run = subprocess.run([str(exe), args.seconds], capture_output=True, text=True, check=True)
    print(run.stdout.strip().splitlines()[-1])                 # the largest tracking error
    return float(np.max(np.abs(c - s))), run.stdout


if __name__ == "__main__":
    main()
