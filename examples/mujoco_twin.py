"""The Panda with SEAs in MuJoCo: from its URDF and actuator table (problems/panda_sea.toml) to
MJCF files, checked against rscasadi's model, and a controller tried on MuJoCo's physics.

    python examples/mujoco_twin.py [--out DIR] [--seconds 1.0]   # docs/tutorials/mujoco.md
"""
import argparse
from pathlib import Path

import numpy as np

import rscasadi
from rscasadi.export.mujoco import compare_variants, export_mujoco, mujoco_plant
from rscasadi.sim.loop import Encoders, FeedforwardPD, run_loop, tracking
from rscasadi.sim.simulation import feedforward, motor_pd_gains
from rscasadi.sim.trajectory import load_trajectory

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/mujoco_twin", help="where the MJCF files go")
    parser.add_argument("--seconds", type=float, default=1.0, help="of the trajectory to run the controller on")
    args = parser.parse_args(argv)
    model, out = ROOT / "problems" / "panda_sea.toml", Path(args.out)
    for variant in ("complete", "armature"):                   # the files MuJoCo loads
        export_mujoco(model, out / variant, variant=variant)
    arm, trajectory = rscasadi.load(model), load_trajectory(ROOT / "problems" / "trajectory_panda.toml")
    err = compare_variants(arm, trajectory)                    # held feedforward torques, open loop
    print(f"MuJoCo against rscasadi's replay over {err['seconds']:g} s: complete {err['complete']:.1e} rad, "
          f"reduced {err['reduced']:.1e} rad, armature {err['armature']:.1e} rad")
    dt = 1e-3                                                  # the controller on MuJoCo's arm:
    samples = int(round(args.seconds / dt))
    ff = feedforward(arm, trajectory, np.arange(samples + 1) * dt)   # the paper's feedforward
    kp, kd = motor_pd_gains(arm.model)                         # and a motor-position PD around it
    run = run_loop(arm, mujoco_plant(arm, dt), FeedforwardPD(ff, (kp, kd, arm.model.column("gear_ratio"))),
                   ff["x0"], samples, dt, sensors=Encoders(arm, dt))
    error = np.abs(run.x[:arm.n] - trajectory(run.t)[0]).max(axis=0)
    result = tracking(run.t, error)
    print(f"feedforward + motor PD on MuJoCo's Panda, {args.seconds:g} s at 1 kHz with quantised encoders: "
          f"largest link-angle error {result['max_error']:.1e} rad")
    return err, result


if __name__ == "__main__":
    main()
