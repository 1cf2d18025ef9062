"""Benchmark: the generated forward dynamics and its Jacobian on three public arms, against
Pinocchio's ABA and ABA derivatives on the same trees with the rotors as bodies.

The Panda (problems/panda_sea.toml), Baxter's left arm from its whole-robot URDF
(common.baxter_model) and the Unitree Z1 (tests/data/z1_sea.toml), each with an FS-SEA in every
joint: C at -O3 for this processor timed by the harness (benchmarks/harness.c), Pinocchio's C++
through its Python bindings (the call's overhead included) on PinocchioRoute's tree of 3n bodies
(before any projection onto the geared coordinates, which Pinocchio's route needs on top).
Target (issue: stiff springs at full speed): the Jacobian at most 0.33x Pinocchio's derivatives.

    python benchmarks/bench_fd_jacobian_arms.py     # writes results/bench_fd_jacobian_arms.md (~2 min)
"""
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from common import baxter_model, per_call, stamp, RESULTS, ROOT  # noqa: E402
import rscasadi
from rscasadi.codegen import generate

TARGET = 0.33


def main():
    import pinocchio as pin
    from rscasadi.reference.pinocchio_route import PinocchioRoute
    work = Path(tempfile.mkdtemp())
    harness = work / "harness"
    subprocess.run(["cc", "-O2", str(ROOT / "benchmarks" / "harness.c"), "-o", str(harness), "-ldl", "-lm"], check=True)
    arms = [("Panda", ROOT / "problems" / "panda_sea.toml"), ("Baxter's left arm", baxter_model(work)),
            ("Unitree Z1", ROOT / "tests" / "data" / "z1_sea.toml")]
    rows = []
    for label, path in arms:
        print(f"{label} ...", flush=True)
        arm = rscasadi.load(path)
        out = work / label.split()[0].strip("'s")
        names = ["forward_dynamics", "forward_dynamics_jacobian"]
        manifest = generate(arm, out, log=lambda m: None, native=True, only=names)
        run = subprocess.run([str(harness), str(out / manifest["library"]), *names], capture_output=True, text=True,
                             check=True)
        c = {line.split()[0]: float(line.split()[1]) for line in run.stdout.splitlines()}
        route, rng = PinocchioRoute.from_urdf(arm.model), np.random.default_rng(7)
        nq = route.G.shape[1]
        q, v, tau = route.G @ rng.uniform(-1, 1, nq), route.G @ rng.uniform(-1, 1, nq), rng.uniform(-1, 1, route.model.nv)
        aba = 1e9 * per_call(pin.aba, route.model, route.data, q, v, tau, repeat=5, min_time=0.2)
        derivatives = 1e9 * per_call(pin.computeABADerivatives, route.model, route.data, q, v, tau, repeat=5, min_time=0.2)
        rows.append((label, arm.n, route.model.nbodies - 1, c["forward_dynamics"], aba, c["forward_dynamics_jacobian"],
                     derivatives))
        print(f"  forward dynamics {c['forward_dynamics']:.0f} ns (aba {aba:.0f} ns), its Jacobian "
              f"{c['forward_dynamics_jacobian']:.0f} ns (computeABADerivatives {derivatives:.0f} ns)", flush=True)
    md = ["# The forward dynamics' Jacobian on three public arms, against Pinocchio", "", stamp(), "", __doc__.split("\n\n")[1]
          .replace("\n", " "), "",
          "| arm | joints | Pinocchio's bodies | forward dynamics C (ns) | Pinocchio aba (ns) | ratio | Jacobian C (ns) | "
          "computeABADerivatives (ns) | ratio | target |", "|---|---|---|---|---|---|---|---|---|---|"]
    for label, n, bodies, fd, aba, jac, der in rows:
        md.append(f"| {label} | {n} | {bodies} | {fd:.0f} | {aba:.0f} | {fd / aba:.2f}x | {jac:.0f} | {der:.0f} | "
                  f"{jac / der:.2f}x | " + ("met |" if jac / der <= TARGET else f"missed by {jac / der / TARGET:.2f}x |"))
    (RESULTS / "bench_fd_jacobian_arms.md").write_text("\n".join(md) + "\n")
    print(f"wrote {RESULTS / 'bench_fd_jacobian_arms.md'}: {len(rows)} arms timed (timing only)")


if __name__ == "__main__":
    main()
