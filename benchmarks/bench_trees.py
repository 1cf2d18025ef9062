"""Benchmark of the generated C on trees with the rotors as bodies: a humanoid upper body (the
Unitree G1's waist and two arms, 17 joints, from its URDF) and bimanual trees of 8 to 30 joints
(a torso column carrying two arms of the reference arm's joints), against Pinocchio's C++ ABA and
ABA derivatives on the same 3n-body trees (the rotors as bodies of their own), same run.

Forward dynamics and its Jacobian (the implicit-function route past small n; past straight-line
SX a structured kernel, codegen.step_kernel) as `rscasadi codegen` writes them, -O3 with --native, timed by benchmarks/harness.c (the median of 3 processes, each the median of 15
batches); Pinocchio's through its Python bindings (their call overhead, about 0.3 us, included);
the C's size and its generate-and-compile time, and how each grows with n.

    python benchmarks/bench_trees.py     # writes results/bench_trees.{md,csv,png}
"""
import copy
import os
import subprocess
import tempfile
import time
import tomllib
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from common import per_call, stamp, write_results  # noqa: E402
import rscasadi  # noqa: E402
from rscasadi.codegen import generate  # noqa: E402
from rscasadi.model.modelfile import parse  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SIZES = (8, 14, 20, 30)                 # bimanual trees: 2 + 3k per arm
G1 = ROOT / "tests" / "data" / "g1_description" / "urdf" / "g1_29dof_rev_1_0.urdf"
G1_UPPER = (["waist_yaw_joint", "waist_roll_joint", "waist_pitch_joint"]
            + [f"{s}_{j}_joint" for s in ("left", "right") for j in
               ("shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow", "wrist_roll", "wrist_pitch", "wrist_yaw")])
TARGETS = {"fd": 0.5, "jac": 0.33, "size_mb": 5.0, "compile_s": 60.0}


def bimanual(n: int) -> rscasadi.Arm:
    """A torso of two joints carrying two arms of (n - 2) / 2 joints each, the reference arm's
    joints repeated (yaw, pitch, pitch, ...)."""
    with open(ROOT / "problems" / "arm3.toml", "rb") as fh:
        doc = tomllib.load(fh)
    base = doc["joints"]
    joints = [dict(copy.deepcopy(base[0]), name="torso_yaw"),
              dict(copy.deepcopy(base[1]), name="torso_pitch", parent="torso_yaw")]
    per_arm = (n - 2) // 2
    for side, y in (("left", 0.2), ("right", -0.2)):
        parent = "torso_pitch"
        for k in range(per_arm):
            jt = dict(copy.deepcopy(base[k % 3]), name=f"{side}{k + 1}", parent=parent)
            if k == 0:
                jt["origin_xyz"] = [0.3, y, 0.0]
            joints.append(jt)
            parent = jt["name"]
    return rscasadi.Arm(parse(dict(doc, name=f"bimanual-{n}", joints=joints), f"<bimanual {n}>"))


def g1_upper(work: Path) -> rscasadi.Arm:
    lines = [f'name = "g1-upper"\nurdf = "{G1}"\ntips = ["left_rubber_hand", "right_rubber_hand"]\n']
    for name in G1_UPPER:
        lines.append(f'[[joints]]\nname = "{name}"\ngear_ratio = 50.0\nsea = {{ k1 = 1500.0, d = 1.0 }}\n'
                     f'gear_loss = {{ b = 0.5 }}\nslow_rotor = {{ mass = 0.2, com = [0.0, 0.0, 0.0], inertia = '
                     f'[1e-4, 1e-4, 1.6e-4, 0.0, 0.0, 0.0] }}\nfast_rotor = {{ mass = 0.1, com = [0.0, 0.0, 0.0], '
                     f'inertia = [1e-5, 1e-5, 1.6e-5, 0.0, 0.0, 0.0] }}\n')
    (work / "g1.toml").write_text("\n".join(lines))
    return rscasadi.load(work / "g1.toml")


def build(arm, out: Path) -> dict:
    """forward_dynamics and forward_dynamics_jacobian as `rscasadi codegen` writes them (the
    Jacobian as a structured kernel past straight-line SX, codegen.KERNELS), compiled -O3
    --native from an empty cache: the library, the C's size (bytes), the generate-and-compile
    time (s) and the Jacobian's route."""
    os.environ["RSCASADI_CACHE"] = str(out.with_name(out.name + "_cache"))
    t0 = time.perf_counter()
    manifest = generate(arm, out, opt="-O3", native=True, log=lambda m: None, only=list(NAMES))
    return {"lib": out / manifest["library"], "c_bytes": sum((out / f).stat().st_size for f in manifest["sources"]),
            "compile_s": time.perf_counter() - t0, "fd_instructions": arm.forward_dynamics().n_instructions(),
            "route": "kernel" if "forward_dynamics_jacobian" in manifest["kernels"] else "CasADi"}


NAMES = {"forward_dynamics": "fd", "forward_dynamics_jacobian": "fdjac"}     # C symbol -> the row's key


def pinocchio_ns(arm) -> dict:
    """Pinocchio's aba and computeABADerivatives on the same tree with the rotors as bodies."""
    import pinocchio as pin
    from rscasadi.reference.pinocchio_route import PinocchioRoute
    route, rng = PinocchioRoute(arm.model), np.random.default_rng(1)
    nv = route.model.nv
    q, v, tau = rng.uniform(-1, 1, nv), rng.uniform(-1, 1, nv), rng.uniform(-1, 1, nv)
    return {"pin_aba_ns": 1e9 * per_call(pin.aba, route.model, route.data, q, v, tau, repeat=5, min_time=0.2),
            "pin_aba_derivatives_ns": 1e9 * per_call(pin.computeABADerivatives, route.model, route.data, q, v, tau,
                                                     repeat=5, min_time=0.2), "bodies": nv}


def main():
    work = Path(tempfile.mkdtemp(prefix="rscasadi-bench-trees-"))
    harness = work / "harness"
    subprocess.run(["cc", "-O2", "-std=c99", str(HERE / "harness.c"), "-ldl", "-o", str(harness)], check=True)
    arms = {f"bimanual-{n}": bimanual(n) for n in SIZES}
    arms["g1-upper"] = g1_upper(work)
    rows = {}
    for name, arm in arms.items():
        built = build(arm, work / name)
        print(f"{name}: n = {arm.n}, C {built['c_bytes'] / 1e6:.2f} MB, generated and compiled in "
              f"{built['compile_s']:.1f} s", flush=True)
        rows[name] = {"n": arm.n, **built, **pinocchio_ns(arm)}
    for _ in range(3):                                  # harness rounds after every compile
        for name, row in rows.items():
            run = subprocess.run([str(harness), str(row["lib"]), *NAMES], capture_output=True, text=True, check=True)
            for line in run.stdout.splitlines():
                row.setdefault(NAMES[line.split()[0]], []).append(float(line.split()[1]))
    for row in rows.values():
        row["fd_ns"], row["jac_ns"] = float(np.median(row.pop("fd"))), float(np.median(row.pop("fdjac")))
    checks = []
    for name, row in rows.items():
        fd_ratio, jac_ratio = row["fd_ns"] / row["pin_aba_ns"], row["jac_ns"] / row["pin_aba_derivatives_ns"]
        checks.append(f"{name} (n = {row['n']}, {row['bodies']} bodies): forward dynamics C {row['fd_ns']:.0f} ns = "
                      f"{fd_ratio:.2f}x Pinocchio's ABA {row['pin_aba_ns']:.0f} ns (target <= {TARGETS['fd']}x): "
                      + ("met" if fd_ratio <= TARGETS["fd"] else "MISSED")
                      + f"; its Jacobian {row['jac_ns']:.0f} ns = {jac_ratio:.2f}x Pinocchio's ABA derivatives "
                      f"{row['pin_aba_derivatives_ns']:.0f} ns (target <= {TARGETS['jac']}x): "
                      + ("met" if jac_ratio <= TARGETS["jac"] else "MISSED"))
    big = rows[f"bimanual-{max(SIZES)}"]
    checks.append(f"n = {big['n']}: C {big['c_bytes'] / 1e6:.2f} MB (target < {TARGETS['size_mb']} MB): "
                  + ("met" if big["c_bytes"] / 1e6 < TARGETS["size_mb"] else "MISSED")
                  + f"; generated and compiled in {big['compile_s']:.1f} s (target < {TARGETS['compile_s']:.0f} s): "
                  + ("met" if big["compile_s"] < TARGETS["compile_s"] else "MISSED"))
    ns = np.array([rows[f"bimanual-{n}"]["n"] for n in SIZES], float)
    for key, what in (("fd_ns", "forward dynamics time"), ("jac_ns", "Jacobian time"), ("c_bytes", "C size")):
        slope = np.polyfit(np.log(ns), np.log([rows[f"bimanual-{n}"][key] for n in SIZES]), 1)[0]
        checks.append(f"growth with n (bimanual trees {SIZES[0]}-{SIZES[-1]}): {what} ~ n^{slope:.2f}")
    for c in checks:
        print(c)
    header = "tree,n,bodies,fd_instructions,c_bytes,compile_s,fd_ns,jac_ns,pin_aba_ns,pin_aba_derivatives_ns\n"
    csv = header + "".join(f"{k},{r['n']},{r['bodies']},{r['fd_instructions']},{r['c_bytes']},{r['compile_s']:.2f},"
                           f"{r['fd_ns']:.1f},{r['jac_ns']:.1f},{r['pin_aba_ns']:.1f},{r['pin_aba_derivatives_ns']:.1f}\n"
                           for k, r in rows.items())
    md = ["# Generated C on trees, against Pinocchio's ABA", "", stamp(), "",
          "Measured by `python benchmarks/bench_trees.py`: every joint an SEA with its two rotors as bodies",
          "(3n bodies). C: `benchmarks/harness.c`, median of 3 processes of 15 batches, -O3 --native. Pinocchio:",
          "`aba` and `computeABADerivatives` on the same 3n-joint tree, C++ through the Python bindings (their",
          "call overhead included), before any projection onto the geared coordinates. The Jacobian's C: CasADi's",
          "straight-line SX, or the structured kernel (`rscasadi/codegen/templates/fd_jacobian.c`) past it.", "",
          "| tree | n | bodies | FD (ns) | Pinocchio ABA (ns) | ratio | FD Jacobian (ns) | its C | ABA derivatives (ns) |"
          " ratio | C (MB) | generate + compile (s) |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    md += [f"| {k} | {r['n']} | {r['bodies']} | {r['fd_ns']:.0f} | {r['pin_aba_ns']:.0f} | "
           f"{r['fd_ns'] / r['pin_aba_ns']:.2f} | {r['jac_ns']:.0f} | {r['route']} | {r['pin_aba_derivatives_ns']:.0f} | "
           f"{r['jac_ns'] / r['pin_aba_derivatives_ns']:.2f} | {r['c_bytes'] / 1e6:.2f} | {r['compile_s']:.1f} |"
           for k, r in rows.items()]
    md += ["", "## Targets", ""] + [f"- {c}" for c in checks]
    fig, ax = plt.subplots(figsize=(7, 4))
    for key, label in (("fd_ns", "forward dynamics (C)"), ("pin_aba_ns", "Pinocchio ABA"),
                       ("jac_ns", "FD Jacobian (C)"), ("pin_aba_derivatives_ns", "Pinocchio ABA derivatives")):
        ax.loglog(ns, [rows[f"bimanual-{n}"][key] for n in SIZES], "o-", label=label)
    ax.set(xlabel="joints n (bimanual trees, 3n bodies)", ylabel="ns per call", title="trees with rotors as bodies")
    ax.legend(fontsize=8)
    fig.tight_layout()
    write_results("bench_trees", fig, csv, "\n".join(md) + "\n")
    print(f"bench_trees: wrote results/bench_trees.md (5 trees, n up to {max(SIZES)}); figures measured, "
          "targets stated met or MISSED")


if __name__ == "__main__":
    main()
