"""The complete model the Pinocchio way, as an outside reference (optional: `pip install pin`).

Every rotor is a separate revolute joint of the tree: each joint's two rotors (if its kind has
them) on its parent link beside it, added before its link, and the joints added depth first
(whatever the model's order), which Pinocchio's CRBA needs.
The gear constraint q_tree = G q, with fast-rotor angle -mu times the coordinate the rotors turn
with (an SEA's phi, a geared joint's theta), projects the tree's dynamics onto q = (theta, phi):
M = G^T M_tree G, c = G^T rnea(q_tree, G dq, 0).  The generalised forces of each kind are
written here again, in numpy, from docs/user-guide/model.md.

Two ways to build it: from our ArmModel (`PinocchioRoute(model)`), or from the URDF itself
(`PinocchioRoute.from_urdf(model)`), where Pinocchio parses the URDF, merges fixed links and
locks joints by its own code, and only the actuators come from our model file.
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin

from rscasadi.model.urdf import axis_rotation
from rscasadi.errors import InvalidArgument


class PinocchioRoute:
    """The arm as a Pinocchio tree with the rotors as bodies of their own: the independent oracle."""

    def __init__(self, model, stages=None, gravity=None, base_inertia=None):
        """stages: per joint (placement SE3 in the parent joint frame, joint model, link Inertia,
        rotation from the joint frame to J_j, whose z is the axis); default: from `model`.  A
        floating model's base is a free-flyer joint first (its Inertia: `base_inertia`, default
        the model's); q = (base, ...) and v = (base, ...) as docs/user-guide/floating.md."""
        self.arm_model, n = model, model.n
        if stages is None:
            stages = [(pin.SE3(jt.R, np.asarray(jt.origin_xyz, float)),
                       pin.JointModelRZ() if jt.joint_motion.turns else pin.JointModelPZ(),
                       _inertia(jt.link, np.eye(3)), np.eye(3)) for jt in model.joints]
        self.model = pin.Model()
        self.model.gravity.linear = np.asarray(model.gravity if gravity is None else gravity, float)
        motors = [j for j, jt in enumerate(model.joints) if jt.kind == "sea"]
        with_rotors = [j for j, jt in enumerate(model.joints) if jt.kind in ("sea", "geared")]
        self.nb = 6 if model.base is not None else 0          # a floating base's velocities, first
        G, link_id = np.zeros((self.nb + n + 2 * len(with_rotors), self.nb + n + len(motors))), {-1: 0}
        if self.nb:
            link_id[-1] = self.model.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(), "base")
            self.model.appendBodyToJoint(link_id[-1], base_inertia if base_inertia is not None
                                         else _inertia(model.base, np.eye(3)), pin.SE3.Identity())
            G[:6, :6] = np.eye(6)
        for j in _depth_first(model.parent):
            (placement, jmodel, link_inertia, R_a), jt = stages[j], model.joints[j]
            turns = self.nb + (n + motors.index(j) if jt.kind == "sea" else j)   # the coordinate the rotors follow
            bodies = [(_inertia(jt.slow_rotor, R_a), turns, 1.0), (_inertia(jt.fast_rotor, R_a), turns, -jt.gear_ratio)]
            for k, (inertia, col, gear) in enumerate((bodies if j in with_rotors else [])
                                                     + [(link_inertia, self.nb + j, 1.0)]):
                jid = self.model.addJoint(link_id[model.parent[j]], jmodel, placement, f"joint{j}_{k}")
                self.model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
                G[self.model.joints[jid].idx_v, col] = gear
            link_id[j] = jid                               # the link carries its child joints
            held = model.payload
            if held is not None and model.frame(held.frame).body == j + 1:   # a payload on this link
                f = model.frame(held.frame)
                self.model.appendBodyToJoint(jid, _inertia(held.body, np.eye(3)), pin.SE3(R_a @ f.R, R_a @ f.p))
        self.axes = [np.eye(3)] + [stage[3] for stage in stages]         # J_j = the Pinocchio joint frame R_a
        for f in model.frames:                                   # our frames, on Pinocchio's joints
            parent = link_id[f.body - 1]
            self.model.addFrame(pin.Frame(f.name, parent, pin.SE3(self.axes[f.body] @ f.R, self.axes[f.body] @ f.p),
                                          pin.FrameType.OP_FRAME))
        self.G, self.data, self.motors = G, self.model.createData(), motors
        self.kinds = [jt.kind for jt in model.joints]
        self.actuated = [j for j, k in enumerate(self.kinds) if k in ("sea", "geared", "direct")]
        self.link_ids = [self.model.getJointId(f"joint{j}_{2 if j in with_rotors else 0}") for j in range(n)]
        self._cols = {a: model.column(a) for a in ("k1", "k3", "d", "b", "c", "eps", "gear_ratio", "link_b", "link_c",
                                                   "cb_k", "cb_theta0", "c1", "stribeck", "v_stribeck")}

    @classmethod
    def from_urdf(cls, model):
        """The link tree from Pinocchio's own URDF parser (fixed links merged, locked joints
        removed by buildReducedModel at their locked values); rotors from our model file."""
        reduced = urdf_model(model)
        first = 2 if model.floating else 1                  # joint 1 of a floating robot: Pinocchio's root_joint
        names = [reduced.names[i] for i in range(first, reduced.njoints)]
        ours = [jt.name for jt in model.joints]
        parents = [ours.index(reduced.names[reduced.parents[i]]) if reduced.parents[i] >= first else -1
                   for i in (reduced.getJointId(name) for name in ours if name in names)]
        if sorted(names) != sorted(ours) or tuple(parents) != model.parent:
            raise InvalidArgument(f"Pinocchio's tree {names} differs from the model's joints {ours}")
        stages = []
        for i in (reduced.getJointId(name) for name in ours):
            axis, slides = _axis(reduced.joints[i])
            jmodel = (pin.JointModelPrismaticUnaligned if slides else pin.JointModelRevoluteUnaligned)(*axis)
            stages.append((reduced.jointPlacements[i], jmodel,
                           reduced.inertias[i], axis_rotation(axis)))
        return cls(model, stages, base_inertia=reduced.inertias[1] if model.floating else None)

    def tree_state(self, q, v) -> tuple:
        """Pinocchio's (q, v) of the tree from ours: q = (base, theta, phi), v likewise."""
        nb = 7 if self.nb else 0
        q_tree = np.r_[np.asarray(q[:nb], float), self.G[self.nb:, self.nb:] @ np.asarray(q[nb:], float)]
        return q_tree, self.G @ np.asarray(v, float)

    def dynamics(self, q, v) -> tuple:
        """M and h = C v + g (Pinocchio's nle) on our v at our (q, v)."""
        qt, vt = self.tree_state(q, v)
        M = pin.crba(self.model, self.data, qt)
        M = np.triu(M) + np.triu(M, 1).T                  # crba fills the upper triangle
        return self.G.T @ M @ self.G, self.G.T @ pin.rnea(self.model, self.data, qt, vt, np.zeros(self.model.nv))

    def frame_motion(self, name, q, v, reference) -> tuple:
        """The frame's Jacobian on our v and its classical acceleration at a = 0 (J-dot v), [linear;
        angular], in `reference` (a pin.ReferenceFrame), and its spatial acceleration at a = 0."""
        qt, vt = self.tree_state(q, v)
        fid = self.model.getFrameId(name)
        pin.forwardKinematics(self.model, self.data, qt, vt, np.zeros(self.model.nv))
        pin.computeJointJacobians(self.model, self.data, qt)
        pin.updateFramePlacements(self.model, self.data)
        J = pin.getFrameJacobian(self.model, self.data, fid, reference) @ self.G
        classical = pin.getFrameClassicalAcceleration(self.model, self.data, fid, reference).vector
        spatial = pin.getFrameAcceleration(self.model, self.data, fid, reference).vector
        return J, classical, spatial, self.data.oMf[fid]

    def mass_bias(self, theta, phi, dtheta, dphi):
        """M and c on (theta, phi) of a fixed-base robot."""
        return self.dynamics(np.r_[theta, phi], np.r_[dtheta, dphi])

    def forward_dynamics(self, theta, phi, dtheta, dphi, tau):
        M, c = self.mass_bias(theta, phi, dtheta, dphi)
        L = np.linalg.cholesky(M)                          # M = L L^T, then two triangular solves
        ddq = np.linalg.solve(L.T, np.linalg.solve(L, self.forces(theta, phi, dtheta, dphi, tau) - c))
        n = self.arm_model.n
        return ddq[:n], ddq[n:]

    def forces(self, theta, phi, dtheta, dphi, tau):
        """The generalised forces on (theta, phi) besides the inertial ones, per kind: an SEA's
        spring T on its link and -T - T_B2 - mu tau on its motor; a geared joint's -mu tau -
        T_B2(dtheta) (no load term); a direct joint's tau; every link's -T_L."""
        k, mot = self._cols, self.motors
        theta, dtheta = np.asarray(theta, float), np.asarray(dtheta, float)
        u = np.zeros(len(theta))
        u[self.actuated] = tau
        def loss(v, j, T):
            coulomb = k["c"][j] + k["c1"][j] * (np.sqrt(T ** 2 + 1e-6) - 1e-3) + k["stribeck"][j] * np.exp(-(v / k["v_stribeck"][j]) ** 2)
            return k["b"][j] * v + coulomb * np.tanh(v / k["eps"][j])
        Q = -(k["link_b"] * dtheta + k["link_c"] * np.tanh(dtheta / k["eps"]) + k["cb_k"] * (theta - k["cb_theta0"]))
        psi, dpsi = np.asarray(phi) - theta[mot], np.asarray(dphi) - dtheta[mot]
        T = k["k1"][mot] * psi + k["k3"][mot] * psi ** 3 + k["d"][mot] * dpsi
        Q[mot] += T
        Q_phi = -T - loss(np.asarray(dphi, float), mot, T) - k["gear_ratio"][mot] * u[mot]
        for j, kind in enumerate(self.kinds):
            if kind == "geared":
                Q[j] += -k["gear_ratio"][j] * u[j] - loss(dtheta[j], j, 0.0)
            elif kind == "direct":
                Q[j] += u[j]
        return np.r_[Q, Q_phi]


def urdf_model(model) -> "pin.Model":
    """Pinocchio's own model of a URDF-based model's URDF, the held joints (locked, and those off
    the chain at lock_others) removed at their values (buildReducedModel): the links only, its
    frames the URDF's links."""
    full = (pin.buildModelFromUrdf(model.extra["urdf"], pin.JointModelFreeFlyer()) if model.floating
            else pin.buildModelFromUrdf(model.extra["urdf"]))
    q0, lock_ids = pin.neutral(full), []
    for name, value in model.extra["locked"].items():
        jid = full.getJointId(name)
        lock_ids.append(jid)
        jm = full.joints[jid]
        if jm.nq == 2:
            q0[jm.idx_q:jm.idx_q + 2] = [np.cos(value), np.sin(value)]
        else:
            q0[jm.idx_q] = value
    return pin.buildReducedModel(full, lock_ids, q0) if lock_ids else full


def _depth_first(parent) -> list:
    """The joints of a tree (each after its parent) in depth-first order, children in index order."""
    out: list = []
    todo = [j for j in reversed(range(len(parent))) if parent[j] < 0]
    while todo:
        j = todo.pop()
        out.append(j)
        todo += [c for c in reversed(range(len(parent))) if parent[c] == j]
    return out


def configuration(pin_model, theta) -> np.ndarray:
    """Pinocchio's q of joint angles theta (a continuous joint takes (cos, sin))."""
    q = pin.neutral(pin_model)
    for i, th in enumerate(theta):
        jm = pin_model.joints[i + 1]
        q[jm.idx_q:jm.idx_q + jm.nq] = [np.cos(th), np.sin(th)] if jm.nq == 2 else [th]
    return q


def _inertia(body, R):
    """A body given in J_j (z = axis) as a Pinocchio Inertia in the joint frame J_j R^T."""
    return pin.Inertia(body.mass, R @ np.asarray(body.com, float), R @ body.inertia @ R.T)


def _axis(jmodel) -> tuple:
    """The axis of a Pinocchio revolute or prismatic joint model, in its joint frame, and
    whether it slides."""
    short = jmodel.shortname()
    for letter, axis in (("X", [1.0, 0, 0]), ("Y", [0, 1.0, 0]), ("Z", [0, 0, 1.0])):
        if short in (f"JointModelR{letter}", f"JointModelRUB{letter}", f"JointModelP{letter}"):
            return np.array(axis), short.startswith("JointModelP")
    specific = jmodel.extract() if hasattr(jmodel, "extract") else jmodel
    if hasattr(specific, "axis"):
        return np.asarray(specific.axis, float), "Prismatic" in short
    raise InvalidArgument(f"not a revolute or prismatic joint: {short}")
