"""Legs and a floating base: ANYmal C from its URDF with a series elastic actuator in every joint,
on a free-flying base with four point feet: its named coordinates, a standing posture on its
feet, the contact dynamics in C, and the robot standing on MuJoCo's floor.

    python examples/legs.py [--out DIR]          # docs/tutorials/legs.md
"""
import argparse
from pathlib import Path

import numpy as np

import rscasadi
from rscasadi.dynamics.stance import stand
from rscasadi.export.mujoco import export_mujoco, mujoco_state, standing_height, state_from_mujoco

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "problems" / "anymal_c_sea.toml"


def crouch(robot) -> np.ndarray:
    """The links' angles of a crouch: hips flexed 0.5 rad, knees 1 rad, hind legs mirrored."""
    theta = np.zeros(robot.n)
    for j, jt in enumerate(robot.model.joints):
        front = jt.name[1] == "F"
        if jt.name.endswith("HFE"):
            theta[j] = 0.5 if front else -0.5
        elif jt.name.endswith("KFE"):
            theta[j] = -1.0 if front else 1.0
    return theta


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/legs", help="where to write the C and the MJCF")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    # 1. the robot on its floating base
    robot = rscasadi.load_robot(MODEL)
    print(f"{robot.model.name}: {robot.n} joints, nq = {robot.nq}, nv = {robot.nv}, {robot.u} inputs; "
          f"contacts {[f for f, _ in robot.model.contacts]}")
    print("q =", robot.coordinates[:8], "...", robot.coordinates[-2:])

    # 2. standing: the springs deflected, least-effort torques, forces inside the friction cones
    theta = crouch(robot)
    s = stand(robot, theta, np.r_[0, 0, standing_height(robot.model, theta), 0, 0, 0, 1], mu=0.7)
    print(f"standing: motor torques up to {np.max(np.abs(s.tau)):.3f} N m, feet carry "
          f"{np.round(s.f[2::3], 1)} N, contact dynamics there: |a| = {s.residual:.1e}")

    # 3. the contact dynamics in C (only what a controller needs)
    from rscasadi.codegen import generate
    manifest = generate(robot, out / "c", only=["contact_dynamics", "integrate"], opt="-O1", log=lambda m: None)
    compiled = rscasadi.load_compiled(out / "c")
    rng = np.random.default_rng(0)
    q = s.q.copy()
    q[7:] += rng.uniform(-0.05, 0.05, robot.n + robot.m)
    v, tau = rng.normal(size=robot.nv), rng.uniform(-0.5, 0.5, robot.u)
    c_error = max(float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
                  for a, b in zip(compiled["contact_dynamics"](q, v, tau), robot.contact_dynamics()(q, v, tau)))
    print(f"C: {list(manifest['functions'])} in {manifest['library']}; off the Functions by {c_error:.1e}")

    # 4. MuJoCo: standing on its floor under a motor PD about the posture
    export_mujoco(MODEL, out / "mujoco", log=print)
    force_gap = None
    try:
        import mujoco
    except ImportError:
        mujoco = None
    if mujoco is not None:
        m = mujoco.MjModel.from_xml_path(str(out / "mujoco" / "model.xml"))
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:] = mujoco_state(robot, m, s.q, np.zeros(robot.nv))
        phi = s.q[7 + robot.n:]
        for _ in range(2000):                              # 2 s: 20 N m/rad, 0.5 N m s/rad at the motors
            q, v = state_from_mujoco(robot, m, d.qpos, d.qvel)
            d.ctrl[:] = s.tau + 20.0 * (q[7 + robot.n:] - phi) + 0.5 * v[6 + robot.n:]
            mujoco.mj_step(m, d)
        feet = {}
        for i in range(d.ncon):
            c, f6 = d.contact[i], np.zeros(6)
            mujoco.mj_contactForce(m, d, i, f6)
            foot = c.geom2 if m.geom(c.geom2).name.startswith("contact_") else c.geom1
            sign = 1.0 if foot == c.geom2 else -1.0
            feet[m.geom(foot).name] = feet.get(m.geom(foot).name, 0) + sign * c.frame.reshape(3, 3).T @ f6[:3]
        f_mj = np.concatenate([feet[f"contact_{name}"] for name, _ in robot.model.contacts])
        f_model = np.asarray(robot.contact_dynamics()(q, v, d.ctrl)[1]).ravel()
        force_gap = float(np.max(np.abs(f_mj - f_model)))
        print(f"MuJoCo after 2 s: base {1e3 * abs(q[2] - s.q[2]):.1f} mm lower; its foot forces against the "
              f"model's contact forces at its state: {force_gap:.2f} N apart (of {np.sum(s.f[2::3]):.0f} N)")
    verified = c_error < 1e-9 and (force_gap is None or force_gap < 0.01 * np.sum(s.f[2::3]))
    print(f"legs: wrote {out / 'c'} and {out / 'mujoco' / 'model.xml'}; "
          f"{'verified' if verified else 'NOT verified'} (C against the Functions"
          f"{', MuJoCo against the contact forces' if force_gap is not None else ''})")
    return {"stance": s, "c_error": c_error, "force_gap": force_gap, "verified": verified}


if __name__ == "__main__":
    main()
