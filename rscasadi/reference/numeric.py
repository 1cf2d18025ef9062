"""The numerical core: the paper's algorithms step by step in plain numpy.

Written apart from the symbolic recursions (`recursions.py`, body frames, CasADi) so
that comparing the two means something.  Here everything is in the base frame
(eq. 12) and the index is the paper's: k = 1 is the tip link, k = n the base joint,
k = n + 1 the base.  Arrays indexed by k have n + 2 slots; public arguments and
results run base to tip (j = n - k in 0-based public order).
"""
from __future__ import annotations

import numpy as np

from rscasadi.model.modelfile import ArmModel

z3 = np.array([0.0, 0.0, 1.0])


def tilde(v):
    """The cross-product matrix of a 3-vector: tilde(v) @ w = v x w."""
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def Rz(q):
    """The rotation by q about z."""
    c, s = np.cos(q), np.sin(q)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def Phi(l):
    """Eq. (8): the composite body transformation operator."""
    return np.block([[np.eye(3), tilde(l)], [np.zeros((3, 3)), np.eye(3)]])


def M_of(body, R):
    """Eq. (11) with eq. (12): the spatial inertia about the body origin, in the base frame."""
    m, p, I = body.mass, R @ body.com, R @ body.inertia_origin @ R.T
    return np.block([[I, m * tilde(p)], [-m * tilde(p), m * np.eye(3)]]), m, p


def a_of(w_s, h, rate, l):
    """Eqs. (9), (18): the Coriolis term a_{s,t}."""
    return np.concatenate([np.cross(w_s, h) * rate, np.cross(w_s, np.cross(w_s, l))])


def b_of(w, M):
    """Eq. (10): [w~ I_O w; m w~ w~ p] (I_O and m p read off M)."""
    I_O, mp = M[:3, :3], np.array([M[2, 4], M[0, 5], M[1, 3]])
    return np.concatenate([np.cross(w, I_O @ w), np.cross(w, np.cross(w, mp))])


class Numeric:
    """The paper's rotor-separated model of an arm, evaluated numerically."""

    def __init__(self, model: ArmModel):
        self.model, self.n = model, model.n
        self.alpha_base = np.concatenate([np.zeros(3), -model.gravity])   # gravity as base acceleration
        self.mu = model.column("gear_ratio")

    # -- the state in the paper's order and frame ------------------------------------------
    def _k(self, x):
        """Public base-to-tip array -> slots k = 1..n (index 0 and n+1 unused)."""
        out = np.zeros(self.n + 2)
        out[1:self.n + 1] = np.asarray(x, float)[::-1]
        return out

    def _j(self, xk):
        return np.asarray(xk[1:self.n + 1], float)[::-1].copy()

    def _joint(self, k):
        return self.model.joints[self.n - k]

    def sea(self, theta, phi, dtheta, dphi):
        """T_K(psi) + T_B(dpsi), T_B2(dphi) per joint (eq. 21; docs/user-guide/model.md section 2), public order."""
        m = self.model
        psi, dpsi = np.asarray(phi) - theta, np.asarray(dphi) - dtheta
        T = m.column("k1") * psi + m.column("k3") * psi ** 3 + m.column("d") * dpsi
        load = np.sqrt(T ** 2 + 1e-6) - 1e-3                       # |T|, smoothed as the model's (1e-3 N m)
        static = m.column("stribeck") * np.exp(-(np.asarray(dphi) / m.column("v_stribeck")) ** 2)
        TB2 = m.column("b") * dphi + (m.column("c") + m.column("c1") * load + static) * np.tanh(np.asarray(dphi) / m.column("eps"))
        return T, TB2

    def link_side(self, theta, dtheta):
        """T_L per joint, public order: the link's viscous and Coulomb loss and its counterbalance
        spring (docs/user-guide/model.md section 2)."""
        m, theta, dtheta = self.model, np.asarray(theta, float), np.asarray(dtheta, float)
        return (m.column("link_b") * dtheta + m.column("link_c") * np.tanh(dtheta / m.column("eps"))
                + m.column("cb_k") * (theta - m.column("cb_theta0")))

    def frames(self, theta, phi, dtheta, dphi):
        """Eq. (12) and eqs. (1), (9), (18): every operator in the base frame, tip (k=1) to base."""
        n, th, ph, dth, dph = self.n, self._k(theta), self._k(phi), self._k(dtheta), self._k(dphi)
        s = {key: [None] * (n + 2) for key in ("R", "o", "l", "h", "M", "Ms", "Mf", "V", "Vs", "Vf",
                                                "a", "as_", "af", "b", "bs", "bf", "mp")}
        R_p, o_p, V_p = np.eye(3), np.zeros(3), np.zeros(6)
        for k in range(n, 0, -1):                                  # base to tip: k = n..1
            jt = self._joint(k)
            R_J = R_p @ jt.R                                       # J_k in the base frame
            o = o_p + R_p @ jt.origin_xyz
            l = o - o_p                                            # l_{k+1,k}
            h = R_J @ z3                                           # H_k of eq. (12)
            H = np.concatenate([h, np.zeros(3)])
            w_p = V_p[:3]
            R = R_J @ Rz(th[k])
            M, m, p = M_of(jt.link, R)
            Ms, _, _ = M_of(jt.slow_rotor, R_J @ Rz(ph[k]))
            Mf, _, _ = M_of(jt.fast_rotor, R_J @ Rz(-self.mu[n - k] * ph[k]))
            V = Phi(l).T @ V_p + H * dth[k]                        # eq. (1)
            Vs = Phi(l).T @ V_p + H * dph[k]
            Vf = Phi(l).T @ V_p - H * self.mu[n - k] * dph[k]
            for key, val in (("R", R), ("o", o), ("l", l), ("h", H), ("M", M), ("Ms", Ms), ("Mf", Mf),
                             ("V", V), ("Vs", Vs), ("Vf", Vf), ("mp", (m, p)),
                             ("a", a_of(w_p, h, dth[k], l)),                     # eq. (9)
                             ("as_", a_of(w_p, h, dph[k], l)),                   # eq. (18), a_{k+1,ks}
                             ("af", a_of(w_p, h, -self.mu[n - k] * dph[k], l)),  # eq. (18), a_{k+1,kf}
                             ("b", b_of(V[:3], M)), ("bs", b_of(Vs[:3], Ms)), ("bf", b_of(Vf[:3], Mf))):
                s[key][k] = val
            R_p, o_p, V_p = R, o, V
        return s

    # -- inverse dynamics -------------------------------------------------------------------
    def link_accelerations(self, s, ddtheta, ddphi):
        """Eq. (2) for links, and the rotors' alpha_ks, alpha_kf by eq. (2) with eq. (18)."""
        n, ddth, ddph = self.n, self._k(ddtheta), self._k(ddphi)
        alpha, alpha_s, alpha_f = [None] * (n + 2), [None] * (n + 2), [None] * (n + 2)
        alpha[n + 1] = self.alpha_base
        for k in range(n, 0, -1):
            PhiT_alpha = Phi(s["l"][k]).T @ alpha[k + 1]
            alpha[k] = PhiT_alpha + s["h"][k] * ddth[k] + s["a"][k]
            alpha_s[k] = PhiT_alpha + s["h"][k] * ddph[k] + s["as_"][k]
            alpha_f[k] = PhiT_alpha - s["h"][k] * self.mu[n - k] * ddph[k] + s["af"][k]
        return alpha, alpha_s, alpha_f

    def inverse_dynamics(self, theta, phi, dtheta, dphi, ddtheta, ddphi):
        """Eqs. (1)-(3), (25)-(26) for T and eq. (22) for tau.  Returns (tau, T), public order."""
        n, s = self.n, self.frames(theta, phi, dtheta, dphi)
        alpha, alpha_s, alpha_f = self.link_accelerations(s, ddtheta, ddphi)
        Fs = [None] + [s["Ms"][k] @ alpha_s[k] + s["bs"][k] for k in range(1, n + 1)]
        Ff = [None] + [s["Mf"][k] @ alpha_f[k] + s["bf"][k] for k in range(1, n + 1)]
        f, T = np.zeros(6), np.zeros(n + 2)                        # f_0 = f_ext = 0
        for k in range(1, n + 1):                                  # eq. (25), tip to base
            inboard = np.zeros(6) if k == 1 else Phi(s["l"][k - 1]) @ (f + Fs[k - 1] + Ff[k - 1])
            f = inboard + s["M"][k] @ alpha[k] + s["b"][k]
            T[k] = s["h"][k] @ f                                   # eq. (26)
        T = T + self._k(self.link_side(theta, dtheta))             # the spring carries the link's losses too
        T_spring, TB2 = self.sea(theta, phi, dtheta, dphi)
        T_spring, TB2, tau = self._k(T_spring), self._k(TB2), np.zeros(n + 2)
        for k in range(1, n + 1):                                  # eq. (22)
            mu, H = self.mu[n - k], s["h"][k]
            tau[k] = -(T_spring[k] + TB2[k] + H @ Fs[k]) / mu + H @ Ff[k]
        return self._j(tau), self._j(T)

    # -- flexible-joint forward dynamics ----------------------------------------------------
    def rotor_terms(self, s, k, alpha_parent_plus):
        """Eq. (24): F_ks, F_kf with alpha_k^+ = Phi_{k+1,k}^T alpha_{k+1}."""
        F_ks = s["Ms"][k] @ alpha_parent_plus + s["Ms"][k] @ s["as_"][k] + s["bs"][k]
        F_kf = s["Mf"][k] @ alpha_parent_plus + s["Mf"][k] @ s["af"][k] + s["bf"][k]
        return F_ks, F_kf

    def eq23(self, s, k, tau_k, T_k, TB2_k, alpha_parent_plus):
        """Eq. (23): ddphi_k."""
        mu, H = self.mu[self.n - k], s["h"][k]
        F_ks, F_kf = self.rotor_terms(s, k, alpha_parent_plus)
        B = H @ s["Ms"][k] @ H + mu ** 2 * H @ s["Mf"][k] @ H      # I_ks,O(3,3) + mu^2 I_kf,O(3,3)
        return (-mu * tau_k - T_k - TB2_k - H @ F_ks + mu * H @ F_kf) / B

    def joint_forward_dynamics(self, theta, phi, dtheta, dphi, tau, ddtheta):
        """Eq. (23) for every joint, parent accelerations by eq. (2) from ddtheta."""
        s = self.frames(theta, phi, dtheta, dphi)
        alpha, _, _ = self.link_accelerations(s, ddtheta, np.zeros(self.n))
        T, TB2 = (self._k(v) for v in self.sea(theta, phi, dtheta, dphi))
        tau_k, out = self._k(tau), np.zeros(self.n + 2)
        for k in range(1, self.n + 1):
            out[k] = self.eq23(s, k, tau_k[k], T[k], TB2[k], Phi(s["l"][k]).T @ alpha[k + 1])
        return self._j(out)

    # -- complete forward dynamics: eqs. (4)-(6) with eq. (23) rotor leaves -----------------
    def forward_dynamics(self, theta, phi, dtheta, dphi, tau):
        n, s = self.n, self.frames(theta, phi, dtheta, dphi)
        T, TB2 = (self._k(v) for v in self.sea(theta, phi, dtheta, dphi))
        T_link = T - self._k(self.link_side(theta, dtheta))        # what turns the link: the spring less T_L
        tau_k = self._k(tau)
        G, nu, leaf = [None] * (n + 2), np.zeros(n + 2), [None] * (n + 2)
        P_plus, z_plus = np.zeros((6, 6)), np.zeros(6)             # P_0^+ = 0, z_0^+ = f_ext = 0
        for k in range(1, n + 1):
            H, mu = s["h"][k], self.mu[n - k]
            if k == 1:
                P, z = s["M"][1], s["M"][1] @ s["a"][1] + s["b"][1]
            else:
                Ph = Phi(s["l"][k - 1])
                P = Ph @ P_plus @ Ph.T + s["M"][k]                 # eq. (4)
                z = Ph @ z_plus + P @ s["a"][k] + s["b"][k]        # eq. (5)
            D = H @ P @ H
            G[k] = P @ H / D
            eps = T_link[k] - H @ z
            nu[k] = eps / D
            P_plus = (np.eye(6) - np.outer(G[k], H)) @ P
            z_plus = z + G[k] * eps
            # the rotor leaf of joint k, seen at O_k (eqs. 13, 23, 24): D_r, U, eps_r
            F_ks, F_kf = self.rotor_terms(s, k, np.zeros(6))
            U = s["Ms"][k] @ H - mu * s["Mf"][k] @ H
            D_r = H @ s["Ms"][k] @ H + mu ** 2 * H @ s["Mf"][k] @ H
            eps_r = -mu * tau_k[k] - T[k] - TB2[k] - H @ F_ks + mu * H @ F_kf
            leaf[k] = (U, D_r, eps_r)
            P_plus = P_plus + s["Ms"][k] + s["Mf"][k] - np.outer(U, U) / D_r
            z_plus = z_plus + F_ks + F_kf + U * eps_r / D_r
        ddth, ddph = np.zeros(n + 2), np.zeros(n + 2)
        alpha = self.alpha_base
        for k in range(n, 0, -1):                                  # eq. (6)
            alpha_plus = Phi(s["l"][k]).T @ alpha
            ddth[k] = nu[k] - G[k] @ alpha_plus
            U, D_r, eps_r = leaf[k]
            ddph[k] = (eps_r - U @ alpha_plus) / D_r               # eq. (23)
            alpha = alpha_plus + s["h"][k] * ddth[k] + s["a"][k]
        return self._j(ddth), self._j(ddph)

    # -- whole-arm forward dynamics: eqs. (29)-(32) ----------------------------------------
    def arm_forward_dynamics(self, theta, phi, dtheta, dphi, ddphi, ddtheta_guess):
        """Eqs. (30)-(32) on the chain 1, 1s, 1f, 2, ..., n (eq. 17); T_ks, T_kf by eq. (29) from
        the rotors' accelerations formed with ddtheta_guess.  Returns ddtheta."""
        n, s = self.n, self.frames(theta, phi, dtheta, dphi)
        _, alpha_s, alpha_f = self.link_accelerations(s, ddtheta_guess, ddphi)
        T = self._k(self.sea(theta, phi, dtheta, dphi)[0] - self.link_side(theta, dtheta))
        dth, dph, ddph = self._k(dtheta), self._k(dphi), self._k(ddphi)

        def step(P, z, H, torque):                                 # D, G, tau-bar, P^+, eps, v, z^+
            D = H @ P @ H
            G = P @ H / D
            eps = torque - H @ z
            return G, eps / D, (np.eye(6) - np.outer(G, H)) @ P, z + G * eps

        def a_inner(w_s, H, rate):                                 # eq. (18) inside a joint: l = 0
            return a_of(w_s, H[:3], rate, np.zeros(3))

        G, v = [None] * (n + 2), np.zeros(n + 2)
        H1 = s["h"][1]
        a_link = lambda k: s["a"][k] if k == n else a_inner(s["Vs"][k][:3], s["h"][k], dth[k] - dph[k])
        P = s["M"][1]                                              # eq. (30), k = 1
        z = P @ a_link(1) + s["b"][1]                              # eq. (31), f_ext = 0
        G[1], v[1], P_plus, z_plus = step(P, z, H1, T[1])
        for k in range(1, n):
            H, mu = s["h"][k], self.mu[n - k]
            T_ks = T[k] + H @ (s["Ms"][k] @ alpha_s[k] + s["bs"][k])           # eq. (29)
            T_kf = T_ks + H @ (s["Mf"][k] @ alpha_f[k] + s["bf"][k])
            P_ks = P_plus + s["Ms"][k]
            z_ks = z_plus + P_ks @ a_inner(s["Vf"][k][:3], H, (1 + mu) * dph[k]) + s["bs"][k]
            _, _, P_ks_plus, z_ks_plus = step(P_ks, z_ks, H, T_ks)
            P_kf = P_ks_plus + s["Mf"][k]
            z_kf = z_ks_plus + P_kf @ s["af"][k] + s["bf"][k]
            _, _, P_kf_plus, z_kf_plus = step(P_kf, z_kf, H, T_kf)
            Ph = Phi(s["l"][k])
            P = Ph @ P_kf_plus @ Ph.T + s["M"][k + 1]
            z = Ph @ z_kf_plus + P @ a_link(k + 1) + s["b"][k + 1]
            G[k + 1], v[k + 1], P_plus, z_plus = step(P, z, s["h"][k + 1], T[k + 1])
        ddth = np.zeros(n + 2)                                     # eq. (32)
        a_plus = Phi(s["l"][n]).T @ self.alpha_base
        ddth[n] = v[n] - G[n] @ a_plus
        alpha = a_plus + s["h"][n] * ddth[n] + s["a"][n]
        for k in range(n - 1, 0, -1):
            a_plus = Phi(s["l"][k]).T @ alpha + s["h"][k] * ddph[k] + s["as_"][k]
            ddth[k] = ddph[k] + v[k] - G[k] @ a_plus
            alpha = a_plus + s["h"][k] * (ddth[k] - ddph[k]) + a_link(k)
        return self._j(ddth)

    # -- energy --------------------------------------------------------------------------
    def energy(self, theta, phi, dtheta, dphi):
        """Kinetic 0.5 V^T M V + gravitational -m g.(o + p) of all 3n bodies + SEA spring energy."""
        s, g, m = self.frames(theta, phi, dtheta, dphi), self.model.gravity, self.model
        E = 0.0
        for k in range(1, self.n + 1):
            jt = self._joint(k)
            for V, M, body in ((s["V"][k], s["M"][k], jt.link), (s["Vs"][k], s["Ms"][k], jt.slow_rotor),
                               (s["Vf"][k], s["Mf"][k], jt.fast_rotor)):
                mp = np.array([M[2, 4], M[0, 5], M[1, 3]])
                E += 0.5 * V @ M @ V - g @ (body.mass * s["o"][k] + mp)
        psi = np.asarray(phi) - theta
        return E + np.sum(0.5 * m.column("k1") * psi ** 2 + 0.25 * m.column("k3") * psi ** 4)


class ReducedNumeric(Numeric):
    """The DLR/Spong reduced model (docs/user-guide/model.md section 3): the rotors of joint k ride rigidly on
    link k+1 (merged into its spatial inertia about O_{k+1}) and spin with inertia B_k alone."""

    def frames(self, theta, phi, dtheta, dphi):
        s = super().frames(theta, phi, dtheta, dphi)
        n = self.n
        for k in range(1, n):                                      # rotors of joint k onto link k+1
            Ph = Phi(s["l"][k])
            s["M"][k + 1] = s["M"][k + 1] + Ph @ (s["Ms"][k] + s["Mf"][k]) @ Ph.T
            s["b"][k + 1] = b_of(s["V"][k + 1][:3], s["M"][k + 1])
        self.B = np.array([jt.rotor_inertia for jt in self.model.joints])
        return s

    def inverse_dynamics(self, theta, phi, dtheta, dphi, ddtheta, ddphi):
        """Eqs. (1)-(3) on the links; tau from B ddphi + T + T_B2 = -mu tau."""
        n, s = self.n, self.frames(theta, phi, dtheta, dphi)
        alpha, _, _ = self.link_accelerations(s, ddtheta, ddphi)
        f, T = np.zeros(6), np.zeros(n + 2)
        for k in range(1, n + 1):                                  # eq. (3)
            f = (Phi(s["l"][k - 1]) @ f if k > 1 else f) + s["M"][k] @ alpha[k] + s["b"][k]
            T[k] = s["h"][k] @ f
        T_spring, TB2 = self.sea(theta, phi, dtheta, dphi)
        return -(self.B * ddphi + T_spring + TB2) / self.mu, self._j(T) + self.link_side(theta, dtheta)

    def forward_dynamics(self, theta, phi, dtheta, dphi, tau):
        """Eqs. (4)-(6) on the links; ddphi = (-mu tau - T - T_B2) / B."""
        n, s = self.n, self.frames(theta, phi, dtheta, dphi)
        T_spring, TB2 = self.sea(theta, phi, dtheta, dphi)
        T = self._k(T_spring - self.link_side(theta, dtheta))
        G, nu = [None] * (n + 2), np.zeros(n + 2)
        P_plus, z_plus = np.zeros((6, 6)), np.zeros(6)
        for k in range(1, n + 1):
            Ph, H = Phi(s["l"][k - 1]) if k > 1 else np.zeros((6, 6)), s["h"][k]
            P = Ph @ P_plus @ Ph.T + s["M"][k]                     # eq. (4)
            z = Ph @ z_plus + P @ s["a"][k] + s["b"][k]            # eq. (5)
            D = H @ P @ H
            G[k], eps = P @ H / D, T[k] - H @ z
            nu[k] = eps / D
            P_plus, z_plus = (np.eye(6) - np.outer(G[k], H)) @ P, z + G[k] * eps
        ddth, alpha = np.zeros(n + 2), self.alpha_base
        for k in range(n, 0, -1):                                  # eq. (6)
            alpha_plus = Phi(s["l"][k]).T @ alpha
            ddth[k] = nu[k] - G[k] @ alpha_plus
            alpha = alpha_plus + s["h"][k] * ddth[k] + s["a"][k]
        return self._j(ddth), (-self.mu * np.asarray(tau) - T_spring - TB2) / self.B
