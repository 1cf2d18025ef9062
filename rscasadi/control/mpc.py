"""Nonlinear MPC on the complete model, generated to C (`rscasadi mpc PROBLEM.toml --out DIR`).

Real-time iteration (one Gauss-Newton SQP step per sample, Diehl et al.), single shooting on
the complete model: the torque plan U (n x N, held on each of N intervals of length h) is
simulated from the measured state with `substeps` RK4 steps per interval, its sensitivities come
from the structured `step_jacobian` (codegen.generate.step_functions), and the condensed QP in
dU (box constraints: the motor-torque limits) is solved by a fixed number of projected-Newton
iterations (Bertsekas), so the C has no data-dependent loops and allocates nothing.

Cost (per interval end k = 1..N): w_theta |theta_k - theta_ref_k|^2 + w_dtheta |dtheta_k -
dtheta_ref_k|^2 + w_tau |tau_k|^2, and a penalty w_limits (|c| - 0.9 c_max)^2 on the SEA
deflection psi and the slow-side speed dphi beyond 90 % of their limits (Gauss-Newton on the
part active at the linearisation point).

Problem file (TOML):

    model = "arm3.toml"
    trajectory = "trajectory_arm3.toml"  # the reference of the example and the closed-loop study
    sample_time = 0.001                  # s, one mpc_step per sample
    horizon = 10                         # intervals N
    interval = 0.01                      # s, h: the torque is held on each interval
    substeps = 5                         # RK4 steps per interval (d/k1 ~ 1 ms: keep h/substeps <= 2 ms)
    newton_iterations = 6                # of the box QP, per sample
    [weights]
    theta = 1e5
    dtheta = 1.0
    tau = 1e-3
    limits = 1e5

Generated (DIR): `mpc_rti.c` (CasADi: mpc_rti(x, reference, U) -> tau, U_next and
mpc_hold(x) -> U), `rscasadi_mpc.c` and `rscasadi_mpc.h` (the controller: static buffers,
`mpc_init(x_measured)`, `mpc_step(x_measured, reference, tau_out)`), `librscasadi_mpc.so`,
`manifest.json`.  reference is 2n x N, column-major: theta_ref then dtheta_ref at t + k h.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from ..dynamics.arm import Arm, load
from ..model.modelfile import field_checker, read_toml

TOP = {"model", "trajectory", "sample_time", "horizon", "interval", "substeps", "newton_iterations", "weights"}
WEIGHTS = {"theta": 1e5, "dtheta": 1.0, "tau": 1e-3, "limits": 1e5}
SOFT = 0.9                   # penalties start at this fraction of the psi and dphi limits


@dataclass
class MPCProblem:
    path: Path
    model_path: Path
    trajectory: Path | None = None
    sample_time: float = 1e-3
    horizon: int = 10
    interval: float = 0.01
    substeps: int = 5
    newton_iterations: int = 6
    weights: dict = field(default_factory=lambda: dict(WEIGHTS))


def load_mpc_problem(path) -> MPCProblem:
    path = Path(path)
    d = read_toml(path, "MPC problem")

    fail = field_checker(path, d, TOP)
    if not isinstance(d.get("model"), str):
        fail("model", "missing, or not the path of a model file")
    p = MPCProblem(path, (path.parent / d["model"]).resolve())
    if "trajectory" in d:
        if not isinstance(d["trajectory"], str):
            fail("trajectory", "expected the path of a trajectory file")
        p.trajectory = (path.parent / d["trajectory"]).resolve()
    for key in ("sample_time", "interval"):
        v = d.get(key, getattr(p, key))
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v <= 0:
            fail(key, f"must be a positive number, got {v!r}")
        setattr(p, key, float(v))
    for key, lo in (("horizon", 1), ("substeps", 1), ("newton_iterations", 1)):
        v = d.get(key, getattr(p, key))
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            fail(key, f"must be an integer >= {lo}, got {v!r}")
        setattr(p, key, v)
    w = d.get("weights", {})
    if not isinstance(w, dict):
        fail("weights", "expected a table")
    for key, v in w.items():
        if key not in WEIGHTS:
            fail(f"weights.{key}", f"unknown weight (allowed: {', '.join(WEIGHTS)})")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
            fail(f"weights.{key}", f"must be a number >= 0, got {v!r}")
        p.weights[key] = float(v)
    return p


def interval_functions(arm: Arm, h: float, substeps: int) -> ca.Function:
    """(x, tau) -> (x after h, A = dx/dx0, B = dx/dtau): `substeps` RK4 steps and their
    structured Jacobians chained (A = A_s ... A_1, B = A_s (...) B_1 + ... + B_s)."""
    from ..codegen.generate import step_functions
    n = arm.n
    step, step_jac = step_functions(arm)
    x, tau = ca.MX.sym("x", 4 * n), ca.MX.sym("tau", n)
    A, B, z = ca.MX.eye(4 * n), ca.MX.zeros(4 * n, n), x
    for _ in range(substeps):
        Ai, Bi = step_jac(z, tau, h / substeps)
        A, B, z = ca.mtimes(Ai, A), ca.mtimes(Ai, B) + Bi, step(z, tau, h / substeps)
    return ca.Function("interval", [x, tau], [z, A, B])


def rti_function(arm: Arm, p: MPCProblem) -> ca.Function:
    """mpc_rti(x, reference, U) -> (tau, U_next): one Gauss-Newton SQP step, condensed QP."""
    n, N, nx = arm.n, p.horizon, 4 * arm.n
    F = interval_functions(arm, p.interval, p.substeps)
    tau_max = np.array([jt.limits.get("tau", 1e3) for jt in arm.model.joints])
    psi_max = np.array([jt.limits.get("psi", np.inf) for jt in arm.model.joints])
    dphi_max = np.array([jt.limits.get("dphi", np.inf) for jt in arm.model.joints])
    w = p.weights
    xm, ref, U = ca.MX.sym("x", nx), ca.MX.sym("reference", 2 * n, N), ca.MX.sym("U", n, N)
    H = w["tau"] * ca.MX.eye(n * N)
    g = w["tau"] * ca.vec(U)
    G, x = ca.MX.zeros(nx, n * N), xm                                   # G = dx_k/dU
    for k in range(N):
        x, A, B = F(x, U[:, k])
        G = ca.horzcat(ca.mtimes(A, G[:, :n * k]), B, ca.MX.zeros(nx, n * (N - k - 1)))
        for rows, target, weight in ((slice(0, n), ref[:n, k], w["theta"]), (slice(2 * n, 3 * n), ref[n:, k], w["dtheta"])):
            J = G[rows, :]
            H += weight * ca.mtimes(J.T, J)
            g += weight * ca.mtimes(J.T, x[rows] - target)
        for c, J, cmax in ((x[n:2 * n] - x[:n], G[n:2 * n, :] - G[:n, :], psi_max),
                           (x[3 * n:], G[3 * n:, :], dphi_max)):
            finite = np.isfinite(cmax)
            if not finite.any():
                continue
            soft = SOFT * np.where(finite, cmax, 1.0)
            active = (ca.fabs(c) > soft) * finite                       # beyond 90 %: penalised
            excess = active * (c - ca.sign(c) * soft)
            Ja = ca.mtimes(ca.diag(active), J)
            H += w["limits"] * ca.mtimes(Ja.T, Ja)
            g += w["limits"] * ca.mtimes(Ja.T, excess)
    lo, hi = -np.tile(tau_max, N) - ca.vec(U), np.tile(tau_max, N) - ca.vec(U)
    du = ca.MX.zeros(n * N)
    for _ in range(p.newton_iterations):                                # projected Newton on the box
        grad = ca.mtimes(H, du) + g
        fixed = ca.logic_or(ca.logic_and(du <= lo + 1e-12, grad > 0), ca.logic_and(du >= hi - 1e-12, grad < 0))
        free = 1 - fixed
        D = ca.diag(free)
        step = ca.solve(ca.mtimes(ca.mtimes(D, H), D) + ca.diag(fixed), free * grad, "ldl")
        du = ca.fmin(ca.fmax(du - step, lo), hi)
    U_next = U + ca.reshape(du, n, N)
    return ca.Function("mpc_rti", [xm, ref, U], [U_next[:, 0], U_next], ["x", "reference", "U"], ["tau", "U_next"])


def hold_function(arm: Arm, p: MPCProblem) -> ca.Function:
    """mpc_hold(x) -> U: the torque that holds the links where they are, over the horizon."""
    n = arm.n
    x = ca.SX.sym("x", 4 * n)
    z = ca.SX.zeros(n)
    tau = arm.inverse_dynamics()(x[:n], x[n:2 * n], z, z, z, z)[0]
    return ca.Function("mpc_hold", [x], [ca.repmat(tau, 1, p.horizon)], ["x"], ["U"])


WRAPPER_H = """/* rscasadi MPC for {model} ({n} joints): real-time iteration, generated by rscasadi mpc.
 * mpc_init once with the measured state, then mpc_step every {ts} s.  No allocation.
 * x: theta, phi, dtheta, dphi ({nx}); reference: {nref} values, column-major 2n x N: theta_ref
 * then dtheta_ref at t + k * {h} s, k = 1..{N}; tau_out: {n} motor torques. */
#ifndef RSCASADI_MPC_H
#define RSCASADI_MPC_H
#define MPC_NX {nx}
#define MPC_NU {n}
#define MPC_HORIZON {N}
#define MPC_NREF {nref}
int mpc_init(const double *x_measured);
int mpc_step(const double *x_measured, const double *reference, double *tau_out);
#endif
"""

WRAPPER_C = """#include "rscasadi_mpc.h"
#include "mpc_rti.h"

#define MAX(a, b) ((a) > (b) ? (a) : (b))
static casadi_real U[MPC_NU * MPC_HORIZON], U_next[MPC_NU * MPC_HORIZON];
static casadi_real w[MAX(mpc_rti_SZ_W, mpc_hold_SZ_W) + 1];
static casadi_int iw[MAX(mpc_rti_SZ_IW, mpc_hold_SZ_IW) + 1];

int mpc_init(const double *x_measured) {{
  const casadi_real *arg[mpc_hold_SZ_ARG + 1] = {{x_measured}};
  casadi_real *res[mpc_hold_SZ_RES + 1] = {{U}};
  return mpc_hold(arg, res, iw, w, 0);
}}

int mpc_step(const double *x_measured, const double *reference, double *tau_out) {{
  const casadi_real *arg[mpc_rti_SZ_ARG + 1] = {{x_measured, reference, U}};
  casadi_real *res[mpc_rti_SZ_RES + 1] = {{tau_out, U_next}};
  int flag = mpc_rti(arg, res, iw, w, 0);
  for (int i = 0; i < MPC_NU * MPC_HORIZON; ++i) U[i] = U_next[i];
  return flag;
}}
"""


def generate_mpc(problem_file, out, opt: str = "-O2", log=print) -> dict:
    """Write the MPC's C, header, library and manifest into `out` (whole or not at all)."""
    import subprocess
    from ..codegen import _compiler
    from ..files import fresh_directory
    p = load_mpc_problem(problem_file)
    arm = load(p.model_path)
    if p.interval / p.substeps > 2e-3:
        log(f"note: {p.interval / p.substeps * 1e3:.1f} ms RK4 steps: the SEA damping (d/k1 ~ 1 ms) may make them unstable")
    rti, hold = rti_function(arm, p), hold_function(arm, p)
    out = Path(out)
    with fresh_directory(out, "manifest.json") as tmp:
        gen = ca.CodeGenerator("mpc_rti.c", {"with_header": True})
        gen.add(rti)
        gen.add(hold)
        gen.generate(str(tmp) + "/")
        n = arm.n
        # the model's file name goes into a C comment: only characters that cannot end one
        model_name = re.sub(r"[^A-Za-z0-9._-]", "_", Path(arm.model.path).name)
        (tmp / "rscasadi_mpc.h").write_text(WRAPPER_H.format(model=model_name, n=n, nx=4 * n,
                                                           N=p.horizon, nref=2 * n * p.horizon, ts=p.sample_time,
                                                           h=p.interval))
        (tmp / "rscasadi_mpc.c").write_text(WRAPPER_C.format())
        cc = _compiler()
        log(f"compiling the MPC ({opt}) ...")
        run = subprocess.run([*cc, opt, "-std=c99", "-fPIC", "-shared", "mpc_rti.c", "rscasadi_mpc.c", "-o",
                              "librscasadi_mpc.so", "-lm"], cwd=tmp, capture_output=True, text=True)
        if run.returncode != 0:
            raise RuntimeError(f"compiling the MPC failed:\n{run.stderr[-2000:]}")
        manifest = {"model": str(p.model_path), "problem": str(p.path), "header": "rscasadi_mpc.h",
                    "library": "librscasadi_mpc.so", "sources": ["mpc_rti.c", "rscasadi_mpc.c"],
                    "api": {"mpc_init": ["x_measured"], "mpc_step": ["x_measured", "reference", "tau_out"]},
                    "sizes": {"x": 4 * n, "tau": n, "reference": [2 * n, p.horizon]},
                    "horizon": p.horizon, "interval": p.interval, "substeps": p.substeps,
                    "sample_time": p.sample_time, "newton_iterations": p.newton_iterations, "weights": p.weights,
                    "compiler": cc + [opt]}
        (tmp / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    log(f"wrote {out / 'librscasadi_mpc.so'}, rscasadi_mpc.h and manifest.json")
    return manifest


# ------------------------------------------------------------------ closed-loop evidence

def heavier_tip(arm: Arm, factor: float = 1.2) -> Arm:
    """The same arm with its last link's mass (and inertia) scaled: the plant of the mismatch study."""
    import dataclasses
    from ..model.modelfile import Body
    last = arm.model.joints[-1]
    link = Body(last.link.mass * factor, last.link.com, last.link.inertia * factor)
    joints = arm.model.joints[:-1] + (dataclasses.replace(last, link=link),)
    return Arm(dataclasses.replace(arm.model, joints=joints, name=arm.model.name + f"-tip-x{factor:g}"))


class CompiledMPC:
    """The generated C controller through ctypes: init(x), step(x, reference) -> tau, seconds."""

    def __init__(self, directory):
        import ctypes
        self.lib = ctypes.CDLL(str(Path(directory) / "librscasadi_mpc.so"))
        self.c_double_p = ctypes.POINTER(ctypes.c_double)

    def _p(self, a):
        return np.ascontiguousarray(a, float).ctypes.data_as(self.c_double_p)

    def init(self, x):
        assert self.lib.mpc_init(self._p(x)) == 0

    def step(self, x, reference):
        import time
        tau = np.zeros(len(x) // 4)
        x, ref = np.ascontiguousarray(x, float), np.ascontiguousarray(reference.T.ravel(), float)
        t0 = time.perf_counter()
        flag = self.lib.mpc_step(self._p(x), self._p(ref), tau.ctypes.data_as(self.c_double_p))
        return tau, time.perf_counter() - t0, flag


def closed_loop(problem_file, mpc_dir, duration: float | None = None, tip_factor: float = 1.2,
                log=print) -> dict:
    """The reference arm's controller on a plant with a heavier tip, at 1 kHz, encoders quantised
    (speeds by backward differences): feedforward alone, feedforward + motor-side PD, the C MPC.
    Returns per controller the tracking error (max, RMS), the largest limit violation and, for the
    MPC, its time per step."""
    from ..codegen import rk4
    from ..identification.synthetic import LINK_COUNTS, MOTOR_COUNTS       # the same encoders as the logs
    from .simulation import feedforward
    from .trajectory import load_trajectory
    p = load_mpc_problem(problem_file)
    nominal = load(p.model_path)
    plant = heavier_tip(nominal, tip_factor)
    traj = load_trajectory(p.trajectory)
    n, dt = nominal.n, p.sample_time
    T = traj.duration if duration is None else duration
    K = int(round(T / dt))
    t = np.arange(K + 1) * dt
    ff = feedforward(nominal, traj, t)
    fd = plant.forward_dynamics()
    xs, us = ca.SX.sym("x", 4 * n), ca.SX.sym("u", n)
    z = xs
    for _ in range(4):
        z = rk4(lambda v: ca.vertcat(v[2 * n:], *fd(*ca.vertsplit(v, n), us)), z, dt / 4)[0]
    advance = ca.Function("advance", [xs, us], [z])
    mu = nominal.model.column("gear_ratio")
    q_link, q_motor = 2 * np.pi / LINK_COUNTS, 2 * np.pi / MOTOR_COUNTS / mu
    B = np.array([jt.rotor_inertia for jt in nominal.model.joints])
    wn = 2 * np.pi * 4.0
    kp, kd = B * wn ** 2, 2 * 0.8 * B * wn
    limits = {key: np.array([jt.limits.get(key, np.inf) for jt in nominal.model.joints]) for key in ("tau", "psi", "dphi")}
    mpc = CompiledMPC(mpc_dir)
    results = {}
    for name in ("feedforward", "feedforward + PD", "MPC (C)"):
        x = ff["x0"].copy()
        meas_prev = np.concatenate([np.round(x[:n] / q_link) * q_link, np.round(x[n:2 * n] / q_motor) * q_motor])
        errors, violation, times = [], 0.0, []
        if name == "MPC (C)":
            mpc.init(x)
        for k in range(K):
            meas = np.concatenate([np.round(x[:n] / q_link) * q_link, np.round(x[n:2 * n] / q_motor) * q_motor])
            speeds = (meas - meas_prev) / dt if k else x[2 * n:]
            meas_prev = meas
            if name == "MPC (C)":
                tk = t[k] + p.interval * np.arange(1, p.horizon + 1)
                q, dq = traj(np.minimum(tk, T))[:2]
                tau, seconds, flag = mpc.step(np.concatenate([meas, speeds]), np.vstack([q, dq]))
                times.append(seconds)
            else:
                tau = ff["tau"][:, k].copy()
                if name == "feedforward + PD":
                    tau -= (kp * (ff["phi"][:, k] - meas[n:]) + kd * (ff["dphi"][:, k] - speeds[n:])) / mu
            tau = np.clip(tau, -limits["tau"], limits["tau"])
            x = np.array(advance(x, tau)).ravel()
            errors.append(np.max(np.abs(x[:n] - ff["theta_d"][:, k + 1])))
            violation = max(violation, float(np.max(np.abs(x[n:2 * n] - x[:n]) / limits["psi"] - 1)),
                            float(np.max(np.abs(x[3 * n:]) / limits["dphi"] - 1)))
        e = np.array(errors)
        results[name] = {"max_error": float(e.max()), "rms_error": float(np.sqrt(np.mean(e ** 2))),
                         "max_limit_violation": max(violation, 0.0)}
        if times:
            results[name].update(step_median_s=float(np.median(times)), step_worst_s=float(np.max(times)))
        log(f"{name:18s} max error {e.max():.2e} rad, RMS {results[name]['rms_error']:.2e} rad, "
            f"limit violation {max(violation, 0.0):.1e}"
            + (f", step median {np.median(times) * 1e6:.0f} us, worst {np.max(times) * 1e6:.0f} us" if times else ""))
    return results
