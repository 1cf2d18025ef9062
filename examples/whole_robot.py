"""Your whole robot: Baxter's two arms and head from its URDF as one tree, with joints of three
kinds (SEAs in the shoulders and elbows, geared wrists, a direct-drive head), its named
coordinates, its C, and its MuJoCo model checked against the model; then a two-handed handover
planned on the whole tree with the forearms kept apart and verified, and the generated MPC
executing it in MuJoCo.

    python examples/whole_robot.py [--out DIR] [--intervals N]    # docs/tutorials/whole-robot.md
"""
import argparse
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np

import rscasadi
from rscasadi.files import write_text
from rscasadi.model.modelfile import to_toml

ROOT = Path(__file__).resolve().parents[1]
URDF = ROOT / "tests" / "data" / "baxter_description" / "urdf" / "baxter.urdf"
ARM = ("s0", "s1", "e0", "e1", "w0", "w1", "w2")
GOALS = ([0.7, 0.05, 1.0], [0.7, -0.05, 1.0])        # the grippers at the handover (m, world)
# the MPC follows the handover this many times slower: the plan itself has the shoulders'
# torques and every motor's speed at their limits, nothing left to correct with
SLOWER = 2.0


def rotor(mass: float, izz: float) -> dict:
    return {"mass": mass, "com": [0.0, 0.0, 0.0], "inertia": [izz / 1.6, izz / 1.6, izz, 0.0, 0.0, 0.0]}


def sea(name: str) -> dict:
    return {"name": name, "gear_ratio": 100.0, "sea": {"k1": 3000.0, "d": 3.0},
            "gear_loss": {"b": 1.0}, "limits": {"tau": 1.0, "dphi": 2.0, "psi": 0.1},
            "slow_rotor": rotor(0.3, 3.2e-4), "fast_rotor": rotor(0.2, 2.4e-5)}


def model_file() -> dict:
    """Baxter's tree, tips both grippers and the head: SEA shoulders and elbows, geared wrists, a
    direct-drive head; the lower forearms (their URDF cylinders) kept 1 cm apart."""
    joints = [{"name": "head_pan", "kind": "direct", "limits": {"tau": 5.0}}]
    for side in ("left", "right"):
        for j in ARM:
            if not j.startswith("w"):
                joints.append(sea(f"{side}_{j}"))
            else:
                joints.append({"name": f"{side}_{j}", "kind": "geared", "gear_ratio": 80.0, "gear_loss": {"b": 0.2},
                               "limits": {"tau": 0.3, "dphi": 2.0}, "slow_rotor": rotor(0.1, 8e-5),
                               "fast_rotor": rotor(0.05, 8e-6)})
    return {"name": "baxter-kinds", "urdf": str(URDF), "tips": ["left_gripper", "right_gripper", "head"],
            "joints": joints, "collision": {"margin": 0.01, "pairs": [["left_lower_forearm", "right_lower_forearm"]]}}


class Follow:
    """The generated MPC following a solution's link angles and speeds `slower` times slower (its
    reference: a column per interval end of the horizon), for rscasadi.sim.loop.run_loop."""

    def __init__(self, mpc, solution, horizon: int, interval: float, dt: float, slower: float = 1.0):
        self.mpc, self.t, self.seconds = mpc, slower * np.asarray(solution["t"]), None
        self.q = np.vstack([np.asarray(solution["theta"]), np.asarray(solution["dtheta"]) / slower])
        self.ahead, self.dt = interval * np.arange(1, horizon + 1), dt

    def init(self, meas):
        self.mpc.init(meas)

    def step(self, k, meas):
        times = np.minimum(k * self.dt + self.ahead, self.t[-1])
        reference = np.vstack([np.interp(times, self.t, row) for row in self.q])
        tau, self.seconds, flag = self.mpc.step(meas, reference)
        if flag:
            raise RuntimeError(f"mpc_step returned {flag} at sample {k}")
        return tau


def execute(out: Path) -> dict:
    """The generated MPC (out/mpc) following the handover (out/handover/solution.json) SLOWER times
    slower at 1 kHz on the MuJoCo export, the encoders quantised, until 0.5 s after its end:
    out/tracked.json."""
    from rscasadi.export.mujoco import mujoco_plant
    from rscasadi.mpc.compiled import CompiledMPC
    from rscasadi.sim.loop import Encoders, limit_violation, run_loop
    robot = rscasadi.load(out / "baxter_kinds.toml")
    solution = json.loads((out / "handover" / "solution.json").read_text())
    problem = tomllib.loads((out / "mpc.toml").read_text())
    dt, T = problem["sample_time"], SLOWER * solution["t"][-1]
    x0 = np.concatenate([np.asarray(solution[k])[:, 0] for k in ("theta", "phi", "dtheta", "dphi")])
    follow = Follow(CompiledMPC(out / "mpc"), solution, problem["horizon"], problem["interval"], dt, SLOWER)
    loop = run_loop(robot, mujoco_plant(robot, dt), follow, x0, int(round((T + 0.5) / dt)), dt, sensors=Encoders(robot, dt))
    planned = np.vstack([np.interp(loop.t, follow.t, row) for row in np.asarray(solution["theta"])])
    hands = [np.array(robot.frame_placement(f"{side}_gripper")(loop.x[:robot.n, -1])[1]).ravel() for side in ("left", "right")]
    errors = np.max(np.abs(loop.x[:robot.n] - planned), axis=1)
    tracked = {"max_error": float(np.max(errors)), "errors": dict(zip(robot.coordinates, map(float, errors))),
               "hand_error": max(float(np.linalg.norm(h - g)) for h, g in zip(hands, GOALS)),
               "max_limit_violation": limit_violation(robot, loop), "step_median_s": float(np.median(loop.seconds))}
    write_text(out / "tracked.json", json.dumps(tracked))
    return tracked


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/whole_robot", help="where to write the model files, C and MJCF")
    parser.add_argument("--intervals", type=int, default=160, help="the handover's first collocation intervals")
    parser.add_argument("--execute", metavar="DIR", help="only the MPC's closed loop of a finished run in DIR")
    args = parser.parse_args(argv)
    if args.execute:
        return execute(Path(args.execute))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    # 1. the whole robot with joints of three kinds
    write_text(out / "baxter_kinds.toml", to_toml(model_file()))
    robot = rscasadi.load(out / "baxter_kinds.toml")
    print(f"{robot.model.name}: {robot.n} joints, {robot.m} motor coordinates, {robot.u} inputs; "
          f"carried by: {[robot.model.joints[p].name if p >= 0 else 'base' for p in robot.model.parent]}")
    print("q =", robot.coordinates)
    rng = np.random.default_rng(0)
    x = [rng.uniform(-0.5, 0.5, size) for size in (robot.n, robot.m, robot.n, robot.m)]
    tau = rng.uniform(-0.1, 0.1, robot.u)
    ddq = np.concatenate([np.array(v).ravel() for v in robot.forward_dynamics()(*x, tau)])

    # 2. its C: the same Functions, sizes as macros
    from rscasadi.codegen import generate
    manifest = generate(robot, out / "c", log=lambda m: None, opt="-O1")
    compiled = rscasadi.load_compiled(out / "c")
    c_ddq = np.concatenate([np.array(v).ravel() for v in compiled["forward_dynamics"](*x, tau)])
    print(f"C: {len(manifest['functions'])} functions in {manifest['library']}; forward dynamics off by "
          f"{np.max(np.abs(c_ddq - ddq)):.1e}")

    # 3. MuJoCo: its mass matrix and forces, projected through the gears, are the model's
    from rscasadi.export.mujoco import export_mujoco, gear_map
    mismatch = None
    try:
        import mujoco
    except ImportError:
        mujoco = None
    export_mujoco(out / "baxter_kinds.toml", out / "mujoco", log=print)
    if mujoco is not None:
        m = mujoco.MjModel.from_xml_path(str(out / "mujoco" / "model.xml"))
        d, T = mujoco.MjData(m), gear_map(robot, m)
        d.qpos[:], d.qvel[:], d.ctrl[:] = T @ np.r_[x[0], x[1]], T @ np.r_[x[2], x[3]], tau
        mujoco.mj_forward(m, d)
        M = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, M)
        ours = np.array(robot.mass_matrix()(x[0], x[1]))
        mismatch = float(np.max(np.abs(T.T @ M @ T - ours)) / np.max(np.abs(ours)))
        print(f"MuJoCo's mass matrix against the model's: {mismatch:.1e} (relative)")

    # 4. both hands to a handover in front of the torso, every joint free, the forearms apart
    from rscasadi.ocp import load_problem, run
    write_text(out / "handover.toml", "\n".join([
        'model = "baxter_kinds.toml"', 'objective = "min_effort"', f"theta_start = {[0.0] * robot.n}",
        "duration = 2.0", "[transcription]", f"intervals = {args.intervals}", "limit_margin = 0.005",
        "[[goal]]", 'frame = "left_gripper"', f"position = {GOALS[0]}",
        "[[goal]]", 'frame = "right_gripper"', f"position = {GOALS[1]}", ""]))
    solution = run(load_problem(out / "handover.toml"), out / "handover", log=print, print_level=0)
    report = solution["verification"]
    print(f"handover: {'verified' if report['passed'] else 'NOT verified'}, hands within "
          f"{report['goal_position_error']:.1e} m of their goals, forearms at least "
          f"{report['min_clearance'] + 0.01:.3f} m apart")

    # 5. the generated MPC executes it in MuJoCo at 1 kHz
    from rscasadi.dynamics.modes import linear_modes, rk4_substeps
    from rscasadi.mpc.generate import generate_mpc
    horizon, interval, dt = 10, 0.02, 0.001
    # the RK4 substeps that amplify none of the springs' modes anywhere along the motion (the
    # problem's "auto" looks at its start only; here the modes speed up from 43 to 51 Hz)
    theta = np.asarray(solution["theta"])
    substeps = max(rk4_substeps(linear_modes(robot, theta[:, k]), interval) or 50
                   for k in np.linspace(0, theta.shape[1] - 1, 5).astype(int))
    write_text(out / "mpc.toml", "\n".join([
        'model = "baxter_kinds.toml"', f"sample_time = {dt}", f"horizon = {horizon}", f"interval = {interval}",
        f"substeps = {substeps}", "[weights]", "theta = 1e4", "dtheta = 100.0", "tau = 1e-3", "limits = 1e6", ""]))
    generate_mpc(out / "mpc.toml", out / "mpc", opt="-O1", log=print)
    tracked = None
    if mujoco is not None:
        # in a process of its own, as `rscasadi mpc` would run it: in the process that had just
        # solved the handover, the same loop once measured a state out of its box at 1.76 s
        # (a known, open defect: something the solve leaves loaded changes the controller)
        subprocess.run([sys.executable, __file__, "--execute", str(out)], check=True)
        tracked = json.loads((out / "tracked.json").read_text())
        worst = max(tracked["errors"], key=tracked["errors"].get)
        print(f"MPC in MuJoCo: largest deviation from the plan {tracked['max_error']:.1e} rad ({worst}), hands "
              f"{tracked['hand_error']:.1e} m from their goals 0.5 s after it, limits exceeded by "
              f"{tracked['max_limit_violation']:.1%}, {1e3 * tracked['step_median_s']:.2f} ms a step (median)")
    return {"c_error": float(np.max(np.abs(c_ddq - ddq))), "mujoco_mismatch": mismatch, "solution": solution,
            "tracked": tracked}


if __name__ == "__main__":
    main()
