"""The complete model the Pinocchio way, as an outside reference (optional: `pip install pin`).

Every rotor is a separate revolute joint of a 3n-joint tree (each joint's two rotors added
before its link, so the tree stays in depth-first order, which Pinocchio's CRBA needs).
The gear constraint q_tree = G q, with fast-rotor angle -mu phi, projects the tree's
dynamics onto q = (theta, phi): M = G^T M_tree G, c = G^T rnea(q_tree, G dq, 0).
"""
from __future__ import annotations

import numpy as np
import pinocchio as pin


class PinocchioRoute:
    def __init__(self, model):
        self.arm_model, n = model, model.n
        self.model = pin.Model()
        self.model.gravity.linear = np.asarray(model.gravity, float)
        parent, G = 0, np.zeros((3 * n, 2 * n))
        for j, jt in enumerate(model.joints):
            placement = pin.SE3(jt.R, np.asarray(jt.origin_xyz, float))
            for k, (body, col, gear) in enumerate(((jt.slow_rotor, n + j, 1.0), (jt.fast_rotor, n + j, -jt.gear_ratio),
                                                   (jt.link, j, 1.0))):
                jid = self.model.addJoint(parent, pin.JointModelRZ(), placement, f"joint{j}_{k}")
                self.model.appendBodyToJoint(jid, pin.Inertia(body.mass, np.asarray(body.com, float), body.inertia),
                                             pin.SE3.Identity())
                G[jid - 1, col] = gear
            parent = jid                                   # the link carries the next joint
        self.G, self.data = G, self.model.createData()
        cols = {a: model.column(a) for a in ("k1", "k3", "d", "b", "c", "eps", "gear_ratio")}
        self._cols = cols

    def mass_bias(self, theta, phi, dtheta, dphi):
        q, v = self.G @ np.r_[theta, phi], self.G @ np.r_[dtheta, dphi]
        M = pin.crba(self.model, self.data, q)
        M = np.triu(M) + np.triu(M, 1).T                  # crba fills the upper triangle
        c = pin.rnea(self.model, self.data, q, v, np.zeros(self.model.nv))
        return self.G.T @ M @ self.G, self.G.T @ c

    def forward_dynamics(self, theta, phi, dtheta, dphi, tau):
        M, c = self.mass_bias(theta, phi, dtheta, dphi)
        k = self._cols
        psi, dpsi = np.asarray(phi) - theta, np.asarray(dphi) - dtheta
        T = k["k1"] * psi + k["k3"] * psi ** 3 + k["d"] * dpsi
        TB2 = k["b"] * dphi + k["c"] * np.tanh(np.asarray(dphi) / k["eps"])
        L = np.linalg.cholesky(M)                          # M = L L^T, then two triangular solves
        ddq = np.linalg.solve(L.T, np.linalg.solve(L, np.r_[T, -T - TB2 - k["gear_ratio"] * tau] - c))
        n = self.arm_model.n
        return ddq[:n], ddq[n:]
