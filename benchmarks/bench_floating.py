"""Benchmark of the generated contact dynamics of a quadruped with an SEA in every joint (ANYmal C,
problems/anymal_c_sea.toml: 12 joints, the rotors as 24 bodies, four point feet), same run,
against Pinocchio's constrained dynamics on the same robot with the rotors as bodies (its
`constraintDynamics` and `computeConstraintDynamicsDerivatives` on the 42-degree-of-freedom tree,
four 3D contacts) and Crocoddyl's contact-dynamics knot on the armature model a user would
otherwise pick (`DifferentialActionModelContactFwdDynamics`: calc, and calc + calcDiff).

The C: -O3 --native, timed by benchmarks/harness.c (median of 3 processes, each the median of 15
batches). Pinocchio through its Python bindings (their call overhead, about 0.3 us, included).
Crocoddyl 3.2.1 crashes with pin 4.1: it runs in its own virtual environment with pin 4.0.0
(`--crocoddyl PYTHON`, default /tmp/croc/bin/python; without it that column is left out).

    python benchmarks/bench_floating.py [--crocoddyl PYTHON]   # writes results/bench_floating.{md,csv,png}
"""
import argparse
import json
import os
import subprocess
import tempfile
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from common import per_call, stamp, write_results  # noqa: E402
import rscasadi  # noqa: E402
from rscasadi.codegen.generate import generate  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
MODEL = ROOT / "problems" / "anymal_c_sea.toml"
TARGETS = {"contact_fd": 0.5, "contact_jacobian": 0.5}
CROCODDYL = """
import json, sys, timeit
import numpy as np, pinocchio as pin, crocoddyl
urdf, feet, armature = sys.argv[1], sys.argv[2].split(","), float(sys.argv[3])
model = pin.buildModelFromUrdf(urdf, pin.JointModelFreeFlyer())
model.armature[6:] = armature
state = crocoddyl.StateMultibody(model)
actuation = crocoddyl.ActuationModelFloatingBase(state)
contacts = crocoddyl.ContactModelMultiple(state, actuation.nu)
for foot in feet:
    fid = model.getFrameId(foot)
    contacts.addContact(foot, crocoddyl.ContactModel3D(state, fid, np.zeros(3), pin.LOCAL_WORLD_ALIGNED,
                                                       actuation.nu, np.array([0.0, 0.0])))
dam = crocoddyl.DifferentialActionModelContactFwdDynamics(state, actuation, contacts,
                                                          crocoddyl.CostModelSum(state, actuation.nu), 0.0, True)
data = dam.createData()
rng = np.random.default_rng(1)
q = pin.randomConfiguration(model, -np.ones(model.nq), np.ones(model.nq))
x, u = np.concatenate([q, rng.uniform(-1, 1, model.nv)]), rng.uniform(-1, 1, actuation.nu)
def best(stmt):
    t = timeit.Timer(stmt, globals=globals())
    n, _ = t.autorange()
    return 1e9 * min(t.repeat(5, n)) / n
print(json.dumps({"calc_ns": best("dam.calc(data, x, u)"),
                  "calc_diff_ns": best("dam.calc(data, x, u); dam.calcDiff(data, x, u)"),
                  "pinocchio": pin.__version__, "crocoddyl": crocoddyl.__version__}))
"""


def pinocchio_ns(robot) -> dict:
    """Pinocchio's constrained dynamics and their derivatives on the tree with the rotors as bodies."""
    import pinocchio as pin
    from rscasadi.reference.pinocchio_route import PinocchioRoute
    route, rng = PinocchioRoute(robot.model), np.random.default_rng(1)
    model, data = route.model, route.data
    contacts, datas = pin.StdVec_RigidConstraintModel(), pin.StdVec_RigidConstraintData()
    for fid in (model.getFrameId(f) for f, _ in robot.model.contacts):
        contacts.append(pin.RigidConstraintModel(pin.ContactType.CONTACT_3D, model, model.frames[fid].parentJoint,
                                                 model.frames[fid].placement, pin.LOCAL_WORLD_ALIGNED))
        datas.append(contacts[-1].createData())
    pin.initConstraintDynamics(model, data, contacts, datas)
    q = pin.randomConfiguration(model, -np.ones(model.nq), np.ones(model.nq))
    v, tau = rng.uniform(-1, 1, model.nv), rng.uniform(-1, 1, model.nv)

    def both():
        pin.constraintDynamics(model, data, q, v, tau, contacts, datas)
        pin.computeConstraintDynamicsDerivatives(model, data, contacts, datas)
    return {"pin_constraint_ns": 1e9 * per_call(pin.constraintDynamics, model, data, q, v, tau, contacts, datas),
            "pin_constraint_derivatives_ns": 1e9 * per_call(both),
            "pin_aba_ns": 1e9 * per_call(pin.aba, model, data, q, v, tau), "pin_nv": model.nv}


def crocoddyl_ns(python: str, robot) -> dict | None:
    """Crocoddyl's calc and calc + calcDiff of one contact-dynamics knot on the armature model (the
    rotors as each joint's armature B), in the environment of `python`; None where it cannot run."""
    if not Path(python).exists():
        return None
    armature = float(np.mean([jt.rotor_inertia for jt in robot.model.joints]))
    run = subprocess.run([python, "-c", CROCODDYL, robot.model.extra["urdf"],
                          ",".join(f for f, _ in robot.model.contacts), repr(armature)],
                         capture_output=True, text=True, timeout=600)
    if run.returncode != 0:
        print(f"Crocoddyl did not run ({run.stderr.strip().splitlines()[-1:]}); its column is left out")
        return None
    return json.loads(run.stdout.strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--crocoddyl", default="/tmp/croc/bin/python",
                        help="a Python with pin 4.0.0 and crocoddyl 3.2.1 (absent: no Crocoddyl column)")
    args = parser.parse_args()
    robot = rscasadi.load_robot(MODEL)
    work = Path(tempfile.mkdtemp(prefix="rscasadi-bench-floating-"))
    harness = work / "harness"
    subprocess.run(["cc", "-O2", "-std=c99", str(HERE / "harness.c"), "-ldl", "-o", str(harness)], check=True)
    names = ["forward_dynamics", "contact_dynamics", "contact_dynamics_jacobian"]
    os.environ["RSCASADI_CACHE"] = str(work / "cache")          # compiled here, not taken from a cache
    t0 = time.perf_counter()
    print("generating and compiling the contact dynamics and their Jacobian (-O3 --native) ...", flush=True)
    manifest = generate(robot, work / "c", only=names, opt="-O3", native=True, log=lambda m: None)
    compile_s = time.perf_counter() - t0
    c_bytes = sum(p.stat().st_size for p in (work / "c").glob("*.c"))
    lib = work / "c" / manifest["library"]
    symbols = [manifest["functions"][n]["symbol"] for n in names]
    times: dict = {}
    for _ in range(3):
        out = subprocess.run([str(harness), str(lib), *symbols], capture_output=True, text=True, check=True).stdout
        for line in out.splitlines():
            times.setdefault(line.split()[0], []).append(float(line.split()[1]))
    c_ns = {n: float(np.median(times[s])) for n, s in zip(names, symbols)}
    print("Pinocchio's constrained dynamics on the tree with the rotors as bodies ...", flush=True)
    pin_ns = pinocchio_ns(robot)
    print("Crocoddyl's contact-dynamics knot on the armature model (own environment) ...", flush=True)
    croc = crocoddyl_ns(args.crocoddyl, robot)
    fd_ratio = c_ns["contact_dynamics"] / pin_ns["pin_constraint_ns"]
    checks = [f"contact forward dynamics C {c_ns['contact_dynamics'] / 1e3:.1f} us = {fd_ratio:.2f}x Pinocchio's "
              f"constraintDynamics {pin_ns['pin_constraint_ns'] / 1e3:.1f} us on the same {pin_ns['pin_nv']}-dof "
              f"tree (target <= {TARGETS['contact_fd']}x): " + ("met" if fd_ratio <= TARGETS["contact_fd"] else "MISSED")]
    jac_pin = c_ns["contact_dynamics_jacobian"] / pin_ns["pin_constraint_derivatives_ns"]
    checks.append(f"its Jacobian C {c_ns['contact_dynamics_jacobian'] / 1e3:.1f} us = {jac_pin:.2f}x Pinocchio's "
                  f"constraintDynamics + computeConstraintDynamicsDerivatives "
                  f"{pin_ns['pin_constraint_derivatives_ns'] / 1e3:.1f} us")
    if croc:
        jac_ratio = c_ns["contact_dynamics_jacobian"] / croc["calc_diff_ns"]
        checks.append(f"its Jacobian = {jac_ratio:.2f}x Crocoddyl's calc + calcDiff {croc['calc_diff_ns'] / 1e3:.1f} us "
                      f"(calc alone {croc['calc_ns'] / 1e3:.1f} us; crocoddyl {croc['crocoddyl']}, pin "
                      f"{croc['pinocchio']}, the armature model) (target <= {TARGETS['contact_jacobian']}x): "
                      + ("met" if jac_ratio <= TARGETS["contact_jacobian"] else "MISSED"))
    else:
        checks.append("Crocoddyl: not measured (no environment with pin 4.0.0 and crocoddyl 3.2.1)")
    checks.append(f"C of the three: {c_bytes / 1e6:.2f} MB, generated and compiled in {compile_s:.0f} s")
    from rscasadi.dynamics import contacts as ct
    cs = ct.contact_set(robot.model)
    parts = {name: robot._functions[key].n_instructions() for name, key in (
        ("contact dynamics", ct._name("contact_dynamics", cs)), ("Jacobian", ct._name("contact_dynamics_jacobian", cs)),
        ("its residual Jacobian (AD of the recursions)", ct._name("contact_residual_jacobian", cs)))}
    checks.append("where the Jacobian's time goes: straight-line instructions " + ", ".join(
        f"{k} {v}" for k, v in parts.items()) + "; the rest are the KKT solves of its 2 nv + u = 72 columns")
    for c in checks:
        print(c)
    row = {**c_ns, **pin_ns, **({f"croc_{k}": v for k, v in croc.items() if k.endswith("_ns")} if croc else {}),
           "c_bytes": c_bytes, "compile_s": compile_s}
    csv = ",".join(row) + "\n" + ",".join(f"{v:.1f}" if isinstance(v, float) else str(v) for v in row.values()) + "\n"
    md = ["# Contact dynamics of a quadruped with SEAs, against Pinocchio and Crocoddyl", "", stamp(), "",
          "Measured by `python benchmarks/bench_floating.py`: ANYmal C with an SEA in every joint (12 joints,",
          "24 rotors as bodies, four point feet). C: `benchmarks/harness.c`, median of 3 processes of 15 batches,",
          "-O3 --native. Pinocchio: the same tree with the rotors as bodies (42 dof), four 3D contacts, through",
          "its Python bindings. Crocoddyl: one `DifferentialActionModelContactFwdDynamics` knot (no costs) on",
          "the armature model (18 dof), its own environment.", "",
          "| what | ns per call |", "|---|---|"]
    md += [f"| {k} | {v:.0f} |" for k, v in row.items() if k.endswith("_ns")]
    md += ["", "## Targets", ""] + [f"- {c}" for c in checks]
    fig, ax = plt.subplots(figsize=(7, 4))
    labels = [k for k in row if k.endswith("_ns")]
    ax.barh(labels, [row[k] / 1e3 for k in labels])
    ax.set(xlabel="us per call", title="ANYmal C, SEA in every joint, four feet")
    fig.tight_layout()
    write_results("bench_floating", fig, csv, "\n".join(md) + "\n")
    print("bench_floating: wrote results/bench_floating.md; figures measured, targets stated met or MISSED")


if __name__ == "__main__":
    main()
