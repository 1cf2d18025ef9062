"""An independent derivation of the complete model: Lagrange's equations from every body's
kinetic and potential energy.  It shares no code with the recursions: it builds each body's
pose from rotation matrices, differentiates positions and rotations with CasADi's AD, and
reads only the raw fields of the model file."""
import casadi as ca
import numpy as np


def _rot(axis, a):
    c, s = ca.cos(a), ca.sin(a)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = ca.SX.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


class Lagrange:
    def __init__(self, model):
        n, self.model = model.n, model
        q, dq = ca.SX.sym("q", 2 * n), ca.SX.sym("dq", 2 * n)
        g = ca.DM(model.gravity)
        KE, PE = 0, 0
        R_p, o_p = ca.SX.eye(3), ca.SX.zeros(3)
        self._q, self._links = q, [(R_p, o_p)]                  # each body's pose: base, then the links
        for j, jt in enumerate(model.joints):
            r, p, y = (float(v) for v in jt.origin_rpy)
            R_J = R_p @ _rot(2, y) @ _rot(1, p) @ _rot(0, r)
            o_J = o_p + R_p @ ca.DM(jt.origin_xyz)
            angles = [q[j], q[n + j], -jt.gear_ratio * q[n + j]]
            for body, angle in zip((jt.link, jt.slow_rotor, jt.fast_rotor), angles):
                R = R_J @ _rot(2, angle)
                c = o_J + R @ ca.DM(body.com)
                v = ca.jtimes(c, q, dq)
                W = ca.reshape(ca.jtimes(ca.vec(R), q, dq), 3, 3) @ R.T          # dR/dt R^T = w~
                w = ca.vertcat(W[2, 1], W[0, 2], W[1, 0])
                KE += 0.5 * body.mass * ca.dot(v, v) + 0.5 * w.T @ R @ ca.DM(body.inertia) @ R.T @ w
                PE += -body.mass * ca.dot(g, c)
            R_p, o_p = R_J @ _rot(2, q[j]), o_J
            self._links.append((R_p, o_p))
        M = ca.hessian(KE, dq)[0]
        c = ca.jacobian(ca.gradient(KE, dq), q) @ dq - ca.gradient(KE, q) + ca.gradient(PE, q)
        self.f = ca.Function("lagrange", [q, dq], [M, c, KE + PE])

    def _Q(self, theta, phi, dtheta, dphi, tau):
        cols = {a: self.model.column(a) for a in ("k1", "k3", "d", "b", "c", "eps", "gear_ratio")}
        psi, dpsi = phi - theta, dphi - dtheta
        T = cols["k1"] * psi + cols["k3"] * psi ** 3 + cols["d"] * dpsi
        TB2 = cols["b"] * dphi + cols["c"] * np.tanh(dphi / cols["eps"])
        return T, TB2, cols["gear_ratio"]

    def mass_bias(self, theta, phi, dtheta, dphi):
        M, c, _ = self.f(np.r_[theta, phi], np.r_[dtheta, dphi])
        return np.array(M), np.array(c).ravel()

    def forward(self, theta, phi, dtheta, dphi, tau):
        M, c = self.mass_bias(theta, phi, dtheta, dphi)
        T, TB2, mu = self._Q(theta, phi, dtheta, dphi, tau)
        ddq = np.linalg.solve(M, np.r_[T, -T - TB2 - mu * tau] - c)
        return ddq[:self.model.n], ddq[self.model.n:]

    def inverse(self, theta, phi, dtheta, dphi, ddtheta, ddphi):
        """(tau, T) by the paper's equations of motion (docs/user-guide/model.md)."""
        M, c = self.mass_bias(theta, phi, dtheta, dphi)
        lhs = M @ np.r_[ddtheta, ddphi] + c
        T, TB2, mu = self._Q(theta, phi, dtheta, dphi, 0)
        n = self.model.n
        return -(lhs[n:] + T + TB2) / mu, lhs[:n]

    def energy(self, theta, phi, dtheta, dphi):
        psi = np.asarray(phi) - theta
        spring = np.sum(0.5 * self.model.column("k1") * psi ** 2 + 0.25 * self.model.column("k3") * psi ** 4)
        return float(self.f(np.r_[theta, phi], np.r_[dtheta, dphi])[2]) + spring

    def wrench_force(self, body, p_f):
        """theta, phi -> the generalized force of a wrench [force; moment] (world axes) at a point
        p_f of `body` (0 base, j the link of joint j - 1): the virtual work of the
        force on the point's velocity and of the moment on the body's angular velocity."""
        q, n = self._q, self.model.n
        R_b, o_b = self._links[body]
        point = o_b + R_b @ ca.DM(p_f)
        dq = ca.SX.sym("dq", 2 * n)
        W = ca.reshape(ca.jtimes(ca.vec(R_b), q, dq), 3, 3) @ R_b.T
        w = ca.vertcat(W[2, 1], W[0, 2], W[1, 0])
        Jv, Jw = ca.jacobian(point, q), ca.jacobian(w, dq)
        f = ca.SX.sym("f", 6)
        return ca.Function("wrench", [q, f], [Jv.T @ f[:3] + Jw.T @ f[3:]])

    def forward_with_wrench(self, theta, phi, dtheta, dphi, tau, Qw):
        """The forward dynamics with the generalized force Qw (2n) of a wrench added."""
        M, c = self.mass_bias(theta, phi, dtheta, dphi)
        T, TB2, mu = self._Q(theta, phi, dtheta, dphi, tau)
        ddq = np.linalg.solve(M, np.r_[T, -T - TB2 - mu * tau] + Qw - c)
        return ddq[:self.model.n], ddq[self.model.n:]
