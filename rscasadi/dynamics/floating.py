"""A robot on a floating base (docs/user-guide/floating.md): its dynamics as named casadi.Functions.

The base is body 0 of the tree, moved by a free-flyer joint from the world, in Pinocchio's
convention: the configuration is q = (base, theta, phi) with base = [x, y, z, qx, qy, qz, qw]
(the base frame's origin in the world and its orientation, a unit quaternion), then every joint's
angle and the SEAs' motor angles; the velocity is v = (base, dtheta, dphi) with base = [v; w], the
linear velocity of the base's origin and its angular velocity, both in the base frame.  q has
nq = 7 + n + m entries, v has nv = 6 + n + m; the generalised forces and accelerations follow v.
`FloatingRobot.coordinates` and `.velocities` name every entry.

The joints, their kinds and their generalised forces are the fixed-base robot's
(rscasadi.dynamics.arm.Arm); the recursions are the same (rscasadi.dynamics.recursions with a
`Base`).  Contacts: rscasadi.dynamics.contacts.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from rscasadi.dynamics import contacts as ct, kinematics, recursions as rec
from rscasadi.dynamics.arm import Arm
from rscasadi.model.checks import identifier
from rscasadi.model.modelfile import ArmModel
from rscasadi.errors import InvalidArgument
from rscasadi.spatial import (quaternion_product as _quaternion_product, quaternion_rotation as rotation, skew,
                              spatial_inertia, transform_inertia)

BASE_Q = ["base.x", "base.y", "base.z", "base.qx", "base.qy", "base.qz", "base.qw"]
BASE_V = ["base.vx", "base.vy", "base.vz", "base.wx", "base.wy", "base.wz"]
REFERENCES = ("local", "local_world_aligned")


def exp_se3(xi):
    """The base's displacement of a body-frame twist xi = [v; w] held for unit time (Pinocchio's
    exp6): the translation V(w) v in the base frame and the rotation as a unit quaternion, with
    V = 1 + (1 - cos t) / t^2 [w]x + (t - sin t) / t^3 [w]x^2, t = |w| (series near t = 0)."""
    v, w = xi[:3], xi[3:]
    t2 = ca.sumsqr(w)
    small = t2 < 1e-8
    t = ca.sqrt(ca.if_else(small, 1.0, t2))
    a = ca.if_else(small, 0.5 - t2 / 24, (1 - ca.cos(t)) / t ** 2)
    b = ca.if_else(small, 1.0 / 6 - t2 / 120, (t - ca.sin(t)) / t ** 3)
    s = ca.if_else(small, 0.5 - t2 / 48, ca.sin(t / 2) / t)          # sin(t/2) / t
    W = skew(w)
    return v + a * (W @ v) + b * (W @ (W @ v)), ca.vertcat(s * w, ca.cos(ca.sqrt(t2) / 2))


class FloatingRobot:
    """A tree of joints of every kind (rscasadi.model.kinds) on a floating base.  Every method
    returns a casadi.Function with inputs and outputs named as in docs/user-guide/floating.md:
    q (nq), v (nv), a (nv), tau (u: the actuated joints' inputs)."""

    def __init__(self, model: ArmModel):
        if not model.floating:
            raise InvalidArgument(f"{model.path}: the base is fixed: give floating = true (and, in the link-list "
                                  "form, a [base] body) for a floating base, or use rscasadi.dynamics.arm.Arm")
        self.model, self.arm = model, Arm(model)
        self.n, self.m, self.u = self.arm.n, self.arm.m, self.arm.u
        self.nq, self.nv = 7 + self.n + self.m, 6 + self.n + self.m
        self.physics = self.arm.physics
        self._functions: dict = {}

    def __repr__(self):
        return f"FloatingRobot({self.model.name!r}, n={self.n}, file={self.model.path!r})"

    @property
    def coordinates(self) -> list:
        """The names of q's entries: BASE_Q, every joint's angle, the SEAs' `<joint>.motor`."""
        return BASE_Q + self.model.coordinates

    @property
    def velocities(self) -> list:
        """The names of v's entries (and of a's and the generalised forces'): BASE_V, then the joints'."""
        return BASE_V + self.model.coordinates

    @property
    def inputs(self) -> list:
        """The names of tau's entries: the actuated joints'."""
        return self.arm.inputs

    # -- plumbing ---------------------------------------------------------------------------
    def _function(self, name, ins, outs, build, sizes=None):
        """The Function `name` built once: build(*inputs) from SX inputs sized by their names
        (q, v, a, tau, dt; others by `sizes`)."""
        if name not in self._functions:
            size = {"q": self.nq, "v": self.nv, "a": self.nv, "tau": self.u, "dt": 1, **(sizes or {})}
            args = [ca.SX.sym(i, size[i]) for i in ins]
            self._functions[name] = ca.Function(name, args, build(*args), ins, outs)
        return self._functions[name]

    def split_q(self, q) -> tuple:
        """q as (base [x, y, z, qx, qy, qz, qw], theta, phi)."""
        return tuple(ca.vertsplit(q, [0, 7, 7 + self.n, self.nq]))

    def split_v(self, v) -> tuple:
        """v as (base [v; w], dtheta, dphi)."""
        return tuple(ca.vertsplit(v, [0, 6, 6 + self.n, self.nv]))

    def base_inertia(self, reduced: bool = False) -> np.ndarray:
        """The base's spatial inertia in its frame (eq. 11); with `reduced`, the rotors of the joints
        on it merged in, as the DLR/Spong model carries them."""
        M = spatial_inertia(self.model.base)
        if reduced:
            for j, jt in enumerate(self.model.joints):
                if self.model.parent[j] < 0 and jt.joint_kind.rotors:
                    for part in ("slow_rotor", "fast_rotor"):
                        M = M + transform_inertia(spatial_inertia(getattr(jt, part)), jt.R, jt.origin_xyz)
        return M

    def _tree(self, q, v, reduced=False):
        """The segments, the kinematics and the Base at (q, v); x = (theta, phi, dtheta, dphi)."""
        (bq, theta, phi), (bv, dtheta, dphi) = self.split_q(q), self.split_v(v)
        base = rec.Base(self.base_inertia(reduced), ca.vertcat(bv[3:], bv[:3]), rotation(bq[3:]), bq[:3])
        segs = rec.segments(self.model, self.physics, reduced)
        x = (theta, phi, dtheta, dphi)
        return segs, rec.kinematics(segs, *x, base=base), base, x

    def _alpha0(self, base, a_base):
        """The base's acceleration in the recursions (classical, gravity as the world's
        acceleration) from a = [dv; dw]: [dw; dv + w x v - R^T g]."""
        w, v = base.V[:3], base.V[3:]
        return ca.vertcat(a_base[3:], a_base[:3] + ca.cross(w, v) - base.R.T @ ca.DM(self.physics.gravity))

    def _a_base(self, base, alpha0):
        """The inverse of `_alpha0`: [dv; dw] of the base from its acceleration in the recursions."""
        w, v = base.V[:3], base.V[3:]
        return ca.vertcat(alpha0[3:] - ca.cross(w, v) + base.R.T @ ca.DM(self.physics.gravity), alpha0[:3])

    def _forces(self, x, tau):
        """The generalised forces on v besides the inertial ones: none on the base, the joints'
        (springs, losses, inputs) as on a fixed base."""
        Q_phi = self.arm._phi_force(self.physics, x, tau) if self.m else ca.DM.zeros(0, 1)
        return ca.vertcat(ca.DM.zeros(6), self.arm._theta_force(self.physics, x, tau), Q_phi)

    def _inverse(self, q, v, a, reduced=False, gravity=True, wrenches=None):
        """The generalised inertial and gravity forces M a + h on v (base rows [force; moment]),
        less those of `wrenches` (`body_wrenches`: what the environment applies, J^T f)."""
        segs, kin, base, x = self._tree(q, v, reduced)
        a_base, ddtheta, ddphi = self.split_v(a)
        g = self.physics.gravity if gravity else np.zeros(3)
        alpha0 = self._alpha0(base, a_base)
        if not gravity:
            alpha0 = alpha0 + ca.vertcat(ca.DM.zeros(3), base.R.T @ ca.DM(self.physics.gravity))
        T, Q_phi, f0 = rec.inverse_dynamics(segs, kin, ddtheta, ddphi, g, wrenches and wrenches[1:], base, alpha0)
        if wrenches:
            f0 = f0 - wrenches[0]
        return ca.vertcat(f0[3:], f0[:3], T, Q_phi)

    def body_poses(self, q) -> list:
        """(R, o) of every body in the world: the base (0) and each joint's link (1..n)."""
        (bq, theta, _) = self.split_q(q)
        return kinematics.body_poses(self.model, theta, (rotation(bq[3:]), bq[:3]))

    def body_wrenches(self, q, applied) -> list:
        """Per body (the base, then each link) the spatial force [moment about its origin; force],
        its own axes, of `applied`: (frame, wrench, world) with wrench [force; moment] at the
        frame's origin, in world axes (world True) or the frame's own."""
        poses = self.body_poses(q)
        out = [ca.DM.zeros(6) for _ in poses]
        for frame, w, world in applied:
            fr = self.model.frame(frame)
            Rf = ca.DM(fr.R)
            R_b = poses[fr.body][0]
            to_body = R_b.T if world else Rf                              # the wrench's axes -> the body's
            force = to_body @ w[:3]
            moment = (to_body @ w[3:] if w.shape[0] == 6 else ca.DM.zeros(3)) + ca.cross(ca.DM(fr.p), force)
            out[fr.body] = out[fr.body] + ca.vertcat(moment, force)
        return out

    # -- dynamics ---------------------------------------------------------------------------------
    def forward_dynamics(self, *, reduced: bool = False) -> ca.Function:
        """q, v, tau -> a: the free motion (no contact) of the complete model, one O(n) sweep with
        the base as the root body; `reduced`: the DLR/Spong model."""
        def build(q, v, tau):
            segs, kin, base, x = self._tree(q, v, reduced)
            Q = self._forces(x, tau)
            ddtheta, ddphi, alpha0 = rec.forward_dynamics(segs, kin, Q[6:6 + self.n], Q[6 + self.n:],
                                                          self.physics.gravity, None, base)
            return [ca.vertcat(self._a_base(base, alpha0), ddtheta, ddphi)]
        return self._function("reduced_forward_dynamics" if reduced else "forward_dynamics",
                              ["q", "v", "tau"], ["a"], build)

    def inverse_dynamics(self) -> ca.Function:
        """q, v, a -> tau (the inputs that give a), T (every joint's link torque), base (the wrench
        [force; moment], base frame, that the base would need: zero for a motion without contact)."""
        return self._function("inverse_dynamics", ["q", "v", "a"], ["tau", "T", "base"],
                              lambda q, v, a: self.inputs_for(q, v, self._inverse(q, v, a)))

    def inputs_for(self, q, v, r) -> list:
        """tau, T and the base's wrench from the generalised forces r the motion needs beside the
        springs', losses' and inputs' (M a + h less what the environment applies)."""
        (_, theta, phi), (_, dtheta, dphi) = self.split_q(q), self.split_v(v)
        x = (theta, phi, dtheta, dphi)
        T = r[6:6 + self.n] + self.arm.link_loss(theta, dtheta, self.physics)
        return [self.arm._input_torques(self.physics, x, T, r[6 + self.n:]), T, r[:6]]

    def mass_matrix(self) -> ca.Function:
        """q -> M (nv x nv): the Jacobian of the generalised inertial forces by a."""
        def build(q):
            a = ca.SX.sym("a", self.nv)
            return [ca.jacobian(self._inverse(q, ca.DM.zeros(self.nv), a, gravity=False), a)]
        return self._function("mass_matrix", ["q"], ["M"], build)

    def nonlinear_effects(self) -> ca.Function:
        """q, v -> h (nv): Coriolis, centrifugal and gravity forces, M a + h = Q (Pinocchio's nle)."""
        return self._function("nonlinear_effects", ["q", "v"], ["h"],
                              lambda q, v: [self._inverse(q, v, ca.DM.zeros(self.nv))])

    def generalized_forces(self) -> ca.Function:
        """q, v, tau -> Q (nv): the springs', the losses' and the inputs' generalised forces."""
        def build(q, v, tau):
            (_, theta, phi), (_, dtheta, dphi) = self.split_q(q), self.split_v(v)
            return [self._forces((theta, phi, dtheta, dphi), tau)]
        return self._function("generalized_forces", ["q", "v", "tau"], ["Q"], build)

    def energy(self) -> ca.Function:
        """q, v -> E: kinetic, gravitational and the springs' energy of every body, the base's too."""
        def build(q, v):
            segs, kin, base, (theta, phi, _, _) = self._tree(q, v)
            c, sel = self.physics.columns, self.arm._at_motors
            spring = ca.sum1(0.5 * c["cb_k"] * (theta - c["cb_theta0"]) ** 2)
            if self.m:
                psi = phi - sel(theta)
                spring += ca.sum1(0.5 * sel(c["k1"]) * psi ** 2 + 0.25 * sel(c["k3"]) * psi ** 4)
            return [rec.energy(segs, kin, self.physics.gravity, base) + spring]
        return self._function("energy", ["q", "v"], ["E"], build)

    def integrate(self) -> ca.Function:
        """q, v, dt -> q (Pinocchio's integrate(q, v dt)): the base moved by the exponential of its
        body-frame twist (its quaternion stays unit), the joints' and motors' angles by v dt."""
        def build(q, v, dt):
            (bq, theta, phi), (bv, dtheta, dphi) = self.split_q(q), self.split_v(v)
            dp, dquat = exp_se3(bv * dt)
            quat = _quaternion_product(bq[3:], dquat)
            return [ca.vertcat(bq[:3] + rotation(bq[3:]) @ dp, quat / ca.norm_2(quat), theta + dtheta * dt,
                               phi + dphi * dt)]
        return self._function("integrate", ["q", "v", "dt"], ["q_next"], build)

    # -- frames, momentum -----------------------------------------------------------------------
    # -- contacts (rscasadi.dynamics.contacts; `contacts` None: the model file's [[contacts]]) ------
    def contact_jacobian(self, contacts=None) -> ca.Function:
        """q -> J (nc x nv): the contacts' rows (docs/user-guide/floating.md, "Contacts")."""
        return ct.jacobian(self, ct.contact_set(self.model, contacts))

    def contact_drift(self, contacts=None) -> ca.Function:
        """q, v -> gamma (nc): J-dot v, the contacts' acceleration at a = 0."""
        return ct.drift(self, ct.contact_set(self.model, contacts))

    def contact_dynamics(self, contacts=None, damping: float = 0.0, stiffness: float = 0.0) -> ca.Function:
        """q, v, tau[, anchors] -> a, f: the motion and the contact forces with the contacts held
        (J a + gamma = -damping J v - stiffness e; with a stiffness, one more input: the anchors
        the errors e are taken from, `contacts.anchor_size`), from the KKT system of the complete model."""
        return ct.forward(self, ct.contact_set(self.model, contacts), damping, stiffness)

    def contact_dynamics_jacobian(self, contacts=None, damping: float = 0.0, stiffness: float = 0.0) -> ca.Function:
        """q, v, tau[, anchors] -> da, df: the contact dynamics' derivatives by (dq, v, tau), dq the
        tangent displacement of q (integrate(q, dq)), by the implicit-function theorem."""
        return ct.forward_jacobian(self, ct.contact_set(self.model, contacts), damping, stiffness)

    def contact_inverse_dynamics(self, contacts=None) -> ca.Function:
        """q, v, a, f -> tau, T, base: inverse dynamics with the contact forces f applied."""
        return ct.inverse(self, ct.contact_set(self.model, contacts))

    def check_contacts(self, contacts, q) -> None:
        """Refuse, naming the contact, a set of contacts whose rows depend on each other at q (the
        contact dynamics would have no unique forces)."""
        ct.check(self, ct.contact_set(self.model, contacts), q)

    def impact(self, contacts=None) -> ca.Function:
        """q, v -> v_plus, impulse: a plastic impact on the contacts (J v_plus = 0)."""
        return ct.impact(self, ct.contact_set(self.model, contacts))

    def frames(self) -> list:
        """The names of the robot's frames: the base's, its links' and the model file's [frames]."""
        return [f.name for f in self.model.frames]

    def _frame_motion(self, frame, q, v, a=None):
        """One frame's `_frame_motions`."""
        return self._frame_motions([frame], q, v, a)[0]

    def _frame_motions(self, frames, q, v, a=None) -> list:
        """Per frame its rotation R and origin p in the world, its velocity [v; w] and (with `a`)
        its classical acceleration [a; dw], both in its own axes (local), from one sweep."""
        segs, kin, base, x = self._tree(q, v)
        poses = self.body_poses(q)
        if a is not None:
            a_base, ddtheta, ddphi = self.split_v(a)
            alpha0 = self._alpha0(base, a_base) + ca.vertcat(ca.DM.zeros(3), base.R.T @ ca.DM(self.physics.gravity))
            alpha = [alpha0] + rec.accelerations(segs, kin, ddtheta, ddphi, np.zeros(3), alpha0)[0]
        out = []
        for frame in frames:
            fr = self.model.frame(frame)
            R_b, o_b = poses[fr.body]
            Rf, pf = ca.DM(fr.R), ca.DM(fr.p)
            V = base.V if fr.body == 0 else kin[fr.body - 1].V
            w, vo = V[:3], V[3:]
            vel = ca.vertcat(Rf.T @ (vo + ca.cross(w, pf)), Rf.T @ w)
            acc = None
            if a is not None:
                dw, ao = alpha[fr.body][:3], alpha[fr.body][3:]
                acc = ca.vertcat(Rf.T @ (ao + ca.cross(dw, pf) + ca.cross(w, ca.cross(w, pf))), Rf.T @ dw)
            out.append((R_b @ Rf, o_b + R_b @ pf, vel, acc))
        return out

    def _frame_name(self, name, frame, reference=None):
        if reference is not None and reference not in REFERENCES:
            raise InvalidArgument(f"reference {reference!r}: choose one of {', '.join(REFERENCES)}")
        self.model.frame(frame)
        return f"{name}_{identifier(frame)}" + (f"_{reference}" if reference else "")

    def frame_placement(self, frame: str) -> ca.Function:
        """q -> rotation R (3 x 3), translation p (3 x 1): the frame in the world."""
        def build(q):
            R, p, _, _ = self._frame_motion(frame, q, ca.DM.zeros(self.nv))
            return [R, p]
        return self._function(self._frame_name("frame_placement", frame), ["q"], ["rotation", "translation"], build)

    def frame_jacobian(self, frame: str, reference: str = "local_world_aligned") -> ca.Function:
        """q -> J (6 x nv, rows [linear; angular]): the frame's velocity J v in `reference`: local
        (its own axes) or local_world_aligned (world axes), Pinocchio's ReferenceFrame."""
        def build(q):
            v = ca.SX.sym("v", self.nv)
            R, _, vel, _ = self._frame_motion(frame, q, v)
            if reference == "local_world_aligned":
                vel = ca.vertcat(R @ vel[:3], R @ vel[3:])
            return [ca.jacobian(vel, v)]
        return self._function(self._frame_name("frame_jacobian", frame, reference), ["q"], ["J"], build)

    def frame_classical_acceleration(self, frame: str, reference: str = "local_world_aligned") -> ca.Function:
        """q, v, a -> [a; dw] (6): the classical acceleration of the frame's origin and its angular
        acceleration in `reference` (Pinocchio's getFrameClassicalAcceleration)."""
        def build(q, v, a):
            R, _, _, acc = self._frame_motion(frame, q, v, a)
            return [ca.vertcat(R @ acc[:3], R @ acc[3:]) if reference == "local_world_aligned" else acc]
        return self._function(self._frame_name("frame_classical_acceleration", frame, reference),
                              ["q", "v", "a"], ["acceleration"], build)

    def center_of_mass(self) -> ca.Function:
        """q -> c (3): the centre of mass of every body, the base and the rotors included."""
        def build(q):
            segs, kin, base, _ = self._tree(q, ca.DM.zeros(self.nv))
            mass, moment = rec.mass_and_moment(segs, kin, base)
            return [moment / mass]
        return self._function("center_of_mass", ["q"], ["c"], build)

    def centroidal_momentum(self) -> ca.Function:
        """q, v -> h (6): the momentum of every body, rotors' spin included, at the centre of mass
        in world axes, [linear; angular] (Pinocchio's computeCentroidalMomentum)."""
        def build(q, v):
            segs, kin, base, _ = self._tree(q, v)
            h = rec.momentum(segs, kin, base)
            mass, moment = rec.mass_and_moment(segs, kin, base)
            return [ca.vertcat(h[:3], h[3:] - ca.cross(moment / mass, h[:3]))]
        return self._function("centroidal_momentum", ["q", "v"], ["h"], build)

    def centroidal_momentum_matrix(self) -> ca.Function:
        """q -> A (6 x nv): h = A v (Pinocchio's ccrba)."""
        def build(q):
            v = ca.SX.sym("v", self.nv)
            return [ca.jacobian(self.centroidal_momentum()(q, v), v)]
        return self._function("centroidal_momentum_matrix", ["q"], ["A"], build)


QUATERNION_TOL = 1e-6      # |q| - 1 beyond this is said when a configuration is normalised


def unit_configuration(robot: FloatingRobot, q, where: str) -> np.ndarray:
    """q (nq finite numbers) with its base quaternion normalised: a zero quaternion is refused,
    one that is not unit to QUATERNION_TOL is normalised with a warning naming `where`."""
    import warnings
    q = np.array(q, float).ravel()
    if q.shape != (robot.nq,) or not np.all(np.isfinite(q)):
        raise InvalidArgument(f"{where}: q must be {robot.nq} finite numbers ({', '.join(robot.coordinates[:7])}, "
                              f"...), got shape {q.shape}")
    norm = float(np.linalg.norm(q[3:7]))
    if norm < 1e-9:
        raise InvalidArgument(f"{where}: the base quaternion {q[3:7].tolist()} is zero: no orientation")
    if abs(norm - 1.0) > QUATERNION_TOL:
        warnings.warn(f"{where}: the base quaternion has norm {norm:.6g}; normalised", stacklevel=3)
    q[3:7] /= norm
    return q


def load_robot(path) -> Arm | FloatingRobot:
    """Read a model file: a FloatingRobot when its base floats (floating = true), else an Arm."""
    from rscasadi.model.modelfile import read
    model = read(path)
    return FloatingRobot(model) if model.floating else Arm(model)


def neutral(robot: FloatingRobot) -> np.ndarray:
    """The configuration at the world origin, level, every joint and motor at zero."""
    q = np.zeros(robot.nq)
    q[6] = 1.0
    return q


def to_mujoco(q, v) -> tuple:
    """The base's q [x, y, z, qx, qy, qz, qw] and v [v; w] (base frame) in MuJoCo's free joint:
    qpos [x, y, z, qw, qx, qy, qz] and qvel [v (world axes); w (base frame)]."""
    q, v = np.asarray(q, float), np.asarray(v, float)
    R = np.array(ca.DM(rotation(ca.DM(q[3:7]))))
    return np.r_[q[:3], q[6], q[3:6]], np.r_[R @ v[:3], v[3:6]]


def from_mujoco(qpos, qvel) -> tuple:
    """The inverse of `to_mujoco`: Pinocchio's base q and v from MuJoCo's free joint's."""
    qpos, qvel = np.asarray(qpos, float), np.asarray(qvel, float)
    quat = np.r_[qpos[4:7], qpos[3]]
    R = np.array(ca.DM(rotation(ca.DM(quat))))
    return np.r_[qpos[:3], quat], np.r_[R.T @ qvel[:3], qvel[3:6]]
