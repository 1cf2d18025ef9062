"""Shared by the benchmarks: n-joint arms built from the reference arm, and the
mass-matrix-and-solve route that the recursive forward dynamics is compared with."""
import json
import os
import subprocess
import sys
import time
import tomllib
from pathlib import Path

# The benchmarks' Python loops make many small numpy calls; OpenBLAS's threads spin between them on
# the other core and made the C step they time 1.4x slower (the Panda's MPC, 751 against 541 us;
# 2026-11-27, 2-core Xeon VM).  Before numpy loads OpenBLAS.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import casadi as ca  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import rscasadi  # noqa: E402
from rscasadi.files import run_stamp  # noqa: E402
from rscasadi.model.modelfile import parse, to_toml  # noqa: E402

RESULTS = ROOT / "results"


def stamp() -> str:
    """The run's date, machine and commit, for the first line under a results file's title."""
    return run_stamp()


def light_panda(work: Path, factor: float) -> Path:
    """The Panda's model file (problems/panda_sea.toml) with its last link `factor` times as
    heavy, written into `work`: a light wrist behind a stiff SEA."""
    from rscasadi.model.modelfile import document, to_toml
    doc = document(rscasadi.load(ROOT / "problems" / "panda_sea.toml").model)
    link = doc["joints"][6]["link"]
    link["mass"] *= factor
    link["inertia"] = [v * factor for v in link["inertia"]]
    (work / "light.toml").write_text(to_toml(doc))
    return work / "light.toml"


def chain_arm(n: int) -> rscasadi.Arm:
    """An n-joint arm repeating the reference arm's joints (yaw, pitch, pitch, yaw, ...)."""
    if n == 3:
        return rscasadi.load(ROOT / "problems" / "arm3.toml")
    with open(ROOT / "problems" / "arm3.toml", "rb") as fh:
        doc = tomllib.load(fh)
    joints = [dict(doc["joints"][j % 3], name=f"joint{j + 1}") for j in range(n)]
    return rscasadi.Arm(parse(dict(doc, name=f"chain-{n}", joints=joints), f"<chain {n}>"))


def mass_matrix_forward_dynamics(arm) -> ca.Function:
    """The same forward dynamics the 'mass matrix and solve' way: M from the recursion's
    Jacobian, bias from inverse dynamics at zero acceleration, then a symbolic solve."""
    n = arm.n
    th, ph, dth, dph, tau = (ca.SX.sym(s, n) for s in ("theta", "phi", "dtheta", "dphi", "tau"))
    M = arm.mass_matrix()(th, ph)
    tau0, T0 = arm.inverse_dynamics()(th, ph, dth, dph, ca.DM.zeros(n), ca.DM.zeros(n))
    rhs = ca.vertcat(arm.sea_torque(th, ph, dth, dph) - T0, ca.DM(arm.model.column("gear_ratio")) * (tau0 - tau))
    ddq = ca.solve(M, rhs)
    return ca.Function("mass_matrix_forward_dynamics", [th, ph, dth, dph, tau], [ddq[:n], ddq[n:]],
                       ["theta", "phi", "dtheta", "dphi", "tau"], ["ddtheta", "ddphi"])


def per_call(fn, *args, repeat=5, min_time=0.2):
    """Median seconds per call over `repeat` batches of at least `min_time` each."""
    fn(*args)
    number, t = 1, 0.0
    while True:
        t0 = time.perf_counter()
        for _ in range(number):
            fn(*args)
        t = time.perf_counter() - t0
        if t > min_time / 5:
            break
        number *= 4
    number = max(1, int(number * min_time / 5 / max(t, 1e-9)))
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn(*args)
        times.append((time.perf_counter() - t0) / number)
    return float(np.median(times))


def write_atomically(path: Path, text: str):
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


def write_results(stem: str, fig, csv: str, md: str):
    """results/STEM.png, .csv and .md, each replaced whole (no half-written file on failure)."""
    RESULTS.mkdir(exist_ok=True)
    tmp = RESULTS / f"{stem}.tmp.png"
    fig.savefig(tmp, dpi=120)
    tmp.replace(RESULTS / f"{stem}.png")
    write_atomically(RESULTS / f"{stem}.csv", csv)
    write_atomically(RESULTS / f"{stem}.md", md)
    print(f"wrote {RESULTS / stem}.md, .csv, .png")


# a fresh interpreter solves one problem file (as a user's first command would) and prints its record
CHILD = """
import json, sys, tempfile, time
t0 = time.perf_counter()
from rscasadi.ocp import load_problem, solve
from rscasadi.ocp.solving import run
say = lambda m: print(m, file=sys.stderr, flush=True)
if sys.argv[2] == "solve":
    sol = solve(load_problem(sys.argv[1]), print_level=0, log=say)
else:                                   # the command: its solution kept, and reused ("reuse")
    with tempfile.TemporaryDirectory() as out:
        sol = run(sys.argv[1], out, print_level=0, log=say, reuse=sys.argv[2] == "reuse")
rounds = sol["rounds"]
print(json.dumps({"wall_s": time.perf_counter() - t0, "success": bool(sol["success"]), "T": sol["t"][-1],
                  "setup_first_s": rounds[0]["setup_time_s"], "solve_first_s": rounds[0]["solve_time_s"],
                  "iterations_first": rounds[0]["iterations"], "rounds": len(rounds),
                  "solve_all_s": sum(r["solve_time_s"] for r in rounds),
                  "setup_all_s": sum(r["setup_time_s"] for r in rounds), "solver": sol["solver"],
                  "threads": sol["threads"]}))
"""


def solve_in_child(problem: Path, cache=None, how: str = "solve") -> dict:
    """`rscasadi.ocp.solve` of a problem file in a child process (with RSCASADI_CACHE=cache if
    given: an empty directory is a cold start); its record (CHILD).  `how`: "solve"; "command",
    `rscasadi ocp --cold` (it keeps its verified solution in the cache); "reuse", `rscasadi ocp`
    (it starts from the solution kept for the same problem)."""
    env = dict(os.environ, **({"RSCASADI_CACHE": str(cache)} if cache else {}))
    print(f"solving {problem.name}" + (f" (compile cache {cache})" if cache else "") + " ...", flush=True)
    run = subprocess.run([sys.executable, "-c", CHILD, str(problem), how], env=env, capture_output=True, text=True,
                         cwd=ROOT)
    if run.returncode != 0:
        raise RuntimeError(f"{problem.name}: {run.stderr[-2000:]}")
    return json.loads(run.stdout.strip().splitlines()[-1])


BAXTER_URDF = ROOT / "tests" / "data" / "baxter_description" / "urdf" / "baxter.urdf"
LEFT = ["left_s0", "left_s1", "left_e0", "left_e1", "left_w0", "left_w1", "left_w2"]
BAXTER_NEUTRAL = [0.0, -0.55, 0.0, 0.75, 0.0, 1.26, 0.0]


def baxter_model(directory: Path) -> Path:
    """Baxter's left arm from its whole-robot URDF (tests/data/baxter_description, as
    example-robot-data ships it) with an FS-SEA in every joint (100 / 30 N m at the link; the rest
    of the robot held still) and capsules round its forearm and wrist: baxter_sea.toml written
    into `directory`; its path.  The second 7-joint arm of the benchmarks."""
    joints = []
    for k, name in enumerate(LEFT):
        big = k < 4
        rotor = lambda m, i: {"mass": m, "com": [0.0, 0.0, 0.0], "inertia": [i, i, 1.6 * i, 0.0, 0.0, 0.0]}  # noqa: E731
        joints.append({"name": name, "gear_ratio": 100.0, "sea": {"k1": 3000.0 if big else 800.0, "d": 3.0 if big else 0.8},
                       "gear_loss": {"b": 1.0}, "limits": {"tau": 1.0 if big else 0.3, "dphi": 2.0, "psi": 0.1},
                       "slow_rotor": rotor(0.3, 2e-4), "fast_rotor": rotor(0.2, 1.5e-5)})
    model = {"name": "baxter-left-sea", "urdf": str(BAXTER_URDF), "tip": "left_gripper",
             "collision": {"margin": 0.02, "tip": "left_gripper",
                           "links": {"left_lower_shoulder": 0.08, "left_lower_elbow": 0.07, "left_lower_forearm": 0.06,
                                     "left_wrist": 0.05}},
             "joints": joints}
    (directory / "baxter_sea.toml").write_text(to_toml(model))
    return directory / "baxter_sea.toml"


def baxter_trajectory(directory: Path) -> Path:
    """A motion of Baxter's left arm of the form of problems/trajectory_panda.toml, from its neutral
    pose and back within its joint ranges (the hand sweeps about 0.4 m), with baxter_model's file:
    trajectory_baxter.toml written into `directory`; its path."""
    baxter_model(directory)
    (directory / "trajectory_baxter.toml").write_text(to_toml({
        "model": "baxter_sea.toml", "period": 2.0, "duration": 2.0, "start": BAXTER_NEUTRAL,
        "amplitude": [0.4, 0.2, 0.0, 0.3, 0.0, -0.3, 0.0]}))
    return directory / "trajectory_baxter.toml"
