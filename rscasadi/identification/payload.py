"""Identify a payload alone (`rscasadi identify MODEL LOG --only payload`): the ten inertial
parameters of the body the model file's [payload] names, everything else held at the model
file's values (an arm identified before), from a short log of the arm moving with it.

The SEAs are torque sensors: with the spring law known, T_spring(state) = k1 psi + k3 psi^3 +
d dpsi is the torque the links receive (or the logged T_j of a link-side log), so the link rows

    Y_T(x) p_payload + y0_T(x) = T_spring(x)

need no motor-side friction model; the motor-torque rows are added where the motor turns
(outside the Coulomb band, as in the full identification).  The parameters the log determines
(base combinations: a slow motion sees mass and first moments, a fast one the inertia too) are
fitted by least squares with standard deviations; the payload written back is the physically
consistent one (its pseudo-inertia positive) closest to that estimate, the undetermined
directions held near the model file's guess.
"""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from rscasadi.dynamics.arm import Arm
from rscasadi.dynamics.statics import spring_torque
from rscasadi.files import CheckError
from rscasadi.identification.identify import REVERSAL, _pseudo_inertia, cutoff_hz, prepare
from rscasadi.identification.logs import Log, LogError
from rscasadi.identification.regressor import base_of, over_samples, regressor
from rscasadi.model.parameters import INERTIAL, body_from_parameters, payload_slice
from rscasadi.model.kinds import require_sea

NAMES = [f"payload.{q}" for q in INERTIAL]
PRIOR = 1e-3          # weight of the model file's guess, relative to the data, where the data is silent


def _rows(arm: Arm, sig, known: list) -> tuple[list, list, list]:
    """A p_payload = y: the link rows with the spring's torque, and the motor rows where it turns."""
    n, count = arm.n, sig.t.size
    Y, y0 = over_samples(regressor(arm, known=known), *sig.state())
    Y = Y.reshape(2 * n, count, -1)
    y0 = y0.reshape(2 * n, count)
    eps = arm.model.column("eps")
    T_link = spring_torque(arm.model, sig.theta, sig.phi, sig.dtheta, sig.dphi) if sig.phi_measured else sig.T
    A, y, labels = [], [], []
    for j in range(n):
        A.append(Y[n + j])
        y.append(T_link[j] - y0[n + j])
        labels.append(f"T_{j + 1}")
        if sig.tau is None:
            continue
        moving = np.abs(sig.dphi[j]) > REVERSAL * eps[j]
        A.append(Y[j][moving])
        y.append(sig.tau[j][moving] - y0[j][moving])
        labels.append(f"tau_{j + 1}")
    return A, y, labels


def identify_payload(arm: Arm, logs: list[Log], fc: float | None = None) -> dict:
    """The payload's parameters from `logs`: {"estimate", "std" (None where the logs do not
    determine it), "base" (the determined combinations with their estimates and standard
    deviations), "payload" (the physically consistent body), "fit_status", "rows"}."""
    if arm.model.payload is None:
        raise CheckError(f"{arm.model.path}: --only payload needs a [payload] table (its frame and a guess)")
    names, nominal = arm.parameters()
    held = payload_slice(arm.model)
    known = [name for name in names[:held.stop] if not name.startswith("payload.")]
    fc = fc or cutoff_hz(arm, logs[0])[0]
    A_b, y_b = [], []                                   # one block per kind, joint and log
    for log in logs:
        A, y, _ = _rows(arm, prepare(log, fc, arm=arm), known)
        A_b += [a for a, v in zip(A, y) if v.size]
        y_b += [v for v in y if v.size]
    size = np.array([max(np.sqrt(np.mean(v ** 2)), 1e-9) for v in y_b])
    sigma = size.copy()
    base = base_of(np.vstack([a / s for a, s in zip(A_b, size)]), NAMES, rtol=1e-6)
    for _ in range(3):                                  # each block weighted by 1 / its residual RMS
        Ab = np.vstack([a[:, base.independent] / s for a, s in zip(A_b, sigma)])
        y_w = np.concatenate([v / s for v, s in zip(y_b, sigma)])
        beta, *_ = np.linalg.lstsq(Ab, y_w, rcond=None)
        sigma = np.array([max(np.sqrt(np.mean((a[:, base.independent] @ beta - v) ** 2)), 1e-4 * sz)
                          for a, v, sz in zip(A_b, y_b, size)])
    Ab = np.vstack([a[:, base.independent] / s for a, s in zip(A_b, sigma)])
    y_w = np.concatenate([v / s for v, s in zip(y_b, sigma)])
    beta, *_ = np.linalg.lstsq(Ab, y_w, rcond=None)
    s2 = float(np.sum((Ab @ beta - y_w) ** 2) / max(Ab.shape[0] - Ab.shape[1], 1))
    cov = s2 * np.linalg.inv(Ab.T @ Ab)
    guess = nominal[held]
    physical, status = _physical(base, beta, Ab.T @ Ab / s2, guess)
    est = np.full(10, np.nan)
    std: list[float | None] = [None] * 10
    for k in range(10):
        d = base.functional(np.eye(10)[k])
        if d is not None:
            est[k], std[k] = float(d @ beta), float(np.sqrt(max(d @ cov @ d, 0.0)))
    combos = [{"combination": line.split(" = ", 1)[1], "estimate": float(b), "std": float(np.sqrt(cov[i, i]))}
              for i, (line, b) in enumerate(zip(base.explain(), beta))]
    return {"names": NAMES, "estimate": est, "std": std, "base": combos, "payload": body_from_parameters(physical),
            "parameters": physical, "fit_status": status, "cutoff_hz": fc, "rows": int(Ab.shape[0])}


def _physical(base, beta, info, guess) -> tuple[np.ndarray, str]:
    """The parameters closest to the base estimate in its information metric with a positive
    pseudo-inertia, the directions the data cannot see held near the guess (cvxpy, Clarabel)."""
    import cvxpy as cp
    scale = np.maximum(np.abs(guess), 1e-3 * max(abs(guess[0]), 1e-3))
    x = cp.Variable(10)
    v = cp.multiply(scale, x)
    J = cp.bmat(_pseudo_inertia([v[k] for k in range(10)]))
    W = np.linalg.cholesky(info + 1e-12 * np.trace(info) / len(info) * np.eye(len(info))).T
    data = W @ base.P @ np.diag(scale)
    cost = cp.sum_squares(data @ x - W @ beta) + PRIOR * cp.sum_squares(x - guess / scale)
    problem = cp.Problem(cp.Minimize(cost), [J >> 1e-9 * np.eye(4)])
    with warnings.catch_warnings():         # cvxpy warns of reduced accuracy; the status below says it
        warnings.simplefilter("ignore", UserWarning)
        problem.solve(solver=cp.CLARABEL)
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or x.value is None:
        raise CheckError(f"the payload's physically consistent fit failed: Clarabel reports {problem.status}")
    return scale * np.asarray(x.value), ("converged" if problem.status == cp.OPTIMAL
                                          else "converged (to Clarabel's reduced tolerances)")


def with_payload(arm: Arm, payload_body) -> Arm:
    """The arm holding `payload_body` at its payload's frame."""
    return Arm(dataclasses.replace(arm.model, payload=dataclasses.replace(arm.model.payload, body=payload_body)))


def check_logs(logs: list[Log]):
    """A log too short to filter is refused by name."""
    for log in logs:
        if log.t[-1] - log.t[0] <= 1.0:
            raise LogError(f"{log.path}: column 't': shorter than 1 s, too short to filter")

def run(model_file, log_files, out, validate=None, cutoff=None, log=print) -> dict:
    """`rscasadi identify MODEL LOGS --only payload`: identify the payload, check it on a
    held-out log if given (its link-torque prediction), and write model.toml (the model with the
    identified payload) and report.json into `out`; returns the report."""
    from pathlib import Path

    from rscasadi.dynamics.arm import load
    from rscasadi.files import check_writable, fresh_directory, write_json, write_text
    from rscasadi.identification.logs import motor_torques, read_log
    from rscasadi.model.modelfile import document, to_toml
    check_writable(out)
    arm = load(model_file)
    require_sea(arm.model, "rscasadi identify")
    if arm.model.payload is None:
        raise CheckError(f"{model_file}: --only payload needs a [payload] table (its frame and a guess)")
    logs = [motor_torques(read_log(f, arm.n), arm.model) for f in log_files]
    check_logs(logs)
    held_out = motor_torques(read_log(validate, arm.n), arm.model) if validate else None
    log(f"identifying the payload at {arm.model.payload.frame!r} of {arm.model.name} from {len(logs)} log(s), "
        "everything else held at the model file's values ...")
    res = identify_payload(arm, logs, cutoff)
    body = res["payload"]
    log(f"payload: mass {body.mass:.4g} kg, com {np.round(body.com, 4).tolist()} m in {arm.model.payload.frame!r} "
        f"(fit {res['fit_status']}); {len(res['base'])} combinations determined by the log(s)")
    identified = with_payload(arm, body)
    report = {"model": str(model_file), "logs": [str(f) for f in log_files], "only": "payload",
              "frame": arm.model.payload.frame, "cutoff_hz": res["cutoff_hz"], "rows": res["rows"],
              "parameters": [{"name": n, "estimate": e, "std": s} for n, e, s in zip(res["names"], res["estimate"],
                                                                                   res["std"])],
              "base": res["base"], "fit_status": res["fit_status"],
              "payload": {"mass": body.mass, "com": body.com.tolist(), "inertia": body.inertia.tolist()}}
    if held_out is not None:
        error = link_torque_error(identified, held_out, res["cutoff_hz"])
        report["validation"] = {"log": str(validate), "link_torque_relative_rms": error}
        log(f"validation on {validate}: link torques predicted within {100 * max(error):.2f} % RMS")
    with fresh_directory(out) as tmp:
        write_text(tmp / "model.toml", f"# the payload identified by rscasadi identify --only payload from "
                                       f"{', '.join(Path(f).name for f in log_files)}\n" + to_toml(document(identified.model)))
        write_json(tmp / "report.json", report, indent=2)
    log(f"wrote {Path(out) / 'model.toml'} and report.json")
    return report


def link_torque_error(arm: Arm, log: Log, fc: float) -> list:
    """Per joint: RMS of (the model's link torque - the spring's torque) / RMS of the spring's
    torque along a filtered log."""
    sig = prepare(log, fc, arm=arm)
    T = np.array(arm.inverse_dynamics().map(sig.t.size)(*sig.state())[1])
    T_spring = spring_torque(arm.model, sig.theta, sig.phi, sig.dtheta, sig.dphi) if sig.phi_measured else sig.T
    return [float(np.sqrt(np.mean((T[j] - T_spring[j]) ** 2)) / max(np.sqrt(np.mean(T_spring[j] ** 2)), 1e-300))
            for j in range(arm.n)]
