"""The rotor-separated recursions (paper section III), symbolic, in body frames, on a tree.

Joints j = 0..n-1 are ordered so that each comes after its parent (`Segment.parent`, -1 for the
base); a serial chain is the tree whose parent of j is j - 1.  As in Featherstone's tree
algorithms, every recursion is one loop forward over j (base to leaves, reading the parent's
quantities) and one backward (leaves to base, adding into the parent's): on a chain the
backward loop is the paper's "for k = 1..n" (k = n - j, k = 1 the tip).

The model (constant) is a list of `Segment`s, one per joint; the per-call workspace
is a list of `Kin` records made by `kinematics`.  A joint's two rotors hang on its parent
link, each (gear, M, spins): the slow rotor (gear 1) and the fast rotor (gear -mu).  An SEA
joint's rotors turn with its motor coordinate phi (`Segment.leaves`: a one-degree-of-freedom
leaf of the parent, paper eq. 23); a geared joint's turn with its link coordinate theta through
the gear (`Segment.geared`: one cluster with the link, one coordinate, as GRBDA's); the other
kinds have none (rscasadi.model.kinds).
A floating base (`Base`) is body 0 of the tree, moved by a six-degree-of-freedom joint from the
world: its velocity V0 starts the forward loops, its articulated inertia ends the backward one,
and its acceleration alpha0 (classical, gravity as an acceleration of the world as everywhere
here) is then solved from it before the forward loop (Featherstone's floating-base ABA).
The DLR/Spong reduced model uses the same code: rotors merged rigidly into the
parent link, and a spin inertia on the coordinate they turn with (`B_spin` on phi, `B_link` on
theta).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from rscasadi.spatial import (REVOLUTE, H, Motion, Xup, as_casadi, base_acceleration, base_pose, coriolis, gyroscopic,
                              joint_rotation)


@dataclass
class Segment:
    """One joint of the chain: its placement in the parent, its link's and rotors' spatial inertias."""

    R: np.ndarray            # J_j relative to the parent frame
    l: np.ndarray            # J_j origin in the parent frame
    M: np.ndarray            # spatial inertia of link j (eq. 11), link frame
    leaves: list             # [(gear, M, spins)] rotors turning with the motor coordinate; see `segments`
    B_spin: float = 0.0      # reduced model only: B_j on the motor coordinate
    parent: int = -1         # the joint whose link carries joint j (-1: the base)
    motor: int | None = None  # the index of joint j's motor coordinate in phi, if it has one
    geared: list = field(default_factory=list)   # [(gear, M, spins)] rotors turning with theta_j
    B_link: float = 0.0      # reduced model only: the spin inertia of geared rotors on theta_j
    motion: Motion = REVOLUTE  # the link turns about z of J_j or slides along it (rotors only on a turn)


@dataclass
class Base:
    """A floating base: its spatial inertia M (its frame), its velocity V = [w; v] (its frame) and
    its pose in the world, rotation R and origin p (for gravity's potential)."""
    M: Any
    V: Any
    R: Any = None
    p: Any = None


@dataclass
class Kin:
    """Per-call workspace of one joint: angles, transforms, velocities and Coriolis terms."""
    q: tuple                 # (theta_j, phi_j, dtheta_j, dphi_j); phi None without a motor
    X: ca.SX
    V: ca.SX
    a: ca.SX
    leaves: list = field(default_factory=list)   # [(gear, M, X, V, a)] rotors on the motor coordinate
    geared: list = field(default_factory=list)   # [(gear, M, X, V, a)] rotors on theta_j


def rotor_frame_angle(gear, spins, phi):
    """A rotor's frame turns by gear * phi about z of J; a balanced rotor's spatial inertia is
    invariant under that turn, so its quantities are written in J itself (no trigonometry)."""
    return gear * phi if spins else 0


def segments(model, phys, reduced: bool = False) -> list:
    """The tree of the complete model, or of the DLR reduced model, with the inertias of `phys`
    (numbers, or expressions of the parameters: then every rotor spins in its own frame)."""
    segs, motors = [], model.motor_of
    for j, (jt, parent) in enumerate(zip(model.joints, model.parent)):
        M, mu, kind = phys.inertias[j], phys.columns["gear_ratio"][j], jt.joint_kind   # mu: a number, or free
        rotors = [(gear, M[part], (phys.symbolic and (jt.name, part) not in phys.balanced)
                   or not getattr(jt, part).balanced)
                  for gear, part in ((1.0, "slow_rotor"), (-mu, "fast_rotor"))] if kind.rotors else []
        on_motor, on_link = kind.rotors == "motor", kind.rotors == "link"
        spin = phys.rotor_inertia(j) if reduced and kind.rotors else 0.0
        segs.append(Segment(jt.R, jt.origin_xyz, M["link"], rotors if on_motor and not reduced else [],
                            spin if on_motor else 0.0, parent, motors.get(j),
                            rotors if on_link and not reduced else [], spin if on_link else 0.0,
                            jt.joint_motion))
    if reduced:  # joint j's rotors carried rigidly by its parent link at zero angle (exact for balanced rotors)
        for jt, M, parent in zip(model.joints, phys.inertias, model.parent):
            if parent < 0 or not jt.joint_kind.rotors:
                continue
            X0 = Xup(ca.DM(jt.R), jt.origin_xyz)
            for part in ("slow_rotor", "fast_rotor"):
                segs[parent].M = as_casadi(segs[parent].M) + X0.T @ as_casadi(M[part]) @ X0
    return segs


def kinematics(segs, theta, phi, dtheta, dphi, base: Base | None = None) -> list:
    """Eqs. (1), (9), (18): velocities and Coriolis terms, base to leaves (from a floating base's V)."""
    kin: list = []
    V0 = base.V if base is not None else ca.DM.zeros(6)
    for j, seg in enumerate(segs):
        V_p = kin[seg.parent].V if seg.parent >= 0 else V0
        R, l = seg.motion.placement(seg.R, seg.l, theta[j])
        X = Xup(R, l)
        m = seg.motor
        q = (theta[j], None, dtheta[j], None) if m is None else (theta[j], phi[m], dtheta[j], dphi[m])
        k = Kin(q, X, X @ V_p + seg.motion.H * dtheta[j], seg.motion.coriolis(R, l, V_p[:3], dtheta[j]))
        k.leaves = [_rotor(seg, V_p, rotor, q[1], q[3]) for rotor in seg.leaves]
        k.geared = [_rotor(seg, V_p, rotor, q[0], q[2]) for rotor in seg.geared]
        kin.append(k)
    return kin


def _rotor(seg, V_p, rotor, angle, rate) -> tuple:
    """A rotor at the joint frame turned by gear * angle: (gear, M, X, V, Coriolis term)."""
    gear, M, spins = rotor
    Rr = joint_rotation(seg.R, rotor_frame_angle(gear, spins, angle))
    Xr = Xup(Rr, seg.l)
    return gear, M, Xr, Xr @ V_p + H * gear * rate, coriolis(Rr, seg.l, V_p[:3], gear * rate)


def accelerations(segs, kin, ddtheta, ddphi, gravity, alpha0=None):
    """Eqs. (2), (18): spatial accelerations of links, motor rotors and geared rotors, base to leaves
    (alpha0: a floating base's acceleration, gravity included; default the fixed base's, -g)."""
    alpha: list = []
    alpha_r: list = []
    alpha_g: list = []
    alpha_base = base_acceleration(gravity) if alpha0 is None else alpha0
    for j, (seg, k) in enumerate(zip(segs, kin)):
        alpha_p = alpha[seg.parent] if seg.parent >= 0 else alpha_base
        alpha_r.append([Xr @ alpha_p + H * gear * ddphi[seg.motor] + ar for gear, _, Xr, _, ar in k.leaves])
        alpha_g.append([Xr @ alpha_p + H * gear * ddtheta[j] + ar for gear, _, Xr, _, ar in k.geared])
        alpha.append(k.X @ alpha_p + seg.motion.H * ddtheta[j] + k.a)
    return alpha, alpha_r, alpha_g


def rotor_force(M, V, alpha):
    """Inertial force of one body, M alpha + b (eq. 3)."""
    return M @ alpha + gyroscopic(M, V[:3])


def inverse_dynamics(segs, kin, ddtheta, ddphi, gravity, f_ext=None, base: Base | None = None, alpha0=None):
    """Eqs. (2), (3), (25), (26): T = theta rows of M ddq + c; Qphi = phi rows (rotor inertia).
    f_ext: per link the spatial force the environment applies to it (link frame), or None.
    With a floating `base` moving at alpha0 (gravity included) a third output: the wrench the
    base needs (base frame, [moment; force]): its own inertial force and the tree's on it."""
    n = len(segs)
    alpha, alpha_r, alpha_g = accelerations(segs, kin, ddtheta, ddphi, gravity, alpha0)
    T, Qphi = [None] * n, {}
    f_child = [ca.DM.zeros(6) for _ in range(n + 1)]   # force of the outboard joints on link j (n: the base)
    for j in reversed(range(n)):
        seg = segs[j]
        f = rotor_force(seg.M, kin[j].V, alpha[j]) + f_child[j]        # eq. (25)
        if f_ext is not None:
            f = f - f_ext[j]                                           # the environment's share
        rotor_f = [rotor_force(M, Vr, ar) for (_, M, _, Vr, _), ar in zip(kin[j].leaves, alpha_r[j])]
        geared_f = [rotor_force(M, Vr, ar) for (_, M, _, Vr, _), ar in zip(kin[j].geared, alpha_g[j])]
        T[j] = f[seg.motion.index]                                     # eq. (26): T_k = H^T f_k
        if kin[j].geared:                                              # and the rotors turning with theta_j
            T[j] = T[j] + seg.B_link * ddtheta[j] + _spin(kin[j].geared, geared_f)
        elif seg.B_link:
            T[j] = T[j] + seg.B_link * ddtheta[j]
        if seg.motor is not None:
            Qphi[seg.motor] = seg.B_spin * ddphi[seg.motor] + _spin(kin[j].leaves, rotor_f)
        f_child[seg.parent] = (f_child[seg.parent] + kin[j].X.T @ f        # parent -1: the base, f_child[n]
                               + _carried(kin[j].leaves, rotor_f) + _carried(kin[j].geared, geared_f))
    out = ca.vertcat(*T), _column([Qphi[m] for m in sorted(Qphi)])
    if base is None:
        return out
    return out + (rotor_force(base.M, base.V, alpha0) + f_child[n],)


def _spin(rotors, forces):
    """The rotors' share of their coordinate's generalised force: sum of gear * H^T f."""
    return sum((gear * f[2] for (gear, *_), f in zip(rotors, forces)), 0)


def _carried(rotors, forces):
    """The rotors' forces on the parent link: sum of X^T f."""
    return sum((Xr.T @ f for (_, _, Xr, _, _), f in zip(rotors, forces)), ca.DM.zeros(6))


def _column(entries):
    """A column of entries (0 x 1 when there are none)."""
    return ca.vertcat(*entries) if entries else ca.DM.zeros(0, 1)


def leaf_articulated(seg, k, Qphi_j):
    """The rotor leaf of a joint seen from its parent link: the terms of eq. (23).

    Returns D (= B_j), U (parent frame), eps (Qphi minus bias), and the leaf's
    articulated inertia and bias force handed to the parent link."""
    D = seg.B_spin + sum(gear ** 2 * M[2, 2] for gear, M, *_ in k.leaves)
    U, eps, P_add, z_add = ca.DM.zeros(6), Qphi_j, ca.DM.zeros(6, 6), ca.DM.zeros(6)
    for gear, M, Xr, Vr, ar in k.leaves:
        Mr, F = as_casadi(M), rotor_force(M, Vr, ar)           # F_ks, F_kf of eq. (24) without alpha_p
        U += gear * Xr.T @ (Mr @ H)
        eps -= gear * F[2]
        P_add += Xr.T @ Mr @ Xr
        z_add += Xr.T @ F
    return D, U, eps, P_add - U @ U.T / D, z_add + U * eps / D


def project(P, z, torque, i: int = 2):
    """One joint of the articulated sweep, eqs. (4)-(5): G, nu, P^+, z^+ from P, z and the joint
    torque (or force); i: the entry its coordinate moves (H = e_i: 2 a turn, 5 a slide)."""
    D = P[i, i]                                                    # D = H^T P H
    G = P[:, i] / D                                                # G = P H D^-1
    eps = torque - z[i]                                            # eps = T - H^T z
    return G, eps / D, P - G @ P[i, :], z + G * eps                # nu, P+ = (1 - G H^T) P, z+ = z + G eps


def geared_cluster(seg, k, P, z, torque):
    """A geared joint's link with the rotors turning with it (gear g_r, through the gear) as one
    body of one coordinate, seen from the parent (the cluster of GRBDA; with no rotors, eqs. 4-5):
    D = H^T P H + B + sum g_r^2 H^T M_r H, U = X^T P H + sum g_r X_r^T M_r H (parent frame),
    u = T - H^T z - sum g_r H^T F_r; theta'' = (u - U^T alpha_parent) / D.  Returns D, U, u and the
    articulated inertia and bias force handed to the parent link."""
    D, U, u = P[2, 2] + seg.B_link, k.X.T @ P[:, 2], torque - z[2]
    P_add, z_add = k.X.T @ P @ k.X, k.X.T @ z
    for gear, M, Xr, Vr, ar in k.geared:
        Mr, F = as_casadi(M), rotor_force(M, Vr, ar)
        D += gear ** 2 * Mr[2, 2]
        U += gear * Xr.T @ Mr[:, 2]
        u -= gear * F[2]
        P_add += Xr.T @ Mr @ Xr
        z_add += Xr.T @ F
    return D, U, u, P_add - U @ U.T / D, z_add + U * u / D


def forward_dynamics(segs, kin, Qtheta, Qphi, gravity, f_ext=None, base: Base | None = None):
    """The complete model solved in one O(n) sweep: eqs. (4)-(6) with each SEA's rotor pair a leaf
    (eq. 23) and each geared joint's link and rotors one cluster (`geared_cluster`).
    f_ext: per link the spatial force the environment applies to it (link frame), or None.
    With a floating `base` a third output: its acceleration alpha0 (gravity as an acceleration of
    the world: the base's classical acceleration less gravity), from P0 alpha0 + z0 = 0."""
    n = len(segs)
    P_c, z_c = [ca.DM.zeros(6, 6)] * (n + 1), [ca.DM.zeros(6)] * (n + 1)   # what children hand to link j (n: base)
    solve: list[Any] = [None] * n                                  # theta_j'' from the parent's alpha
    leaf: list[Any] = [None] * n
    for j in reversed(range(n)):                                   # paper k = 1..n
        seg, k = segs[j], kin[j]
        P = seg.M + P_c[j]                                         # eq. (4)
        z = P @ k.a + gyroscopic(seg.M, k.V[:3]) + z_c[j]          # eq. (5)
        if f_ext is not None:
            z = z - f_ext[j]                                           # the bias less the applied force
        if k.geared or seg.B_link:
            D, U, u, P_add, z_add = geared_cluster(seg, k, P, z, Qtheta[j])
            solve[j] = lambda alpha_p, alpha_plus, D=D, U=U, u=u: (u - U.T @ alpha_p) / D
        else:
            G, nu, P_plus, z_plus = project(P, z, Qtheta[j], seg.motion.index)
            solve[j] = lambda alpha_p, alpha_plus, G=G, nu=nu: nu - G.T @ alpha_plus
            P_add, z_add = k.X.T @ P_plus @ k.X, k.X.T @ z_plus
        if seg.motor is not None:
            leaf[j] = leaf_articulated(seg, k, Qphi[seg.motor])
            P_add, z_add = P_add + leaf[j][3], z_add + leaf[j][4]
        P_c[seg.parent] = P_c[seg.parent] + P_add                  # parent -1: the base, P_c[n]
        z_c[seg.parent] = z_c[seg.parent] + z_add
    alpha0 = base_acceleration(gravity)
    if base is not None:                                           # the base: one 6-dof joint to the world
        alpha0 = -ca.solve(as_casadi(base.M) + P_c[n], gyroscopic(base.M, base.V[:3]) + z_c[n])
    ddtheta: list = []
    ddphi: list = []
    alpha: list = []
    for j in range(n):                                             # eq. (6), paper k = n..1
        alpha_p = alpha[segs[j].parent] if segs[j].parent >= 0 else alpha0
        if leaf[j] is not None:
            D_r, U_r, eps_r = leaf[j][:3]
            ddphi.append((eps_r - U_r.T @ alpha_p) / D_r)          # eq. (23)
        alpha_plus = kin[j].X @ alpha_p
        ddtheta.append(solve[j](alpha_p, alpha_plus))
        alpha.append(alpha_plus + segs[j].motion.H * ddtheta[j] + kin[j].a)
    out = ca.vertcat(*ddtheta), _column(ddphi)
    return out if base is None else out + (alpha0,)


def joint_forward_dynamics(segs, kin, ddtheta, Qphi, gravity):
    """Paper eq. (23): each motor's ddphi from the link accelerations (eq. 2) of its parent."""
    alpha = accelerations(segs, kin, ddtheta, ca.DM.zeros(sum(seg.motor is not None for seg in segs)), gravity)[0]
    out = []
    for j, seg in enumerate(segs):
        if seg.motor is None:
            continue
        D, U, eps = leaf_articulated(seg, kin[j], Qphi[seg.motor])[:3]
        alpha_p = alpha[seg.parent] if seg.parent >= 0 else base_acceleration(gravity)
        out.append((eps - U.T @ alpha_p) / D)
    return _column(out)


def _inner_joint(angle, w_parent, rate):
    """A joint inside a flexible joint (eq. 14: Phi = 1): transform between the two bodies'
    coordinate frames (turned by `angle`) and the Coriolis term of eq. (18) for `rate`."""
    R = joint_rotation(np.eye(3), angle)
    return Xup(R, np.zeros(3)), coriolis(R, np.zeros(3), w_parent, rate)


def arm_forward_dynamics(segs, kin, T, ddphi, ddtheta_guess, gravity):
    """Paper eqs. (29)-(32): link accelerations of the chains link k <- ks <- kf <- parent link.

    The rotor joints are driven by T_ks, T_kf of eq. (29), which need the rotors'
    spatial accelerations: they are formed from ddphi and the parent links'
    accelerations of `ddtheta_guess` (the paper's predictor).  At the exact
    ddtheta the result equals it (a fixed point).  The rotors of a joint on the base sit on
    the fixed base and are not part of the tree (3n - 1 bodies on a chain).  Every joint an SEA
    (phi[j] is joint j's motor)."""
    n = len(segs)
    _, alpha_r, _ = accelerations(segs, kin, ddtheta_guess, ddphi, gravity)
    P_c, z_c = [ca.DM.zeros(6, 6)] * n, [ca.DM.zeros(6)] * n
    G, nu, inner = [None] * n, [None] * n, [None] * n
    for j in reversed(range(n)):                                   # eqs. (30), (31), paper k = 1..n
        a_link, on_base = kin[j].a, segs[j].parent < 0
        if not on_base:
            theta, phi, dtheta, dphi = kin[j].q
            (_, Ms, Xs, Vs, a_s), (gear, Mf, Xf, Vf, a_f) = kin[j].leaves
            (_, _, spins_s), (_, _, spins_f) = segs[j].leaves
            ang_s, ang_f = rotor_frame_angle(1.0, spins_s, phi), rotor_frame_angle(gear, spins_f, phi)
            X_fs, a_fs = _inner_joint(ang_s - ang_f, Vf[:3], (1 - gear) * dphi)       # ks relative to kf
            X_sl, a_link = _inner_joint(theta - ang_s, Vs[:3], dtheta - dphi)         # link relative to ks
            inner[j] = (Xs, a_s, X_sl, a_link)
        P = segs[j].M + P_c[j]
        z = P @ a_link + gyroscopic(segs[j].M, kin[j].V[:3]) + z_c[j]
        G[j], nu[j], P_plus, z_plus = project(P, z, T[j])
        if on_base:
            continue
        F_s = rotor_force(Ms, Vs, alpha_r[j][0])
        T_s = T[j] + F_s[2]                                        # eq. (29)
        T_f = T_s + rotor_force(Mf, Vf, alpha_r[j][1])[2]
        P_s = X_sl.T @ P_plus @ X_sl + Ms
        z_s = X_sl.T @ z_plus + P_s @ a_fs + gyroscopic(Ms, Vs[:3])
        _, _, P_s_plus, z_s_plus = project(P_s, z_s, T_s)
        P_f = X_fs.T @ P_s_plus @ X_fs + Mf
        z_f = X_fs.T @ z_s_plus + P_f @ a_f + gyroscopic(Mf, Vf[:3])
        _, _, P_f_plus, z_f_plus = project(P_f, z_f, T_f)
        P_c[segs[j].parent] = P_c[segs[j].parent] + Xf.T @ P_f_plus @ Xf
        z_c[segs[j].parent] = z_c[segs[j].parent] + Xf.T @ z_f_plus
    ddtheta: list = []
    alpha: list = []
    for j in range(n):                                             # eq. (32), paper k = n..1
        if segs[j].parent < 0:
            alpha_plus = kin[j].X @ base_acceleration(gravity)
            ddtheta.append(nu[j] - G[j].T @ alpha_plus)
            alpha.append(alpha_plus + H * ddtheta[j] + kin[j].a)
        else:
            Xs, a_s, X_sl, a_sl = inner[j]
            alpha_plus = X_sl @ (Xs @ alpha[segs[j].parent] + H * ddphi[j] + a_s)
            ddtheta.append(ddphi[j] + nu[j] - G[j].T @ alpha_plus)
            alpha.append(alpha_plus + H * (ddtheta[j] - ddphi[j]) + a_sl)
    return ca.vertcat(*ddtheta)


def body_states(segs, kin, base: Base | None = None):
    """Every body (a floating base, then per joint its link, its motor's and its geared rotors):
    (M, V, R, o), its spatial inertia and velocity in its frame, and the frame's rotation and origin
    in the world (eq. 12; a fixed base is the world)."""
    poses: list = []
    root = (ca.DM.eye(3), ca.DM.zeros(3)) if base is None else (base.R, base.p)
    if base is not None:
        yield base.M, base.V, base.R, base.p
    for seg, k in zip(segs, kin):
        theta = k.q[0]
        R_p, o_p = poses[seg.parent] if seg.parent >= 0 else root
        R_link, l_link = seg.motion.placement(seg.R, seg.l, theta)
        bodies = [(seg.M, k.V, R_link)]
        bodies += [(M, Vr, joint_rotation(seg.R, rotor_frame_angle(gear, spins, k.q[1])))
                   for (gear, M, _, Vr, _), (_, _, spins) in zip(k.leaves, seg.leaves)]
        bodies += [(M, Vr, joint_rotation(seg.R, rotor_frame_angle(gear, spins, theta)))
                   for (gear, M, _, Vr, _), (_, _, spins) in zip(k.geared, seg.geared)]
        for i, (M, V, R) in enumerate(bodies):
            yield (M, V) + base_pose(R_p, o_p, R, l_link if i == 0 else seg.l)
        poses.append(base_pose(R_p, o_p, R_link, l_link))


def energy(segs, kin, gravity, base: Base | None = None):
    """Kinetic (0.5 V^T M V per body) plus gravitational (-m g . p_com) of every body."""
    E, g = 0, as_casadi(gravity)
    for M, V, R, o in body_states(segs, kin, base):
        m, mp = M[3, 3], ca.vertcat(M[2, 4], M[0, 5], M[1, 3])        # eq. (11): m and m c
        E += 0.5 * V.T @ as_casadi(M) @ V - g.T @ (m * o + R @ mp)
    return E


def momentum(segs, kin, base: Base | None = None):
    """The momentum of every body about the world origin, world axes: [linear; angular]."""
    lin, ang = ca.DM.zeros(3), ca.DM.zeros(3)
    for M, V, R, o in body_states(segs, kin, base):
        h = as_casadi(M) @ V                                          # [moment about its origin; force]
        p = R @ h[3:]
        lin, ang = lin + p, ang + R @ h[:3] + ca.cross(o, p)
    return ca.vertcat(lin, ang)


def mass_and_moment(segs, kin, base: Base | None = None):
    """The total mass and its first moment sum m c (world): the centre of mass is their ratio."""
    mass, moment = 0, ca.DM.zeros(3)
    for M, _, R, o in body_states(segs, kin, base):
        m, mp = M[3, 3], ca.vertcat(M[2, 4], M[0, 5], M[1, 3])
        mass, moment = mass + m, moment + m * o + R @ mp
    return mass, moment
