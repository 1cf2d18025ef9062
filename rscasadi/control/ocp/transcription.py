"""Direct collocation, stage by stage, so that a structure-exploiting solver (fatrop) sees the
optimal-control structure and a general one (IPOPT) is none the worse.

Stage k = 0..N-1 has the state x_k = (theta, phi, dtheta, dphi, [T], [design]) and the
"control" u_k = (tau_k, the collocation states of interval k, [their accelerations]).  The
constraints come in stage order:

    x_{k+1} - F(x_k, u_k) = 0           gap closing: the interval's end point (T, design carried)
    c_k(x_k, u_k) (=, <=) 0             collocation defects, SEA deflection limits, (stage 0) the start
    c_N(x_N)                            the end at rest (rest-to-rest problems)

Rest is the SEA's static equilibrium, stated as constraints (theta given, speeds zero, spring
torque = gravity torque), so it holds for any designed or swept spring.  The mesh is the vector
of interval fractions w (sum 1, h_k = T w_k), an NLP parameter: refining a mesh with the same N
reuses the compiled NLP.  NLP parameters P = (theta_start, theta_end, duration, effort_weight,
objective scale, w, [theta_ref], [fixed model parameters]).
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from ...dynamics.arm import Arm
from ...model.parameters import names as parameter_names, nominal as parameter_nominal
from .problem import Problem


class Transcription:
    def __init__(self, problem: Problem, arm: Arm, N: int | None = None):
        self.p, self.model = problem, arm.model
        self.n, self.N = arm.n, N or problem.intervals
        self.design, self.fixed = list(problem.design), list(problem.parameters)
        free = self.design + self.fixed
        self.arm = Arm(arm.model, free=free) if free else arm
        n = self.n
        if problem.method == "hermite-simpson":
            self.fractions = np.array([0.5, 1.0])                            # midpoint, end
        else:
            tau = ca.collocation_points(problem.degree, problem.method)
            self.C, self.D, _ = (np.array(m) for m in ca.collocation_coeff(tau))
            self.fractions = np.array(tau)
        self.m = len(self.fractions)
        self.n_acc = {"explicit": 0, "implicit": 3 if problem.method == "hermite-simpson" else self.m}[problem.dynamics]
        self.nT = 1 if problem.objective == "min_time" else 0
        self.nz = self.nT + len(self.design)                                 # carried constants
        self.nx = 4 * n + self.nz
        self.nu = n + 4 * n * self.m + 2 * n * self.n_acc
        self.tracking = problem.objective == "tracking"
        self.acc_scale = self._acceleration_scale()
        self.stage = self._stage_function()

    # -- the pieces of one stage ------------------------------------------------------------
    def _call(self, name, *args, pf=None):
        f = getattr(self.arm, name)(parametric=pf is not None)
        return f(*args, *([] if pf is None else [pf]))

    def _f(self, x, u, pf):
        q = ca.vertsplit(x, self.n)
        return ca.vertcat(q[2], q[3], *self._call("forward_dynamics", *q, u, pf=pf))

    def _residual(self, x, a, u, pf):
        """Implicit dynamics: M ddq + c - Q = 0 (MODEL.md section 3) from the inverse dynamics; the
        rotor rows mu (u - tau_id) are generalized forces like the link rows (N m)."""
        n, q = self.n, ca.vertsplit(x, self.n)
        tau_id, T_id = self._call("inverse_dynamics", *q, a[:n], a[n:], pf=pf)
        mu = ca.DM(self.model.column("gear_ratio"))
        phys = self.arm.physics if pf is None else self.arm._physics_of(pf)
        return ca.vertcat(T_id - self.arm.sea_torque(*q, phys=phys), mu * (u - tau_id))

    def rest_residual(self, x, theta, pf):
        """At rest at theta in the SEA's static equilibrium: theta, speeds 0, T_K(psi) = gravity torque."""
        n, q = self.n, ca.vertsplit(x[:4 * self.n], self.n)
        z = ca.DM.zeros(n)
        T_g = self._call("inverse_dynamics", q[0], q[1], z, z, z, z, pf=pf)[1]
        phys = self.arm.physics if pf is None else self.arm._physics_of(pf)
        return ca.vertcat(q[0] - theta, q[2], q[3], self.arm.sea_torque(q[0], q[1], z, z, phys=phys) - T_g)

    def _pf(self, design, p_fixed):
        """The free parameters' values, in the order of Arm(free=design + fixed); None if none."""
        parts = ([design] if self.design else []) + ([p_fixed] if self.fixed else [])
        return ca.vertcat(*parts) if parts else None

    def _acceleration_scale(self):
        """Implicit form: accelerations are variables A = s * A_scaled, s per coordinate about the
        largest acceleration the motor torque limit can cause, so every variable is O(1)."""
        if not self.n_acc:
            return np.ones(0)
        z, n = np.zeros(self.n), self.n
        theta = self.p.theta_start if self.p.theta_start is not None else z
        M = np.array(self.arm.mass_matrix()(theta, theta) if not self.arm.free else
                     Arm(self.model).mass_matrix()(theta, theta))
        tau = np.array([jt.limits.get("tau", 1.0) for jt in self.model.joints]) * self.model.column("gear_ratio")
        k_psi = np.array([jt.k1 * jt.limits.get("psi", 0.1) for jt in self.model.joints])
        force = np.concatenate([k_psi, tau + k_psi])
        acc = np.abs(np.linalg.solve(M, np.diag(force))).max(axis=1)
        return np.maximum(acc, 1e-3)

    def _stage_function(self) -> ca.Function:
        """(x_k, u_k, w_k, P) -> (x_{k+1} target, path constraints, effort): SX, mapped over N."""
        n, m, p = self.n, self.m, self.p
        x, u, w = ca.SX.sym("x", self.nx), ca.SX.sym("u", self.nu), ca.SX.sym("w")
        dur, pfix = ca.SX.sym("duration"), ca.SX.sym("p_fixed", len(self.fixed))
        q, z = x[:4 * n], x[4 * n:]
        T = z[0] if self.nT else dur
        pf = self._pf(z[self.nT:self.nz] if self.design else None, pfix)
        tau = u[:n]
        Xc = ca.reshape(u[n:n + 4 * n * m], 4 * n, m)
        A = ca.reshape(u[n + 4 * n * m:], 2 * n, self.n_acc) * ca.repmat(ca.DM(self.acc_scale), 1, self.n_acc) \
            if self.n_acc else None
        h = T * w
        defects = []

        def f_at(xj, j):
            if A is None:
                return self._f(xj, tau, pf)
            defects.append(self._residual(xj, A[:, j], tau, pf))
            return ca.vertcat(xj[2 * n:], A[:, j])

        if p.method == "hermite-simpson":
            xm, xe = Xc[:, 0], Xc[:, 1]
            fs, fm, fe = f_at(q, 0), f_at(xm, 1), f_at(xe, 2)
            defects += [xe - q - h / 6 * (fs + 4 * fm + fe), xm - (q + xe) / 2 - h / 8 * (fs - fe)]
            x_end = xe
        else:
            P = [q] + [Xc[:, j] for j in range(m)]
            for j in range(m):
                defects.append(sum(self.C[r, j] * P[r] for r in range(m + 1)) - h * f_at(P[j + 1], j))
            x_end = sum(self.D[r, 0] * P[r] for r in range(m + 1))
        points = [Xc[:, j] for j in range(m)] + ([q] if p.method == "legendre" else [])
        psi = [pt[n:2 * n] - pt[:n] for pt in points]                          # SEA deflection
        return ca.Function("stage", [x, u, w, dur, pfix],
                           [ca.vertcat(x_end, z), ca.vertcat(*defects, *psi), h * ca.sumsqr(tau)],
                           ["x", "u", "w", "duration", "p_fixed"], ["x_next", "path", "effort"])

    # -- the NLP ----------------------------------------------------------------------------
    def parameter_layout(self):
        n, N = self.n, self.N
        sizes = [("theta_start", n), ("theta_end", n), ("duration", 1), ("effort_weight", 1), ("scale", 1),
                 ("w", N), ("theta_ref", n * N if self.tracking else 0), ("p_fixed", len(self.fixed))]
        out, i = {}, 0
        for key, size in sizes:
            out[key] = slice(i, i + size)
            i += size
        return out, i

    def nlp(self):
        """The NLP dict and its constant bounds on g; variables and constraints in stage order."""
        n, N, p = self.n, self.N, self.p
        layout, n_par = self.parameter_layout()
        P = ca.MX.sym("P", n_par)
        par = {k: P[s] for k, s in layout.items()}
        w = ca.MX.sym("w", N * (self.nx + self.nu) + self.nx)              # stage by stage
        body = ca.reshape(w[:N * (self.nx + self.nu)], self.nx + self.nu, N)
        X, U = ca.horzcat(body[:self.nx, :], w[N * (self.nx + self.nu):]), body[self.nx:, :]
        x_next, path, effort = self.stage.map(N, "serial")(X[:, :N], U, ca.reshape(par["w"], 1, N),
                                                           par["duration"], par["p_fixed"])
        gap = X[:, 1:] - x_next
        design = lambda k: X[4 * n + self.nT:, k] if self.design else None
        pf0, pfN = self._pf(design(0), par["p_fixed"]), self._pf(design(N), par["p_fixed"])
        start = self.rest_residual(X[:, 0], par["theta_start"], pf0)
        blocks = ca.vertcat(gap, path)
        g = [blocks[:, 0], start, ca.vec(blocks[:, 1:])]
        n_path = path.shape[0]
        n_psi = n * (self.m + (1 if p.method == "legendre" else 0))
        psi_max = np.array([jt.limits.get("psi", np.inf) for jt in self.model.joints])
        stage_lo = np.concatenate([np.zeros(self.nx + n_path - n_psi), np.tile(-psi_max, n_psi // n)])
        stage_hi = np.concatenate([np.zeros(self.nx + n_path - n_psi), np.tile(psi_max, n_psi // n)])
        lbg = [stage_lo, np.zeros(4 * n), np.tile(stage_lo, N - 1)]
        ubg = [stage_hi, np.zeros(4 * n), np.tile(stage_hi, N - 1)]
        if not self.tracking:
            g.append(self.rest_residual(X[:, N], par["theta_end"], pfN))
            lbg.append(np.zeros(4 * n)), ubg.append(np.zeros(4 * n))
        if p.method == "legendre":
            g.append(X[n:2 * n, N] - X[:n, N])
            lbg.append(-psi_max), ubg.append(psi_max)
        total_effort = ca.sum2(effort)
        if p.objective == "min_time":
            f = X[4 * n, 0] + par["effort_weight"] * total_effort
        elif p.objective == "min_effort":
            f = total_effort
        else:
            h = par["duration"] * ca.reshape(par["w"], 1, N)
            e = X[:n, 1:] - ca.reshape(par["theta_ref"], n, N)
            f = ca.sum2(h * ca.sum1(e ** 2)) / ca.fmax(par["effort_weight"], 1e-12) + total_effort
        return {"x": w, "f": par["scale"] * f, "g": ca.vertcat(*g), "p": P}, np.concatenate(lbg), np.concatenate(ubg)

    def structure(self) -> dict:
        """fatrop's manual structure: per stage nx, nu and the number of non-gap constraints."""
        n, N = self.n, self.N
        n_path = self.stage.size1_out(1)
        ng = [n_path + 4 * n] + [n_path] * (N - 1)
        ng.append((0 if self.tracking else 4 * n) + (n if self.p.method == "legendre" else 0))
        return {"structure_detection": "manual", "N": N, "nx": [self.nx] * (N + 1),
                "nu": [self.nu] * N + [0], "ng": ng}

    def bounds(self, max_duration: float):
        """Simple bounds: theta and dphi limits on every state point, tau limits, T and design boxes."""
        n, N, jts = self.n, self.N, self.model.joints
        lo_q, hi_q = np.full(4 * n, -np.inf), np.full(4 * n, np.inf)
        for j, jt in enumerate(jts):
            if "theta" in jt.limits:
                lo_q[j], hi_q[j] = jt.limits["theta"]
            if "dphi" in jt.limits:
                lo_q[3 * n + j], hi_q[3 * n + j] = -jt.limits["dphi"], jt.limits["dphi"]
        lo_z = ([1e-3] if self.nT else []) + [b[0] for b in self.p.design.values()]
        hi_z = ([max_duration] if self.nT else []) + [b[1] for b in self.p.design.values()]
        tau_max = np.array([jt.limits.get("tau", np.inf) for jt in jts])
        lo_u = np.concatenate([-tau_max, np.tile(lo_q, self.m), np.full(2 * n * self.n_acc, -np.inf)])
        hi_u = np.concatenate([tau_max, np.tile(hi_q, self.m), np.full(2 * n * self.n_acc, np.inf)])
        lo_x, hi_x = np.concatenate([lo_q, lo_z]), np.concatenate([hi_q, hi_z])
        lb = np.concatenate([np.tile(np.concatenate([lo_x, lo_u]), N), lo_x])
        ub = np.concatenate([np.tile(np.concatenate([hi_x, hi_u]), N), hi_x])
        return lb, ub

    def parameters(self, theta_start, theta_end, duration, effort_weight, w, theta_ref=None, p_fixed=(), scale=1.0):
        layout, n_par = self.parameter_layout()
        P = np.zeros(n_par)
        for key, value in (("theta_start", theta_start), ("theta_end", theta_end), ("duration", duration),
                           ("effort_weight", effort_weight), ("scale", scale), ("w", w),
                           ("theta_ref", theta_ref), ("p_fixed", p_fixed)):
            if value is not None and layout[key].stop > layout[key].start:
                P[layout[key]] = np.ravel(value, order="F")
        return P

    # -- guesses and solutions --------------------------------------------------------------
    def pack(self, Xs, Xc, U, T, design, A=None):
        """Stage-ordered vector from Xs (4n, N+1), Xc (4n, m N), U (n, N), T, design, A (2n, n_acc N)."""
        n, N = self.n, self.N
        z = np.concatenate([[T] if self.nT else [], design])
        X = np.vstack([Xs, np.repeat(z[:, None], N + 1, axis=1)])
        parts = [U, Xc.reshape(4 * n, N, self.m).transpose(0, 2, 1).reshape(4 * n * self.m, N, order="F")]
        if self.n_acc:
            As = (A.reshape(2 * n, N, self.n_acc) / self.acc_scale[:, None, None])
            parts.append(As.transpose(0, 2, 1).reshape(2 * n * self.n_acc, N, order="F"))
        Ustage = np.vstack(parts)
        return np.concatenate([np.vstack([X[:, :N], Ustage]).ravel("F"), X[:, N]])

    def unpack(self, w) -> dict:
        n, N, m = self.n, self.N, self.m
        w = np.asarray(w, float).ravel()
        body = w[:N * (self.nx + self.nu)].reshape(self.nx + self.nu, N, order="F")
        X = np.hstack([body[:self.nx], w[N * (self.nx + self.nu):, None]])
        Uall = body[self.nx:]
        Xc = Uall[n:n + 4 * n * m].reshape(4 * n, m, N, order="F").transpose(0, 2, 1).reshape(4 * n, N * m)
        z = X[4 * n:, 0]
        return {"Xs": X[:4 * n], "U": Uall[:n], "Xc": Xc, "T": float(z[0]) if self.nT else None,
                "design": z[self.nT:]}
