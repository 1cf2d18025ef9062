"""What the rotors' spin does to a flying robot (docs/user-guide/floating.md, "Functions").

A quadruped with an SEA in every joint swings its legs in flight under the same motor torques in
four models, integrated by CVODES from the same state at rest (quaternion kinematics):

- complete: the rotors as bodies, the springs (FloatingRobot.forward_dynamics);
- reduced: the DLR/Spong model, the springs kept, each motor's spin inertia B on phi but the
  rotors' gyroscopic coupling with the links dropped (forward_dynamics(reduced=True));
- rigid: every joint `geared` (no spring), the rotors still bodies of their own (GRBDA's model);
- armature: every joint `geared`, the rotors as a joint armature B (Pinocchio's, MuJoCo's,
  Crocoddyl's model of a geared motor).

In flight the angular momentum about the centre of mass is conserved, and only what the models
count in it can turn the base: the complete and rigid models count the rotors' spin, the reduced
and armature models do not.  The study reports the base's orientation after the flight phase in
each model and the angle between complete and reduced, and between rigid and armature: the
same physics but the rotors' spin.
"""
from __future__ import annotations

import dataclasses
import time

import casadi as ca
import numpy as np

from rscasadi.dynamics.floating import FloatingRobot, _quaternion_product, rotation
from rscasadi.model.modelfile import read

SWING = 0.1                 # N m at each hip-flexion and knee motor: the legs swing one way


def rigid(model):
    """`model` with every SEA joint `geared`: its spring rigid, the rotors turning with the link."""
    joints = tuple(dataclasses.replace(jt, kind="geared", k1=0.0, k3=0.0, d=0.0) if jt.kind == "sea" else jt
                   for jt in model.joints)
    return dataclasses.replace(model, joints=joints)


def fly(robot: FloatingRobot, q0, duration: float, reduced: bool = False) -> tuple:
    """q after `duration` s of flight from q0 at rest, every hip-flexion and knee motor driven by
    SWING (the legs swing the same way about their parallel axes), the hip abductions at zero."""
    t, x = ca.SX.sym("t"), ca.SX.sym("x", robot.nq + robot.nv)
    q, v = x[:robot.nq], x[robot.nq:]
    pattern = np.array([0.0 if jt.name.endswith("HAA") else 1.0 for jt in robot.model.joints])
    tau = SWING * pattern[robot.model.actuated] + 0 * t
    qdot = ca.vertcat(rotation(q[3:7]) @ v[:3], 0.5 * _quaternion_product(q[3:7], ca.vertcat(v[3:6], 0)), v[6:])
    a = robot.forward_dynamics(reduced=reduced)(q, v, tau)
    F = ca.integrator("flight", "cvodes", {"t": t, "x": x, "ode": ca.vertcat(qdot, a)}, 0.0, duration,
                      {"abstol": 1e-10, "reltol": 1e-10})
    xf = np.asarray(F(x0=np.r_[q0, np.zeros(robot.nv)])["xf"]).ravel()
    q = xf[:robot.nq] / np.r_[np.ones(3), np.full(4, np.linalg.norm(xf[3:7])), np.ones(robot.nq - 7)]
    return q, xf[robot.nq:]


def angle_between(qa, qb) -> float:
    """The rotation angle (degrees) between two bases' orientations (quaternions xyzw)."""
    Ra, Rb = (np.asarray(ca.DM(rotation(ca.DM(q[3:7])))) for q in (qa, qb))
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1.0, 1.0))))


def study(model_file, duration: float = 0.3, log=print) -> dict:
    """The four models' base orientations after `duration` s of flight (module docstring)."""
    model = read(model_file)
    complete, stiff = FloatingRobot(model), FloatingRobot(rigid(model))
    theta = np.zeros(model.n)
    q0 = np.r_[0, 0, 1.0, 0, 0, 0, 1, theta, theta[model.motors]]
    q0_rigid = np.r_[0, 0, 1.0, 0, 0, 0, 1, theta]
    start, out, momentum, swing = time.perf_counter(), {}, {}, {}
    for name, robot, q, reduced in (("complete", complete, q0, False), ("reduced", complete, q0, True),
                                    ("rigid", stiff, q0_rigid, False), ("armature", stiff, q0_rigid, True)):
        log(f"  flying the {name} model for {duration:g} s ...")
        out[name], v = fly(robot, q, duration, reduced)
        h = np.asarray(robot.centroidal_momentum()(out[name], v)).ravel()      # counted with every rotor's spin
        momentum[name] = float(np.linalg.norm(h[3:]))
        swing[name] = float(np.max(np.abs(out[name][7:7 + model.n])))
    return {"duration_s": duration, "swing_Nm": SWING, "largest_link_angle_rad": swing,
            "base_turn_deg": {name: angle_between(q0, q) for name, q in out.items()},
            "complete_vs_reduced_deg": angle_between(out["complete"], out["reduced"]),
            "rigid_vs_armature_deg": angle_between(out["rigid"], out["armature"]),
            "angular_momentum_at_end_Nms": momentum, "seconds": time.perf_counter() - start}


def report(r: dict, stamp: str) -> str:
    """The study as Markdown."""
    rows = "\n".join(f"| {name} | {r['base_turn_deg'][name]:.3f} | {r['largest_link_angle_rad'][name]:.3f} | "
                      f"{r['angular_momentum_at_end_Nms'][name]:.2e} |" for name in r["base_turn_deg"])
    return f"""# The rotors' spin in flight

{stamp}

ANYmal C with an SEA in every joint (`problems/anymal_c_sea.toml`) released at rest in flight;
every hip-flexion and knee motor pushes {r['swing_Nm']:g} N m (x50 at the link) for
{r['duration_s']:g} s, the hip abductions at zero; CVODES (1e-10) on each model's forward dynamics
with the quaternion's kinematics.  Angular momentum at the end: the centroidal momentum of the
state each model reached, counted with every rotor's spin (zero for a model that conserves it).

| model | base turned (deg) | largest link angle (rad) | angular momentum at the end (N m s) |
|---|---|---|---|
{rows}

- complete (rotors as bodies, springs) vs reduced (DLR/Spong, springs): **{r['complete_vs_reduced_deg']:.3f} deg**
  apart after {r['duration_s']:g} s.
- rigid (geared, rotors as bodies) vs armature (Pinocchio's, MuJoCo's, Crocoddyl's rotor):
  **{r['rigid_vs_armature_deg']:.3f} deg** apart.

The fast rotor turns at -50 times its link's rate: its spin opposes the leg's swing, so the
base turns less than a model without it says, and the reduced and armature motions carry
angular momentum that nothing gave them.
"""
