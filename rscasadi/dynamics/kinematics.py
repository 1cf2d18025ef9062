"""Forward kinematics of the links and of named frames, their Jacobians and the centre of mass,
symbolic (docs/user-guide/frames.md).

The links' poses depend on theta only: each joint's rotors turn inside the link that carries
them.  Conventions are Pinocchio's, so that one can be checked against the other: a frame's
placement is its rotation R and origin p in the world (base) frame; a Jacobian or a velocity is
a 6-vector [linear; angular], expressed in one of three references:

- "local_world_aligned": the velocity of the frame's origin and the angular velocity, in world
  axes (dp/dt, omega);
- "local": the same two in the frame's own axes (R^T dp/dt, R^T omega);
- "world": the spatial velocity at the world origin, in world axes (dp/dt + p x omega, omega).

Accelerations are classical (Pinocchio's `getFrameClassicalAcceleration`): in
local_world_aligned the acceleration of the frame's origin and the angular acceleration; in local
the same in the frame's axes; in world the classical acceleration of the body point that is at
the world origin, p'' - omega' x p - omega x (omega x p), and omega'.
"""
from __future__ import annotations

import casadi as ca

from rscasadi.dynamics import recursions as rec
from rscasadi.spatial import base_pose, joint_rotation, skew
from rscasadi.errors import InvalidArgument

REFERENCES = ("local_world_aligned", "local", "world")


def body_poses(model, theta, root=None) -> list:
    """(R, o) of every body in the world frame: the base (0) and each joint's link (1..n), eq. (12);
    `root`: a floating base's (R, o) (default: the fixed base, the world itself)."""
    poses = [(ca.DM.eye(3), ca.DM.zeros(3)) if root is None else root]
    for j, (jt, parent) in enumerate(zip(model.joints, model.parent)):
        R_p, o_p = poses[parent + 1]
        poses.append(base_pose(R_p, o_p, *jt.joint_motion.placement(jt.R, jt.origin_xyz, theta[j])))
    return poses


def frame_pose(model, frame, theta, poses=None) -> tuple:
    """The frame's rotation and origin in the world frame (`poses`: body_poses, if at hand)."""
    R_b, o_b = (poses or body_poses(model, theta))[frame.body]
    return R_b @ ca.DM(frame.R), o_b + R_b @ ca.DM(frame.p)


def frame_jacobian(model, frame, theta, reference: str = "local_world_aligned"):
    """J (6 x n, [linear; angular]) with [v; w] = J dtheta in `reference` (module docstring).
    The angular column of a revolute joint j is its axis in the world (the z of its link's frame)
    when the frame rides on that link or on a link it carries, else zero (always zero for a
    prismatic joint); the linear part is dp/dtheta."""
    R, p, J = _placement_and_jacobian(model, frame, theta)
    return _expressed(reference, R, p, J[:3, :], J[3:, :])


def _placement_and_jacobian(model, frame, theta) -> tuple:
    """R, p and the local_world_aligned J of a frame, from one chain of body poses."""
    poses = body_poses(model, theta)
    R, p = frame_pose(model, frame, theta, poses)
    support = set(model.support(frame.body))
    Jw = ca.horzcat(*[poses[j + 1][0][:, 2] if j in support and jt.joint_motion.turns else ca.DM.zeros(3)
                      for j, jt in enumerate(model.joints)])
    return R, p, ca.vertcat(ca.jacobian(p, theta), Jw)


def _expressed(reference, R, p, lin, ang):
    """[lin; ang] given at the frame's origin in world axes, in another reference."""
    if reference == "local_world_aligned":
        return ca.vertcat(lin, ang)
    if reference == "local":
        return ca.vertcat(R.T @ lin, R.T @ ang)
    if reference == "world":
        return ca.vertcat(lin + skew(p) @ ang, ang)
    raise InvalidArgument(f"reference {reference!r}: choose one of {', '.join(REFERENCES)}")


def frame_classical_acceleration(model, frame, theta, dtheta, ddtheta, reference: str = "local_world_aligned"):
    """[linear; angular] classical acceleration in `reference` (module docstring)."""
    R, p, J = _placement_and_jacobian(model, frame, theta)              # J: local_world_aligned
    v = J @ dtheta
    a = J @ ddtheta + ca.jtimes(v, theta, dtheta)                        # J ddtheta + dJ dtheta
    if reference == "world":
        w, dw = v[3:], a[3:]
        lin = a[:3] - ca.cross(dw, p) - ca.cross(w, ca.cross(w, p))
        return ca.vertcat(lin, dw)
    return _expressed(reference, R, p, a[:3], a[3:])


def jacobian_dot_times_v(model, frame, theta, dtheta):
    """dJ/dt dtheta of the local_world_aligned Jacobian: the classical acceleration at ddtheta = 0."""
    v = frame_jacobian(model, frame, theta) @ dtheta
    return ca.jtimes(v, theta, dtheta)


def center_of_mass(segs, theta, phi):
    """The centre of mass of every moving body: links and rotors (the fixed base excluded).  A
    rotor's centre turns with phi only if it is off its axis (an unbalanced rotor)."""
    mass, moment, poses = 0, ca.DM.zeros(3), []
    for j, seg in enumerate(segs):
        R_p, o_p = poses[seg.parent] if seg.parent >= 0 else (ca.DM.eye(3), ca.DM.zeros(3))
        R_link, l_link = seg.motion.placement(seg.R, seg.l, theta[j])
        bodies = [(seg.M, R_link)]
        bodies += [(M, joint_rotation(seg.R, rec.rotor_frame_angle(gear, spins, phi[seg.motor])))
                   for gear, M, spins in seg.leaves]
        bodies += [(M, joint_rotation(seg.R, rec.rotor_frame_angle(gear, spins, theta[j])))
                   for gear, M, spins in seg.geared]
        for i, (M, R) in enumerate(bodies):
            R_b, o = base_pose(R_p, o_p, R, l_link if i == 0 else seg.l)
            m, mp = M[3, 3], ca.vertcat(M[2, 4], M[0, 5], M[1, 3])       # eq. (11): m and m c
            mass, moment = mass + m, moment + m * o + R_b @ mp
        poses.append(base_pose(R_p, o_p, R_link, l_link))
    return moment / mass


def link_wrenches(model, frames: list, theta, wrenches: list) -> list:
    """Per link (n), the spatial force [moment about the link frame's origin; force], in link
    axes, of wrenches [force; moment] (world axes) applied at the frames' origins (zero where
    none is; a wrench on the fixed base moves nothing)."""
    poses = body_poses(model, theta)
    out = [ca.DM.zeros(6) for _ in model.joints]
    for frame, f in zip(frames, wrenches):
        if frame.body == 0:
            continue
        R_b = poses[frame.body][0]
        force = R_b.T @ f[:3]
        moment = R_b.T @ f[3:] + ca.cross(ca.DM(frame.p), force)
        out[frame.body - 1] = out[frame.body - 1] + ca.vertcat(moment, force)
    return out
