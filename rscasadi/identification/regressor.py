"""The inverse dynamics as a linear function of the parameters, and its identifiable part.

With the gear ratios, eps and gravity fixed, both outputs of the inverse dynamics are linear in
p_lin (the inertial parameters of every body, k1, k3, d, b, c of every joint; see
rscasadi.model.parameters):

    [tau; T] = Y(theta, phi, dtheta, dphi, ddtheta, ddphi) p_lin + y0

tau is the motor torque (eq. 22), T the SEA torque the links require (eq. 26). y0 holds the
contribution of parameters declared `known` (held at their nominal values); with none, y0 = 0.
A further linear relation ties the two: the link equations are driven by the spring, so
T(state) - T_spring(state) = (Y_T - Y_spring) p_lin = 0 for every dynamically consistent
sample; `spring_regressor` gives Y_spring.

Base parameters: the columns of Y over random samples, equilibrated, then a rank-revealing QR
with column pivoting (scipy.linalg.qr): beta = p_I + K p_D, where p_I are the independent
(pivot) parameters and p_D those whose columns are combinations of them.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import casadi as ca
import numpy as np
import scipy.linalg

from rscasadi.errors import InvalidArgument
from rscasadi.model.parameters import n_linear

STATE_ACC = ["theta", "phi", "dtheta", "dphi", "ddtheta", "ddphi"]


CHUNK = 256          # samples per evaluation of a mapped Function (built once per Function)
_MAPPED: dict = {}   # id(Function) -> (Function, its map over CHUNK samples)


def over_samples(f: ca.Function, *args) -> list:
    """f's outputs over the columns of args (each n_i x count) as numpy arrays (rows x count *
    cols: the samples side by side, as Function.map gives them), through one map over CHUNK
    samples built once per f (the last chunk padded): a map built per call cost 0.12 s each on
    the Panda's regressor, more than evaluating it."""
    if id(f) not in _MAPPED:
        if len(_MAPPED) >= 32:
            _MAPPED.pop(next(iter(_MAPPED)))
        _MAPPED[id(f)] = (f, f.map(CHUNK))
    mapped = _MAPPED[id(f)][1]
    count = np.shape(args[0])[1]
    parts: list = [[] for _ in range(f.n_out())]
    for start in range(0, count, CHUNK):
        stop = min(start + CHUNK, count)
        chunk = [np.asarray(a, float)[:, start:stop] for a in args]
        if stop - start < CHUNK:
            chunk = [np.pad(c, ((0, 0), (0, CHUNK - c.shape[1])), mode="edge") for c in chunk]
        outs = mapped(*chunk)
        for k, out in enumerate([outs] if f.n_out() == 1 else outs):
            cols = f.size2_out(k) * (stop - start)
            parts[k].append(np.array(out.nonzeros()).reshape(out.shape, order="F")[:, :cols] if out.is_dense()
                            else np.array(out)[:, :cols])
    return [np.hstack(p) for p in parts]


def regressor(arm, known=(), reduced: bool = False) -> ca.Function:
    """theta, phi, dtheta, dphi, ddtheta, ddphi -> Y (2n x n_free), y0 (2n) with
    [tau; T] = Y p_free + y0; p_free are the linear parameters not in `known`.
    reduced: the same for the DLR/Spong reduced model.  Built once per arm and choice."""
    return _regressor(arm, tuple(known), reduced)


@functools.lru_cache(maxsize=16)
def _regressor(arm, known: tuple, reduced: bool) -> ca.Function:
    names, nominal = arm.parameters()
    n_lin = n_linear(arm.model)
    free = [i for i in range(n_lin) if names[i] not in set(known)]
    p = ca.SX.sym("p", n_lin)
    full = ca.vertcat(p, ca.DM(nominal[n_lin:]))                        # gravity at its nominal value
    args = [ca.SX.sym(s, arm.n) for s in STATE_ACC]
    inverse = arm.reduced_inverse_dynamics if reduced else arm.inverse_dynamics
    tau, T = inverse(parametric=True)(*args, full)
    out = ca.vertcat(tau, T)
    Y = ca.jacobian(out, p[free])
    fixed = ca.DM(nominal[:n_lin])
    fixed[free] = 0
    y0 = ca.substitute(out, p, fixed)
    return ca.Function("regressor", args, [ca.densify(ca.substitute(Y, p, fixed)), y0], STATE_ACC, ["Y", "y0"])


@functools.lru_cache(maxsize=16)
def spring_regressor(arm) -> ca.Function:
    """theta, phi, dtheta, dphi -> Y_spring (n x n_lin): T_spring = k1 psi + k3 psi^3 + d dpsi = Y_spring p_lin."""
    n, names = arm.n, arm.parameters()[0]
    theta, phi, dtheta, dphi = (ca.SX.sym(s, n) for s in STATE_ACC[:4])
    psi, dpsi = phi - theta, dphi - dtheta
    Y = ca.SX.zeros(n, n_linear(arm.model))
    for j, jt in enumerate(arm.model.joints):
        for attr, value in (("sea.k1", psi[j]), ("sea.k3", psi[j] ** 3), ("sea.d", dpsi[j])):
            Y[j, names.index(f"{jt.name}.{attr}")] = value
    return ca.Function("spring_regressor", [theta, phi, dtheta, dphi], [Y], STATE_ACC[:4], ["Y_spring"])


def random_samples(arm, count: int, rng) -> list:
    """Random states and accelerations (n, count) each, for the structure of Y."""
    n = arm.n
    theta = rng.uniform(-np.pi, np.pi, (n, count))
    return [theta, theta + rng.normal(0, 0.05, (n, count)), rng.normal(0, 2, (n, count)),
            rng.normal(0, 2, (n, count)), rng.normal(0, 5, (n, count)), rng.normal(0, 5, (n, count))]


ROW_KINDS = ("tau", "spring", "T")


def stacked(arm, samples, kinds=("tau", "spring"), reduced: bool = False) -> np.ndarray:
    """The rows of `kinds` of every sample stacked: tau (the motor torques), spring (T - T_spring,
    the link equations with the spring as their torque), T (the link torques): the matrix whose
    column space identification from logs with those rows works in."""
    count = samples[0].shape[1]
    Y = over_samples(regressor(arm, reduced=reduced), *samples)[0]          # (2n, count * n_lin)
    n, n_lin = arm.n, n_linear(arm.model)
    Y = Y.reshape(2 * n, count, n_lin)                                    # [row, sample, column]
    rows = []
    for kind in kinds:
        if kind == "tau":
            rows.append(Y[:n])
        elif kind == "spring":
            Ys = over_samples(spring_regressor(arm), *samples[:4])[0].reshape(n, count, n_lin)
            rows.append(Y[n:] - Ys)
        elif kind == "T":
            rows.append(Y[n:])
        else:
            raise InvalidArgument(f"stacked: row kind {kind!r} is none of {ROW_KINDS}")
    return np.concatenate(rows, axis=0).transpose(1, 0, 2).reshape(-1, n_lin)


@dataclass
class BaseParameters:
    """beta = P p_lin: P[:, independent] = 1, P[:, dependent] = K."""
    names: list
    independent: np.ndarray
    dependent: np.ndarray
    K: np.ndarray
    unidentifiable: list            # parameters whose column is zero: no effect on any row

    @property
    def P(self) -> np.ndarray:
        P = np.zeros((len(self.independent), len(self.names)))
        P[np.arange(len(self.independent)), self.independent] = 1.0
        P[:, self.dependent] = self.K
        return P

    @property
    def rank(self) -> int:
        return len(self.independent)

    def explain(self, tol: float = 1e-9) -> list[str]:
        """Each base parameter as a combination of physical ones."""
        lines = []
        for i, col in enumerate(self.independent):
            terms = [self.names[col]] + [f"{'+' if k > 0 else '-'} {abs(k):.6g} {self.names[d]}"
                                         for k, d in zip(self.K[i], self.dependent) if abs(k) > tol]
            lines.append(f"beta_{i + 1} = " + " ".join(terms))
        return lines

    def functional(self, c) -> np.ndarray | None:
        """d with c . p_lin = d . beta for every p_lin, or None when c . p_lin is not identifiable."""
        c = np.asarray(c, float)
        d = c[self.independent]
        if np.max(np.abs(self.K.T @ d - c[self.dependent]), initial=0.0) > 1e-8 * max(1.0, np.max(np.abs(c))):
            return None
        return d


def base_of(A: np.ndarray, names: list, rtol: float = 1e-7) -> BaseParameters:
    """Base parameters of the columns of A: QR with column pivoting of the equilibrated matrix;
    columns whose pivot falls below rtol of the first are combinations of the others."""
    norms = np.linalg.norm(A, axis=0)
    zero = norms <= 1e-12 * norms.max()
    scale = np.where(zero, 1.0, norms)
    _, R, piv = scipy.linalg.qr(A / scale, mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    r = int(np.sum(diag > rtol * diag[0]))
    ind, dep = piv[:r], piv[r:]
    K = scipy.linalg.solve_triangular(R[:r, :r], R[:r, r:]) * scale[dep][None, :] / scale[ind][:, None]
    return BaseParameters(names, ind, dep, K, [names[i] for i in np.flatnonzero(zero)])


def base_parameters(arm, samples: int = 200, rng=None, rtol: float = 1e-9) -> BaseParameters:
    """The identifiable combinations of p_lin, from the rows of random samples (tau rows and the
    spring-driven link rows)."""
    rng = np.random.default_rng(0) if rng is None else rng
    W = stacked(arm, random_samples(arm, samples, rng))
    return base_of(W, arm.parameters()[0][:W.shape[1]], rtol)
