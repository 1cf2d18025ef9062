"""Contacts of a floating robot (docs/user-guide/floating.md, "Contacts"): their Jacobians and
drifts, the contact forward dynamics (KKT), the inverse dynamics with contact forces, the impact.

A contact holds a frame of the robot still: a `point` contact its origin (3 rows: the velocity of
the origin in world axes, forces [fx, fy, fz] in world axes), a `flat` contact the whole frame (6
rows: its velocity [v; w] in its own axes, the wrench [force; moment] in its own axes, as a foot
sole's).  The rows' acceleration at a = 0, J-dot v (the drift gamma), is the classical
acceleration of the origin in world axes for a point, the spatial acceleration in the frame's
axes (classical less w x v) for a flat contact: the time derivatives of the rows' velocities.

With the contacts held (J a + gamma = -damping J v - stiffness e, Baumgarte's gains >= 0 pulling
the contacts' velocity and, with a stiffness, their position errors e from given anchors to
zero: `errors`), M a + h = Q + J^T f; solved as Pinocchio's contact dynamics: a_free = M^-1 (Q - h),
f = -(J M^-1 J^T)^-1 (J a_free + gamma + damping J v + stiffness e), a = a_free + M^-1 J^T f, both inverses by
symbolic LDL^T factorisations: straight-line code that skips the mass matrix's structural zeros
(a leg's joints do not couple with another leg's).  `robot` is a rscasadi.dynamics.floating.FloatingRobot.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from rscasadi.errors import InvalidArgument
from rscasadi.model.checks import identifier
from rscasadi.spatial import quaternion_rotation

KINDS = {"point": 3, "flat": 6}


@dataclass(frozen=True)
class Contact:
    """A contact at a frame: `point` (3 rows) or `flat` (6 rows)."""
    frame: str
    kind: str = "point"

    @property
    def rows(self) -> int:
        return KINDS[self.kind]


def contact_set(model, contacts=None) -> tuple:
    """Contacts from frame names (point contacts), (frame, kind) pairs, Contact objects or a
    {frame: kind} table (None: the model file's [[contacts]]); every unknown frame or kind and
    every frame given twice, in one message."""
    if contacts is None:
        if not model.contacts:
            raise InvalidArgument(f"{model.path}: no contacts given and the model file has no [[contacts]]")
        contacts = list(model.contacts)
    if isinstance(contacts, dict):
        contacts = list(contacts.items())
    if isinstance(contacts, (str, Contact)) or not contacts:
        raise InvalidArgument(f"contacts: expected a list of frames (or of (frame, kind) pairs), got {contacts!r}")
    out: list = []
    bad: list = []
    names = {f.name for f in model.frames}
    for c in contacts:
        c = c if isinstance(c, Contact) else Contact(c) if isinstance(c, str) else Contact(*c)
        if c.frame not in names:
            bad.append(f"no frame {c.frame!r}")
        elif c.kind not in KINDS:
            bad.append(f"{c.frame!r}: kind {c.kind!r} is not one of {', '.join(KINDS)}")
        elif c.frame in [o.frame for o in out]:
            bad.append(f"{c.frame!r} given twice")
        out.append(c)
    if bad:
        raise InvalidArgument(f"{model.path}: contacts: " + "; ".join(bad) + f" (frames: {', '.join(sorted(names))})")
    return tuple(out)


def _name(what: str, contacts) -> str:
    return what + "_" + "_".join(f"{identifier(c.frame)}{'' if c.kind == 'point' else '_flat'}" for c in contacts)


def _rows(robot, contacts, q, v, a=None) -> tuple:
    """The contacts' rows' velocity (and with `a`, their acceleration), stacked."""
    vel, acc = [], []
    for c, (R, _, v_loc, a_loc) in zip(contacts, robot._frame_motions([c.frame for c in contacts], q, v, a)):
        if c.kind == "point":
            vel.append(R @ v_loc[:3])
            acc += [R @ a_loc[:3]] if a is not None else []
        else:
            vel.append(v_loc)
            acc += [ca.vertcat(a_loc[:3] - ca.cross(v_loc[3:], v_loc[:3]), a_loc[3:])] if a is not None else []
    return ca.vertcat(*vel), (ca.vertcat(*acc) if a is not None else None)


def wrenches(robot, contacts, q, f) -> list:
    """The contact forces f as spatial forces on the bodies (FloatingRobot.body_wrenches): a
    point's [fx, fy, fz] in world axes, a flat contact's [force; moment] in its frame's axes."""
    applied, row = [], 0
    for c in contacts:
        applied.append((c.frame, f[row:row + c.rows], c.kind == "point"))
        row += c.rows
    return robot.body_wrenches(q, applied)


def jacobian(robot, contacts) -> ca.Function:
    """q -> J (nc x nv)."""
    def build(q):
        v = ca.SX.sym("v", robot.nv)
        return [ca.jacobian(_rows(robot, contacts, q, v)[0], v)]
    return robot._function(_name("contact_jacobian", contacts), ["q"], ["J"], build)


def drift(robot, contacts) -> ca.Function:
    """q, v -> gamma (nc): the rows' acceleration at a = 0."""
    return robot._function(_name("contact_drift", contacts), ["q", "v"], ["gamma"],
                           lambda q, v: [_rows(robot, contacts, q, v, ca.DM.zeros(robot.nv))[1]])


def _parts(robot, contacts, q, v):
    """M, J and gamma at (q, v)."""
    return robot.mass_matrix()(q), jacobian(robot, contacts)(q), drift(robot, contacts)(q, v)


def _solver(M, J):
    """Solves with M and with the contacts' inverse inertia J M^-1 J^T, both by a symbolic LDL^T
    (ca.ldl: straight-line code that skips M's structural zeros, the tree's legs apart)."""
    D, LT, p = ca.ldl(M)

    def by_M(b):
        return ca.ldl_solve(b, D, LT, p)
    MiJt = by_M(J.T)
    D2, LT2, p2 = ca.ldl(J @ MiJt)
    return by_M, MiJt, lambda b: ca.ldl_solve(b, D2, LT2, p2)


def anchor_size(contacts) -> int:
    """The length of the anchors input: 3 per point contact (where its origin is held, world),
    7 per flat contact (its origin, world, and its orientation, a quaternion xyzw)."""
    return sum(3 if c.kind == "point" else 7 for c in contacts)


def errors(robot, contacts, q, anchors):
    """The rows' position errors from their anchors: a point's p - p_ref (world axes); a flat
    contact's R^T (p - p_ref) and vee(R_ref^T R - R^T R_ref) / 2 (its axes; the rotation vector
    to first order)."""
    out, at = [], 0
    for c, (R, p, _, _) in zip(contacts, robot._frame_motions([c.frame for c in contacts], q, ca.DM.zeros(robot.nv))):
        if c.kind == "point":
            out.append(p - anchors[at:at + 3])
            at += 3
        else:
            R0 = quaternion_rotation(anchors[at + 3:at + 7])
            S = (R0.T @ R - R.T @ R0) / 2
            out += [R.T @ (p - anchors[at:at + 3]), ca.vertcat(S[2, 1], S[0, 2], S[1, 0])]
            at += 7
    return ca.vertcat(*out)


def _stabilised(robot, contacts, q, vel, gains, anchors=None):
    """The Baumgarte terms the contact rows' acceleration is held to less: damping J v + stiffness e."""
    damping, stiffness = gains
    return damping * vel + (stiffness * errors(robot, contacts, q, anchors) if stiffness else 0)


def _kkt(robot, contacts, q, v, tau, gains, anchors=None):
    """a and f of the contact dynamics (SX), and the solves that gave them."""
    M, J, gamma = _parts(robot, contacts, q, v)
    by_M, MiJt, by_L = _solver(M, J)
    a_free = by_M(robot.generalized_forces()(q, v, tau) - robot.nonlinear_effects()(q, v))
    f = -by_L(J @ a_free + gamma + _stabilised(robot, contacts, q, J @ v, gains, anchors))
    return a_free + MiJt @ f, f, (J, by_M, MiJt, by_L)


def _gains(damping, stiffness) -> tuple:
    if not (damping >= 0 and stiffness >= 0):
        raise InvalidArgument(f"contact damping {damping!r} (1/s) and stiffness {stiffness!r} (1/s^2): expected "
                              "numbers >= 0")
    return float(damping), float(stiffness)


def _inputs(contacts, stiffness, *names) -> tuple:
    """The Function's input names (anchors last with a stiffness) and the sizes of the odd ones."""
    return list(names) + (["anchors"] if stiffness else []), {"anchors": anchor_size(contacts)}


def forward(robot, contacts, damping: float = 0.0, stiffness: float = 0.0) -> ca.Function:
    """q, v, tau[, anchors] -> a (nv), f (nc): the contact forward dynamics (module docstring);
    with a stiffness, J a + gamma = -damping J v - stiffness e, e the rows' errors from `anchors`."""
    gains = _gains(damping, stiffness)
    ins, sizes = _inputs(contacts, stiffness, "q", "v", "tau")

    def build(q, v, tau, *anchors):
        a, f, _ = _kkt(robot, contacts, q, v, tau, gains, *anchors)
        return ca.cse([a, f])
    return robot._function(_name("contact_dynamics", contacts) + _damped(*gains), ins, ["a", "f"], build, sizes)


def inverse(robot, contacts) -> ca.Function:
    """q, v, a, f -> tau, T, base: the inputs with the contact forces f applied (base: the wrench
    the base still lacks, zero when a and f are consistent)."""
    nc = sum(c.rows for c in contacts)

    def build(q, v, a, f):
        return robot.inputs_for(q, v, robot._inverse(q, v, a, wrenches=wrenches(robot, contacts, q, f)))
    return robot._function(_name("contact_inverse_dynamics", contacts), ["q", "v", "a", "f"],
                           ["tau", "T", "base"], build, {"f": nc})


def impact(robot, contacts) -> ca.Function:
    """q, v -> v_plus, impulse: the plastic impact, M (v_plus - v) = J^T impulse, J v_plus = 0."""
    def build(q, v):
        M, J = robot.mass_matrix()(q), jacobian(robot, contacts)(q)
        _, MiJt, by_L = _solver(M, J)
        impulse = -by_L(J @ v)
        return ca.cse([v + MiJt @ impulse, impulse])
    return robot._function(_name("impact", contacts), ["q", "v"], ["v_plus", "impulse"], build)


def check(robot, contacts, q, rtol: float = 1e-9) -> None:
    """Refuse, naming them, contacts whose rows depend on the others' at q (the contact dynamics'
    KKT system is then singular and its forces undetermined): a flat contact and a point contact
    on the same leg, two contacts on one link, a leg with fewer joints than its contact has rows."""
    J = np.asarray(jacobian(robot, contacts)(np.asarray(q, float)))
    scale, rows = max(np.max(np.abs(J)), 1e-300), 0
    held: list = []
    for c in contacts:
        block = J[:rows + c.rows]
        s = np.linalg.svd(block / scale, compute_uv=False)
        if s[-1] < rtol:
            raise InvalidArgument(f"{robot.model.path}: contacts: the rows of {c.frame!r} ({c.kind}) depend on "
                                  + (f"those of {', '.join(repr(h) for h in held)}" if held else "each other")
                                  + " at this configuration: the contact forces are undetermined (a singular KKT "
                                  "system); drop that contact, make it a point contact, or move the robot")
        rows += c.rows
        held.append(c.frame)


def residual_jacobian(robot, contacts, damping: float = 0.0, stiffness: float = 0.0) -> ca.Function:
    """q, v, tau, a, f -> dr/d(dq, v, tau) ((nv + nc) x (2 nv + u)) of the contact dynamics'
    residual r = [M a + h - Q - J^T f; J a + gamma + damping J v + stiffness e], dq the tangent displacement of q
    (q moved to integrate(q, dq)); an SX Function of the recursions' derivatives, J^T f as the
    contact wrenches applied in the inverse dynamics."""
    nc, gains = sum(c.rows for c in contacts), _gains(damping, stiffness)
    ins, sizes = _inputs(contacts, stiffness, "q", "v", "tau", "a", "f")

    def build(q, v, tau, a, f, *anchors):
        dq = ca.SX.sym("dq", robot.nv)
        moved = robot.integrate()(q, dq, 1.0)
        vel, acc = _rows(robot, contacts, moved, v, a)
        r = ca.vertcat(robot._inverse(moved, v, a, wrenches=wrenches(robot, contacts, moved, f))
                       - robot.generalized_forces()(moved, v, tau),
                       acc + _stabilised(robot, contacts, moved, vel, gains, *anchors))
        D = ca.jacobian(r, ca.vertcat(dq, v, tau))
        return [ca.cse(ca.substitute(D, dq, ca.DM.zeros(robot.nv)))]
    return robot._function(_name("contact_residual_jacobian", contacts) + _damped(*gains), ins, ["jacobian"], build,
                           {"f": nc, **sizes})


def _damped(damping, stiffness=0.0) -> str:
    """The Function name's suffix for Baumgarte gains."""
    tag = (f"_damped_{damping:g}" if damping else "") + (f"_stiff_{stiffness:g}" if stiffness else "")
    return tag.replace(".", "p").replace("+", "").replace("-", "m")


def forward_jacobian(robot, contacts, damping: float = 0.0, stiffness: float = 0.0) -> ca.Function:
    """q, v, tau[, anchors] -> da (nv x (2 nv + u)), df (nc x (2 nv + u)): the contact dynamics'
    derivatives by (dq, v, tau), dq the tangent displacement of q, by the implicit-function theorem
    on the KKT system: K (da, df) = -dr/d(dq, v, tau) with K = ((M, -J^T), (J, 0)), solved as the
    dynamics themselves."""
    gains = _gains(damping, stiffness)
    ins, sizes = _inputs(contacts, stiffness, "q", "v", "tau")

    def build(q, v, tau, *anchors):
        a, f, (J, by_M, MiJt, by_L) = _kkt(robot, contacts, q, v, tau, gains, *anchors)
        D = -residual_jacobian(robot, contacts, *gains)(q, v, tau, a, f, *anchors)
        R1, R2 = D[:robot.nv, :], D[robot.nv:, :]
        MiR1 = by_M(R1)
        df = by_L(R2 - J @ MiR1)
        return ca.cse([MiR1 + MiJt @ df, df])
    return robot._function(_name("contact_dynamics_jacobian", contacts) + _damped(*gains), ins, ["da", "df"], build,
                           sizes)
