"""Spatial operator algebra (paper section II), symbolic in CasADi.

The paper writes every operator in the base frame (eq. 12).  Here each body's
quantities are written in the body's own frame instead, which is the same algebra
(eq. 12 with the base frame replaced by the body frame) and keeps the inertias
constant, so CasADi folds them into the expressions.  Conventions, as in the paper:

- spatial velocity V = [omega; v_O]: angular velocity and the velocity of the frame
  origin O; spatial acceleration alpha = d/dt of both (classical accelerations);
- spatial force f = [moment about O; force];
- Phi_{k+1,k}^T maps a parent's velocity to the child (``Xup``), Phi_{k+1,k} maps a
  child's force to the parent (``Xup.T``); in the body frames it carries the rotation.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

H = ca.DM([0, 0, 1, 0, 0, 0])          # eq. (7): a revolute joint turns about its local z
Z3 = ca.DM.zeros(3, 3)


def as_casadi(x):
    """A CasADi matrix as it is; numbers (numpy) as a DM."""
    return x if isinstance(x, (ca.SX, ca.MX, ca.DM)) else ca.DM(x)


def skew(v):
    """The cross-product matrix: skew(v) @ w = v x w (the paper's tilde)."""
    return ca.vertcat(ca.horzcat(0, -v[2], v[1]), ca.horzcat(v[2], 0, -v[0]), ca.horzcat(-v[1], v[0], 0))


def rot_z(q):
    """The rotation about z by q (a joint's motion about its own axis)."""
    c, s = ca.cos(q), ca.sin(q)
    return ca.vertcat(ca.horzcat(c, -s, 0), ca.horzcat(s, c, 0), ca.horzcat(0, 0, 1))


def joint_rotation(R_tree, q):
    """Rotation of a body turned by q about z of its joint frame, relative to the parent frame."""
    return ca.DM(R_tree) @ rot_z(q)


def Xup(R, l):
    """Phi_{k+1,k}^T in body frames (eq. 8 with rotation): parent velocity -> child frame.

    R: child frame relative to parent; l: child origin in parent coordinates."""
    Rt = R.T
    return ca.vertcat(ca.horzcat(Rt, Z3), ca.horzcat(-Rt @ skew(as_casadi(l)), Rt))


def spatial_inertia(body) -> np.ndarray:
    """M_k of eq. (11): [[I_O, m p~], [-m p~, m 1]] about the body-frame origin."""
    m, p = body.mass, body.com
    mp = m * np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
    return np.block([[body.inertia_origin, mp], [-mp, m * np.eye(3)]])


def transform_inertia(M, R, l) -> np.ndarray:
    """A spatial inertia M given in a child frame moved to its parent frame: Phi M Phi^T in body
    frames, X^T M X with X = Xup(R, l) (R: child relative to parent, l: child origin)."""
    X = np.array(Xup(ca.DM(R), np.asarray(l, float)))
    return X.T @ M @ X


def coriolis(R, l, w_parent, rate):
    """a_{s,t} of eqs. (9) and (18) in the child frame: [(R^T w_s) x h rate; R^T (w_s x w_s x l)]."""
    w = R.T @ w_parent
    ang = ca.vertcat(w[1], -w[0], 0) * rate          # w x z
    lin = R.T @ ca.cross(w_parent, ca.cross(w_parent, as_casadi(l)))
    return ca.vertcat(ang, lin)


class Motion:
    """How a joint moves its child frame within J (whose z is the joint's axis): it turns about z
    (revolute, eq. 7) or slides along it (prismatic).  `index`: the entry of a spatial vector
    [omega; v] its coordinate moves (H = e_index), 2 or 5."""

    def __init__(self, name: str, index: int):
        self.name, self.index = name, index
        self.H = ca.DM.zeros(6)
        self.H[index] = 1.0

    @property
    def turns(self) -> bool:
        return self.index == 2

    def placement(self, R_tree, l, q) -> tuple:
        """The child frame's rotation and origin in the parent frame at coordinate q (J at R_tree, l)."""
        if self.turns:
            return joint_rotation(R_tree, q), as_casadi(l)
        R = ca.DM(R_tree)
        return R, as_casadi(l) + R[:, 2] * q

    def coriolis(self, R, l, w_parent, rate):
        """The child's acceleration at zero coordinate acceleration and zero parent acceleration,
        child frame (eqs. 9 and 18 for a turn).  A slide: the origin's centripetal acceleration
        about the parent plus the Coriolis one, [0; R^T (w_s x w_s x l) + 2 (R^T w_s) x z rate]."""
        if self.turns:
            return coriolis(R, l, w_parent, rate)
        w = R.T @ w_parent
        lin = R.T @ ca.cross(w_parent, ca.cross(w_parent, as_casadi(l))) + 2 * rate * ca.vertcat(w[1], -w[0], 0)
        return ca.vertcat(ca.DM.zeros(3), lin)


REVOLUTE, PRISMATIC = Motion("revolute", 2), Motion("prismatic", 5)
MOTIONS = {m.name: m for m in (REVOLUTE, PRISMATIC)}


def gyroscopic(M, w):
    """b_k of eq. (10): [w x I_O w; w x (w x m p)], read off a spatial inertia M (eq. 11)."""
    I_O, mp = as_casadi(M[:3, :3]), ca.vertcat(M[2, 4], M[0, 5], M[1, 3])   # m p~ = M[:3, 3:]
    return ca.vertcat(ca.cross(w, I_O @ w), ca.cross(w, ca.cross(w, mp)))


def base_acceleration(gravity):
    """alpha_base with gravity as a base acceleration (end of section II): [0; -g]."""
    return ca.vertcat(ca.DM.zeros(3), -as_casadi(gravity))


def base_pose(R_parent, o_parent, R, l):
    """Eq. (12): a body frame's rotation and origin in the base frame from its parent's."""
    return R_parent @ R, o_parent + R_parent @ as_casadi(l)


def quaternion_rotation(quat):
    """The rotation of a quaternion [x, y, z, w] (normalised here: any nonzero one is a rotation):
    R = 1 + 2 (w [u]x + [u]x^2) / |q|^2, u = (x, y, z)."""
    u, w = quat[:3], quat[3]
    U = skew(u)
    return ca.DM.eye(3) + 2 * (w * U + U @ U) / ca.sumsqr(quat)


def quaternion_product(a, b):
    """a b for quaternions [x, y, z, w] (the rotation of b, then a's: R(a b) = R(a) R(b))."""
    va, wa, vb, wb = a[:3], a[3], b[:3], b[3]
    return ca.vertcat(wa * vb + wb * va + ca.cross(va, vb), wa * wb - ca.dot(va, vb))
