"""Task space on the Panda: the tool's position and Jacobian, the SEA and motor torques that hold
20 N pushing down on the tool at rest, and a tool pose reached by inverse kinematics.

    python examples/task_space.py                       # docs/user-guide/frames.md
"""
from pathlib import Path

import numpy as np

import rscasadi

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None):
    arm = rscasadi.load(ROOT / "problems" / "panda_sea.toml")
    tool = "panda_hand_tcp"                                            # a URDF link: the tool centre point
    theta = np.array([0.0, -0.3, 0.0, -2.2, 0.0, 1.9, 0.8])
    R, p = (np.array(v) for v in arm.frame_placement(tool)(theta))
    J = np.array(arm.frame_jacobian(tool, "local_world_aligned")(theta))   # [linear; angular] x 7
    print(f"tool at {np.round(p.ravel(), 4)} m; its Jacobian is {J.shape[0]} x {J.shape[1]}")

    # at rest, the environment pushes up on the tool with 20 N (the arm pushes down with 20 N):
    # the SEA torques T that hold it, and the motor torques tau, from the inverse dynamics
    zero = np.zeros(arm.n)
    f = np.array([0.0, 0.0, 20.0, 0.0, 0.0, 0.0])                     # [force; moment], world axes
    inv = arm.inverse_dynamics(external=[tool])
    _, T_free = (np.array(v).ravel() for v in arm.inverse_dynamics()(theta, theta, zero, zero, zero, zero))
    tau, T = (np.array(v).ravel() for v in inv(theta, theta, zero, zero, zero, zero, f))
    print("SEA torques holding the arm (N m):          ", np.round(T_free, 2))
    print("... and pushing 20 N down on the table (N m):", np.round(T, 2))
    assert np.allclose(T_free - T, J.T @ f)                           # the wrench's share is J^T f

    # the same tool orientation 5 cm lower, as close to theta as the limits allow
    res = rscasadi.inverse_kinematics(arm, tool, position=p.ravel() - [0.0, 0.0, 0.05], R=R, theta_guess=theta)
    print(f"inverse kinematics: {res['status']}, position error {res['position_error']:.1e} m")
    return {"T_free": T_free, "T": T, "J": J, "ik": res}


if __name__ == "__main__":
    main()
