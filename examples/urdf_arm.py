"""Bring your URDF: an arm from a URDF plus an actuator table, its dynamics, and the model written
back as a complete link-list model file that loads to the same dynamics.

    python examples/urdf_arm.py [--out DIR]          # docs/tutorials/urdf.md
"""
import argparse
from pathlib import Path

import numpy as np

import rscasadi
from rscasadi.files import write_text
from rscasadi.model.modelfile import document, to_toml

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/urdf_arm", help="where to write panda_link_list.toml")
    args = parser.parse_args(argv)
    arm = rscasadi.load(ROOT / "problems" / "panda_sea.toml")      # URDF form: panda.urdf + actuators
    print(f"{arm.model.name}: {arm.n} joints: {', '.join(jt.name for jt in arm.model.joints)}")

    # holding the arm still at a pose: the SEA torques T balance gravity, the motors hold T
    theta = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.8])
    zero = np.zeros(arm.n)
    tau, T = (np.array(v).ravel() for v in arm.inverse_dynamics()(theta, theta, zero, zero, zero, zero))
    print("SEA torques holding the pose (N m):", np.round(T, 3))

    # the same arm as a link-list model file, read back: the same dynamics
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "panda_link_list.toml", to_toml(document(arm.model)))
    again = rscasadi.load(out / "panda_link_list.toml")
    phi = theta + 0.01
    tau_cmd = np.linspace(-0.1, 0.1, arm.n)
    a = np.array(arm.forward_dynamics()(theta, phi, zero, zero, tau_cmd)[0]).ravel()
    b = np.array(again.forward_dynamics()(theta, phi, zero, zero, tau_cmd)[0]).ravel()
    print(f"wrote {out / 'panda_link_list.toml'}; forward dynamics equal to {np.max(np.abs(a - b)):.1e} rad/s^2")
    return float(np.max(np.abs(a - b)))


if __name__ == "__main__":
    main()
