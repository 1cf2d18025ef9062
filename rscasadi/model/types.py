"""The constant model: bodies, joints and the arm (docs/user-guide/model.md section 4), as plain data.

Everything here is numpy; the recursions read it and never change it.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np

from rscasadi.errors import Error, NotFound

DEFAULT_GRAVITY = (0.0, 0.0, -9.81)
TOP_KEYS = {"name", "gravity", "joints", "frames", "payload", "collision", "floating", "base", "contacts"}
JOINT_KEYS = {"name", "kind", "type", "spring", "parent", "origin_xyz", "origin_rpy", "origin_R", "gear_ratio", "sea", "gear_loss", "limits",
              "link", "slow_rotor", "fast_rotor", "link_loss", "counterbalance", "torque_constant"}
BODY_KEYS = {"mass", "com", "inertia"}
SEA_KEYS = {"k1", "k3", "d"}
GEAR_LOSS_KEYS = {"b", "c", "eps", "c1", "stribeck", "v_stribeck"}
LINK_LOSS_KEYS = {"b", "c"}                 # link side: b dtheta + c tanh(dtheta / eps)
COUNTERBALANCE_KEYS = {"k", "theta0"}       # a joint spring beside the SEA: k (theta - theta0)
LIMIT_KEYS = {"tau", "dphi", "psi", "theta"}
BODIES = ("link", "slow_rotor", "fast_rotor")


class ModelFileError(Error, ValueError):
    """A model file breaks a rule of docs/user-guide/model.md section 4."""


def rpy_matrix(rpy) -> np.ndarray:
    """URDF convention: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


@dataclass(frozen=True)
class Body:
    """A rigid body's inertial parameters in its own frame."""
    mass: float
    com: np.ndarray          # (3,) centre of mass in the body frame
    inertia: np.ndarray      # (3, 3) about the centre of mass

    @property
    def inertia_origin(self) -> np.ndarray:
        """Inertia about the frame origin (parallel-axis theorem): I_O = I_C + m (p.p 1 - p p^T)."""
        p = self.com
        return self.inertia + self.mass * (p @ p * np.eye(3) - np.outer(p, p))

    @staticmethod
    def from_spatial(M: np.ndarray) -> "Body":
        """The inverse of eq. (11): mass, centre of mass and inertia about it from a 6x6 M."""
        m = M[3, 3]
        com = np.array([M[2, 4], M[0, 5], M[1, 3]]) / m
        return Body(m, com, M[:3, :3] - m * (com @ com * np.eye(3) - np.outer(com, com)))

    @property
    def balanced(self) -> bool:
        """Centre of mass on the z axis and inertia symmetric about it (docs/user-guide/model.md section 3)."""
        I = self.inertia
        return (self.com[0] == 0.0 and self.com[1] == 0.0 and I[0, 0] == I[1, 1]
                and I[0, 1] == 0.0 and I[0, 2] == 0.0 and I[1, 2] == 0.0)


@dataclass(frozen=True)
class Joint:
    """One joint: its placement and axis (origin_xyz, origin_rpy, R), its actuator (gear ratio, SEA
    spring k1, k3 and damping d, gear losses b, c, eps, limits), its three bodies (link, slow
    rotor, fast rotor), and what acts on the link beside the spring: a link-side loss (link_b,
    link_c) and a counterbalance spring (cb_k, cb_theta0)."""
    name: str
    origin_xyz: np.ndarray   # J_j origin in the parent frame
    origin_rpy: np.ndarray
    gear_ratio: float        # mu_j
    k1: float
    k3: float
    d: float
    b: float
    c: float
    eps: float
    limits: dict
    link: Body
    slow_rotor: Body
    fast_rotor: Body

    origin_R: np.ndarray | None = None   # J_j's rotation when it came from a URDF (else from origin_rpy)
    link_b: float = 0.0                  # link-side viscous loss (N m s/rad), [joints.link_loss] b
    link_c: float = 0.0                  # link-side Coulomb loss (N m), [joints.link_loss] c
    cb_k: float = 0.0                    # counterbalance spring on the link (N m/rad), [joints.counterbalance] k
    cb_theta0: float = 0.0               # where it is relaxed (rad)
    c1: float = 0.0                      # the gear's load-dependent Coulomb loss, per N m it transmits
    stribeck: float = 0.0                # the gear's static friction beyond c at rest (N m), falling off
    v_stribeck: float = 1.0              # as exp(-(dphi / v_stribeck)^2) with the speed (rad/s)
    torque_constant: float | None = None  # N m/A, motor side: logged currents i_j become tau_j = kt i_j
    declared: frozenset = frozenset()    # the optional terms the file gives (link_loss, counterbalance,
    #                                      gear_loss.c1, gear_loss.stribeck)
    kind: str = "sea"                    # rscasadi.model.kinds: sea, geared, spring, free, direct
    type: str = "revolute"               # the link turns about J_j's z ("revolute") or slides along it ("prismatic")

    @property
    def R(self) -> np.ndarray:
        """Rotation of J_j relative to the parent frame; the round-off of exact right angles
        (cos(pi/2) = 6e-17) is set to 0 so that symbolic code folds it away."""
        R = rpy_matrix(self.origin_rpy) if self.origin_R is None else np.array(self.origin_R, dtype=float)
        R[np.abs(R) < 1e-15] = 0.0
        return R

    @property
    def joint_kind(self):
        """The joint's Kind (rscasadi.model.kinds)."""
        from rscasadi.model.kinds import KINDS
        return KINDS[self.kind]

    @property
    def joint_motion(self):
        """How the link moves within J_j (rscasadi.spatial.Motion)."""
        from rscasadi.spatial import MOTIONS
        return MOTIONS[self.type]

    @property
    def rotor_inertia(self) -> float:
        """B_j = Izz_O(S_j) + mu_j^2 Izz_O(F_j) (docs/user-guide/model.md section 3)."""
        return float(self.slow_rotor.inertia_origin[2, 2]
                     + self.gear_ratio ** 2 * self.fast_rotor.inertia_origin[2, 2])


@dataclass(frozen=True)
class Frame:
    """A named frame fixed to a body: `body` 0 is the base (the world frame), body j >= 1 the link
    moved by joint j - 1 (base to tip, in its frame L whose z is that joint's axis).  `R` and `p`
    are the frame's rotation and origin in the body's frame.  `user`: from the model file's
    [frames] table (written back by `document`), else a link's own frame."""
    name: str
    body: int
    R: np.ndarray
    p: np.ndarray
    user: bool = False


BASE = "base"          # the base frame's name in a link-list model (a URDF's is its root link)


@dataclass(frozen=True)
class Capsule:
    """A link's collision geometry: the segment from `a` to `b` (in the frame of `body`) swept by
    a sphere of `radius`."""
    link: str
    body: int
    a: np.ndarray
    b: np.ndarray
    radius: float


@dataclass(frozen=True)
class Collision:
    """The arm's collision geometry: capsules, the clearance `margin` (m) every obstacle must keep,
    and the `pairs` of links (named by a frame on each) whose capsules must keep it from each other."""
    margin: float
    capsules: tuple
    tip: str | list | None
    links: dict = field(default_factory=dict, compare=False)     # as the [collision] table gave them
    notes: tuple = field(default=(), compare=False)              # URDF shapes added, or not readable
    pairs: tuple = ()                    # ((frame, frame), ...): links whose capsules keep the margin apart


@dataclass(frozen=True)
class Payload:
    """A rigid body held at a frame (a tool, a load): its inertial parameters in that frame, and
    the radius of the sphere about its com that keeps clear of obstacles (None: not checked)."""
    frame: str
    body: Body
    radius: float | None = None


@dataclass(frozen=True)
class ArmModel:
    """The constant description of an n-joint FS-SEA robot: a tree of joints, each after its parent
    (`parents[j]`: the joint whose link carries joint j, -1 for the base; empty: a serial chain,
    joint j on the link of joint j - 1); `frames` by name (docs/user-guide/frames.md)."""
    name: str
    gravity: np.ndarray
    joints: tuple
    path: str = "<memory>"
    extra: dict = field(default_factory=dict, compare=False)
    frames: tuple = field(default=(), compare=False)
    payload: Payload | None = None
    collision: Collision | None = field(default=None, compare=False)
    parents: tuple = ()
    base: Body | None = None             # a floating base's body (its own frame); None: the base is fixed
    contacts: tuple = ()                 # ((frame, "point" | "flat"), ...): where a floating robot may touch
    soles: tuple = ()                    # ((frame, lx, ly), ...): a flat contact's sole, lx by ly about its origin

    def __post_init__(self):
        if self.parents and (len(self.parents) != len(self.joints)
                             or any(not -1 <= p < j for j, p in enumerate(self.parents))):
            raise ModelFileError(f"{self.path}: parents {list(self.parents)} is not a tree of {len(self.joints)} "
                                 "joints each after its parent (-1: the base)")

    @property
    def floating(self) -> bool:
        """Whether the base is a free-flying body (docs/user-guide/floating.md), not the fixed world."""
        return self.base is not None

    @property
    def parent(self) -> tuple:
        """Per joint the index of the joint whose link carries it, -1 for the base."""
        return tuple(self.parents) if self.parents else tuple(range(-1, len(self.joints) - 1))

    @property
    def is_chain(self) -> bool:
        """Whether the tree is one serial chain (each joint on the link of the one before it)."""
        return self.parent == tuple(range(-1, len(self.joints) - 1))

    def support(self, body: int) -> list:
        """The joints that move `body` (0: the base, j >= 1: the link of joint j - 1), root first."""
        out, j = [], body - 1
        while j >= 0:
            out.append(j)
            j = self.parent[j]
        return out[::-1]

    @property
    def kinds(self) -> list:
        """Per joint its Kind (rscasadi.model.kinds)."""
        return [jt.joint_kind for jt in self.joints]

    @property
    def motors(self) -> list:
        """The joints with a motor coordinate phi (sea), in order: phi[i] is joint motors[i]'s."""
        return [j for j, jt in enumerate(self.joints) if jt.joint_kind.motor]

    @property
    def actuated(self) -> list:
        """The joints with a torque input, in order: tau[i] is joint actuated[i]'s."""
        return [j for j, jt in enumerate(self.joints) if jt.joint_kind.actuated]

    @property
    def motor_of(self) -> dict:
        """Joint index -> the index of its motor coordinate in phi (the joints that have one)."""
        return {j: i for i, j in enumerate(self.motors)}

    @property
    def input_of(self) -> dict:
        """Joint index -> the index of its input in tau (the actuated joints)."""
        return {j: i for i, j in enumerate(self.actuated)}

    @property
    def all_sea(self) -> bool:
        """Whether every joint is an SEA (the arm of the paper)."""
        return all(jt.kind == "sea" for jt in self.joints)

    @property
    def coordinates(self) -> list:
        """The names of q = (theta, phi): every joint's, then `<joint>.motor` of each sea joint."""
        return [jt.name for jt in self.joints] + [f"{self.joints[j].name}.motor" for j in self.motors]

    def children(self, j: int) -> list:
        """The joints carried by the link of joint j (j = -1: by the base)."""
        return [c for c, p in enumerate(self.parent) if p == j]

    def frame(self, name: str) -> Frame:
        """The frame called `name`, or a KeyError listing the frames there are."""
        for f in self.frames:
            if f.name == name:
                return f
        raise NotFound(f"{self.path}: no frame {name!r} (frames: {', '.join(f.name for f in self.frames)})")

    @property
    def n(self) -> int:
        return len(self.joints)

    def column(self, attr: str) -> np.ndarray:
        """One joint parameter as an (n,) array, e.g. column('gear_ratio')."""
        return np.array([getattr(jt, attr) for jt in self.joints], dtype=float)


def inertia_problem(inertia: np.ndarray, rtol: float = 1e-12, point_mass: bool = False,
                    triangle: bool = True) -> str | None:
    """Why a 3x3 inertia about the centre of mass is not physical, or None: not finite, a
    principal moment <= 0 (< 0 where `point_mass` allows a URDF link's point mass or a tool frame
    of no size: zero moments), or (with `triangle`) moments breaking the triangle inequality (no
    body has them)."""
    if not np.all(np.isfinite(inertia)):
        return "has a value that is not finite"
    eig = np.linalg.eigvalsh(inertia)
    if eig[0] < -rtol * max(abs(eig[-1]), 1e-300) if point_mass else eig[0] <= 0.0:
        return (f"not positive semidefinite (principal moments {eig.tolist()})" if point_mass
                else f"not positive definite (principal moments {eig.tolist()})")
    if triangle and eig[2] > eig[0] + eig[1] + rtol * eig[-1]:
        return f"principal moments {eig.tolist()} break the triangle inequality"
    return None


def rpy_of(R) -> np.ndarray | None:
    """Roll, pitch, yaw (URDF convention) of a rotation, or None where scipy's angles do not give
    R back to 1e-12 (a gimbal lock it resolves badly)."""
    from scipy.spatial.transform import Rotation
    with warnings.catch_warnings():                                  # gimbal lock: checked below
        warnings.simplefilter("ignore")
        rpy = Rotation.from_matrix(R).as_euler("xyz")
    return rpy if np.max(np.abs(rpy_matrix(rpy) - R)) <= 1e-12 else None


def rotation_document(R, rpy_key: str, matrix_key: str) -> dict:
    """A rotation as a model file writes it: its roll-pitch-yaw where they give it back to 1e-12,
    else the matrix itself (three rows), so every written file reads back the same rotation."""
    rpy = rpy_of(R)
    if rpy is not None:
        return {rpy_key: [float(x) for x in rpy]}
    return {matrix_key: [[float(v) for v in row] for row in np.asarray(R, float)]}
