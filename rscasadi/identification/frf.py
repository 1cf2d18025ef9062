"""Frequency responses of a joint: the model's, linearised, and a log's, estimated (`rscasadi frf`).

An elastic joint shows itself in the response from its motor torque tau_j to its motor angle
phi_j (collocated): an anti-resonance where the link alone rings on the spring (for one joint,
w_a^2 = k1 / J_link) and a resonance where motor and link ring against each other
(w_r^2 = k1 (1 / J_link + 1 / J_motor)); from tau_j to the link angle theta_j only the resonance.
A rigid joint (the "armature" model) has neither: its response falls as 1 / w^2 throughout.

Model: the complete model linearised at rest at a pose (the springs holding the links against
gravity, `rest_state`), x' = A x + B tau, G(jw) = e_out (jw I - A)^-1 B e_j.  The Coulomb terms
(c, c1 |T| and Stribeck's on the gear, link_c on the link, each times tanh(speed / eps)) are left
out: linearised at rest they would be a damping (c + c1 |T| + s) / eps, where at a log's
amplitudes they act as a dead band; an FRF is the response of the linear part.  The rigid
comparison is the same arm with every spring 1e6 times stiffer (its modes far above the band).

Log: the H1 estimate P_tau,y / P_tau,tau (Welch, Hann windows, half overlap; scipy.signal) and
the coherence, from a log with tau_j (the torque actually applied: feedback in the loop does not
bias H1 when the torque is measured without noise).  A log shows a model's peak only where it was
excited there (`what_the_log_shows`): most bins near the peak coherent, and, for the collocated
output phi, a passive response.  A joint driven by its own torque is passive: tau -> phi's phase
(the gear's sign taken out) lies within [-180, 0] degrees; a closed-loop log whose torque is the
controller's answer to sensor noise gives instead minus the controller's inverse, whose phase lies
outside it.  Where a log cannot show a peak, its value is null and the reason is said.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import scipy.signal

from rscasadi.dynamics.arm import Arm
from rscasadi.dynamics.statics import rest_state
from rscasadi.errors import InvalidArgument
from rscasadi.identification.logs import Log, LogError
from rscasadi.model.kinds import require_sea

OUTPUTS = ("phi", "theta")
COHERENT = 0.9       # log bins drawn and searched: coherence above this
RIGID = 1e6          # the rigid comparison's springs, times the model's


def linearised(arm: Arm, theta) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) of x' = A x + B tau at rest at the pose theta (x = theta, phi, dtheta, dphi; the
    Coulomb terms left out)."""
    import casadi as ca
    plain = Arm(dataclasses.replace(arm.model, joints=tuple(dataclasses.replace(jt, c=0.0, c1=0.0, stribeck=0.0, link_c=0.0)
                                                            for jt in arm.model.joints)))
    n, fd = plain.n, plain.forward_dynamics()
    x, u = ca.SX.sym("x", 4 * n), ca.SX.sym("u", n)
    f = ca.vertcat(x[2 * n:], *fd(*ca.vertsplit(x, n), u))
    x0 = rest_state(plain, np.asarray(theta, float))
    tau0 = np.array(plain.inverse_dynamics()(*np.split(x0, 4), np.zeros(n), np.zeros(n))[0]).ravel()   # holding it
    AB = ca.Function("AB", [x, u], [ca.jacobian(f, x), ca.jacobian(f, u)])
    A, B = (np.array(M) for M in AB(x0, tau0))
    return A, B


def rigid(arm: Arm) -> Arm:
    """The same arm with every spring RIGID times stiffer: a rigid joint with the rotors as
    armature, within any band below its modes."""
    return Arm(dataclasses.replace(arm.model, joints=tuple(dataclasses.replace(jt, k1=jt.k1 * RIGID, k3=jt.k3 * RIGID)
                                                             for jt in arm.model.joints)))


def model_frf(arm: Arm, theta, joint: int, freqs, output: str = "phi") -> np.ndarray:
    """G(j 2 pi f) from tau_joint to output_joint (rad / N m) at rest at theta; joint from 0."""
    if output not in OUTPUTS:
        raise InvalidArgument(f"frf: output must be one of {', '.join(OUTPUTS)}, got {output!r}")
    A, B = linearised(arm, theta)
    n = arm.n
    row = joint + (n if output == "phi" else 0)
    eye = np.eye(A.shape[0])
    return np.array([np.linalg.solve(2j * np.pi * f * eye - A, B[:, joint])[row] for f in np.asarray(freqs, float)])


def log_frf(log: Log, joint: int, output: str = "phi", resolution: float = 0.25) -> tuple:
    """(f, G, coherence) of a log: H1 from tau_joint to output_joint, Welch segments of
    1 / resolution s (or the log's length), their first bin dropped."""
    if log.tau is None:
        raise LogError(f"{log.path}: column 'tau_{joint + 1}': a frequency response needs the motor torque "
                       f"(the input); the log has {log.describe()}")
    y = getattr(log, output, None)
    if output not in OUTPUTS or y is None:
        raise LogError(f"{log.path}: column '{output}_{joint + 1}': not in the log ({log.describe()})")
    fs = 1.0 / log.dt
    nper = int(min(log.t.size, round(fs / resolution)))
    u, y = log.tau[joint], y[joint]
    f, Puy = scipy.signal.csd(u, y, fs=fs, nperseg=nper, detrend="linear")
    _, Puu = scipy.signal.welch(u, fs=fs, nperseg=nper, detrend="linear")
    _, coh = scipy.signal.coherence(u, y, fs=fs, nperseg=nper, detrend="linear")
    return f[1:], (Puy / Puu)[1:], coh[1:]              # csd(u, y) = conj(U) Y: H1 = Puy / Puu


NEAR = 1.5           # a model's peak at f0 is looked for in the log's bins within f0 / NEAR .. f0 NEAR
SHOWN = 0.6          # ... and shown when this share of them (at least MIN_BINS) is coherent
MIN_BINS = 4
PASSIVE_SLACK = 30.0  # degrees beyond [-180, 0] still taken as passive (leakage, the torque held a sample)
ACTIVE_SHARE = 0.2   # a log whose coherent bins break passivity at least this often is taken as closed loop


def what_the_log_shows(f, G, coh, model_peaks: dict, output: str) -> dict:
    """For each of the model's peaks ("antiresonance", "resonance"): "" where the log can show it,
    else why not (a sentence).  Closed loop (output phi: ACTIVE_SHARE of the coherent bins with the
    phase of -G outside [-180, 0] degrees by more than PASSIVE_SLACK) answers for every peak; then
    each peak needs SHOWN of its bins within a factor NEAR coherent."""
    f, G, coh = (np.asarray(a) for a in (f, G, coh))
    good = coh > COHERENT
    why = {}
    if output == "phi" and good.sum() >= MIN_BINS:
        phase = np.degrees(np.angle(-G[good]))          # -G: the fast rotor turns by -mu
        active = np.mean((phase > PASSIVE_SLACK) & (phase < 180.0 - PASSIVE_SLACK))
        if active >= ACTIVE_SHARE:
            reason = (f"its tau -> phi is not passive in {100 * active:.0f} % of its coherent bins (a joint driven by "
                      "its own torque keeps the phase within 180 degrees): a closed-loop log, where tau is the "
                      "controller's answer to sensor noise; add noise or a chirp to tau to measure a response")
            return {kind: reason for kind in ("antiresonance", "resonance")}
    for kind in ("antiresonance", "resonance"):
        f0 = model_peaks.get(f"{kind}_hz")
        if f0 is None:
            why[kind] = "the model has none in the band"
            continue
        near = (f >= f0 / NEAR) & (f <= f0 * NEAR)
        k, m = int(good[near].sum()), int(near.sum())
        why[kind] = "" if m >= MIN_BINS and k >= SHOWN * m else (
            f"coherence above {COHERENT:g} in {k} of its {m} bins between {f0 / NEAR:.1f} and {f0 * NEAR:.1f} Hz, "
            f"around the model's {kind} at {f0:.1f} Hz: too little excitation there (add noise or a chirp to tau)")
    return why


PROMINENCE = 0.5     # a peak stands out of its neighbourhood by this much in ln |G / G_rigid| (4.3 dB)


def peaks(freqs, G, G_rigid) -> dict:
    """The first anti-resonance and the first resonance (Hz; None where there is none in the
    band): the first prominent minimum and maximum of |G / G_rigid|, the rigid joint's response
    (its inertia and damping: the trend every joint has) divided out."""
    r = np.log(np.maximum(np.abs(np.asarray(G) / np.asarray(G_rigid)), 1e-300))
    f = np.asarray(freqs, float)
    highs, _ = scipy.signal.find_peaks(r, prominence=PROMINENCE)
    lows, _ = scipy.signal.find_peaks(-r, prominence=PROMINENCE)
    return {"antiresonance_hz": float(f[lows[0]]) if lows.size else None,
            "resonance_hz": float(f[highs[0]]) if highs.size else None}


def plot(path, curves: list, title: str):
    """Bode magnitude and phase of `curves` [(label, f, G, style)] into `path` (PNG)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (mag, ph) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    for label, f, G, style in curves:
        mag.semilogx(f, 20 * np.log10(np.maximum(np.abs(G), 1e-300)), style, label=label, lw=1)
        ph.semilogx(f, np.degrees(np.unwrap(np.angle(G))), style, lw=1)
    mag.set_ylabel("|G| (dB rad/N m)")
    ph.set_ylabel("phase (deg)")
    ph.set_xlabel("frequency (Hz)")
    mag.set_title(title)
    mag.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(model_file, out, log_file=None, joint: int = 1, output: str = "phi", pose=None,
        band=(0.5, 200.0), resolution: float = 0.25, say=print) -> dict:
    """`rscasadi frf MODEL [LOG] --joint J --out DIR`: DIR/frf.png (the complete model's response,
    the rigid one's and, with a log, the log's estimate where its coherence exceeds COHERENT) and
    DIR/frf.json (the first anti-resonance and resonance of the model's and the log's).  The
    pose: `pose`, else the log's mean link angles, else every joint at the middle of its range;
    `resolution`: the log's bins (Hz; finer bins average fewer segments).  Joints from 1."""
    from pathlib import Path

    from rscasadi.dynamics.arm import load
    from rscasadi.files import check_writable, fresh_directory, write_json
    from rscasadi.identification.logs import motor_torques, read_log
    from rscasadi.model.limits import limit_arrays
    check_writable(out)
    arm = load(model_file)
    require_sea(arm.model, "rscasadi frf")
    if not 1 <= joint <= arm.n:
        raise InvalidArgument(f"frf: --joint {joint}: {model_file} has joints 1..{arm.n}")
    if output not in OUTPUTS:
        raise InvalidArgument(f"frf: --output must be one of {', '.join(OUTPUTS)}, got {output!r}")
    lg = motor_torques(read_log(log_file, arm.n), arm.model) if log_file else None
    if lg is not None and lg.tau is None:
        raise LogError(f"{log_file}: column 'tau_{joint}': a frequency response needs the motor torque (the input); "
                       f"the log has {lg.describe()}")
    if pose is not None:
        theta = np.asarray(pose, float)
        if theta.shape != (arm.n,):
            raise InvalidArgument(f"frf: --pose has {theta.size} angles, {model_file} has {arm.n} joints")
        if not np.all(np.isfinite(theta)):
            bad = int(np.flatnonzero(~np.isfinite(theta))[0])
            raise InvalidArgument(f"frf: --pose: angle {bad + 1} ({arm.model.joints[bad].name}) is {theta[bad]}, "
                                  "not a finite number")
    elif lg is not None:
        theta = np.mean(lg.theta, axis=1)
    else:
        lim = limit_arrays(arm.model)
        lo, hi = lim["theta_lo"], lim["theta_hi"]
        theta = np.where(np.isfinite(lo) & np.isfinite(hi), 0.5 * (lo + hi), 0.0)
    j = joint - 1
    hi_f = band[1] if lg is None else min(band[1], 0.45 / lg.dt)
    f = np.geomspace(band[0], hi_f, 600)
    stiff = rigid(arm)
    curves = [("complete model", f, model_frf(arm, theta, j, f, output), "C0-"),
              ("rigid joints (armature)", f, model_frf(stiff, theta, j, f, output), "C7--")]
    result = {"model": str(model_file), "joint": joint, "output": output, "pose": theta.tolist(),
              "complete": peaks(f, curves[0][2], curves[1][2])}
    if lg is not None:
        fl, Gl, coh = log_frf(lg, j, output, resolution)
        good = (fl >= band[0]) & (fl <= hi_f) & (coh > COHERENT)
        curves.append((f"log {Path(log_file).name} (H1, coherence > {COHERENT:g})", fl[good], Gl[good], "C3."))
        rigid_there = model_frf(stiff, theta, j, fl[good], output)
        found = peaks(fl[good], Gl[good], rigid_there)
        inband = (fl >= band[0]) & (fl <= hi_f)
        why = what_the_log_shows(fl[inband], Gl[inband], coh[inband], result["complete"], output)
        result["log"] = {"file": str(log_file),
                         **{f"{k}_hz": found[f"{k}_hz"] if not why[k] else None for k in why},
                         "not_shown": {k: w for k, w in why.items() if w},
                         "coherent_band_hz": [float(fl[good].min()), float(fl[good].max())] if good.any() else None}
    hidden = (result.get("log") or {}).get("not_shown", {})
    say(f"{arm.model.name}, joint {joint}, tau -> {output}: " + "; ".join(
        f"{name} anti-resonance {_hz(r['antiresonance_hz'], name == 'log' and 'antiresonance' in hidden)}, "
        f"resonance {_hz(r['resonance_hz'], name == 'log' and 'resonance' in hidden)}"
        for name, r in result.items() if isinstance(r, dict) and "resonance_hz" in r))
    for kind, reason in (result.get("log") or {}).get("not_shown", {}).items():
        say(f"the log cannot show the {kind}: {reason}")
    with fresh_directory(Path(out)) as tmp:
        plot(tmp / "frf.png", curves, f"{arm.model.name}: tau_{joint} -> {output}_{joint} at rest")
        write_json(tmp / "frf.json", result, indent=2)
    say(f"wrote {Path(out) / 'frf.png'} and frf.json")
    return result


def _hz(v, hidden: bool = False) -> str:
    return "not shown" if hidden else "none in the band" if v is None else f"{v:.2f} Hz"
