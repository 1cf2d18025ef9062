"""Your whole robot: Baxter's two arms and head from its URDF as one tree, with joints of three
kinds (SEAs in the shoulders and elbows, geared wrists, a direct-drive head), its named
coordinates, its C, and its MuJoCo model checked against the model; then, every joint an SEA, a
two-handed handover planned and verified (the shoulders and elbows SEAs, the wrists and head
held).

    python examples/whole_robot.py [--out DIR] [--intervals N]    # docs/tutorials/whole-robot.md
"""
import argparse
from pathlib import Path

import numpy as np

import rscasadi
from rscasadi.files import write_text
from rscasadi.model.modelfile import to_toml

ROOT = Path(__file__).resolve().parents[1]
URDF = ROOT / "tests" / "data" / "baxter_description" / "urdf" / "baxter.urdf"
ARM = ("s0", "s1", "e0", "e1", "w0", "w1", "w2")


def rotor(mass: float, izz: float) -> dict:
    return {"mass": mass, "com": [0.0, 0.0, 0.0], "inertia": [izz / 1.6, izz / 1.6, izz, 0.0, 0.0, 0.0]}


def sea(name: str) -> dict:
    return {"name": name, "gear_ratio": 100.0, "sea": {"k1": 3000.0, "d": 3.0},
            "gear_loss": {"b": 1.0}, "limits": {"tau": 1.0, "dphi": 2.0, "psi": 0.1},
            "slow_rotor": rotor(0.3, 3.2e-4), "fast_rotor": rotor(0.2, 2.4e-5)}


def model_file(kinds: bool) -> dict:
    """Baxter's tree, tips both grippers and the head: SEA shoulders and elbows, geared wrists and
    a direct-drive head (kinds); or for the handover the shoulders and elbows alone, SEAs, the
    wrists and head held at 0."""
    joints = [{"name": "head_pan", "kind": "direct", "limits": {"tau": 5.0}}] if kinds else []
    for side in ("left", "right"):
        for k, j in enumerate(ARM):
            if not j.startswith("w"):
                joints.append(sea(f"{side}_{j}"))
            elif kinds:
                joints.append({"name": f"{side}_{j}", "kind": "geared", "gear_ratio": 80.0, "gear_loss": {"b": 0.2},
                               "limits": {"tau": 0.3, "dphi": 2.0}, "slow_rotor": rotor(0.1, 8e-5),
                               "fast_rotor": rotor(0.05, 8e-6)})
    doc = {"name": "baxter-kinds" if kinds else "baxter-arms", "urdf": str(URDF),
           "tips": ["left_gripper", "right_gripper"] + (["head"] if kinds else []), "joints": joints}
    if not kinds:
        doc["locked"] = {f"{side}_{j}": 0.0 for side in ("left", "right") for j in ARM if j.startswith("w")}
    return doc


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/whole_robot", help="where to write the model files, C and MJCF")
    parser.add_argument("--intervals", type=int, default=40, help="the handover's collocation intervals")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    # 1. the whole robot with joints of three kinds
    write_text(out / "baxter_kinds.toml", to_toml(model_file(kinds=True)))
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

    # 4. the arms' SEAs: both hands to a handover in front of the torso
    write_text(out / "baxter_arms.toml", to_toml(model_file(kinds=False)))
    from rscasadi.ocp import load_problem, run
    write_text(out / "handover.toml", "\n".join([
        'model = "baxter_arms.toml"', 'objective = "min_effort"', f"theta_start = {[0.0] * 8}", "duration = 2.0",
        "[transcription]", f"intervals = {args.intervals}", "limit_margin = 0.005",
        "[[goal]]", 'frame = "left_gripper"', "position = [0.7, 0.05, 1.0]",
        "[[goal]]", 'frame = "right_gripper"', "position = [0.7, -0.05, 1.0]", ""]))
    solution = run(load_problem(out / "handover.toml"), out / "handover", log=print, print_level=0)
    report = solution["verification"]
    print(f"handover: {'verified' if report['passed'] else 'NOT verified'}, hands within "
          f"{report['goal_position_error']:.1e} m of their goals")
    return {"c_error": float(np.max(np.abs(c_ddq - ddq))), "mujoco_mismatch": mismatch, "solution": solution}


if __name__ == "__main__":
    main()
