"""Compliant contacts and scripted pushes for closed-loop simulation: what the world does to the
arm, as a wrench at a frame that the complete model's forward dynamics takes
(`Arm.forward_dynamics(external=[frame])`).

A contact is a half-space (a plane: a point on it and its outward normal) or an axis-aligned
box, with stiffness k (N/m), damping c (N s/m) and Coulomb friction mu.  At penetration depth
delta >= 0 along the surface's normal n, the frame's origin feels

    F_n = max(0, k delta + c d(delta)/dt) n,    F_t = -mu |F_n| v_t / sqrt(|v_t|^2 + v_eps^2)

(Kelvin-Voigt, clipped so that the surface never pulls; friction smoothed below v_eps), in world
axes, no moment.  A box pushes out through its nearest face.  A `Push` adds a wrench [force;
moment] at a frame between two times.  `plant_with_contacts` is one sample of the plant: RK4
substeps of the complete model with the contacts' and pushes' wrenches.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from rscasadi.dynamics.arm import Arm
from rscasadi.errors import InvalidArgument


@dataclass
class Contact:
    """A plane (`point`, outward `normal`) or an axis-aligned box (`center`, `size`), its
    stiffness k (N/m), damping c (N s/m) and friction coefficient mu, felt at `frame`."""
    frame: str
    k: float
    c: float = 0.0
    mu: float = 0.0
    point: np.ndarray | None = None
    normal: np.ndarray | None = None
    center: np.ndarray | None = None
    size: np.ndarray | None = None
    v_eps: float = 1e-2                               # m/s: friction smoothed below this speed (it adds
                                                      # a damping mu F_n / v_eps that short substeps must resolve)

    def __post_init__(self):
        for key in ("point", "normal", "center", "size"):
            if getattr(self, key) is not None:
                setattr(self, key, np.asarray(getattr(self, key), float).ravel())
        if (self.point is None) == (self.center is None):
            raise InvalidArgument("contact: give a plane (point, normal) or a box (center, size)")
        if self.point is not None:
            if self.normal is None or not np.any(self.normal):
                raise InvalidArgument("contact: a plane needs a normal, not all zero")
            self.normal = self.normal / np.linalg.norm(self.normal)
        elif self.size is None or np.any(self.size <= 0):
            raise InvalidArgument("contact: a box needs a size of three positive numbers")
        if not (self.k > 0 and self.c >= 0 and self.mu >= 0):
            raise InvalidArgument(f"contact: k > 0, c >= 0, mu >= 0, got k={self.k!r}, c={self.c!r}, mu={self.mu!r}")


@dataclass
class Push:
    """A wrench [force; moment] (N, N m; world axes) at `frame`'s origin from t1 to t2 (s)."""
    frame: str
    wrench: np.ndarray
    t1: float
    t2: float

    def __post_init__(self):
        self.wrench = np.asarray(self.wrench, float).ravel()


def _depth_and_normal(contact: Contact, p):
    """Penetration depth (> 0 inside) and the outward normal there, smooth enough for RK4."""
    if contact.point is not None:
        n = ca.DM(contact.normal)
        return -ca.dot(n, p - ca.DM(contact.point)), n
    d = p - ca.DM(contact.center)
    h = ca.DM(contact.size / 2)
    gaps = ca.vertcat(h - d, h + d)                  # distance inside to each of the six faces
    normals = [ca.DM(v) for v in np.vstack([np.eye(3), -np.eye(3)])]
    depth, n = gaps[0], normals[0]
    for i in range(1, 6):                            # the nearest face
        nearer = gaps[i] < depth
        depth, n = ca.if_else(nearer, gaps[i], depth), ca.if_else(nearer, normals[i], n)
    inside = ca.mmin(gaps) > 0
    return ca.if_else(inside, depth, -1.0), n


def contact_force(contact: Contact, p, v):
    """The force (3, world) of `contact` on a point at p moving at v."""
    depth, n = _depth_and_normal(contact, p)
    rate = -ca.dot(n, v)                             # d(depth)/dt
    fn = ca.if_else(depth > 0, ca.fmax(0, contact.k * depth + contact.c * rate), 0)
    vt = v - ca.dot(n, v) * n
    friction = -contact.mu * fn * vt / ca.sqrt(ca.sumsqr(vt) + contact.v_eps ** 2)
    return fn * n + friction


@dataclass
class World:
    """The contacts and pushes the arm meets; `frames`: the frames they act at, in order."""
    contacts: tuple = ()
    pushes: tuple = ()
    frames: list = field(default_factory=list)

    def __post_init__(self):
        for item in (*self.contacts, *self.pushes):
            if item.frame not in self.frames:
                self.frames.append(item.frame)


def world_wrenches(arm: Arm, world: World) -> ca.Function:
    """(theta, dtheta, t) -> the wrench at each of world.frames (6 x frames), world axes."""
    n = arm.n
    th, dth, t = ca.SX.sym("theta", n), ca.SX.sym("dtheta", n), ca.SX.sym("t")
    out = []
    for frame in world.frames:
        p = arm.frame_placement(frame)(th)[1]
        v = ca.mtimes(arm.frame_jacobian(frame, "local_world_aligned")(th)[:3, :], dth)
        f = ca.DM.zeros(6)
        for c in world.contacts:
            if c.frame == frame:
                f += ca.vertcat(contact_force(c, p, v), ca.DM.zeros(3))
        for push in world.pushes:
            if push.frame == frame:
                f += ca.if_else(ca.logic_and(t >= push.t1, t < push.t2), ca.DM(push.wrench), ca.DM.zeros(6))
        out.append(f)
    return ca.Function("world_wrenches", [th, dth, t], [ca.horzcat(*out) if out else ca.DM.zeros(6, 0)])


def plant_with_contacts(arm: Arm, world: World, dt: float, substeps: int = 8) -> ca.Function:
    """(x, tau, t) -> (x after dt, the wrenches at the sample's end): RK4 substeps of the complete
    model under the contacts and pushes (stiff contacts need short substeps: dt / substeps
    below about 2.8 / sqrt(k / m), m the arm's mass felt at the frame)."""
    n = arm.n
    fd = arm.forward_dynamics(external=world.frames)
    wrenches = world_wrenches(arm, world)
    x, tau, t = ca.SX.sym("x", 4 * n), ca.SX.sym("tau", n), ca.SX.sym("t")
    h = dt / substeps

    def xdot(z, s):
        W = wrenches(z[:n], z[2 * n:3 * n], s)
        return ca.vertcat(z[2 * n:], *fd(*ca.vertsplit(z, n), tau, *[W[:, i] for i in range(len(world.frames))]))

    z = x
    for i in range(substeps):
        s0 = t + i * h
        k1 = xdot(z, s0)
        k2 = xdot(z + h / 2 * k1, s0 + h / 2)
        k3 = xdot(z + h / 2 * k2, s0 + h / 2)
        k4 = xdot(z + h * k3, s0 + h)
        z = z + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return ca.Function("plant_with_contacts", [x, tau, t], [z, wrenches(z[:n], z[2 * n:3 * n], t + dt)],
                       ["x", "tau", "t"], ["x_next", "wrenches"])
