"""Identification of the complete FS-SEA model from logs (`rscasadi identify`).

1. Signals (`prepare`): every logged angle is low-passed by a zero-phase Butterworth filter
   (scipy.signal, order 4, run forwards and backwards) and differentiated twice; the logged
   torques go through the same filter, so regressor and torque see the same attenuation.
   With motor angles, the cut-off is twice the highest SEA mode of the arm (at least 20 Hz, at
   most Nyquist/2): the modes are in the data (they carry k1 and d) and must pass, while the
   encoder quantisation, amplified by differentiation, is cut above them.  Link-side logs (no
   spring rows) take the cut-off that predicts unseen data best (`cross_validated_cutoff`).  Measured on the synthetic
   arm of the tests: at 1.5x the modes the estimates of k1 move by 100 standard deviations.
   Rows are kept every 1 / (2 fc) s, so that their noise is close to independent.
2. Rows: the motor-torque rows tau = Y_tau theta, the link rows, whose torque is the spring
   (T - T_spring = 0, measured angles only), and T = Y_T theta when a torque sensor is logged.
3. Least squares in the base parameters (`BaseParameters`), each row block weighted by the
   inverse of its residual standard deviation (two passes): the estimate, its covariance, and
   the standard deviation of every identifiable combination.
4. A physically consistent model (`physical_fit`): each body's pseudo-inertia J is positive
   definite (a linear matrix inequality, Wensing, Kim and Slotine 2017; balanced rotors keep
   their balanced parameters), k1 > 0 and k3, d, b, c (and c1, the Stribeck excess, the link
   losses and the counterbalance where declared) >= 0, fitted to the base estimate in its
   information metric plus a weak prior (30 %) on the model file's values for the directions the
   data cannot see: a convex semidefinite program (cvxpy, Clarabel) with one optimum.
"""
from __future__ import annotations

import dataclasses
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.linalg
import scipy.signal

from rscasadi.dynamics.arm import Arm, load
from rscasadi.dynamics.statics import spring_deflection, spring_torque
from rscasadi.files import CheckError, check_writable, fresh_directory, write_json
from rscasadi.model.modelfile import BODIES, ArmModel, document, to_toml
from rscasadi.model.parameters import (ACTUATOR, ACTUATOR_ATTR, INERTIAL, PER_JOINT, body_from_parameters, n_linear,
                                       payload_slice)
from rscasadi.identification.logs import Log, LogError, motor_torques, read_log
from rscasadi.identification.regressor import (BaseParameters, base_of, over_samples, random_samples, regressor,
                                               spring_regressor, stacked)
from rscasadi.model.kinds import require_sea

PRIOR = 0.3          # relative standard deviation of the prior on the model file's values
CUTOFF_FACTOR = 2.0  # filter cut-off / highest SEA mode (1.5 biases k1 by 100 sigma, see above)
EDGE_S = 0.25        # seconds dropped at both ends of a log (filter transients)
REVERSAL = 10.0      # motor-torque rows with |dphi| < REVERSAL * eps (Coulomb's tanh) are left out
MIN_ROWS = 20        # a joint with fewer motor-torque rows than this is not moved by the log
OPTIONAL = ("link_loss", "counterbalance")   # identified only at joints whose model file gives the table
LOAD_PASSES = 3      # fixed-point passes for a gear's load-dependent loss without a logged T


# ----------------------------------------------------------------------------- the unknowns

@dataclass
class Unknowns:
    """The identification vector th: p_lin = E th.  Links keep their ten parameters; a rotor
    that is balanced in the model file stays balanced (mass, mz, Ixx = Iyy, Izz); every
    actuator keeps k1, k3, d, b, c, and its link-side loss and counterbalance spring where the
    model file gives those tables (elsewhere they are held at zero)."""
    names: list
    E: np.ndarray
    kinds: list        # per entry: ("link" | "rotor", joint, body), ("actuator", joint, attr),
    #                    ("offset", joint, "T"), ("c1", joint, "gear_loss.c1"), ("stribeck", joint,
    #                    "gear_loss.stribeck") or ("kt", joint, "torque_constant"): the last four not in p_lin
    fixed: dict        # {index: nominal} of the unknowns not in p_lin (E's column zero)
    shift: dict = dataclasses.field(default_factory=dict)   # {index: value}: th holds value - shift there

    @staticmethod
    def of(model: ArmModel, sensor_offsets: bool = False, load_losses: bool = True,
           torque_constants: str | None = None) -> "Unknowns":
        """The unknowns of `model`; sensor_offsets: one more per joint, the offset of its T
        sensor (T_j logged = T_j + offset); load_losses: the gear's load-dependent loss c1 and its
        Stribeck excess at the joints whose file gives them (at the file's v_stribeck);
        torque_constants: the motors' torque constants, from logged currents (`kt_scale`):
        "sensor", each one (a logged T fixes the scale); "ratios", all but the last joint's, which
        follows from them: their mean relative change is held at zero (currents alone fix tau = kt
        i only up to a scale every parameter shares).  Each is held in th as its change from the
        file's (`shift`), so that the motor-torque rows keep tau = kt_file i as their data.
        None of these is in p_lin (their columns of E are zero): `rows` forms their columns from the data."""
        n_lin = n_linear(model)
        cols, names, kinds = [], [], []

        def add(name, rows, kind):
            c = np.zeros(n_lin)
            c[rows] = 1.0
            cols.append(c), names.append(name), kinds.append(kind)

        for j, jt in enumerate(model.joints):
            base = j * PER_JOINT
            for i, body in enumerate(BODIES):
                first = base + 10 * i
                if body != "link" and getattr(jt, body).balanced:
                    for q, rows in (("mass", [0]), ("mz", [3]), ("Ixx=Iyy", [4, 5]), ("Izz", [6])):
                        add(f"{jt.name}.{body}.{q}", [first + r for r in rows], ("rotor", j, body))
                else:
                    for r, q in enumerate(INERTIAL):
                        add(f"{jt.name}.{body}.{q}", [first + r], ("link" if body == "link" else "body", j, body))
            for r, a in enumerate(ACTUATOR):
                if a.split(".")[0] in OPTIONAL and a.split(".")[0] not in jt.declared:
                    continue                   # a term the model file does not give: held at zero
                add(f"{jt.name}.{a}", [base + 30 + r], ("actuator", j, a))
        held = payload_slice(model)
        for r, q in enumerate(INERTIAL[:held.stop - held.start]):             # a payload: its ten, as a link's
            add(f"payload.{q}", [held.start + r], ("body", model.n, "payload"))
        fixed = {}
        for j, jt in enumerate(model.joints):
            if load_losses and "gear_loss.c1" in jt.declared:
                fixed[len(names)] = jt.c1
                add(f"{jt.name}.gear_loss.c1", [], ("c1", j, "gear_loss.c1"))
            if load_losses and "gear_loss.stribeck" in jt.declared:
                fixed[len(names)] = jt.stribeck
                add(f"{jt.name}.gear_loss.stribeck", [], ("stribeck", j, "gear_loss.stribeck"))
        for j, jt in enumerate(model.joints):
            if sensor_offsets:
                fixed[len(names)] = 0.0
                add(f"{jt.name}.T_offset", [], ("offset", j, "T"))
        shift = {}
        for j, jt in enumerate(model.joints):
            if torque_constants == "sensor" or (torque_constants == "ratios" and j < model.n - 1):
                fixed[len(names)], shift[len(names)] = 0.0, jt.torque_constant
                add(f"{jt.name}.torque_constant", [], ("kt", j, "torque_constant"))
        return Unknowns(names, np.array(cols).T, kinds, fixed, shift)

    def kt_change(self, model: ArmModel) -> np.ndarray:
        """(n, len(th)): each motor's torque-constant change kt_j - kt_file_j as a linear function
        of th (zero rows without currents; with "ratios" the last joint's from the others')."""
        K = np.zeros((model.n, len(self.names)))
        for k, j in self.torque_constants():
            K[j, k] = 1.0
        if self.torque_constants() and len(self.torque_constants()) < model.n:     # sum_j change_j / kt_j = 0
            kt = model.column("torque_constant")
            for k, j in self.torque_constants():
                K[-1, k] = -kt[-1] / kt[j]
        return K

    def values(self, th) -> np.ndarray:
        """th as the parameters' values: a torque constant's change from the file's plus the file's."""
        out = np.asarray(th, float).copy()
        for k, v in self.shift.items():
            out[k] += v
        return out

    def torque_constants(self) -> list:
        """(index in th, joint) of every motor's torque constant (its change from the file's)."""
        return [(k, kind[1]) for k, kind in enumerate(self.kinds) if kind[0] == "kt"]

    def offsets(self) -> list:
        """(index in th, joint) of every sensor offset."""
        return [(k, kind[1]) for k, kind in enumerate(self.kinds) if kind[0] == "offset"]

    def load_losses(self) -> list:
        """(index in th, joint) of every gear's load-dependent loss c1."""
        return [(k, kind[1]) for k, kind in enumerate(self.kinds) if kind[0] == "c1"]

    def stribeck(self) -> list:
        """(index in th, joint) of every gear's Stribeck excess."""
        return [(k, kind[1]) for k, kind in enumerate(self.kinds) if kind[0] == "stribeck"]

    def from_p(self, p_lin) -> np.ndarray:
        """th from p_lin: each unknown read off its first physical parameter (tied ones are
        equal); those not in p_lin at their nominal (`fixed`)."""
        th = np.asarray(p_lin, float)[np.argmax(self.E > 0, axis=0)]
        for k, v in self.fixed.items():
            th[k] = v
        return th


# ----------------------------------------------------------------------------- signals

def sea_modes_hz(arm: Arm, theta) -> np.ndarray:
    """Undamped frequencies of the SEA modes linearised at the pose theta (static deflection
    neglected): eigenvalues of M^-1 K, K the spring stiffness between theta and phi."""
    n = arm.n
    M = np.array(arm.mass_matrix()(theta, theta))
    k1 = arm.model.column("k1")
    K = np.block([[np.diag(k1), -np.diag(k1)], [-np.diag(k1), np.diag(k1)]])
    w2 = np.real(scipy.linalg.eigvals(K, M))
    return np.sqrt(np.clip(np.sort(w2)[n:], 0, None)) / (2 * np.pi)


def cutoff_hz(arm: Arm, log: Log) -> tuple[float, str]:
    """The filter cut-off for this arm and log, and why.  A link-side log (no motor angle, so no
    spring rows): where the logged motion ends, `motion_cutoff_hz`.  A log with motor angles:
    `motor_side_cutoff_hz`, the motion's band unless the log excites the SEA modes."""
    if log.link_side:
        return motion_cutoff_hz(log)
    return motor_side_cutoff_hz(arm, log)


SIGNAL_OVER_NOISE = 100.0     # motion (or a ringing mode): where a spectrum is this far above its noise
MODE_BAND = 0.15         # ... within this relative distance of the mode at the mean pose (the modes move with it)


def excited_modes(arm: Arm, log: Log) -> tuple[np.ndarray, np.ndarray]:
    """The SEA modes at the log's mean pose (`sea_modes_hz`) and, for each, how far the spring
    deflection phi - theta rises above its noise floor near it (Welch, the largest over joints
    and over MODE_BAND about the mode; the floor is the median of the top fifth of the band).  A
    smooth motion leaves the modes near the noise (the Panda's Fourier motions: 3-45x); steps,
    bumps and a rich excitation ring them (500-30000x, the reference arm's logs)."""
    modes = sea_modes_hz(arm, np.mean(log.theta, axis=1))
    fs, nyquist = 1.0 / log.dt, 0.5 / log.dt
    f, P = scipy.signal.welch(log.phi - log.theta, fs=fs, nperseg=min(log.t.size, max(256, int(4 * fs))),
                              detrend="linear", axis=1)
    floor = np.maximum(np.median(P[:, f >= 0.8 * nyquist], axis=1), 1e-300)
    rise = np.array([float(np.max(P[:, near] / floor[:, None])) if np.any(near := np.abs(f - m) <= MODE_BAND * m)
                     else 0.0 for m in modes])
    return modes, rise


def motor_side_cutoff_hz(arm: Arm, log: Log) -> tuple[float, str]:
    """The cut-off of a log with motor angles: CUTOFF_FACTOR x the highest SEA mode the log
    excites (`excited_modes`; a mode rings where the deflection rises SIGNAL_OVER_NOISE above its
    noise: ringing springs carry k1 and d, and a filter through them biased k1 by 100 standard
    deviations at 1.5x), else 1.5x where the link angles' motion ends (`band_ends_hz`: above it
    differentiation amplifies only noise; the motor angles are no guide, their spectrum stays high
    up to the modes with the controller's answer to torque noise); never above CUTOFF_FACTOR x
    the highest mode, at least 20 Hz, at most half the Nyquist frequency."""
    modes, rise = excited_modes(arm, log)
    nyquist = 0.5 / log.dt
    ends = band_ends_hz(log.theta, log.dt)
    rung = modes[rise >= SIGNAL_OVER_NOISE]
    need = CUTOFF_FACTOR * rung.max() if rung.size else 0.0
    fc = min(max(20.0, need, 1.5 * ends.max()), CUTOFF_FACTOR * modes.max(), 0.5 * nyquist)
    listed = ", ".join(f"{m:.1f} ({r:.0f}x)" for m, r in zip(modes, rise))
    if rung.size and fc == need:
        reason = (f"{CUTOFF_FACTOR:g}x the highest SEA mode the log excites ({rung.max():.1f} Hz), so the ringing "
                  "springs that carry k1 and d pass")
    else:
        reason = (f"the logged motion ends at {ends.max():.1f} Hz (joint {int(np.argmax(ends)) + 1}'s link angle) and "
                  f"no SEA mode above it rings: 1.5x that, so the accelerations keep the motion and lose the noise "
                  f"that differentiation amplifies")
        reason += {20.0: ", raised to 20 Hz (the lowest for motor rows)",
                   CUTOFF_FACTOR * modes.max(): f", capped at {CUTOFF_FACTOR:g}x the highest SEA mode",
                   0.5 * nyquist: ", capped at half the Nyquist frequency"}.get(fc, "")
    why = (f"{fc:.1f} Hz: {reason} (SEA modes at the mean pose, Hz, and how far the deflection rises above its "
           f"noise there: {listed}; a mode rings above {SIGNAL_OVER_NOISE:g}x; Nyquist {nyquist:.0f} Hz)")
    return fc, why


def band_ends_hz(x: np.ndarray, dt: float) -> np.ndarray:
    """Per row of x (joints x samples): the highest frequency at which its power spectrum (Welch,
    detrended) is still SIGNAL_OVER_NOISE above its noise floor (the median of the top fifth of
    the band): where the logged motion ends."""
    fs, nyquist = 1.0 / dt, 0.5 / dt
    f, P = scipy.signal.welch(x, fs=fs, nperseg=min(x.shape[1], max(256, int(4 * fs))), detrend="linear", axis=1)
    ends = []
    for Pj in P:
        floor = max(float(np.median(Pj[f >= 0.8 * nyquist])), 1e-300)
        above = np.flatnonzero(Pj[1:] > SIGNAL_OVER_NOISE * floor) + 1
        ends.append(float(f[above[-1]]) if above.size else float(f[1]))
    return np.array(ends)


def motion_cutoff_hz(log: Log) -> tuple[float, str]:
    """The cut-off of a link-side log from its data: per joint, the power spectrum of the link
    angle (Welch, detrended) against its noise floor (the median of the top fifth of the band);
    the motion's band ends at the highest frequency still SIGNAL_OVER_NOISE above that floor,
    and the cut-off is 1.5x the widest joint's band end (at least 1 Hz, at most 0.4 Nyquist).
    Differentiating twice multiplies the noise by (2 pi f)^2, so everything above the motion is
    noise in the accelerations; the SEA modes carry nothing these rows can identify."""
    nyquist = 0.5 / log.dt
    ends = band_ends_hz(log.theta, log.dt)
    widest = int(np.argmax(ends))
    fc = float(min(max(1.5 * ends[widest], 1.0), 0.4 * nyquist))
    why = (f"{fc:.1f} Hz: 1.5x where the logged motion ends ({ends[widest]:.1f} Hz, joint {widest + 1}: its link "
           f"angle's spectrum falls to {SIGNAL_OVER_NOISE:g}x its noise floor; per joint "
           f"{', '.join(f'{e:.1f}' for e in ends)} Hz), so the accelerations keep the motion and lose the noise "
           f"that differentiation amplifies (a link-side log has no spring rows; Nyquist {nyquist:.0f} Hz)")
    return fc, why


CV_GRID = (1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 7.0, 10.0, 14.0, 20.0, 28.0, 40.0, 56.0, 80.0)   # Hz
CV_MAX = 0.4         # of the Nyquist frequency: the highest cut-off tried


def halves(log: Log) -> tuple[Log, Log]:
    """The log's first and second half in time (every column cut alike)."""
    m = log.t.size // 2
    cut = lambda k: {f: (None if getattr(log, f) is None else getattr(log, f)[..., k])     # noqa: E731
                     for f in ("t", "theta", "phi", "tau", "i", "T", "dtheta", "dphi")}
    return Log(f"{log.path} (first half)", **cut(slice(0, m))), Log(f"{log.path} (second half)", **cut(slice(m, None)))


def cross_validated_cutoff(arm: Arm, logs: list[Log], unknowns: Unknowns, base, th_nominal,
                           reduced: bool = False) -> tuple[float, str, dict] | None:
    """The cut-off that predicts unseen data best, from the training logs alone: each log split
    in two halves in time; for a cut-off, the base parameters fitted (least squares) on the first
    halves predict the second halves' torques, and the reverse; its score is the mean over both
    folds and every joint of the relative mean-square error against the held-out torque filtered
    at the highest cut-off tried (one target for all: a lower cut-off would otherwise win by
    smoothing its own target).  Every other cut-off of CV_GRID (up to CV_MAX of the Nyquist
    frequency) is tried, then the two beside the best.  Returns (cut-off, why, {cut-off: score}),
    or None where the halves are too short to tell."""
    nyquist = 0.5 / max(lg.dt for lg in logs)
    grid = [f for f in CV_GRID if f <= CV_MAX * nyquist]
    if len(grid) < 3 or any(lg.t[-1] - lg.t[0] < 2 * (4 * EDGE_S + 1.0) for lg in logs):
        return None
    parts = [half for lg in logs for half in halves(lg)]            # first, second, first, second, ...
    every = [max(1, int(0.5 / (grid[-1] * lg.dt))) for lg in parts]
    targets = [rows(arm, prepare(lg, grid[-1], k, arm=arm), unknowns, reduced) for lg, k in zip(parts, every)]
    scores: dict = {}

    def score(fc: float) -> float:
        seen = [rows(arm, prepare(lg, fc, k, arm=arm), unknowns, reduced) for lg, k in zip(parts, every)]
        errors = []
        for fold in (0, 1):                                          # fit on one half of each log, score the other
            try:
                beta = least_squares(combine(seen[fold::2]), base, th_nominal, bootstrap=False).beta
            except (np.linalg.LinAlgError, ValueError):
                return float("inf")
            for held, target in zip(seen[1 - fold::2], targets[1 - fold::2]):
                pred = held.A[:, base.independent] @ beta
                errors += [float(np.mean((pred[sel] - target.y[sel]) ** 2) / max(np.mean(target.y[sel] ** 2), 1e-300))
                           for b, label in enumerate(target.labels) if not label.startswith("spring")
                           for sel in [target.block == b]]
        return float(np.mean(errors))

    for fc in grid[::2] + ([grid[-1]] if len(grid) % 2 == 0 else []):
        scores[fc] = score(fc)
    k = grid.index(min(scores, key=scores.get))
    for fc in grid[max(k - 1, 0):k + 2]:
        if fc not in scores:
            scores[fc] = score(fc)
    scores = dict(sorted(scores.items()))
    best = min(scores, key=scores.get)
    why = (f"{best:g} Hz: of the cut-offs tried, the one whose fit on one half of each log predicts the other half "
           f"best (two folds; mean relative mean-square error of the held-out torques: "
           + ", ".join(f"{f:g} Hz {v:.3g}" for f, v in scores.items()) + f"; Nyquist {nyquist:.0f} Hz)")
    return best, why, scores


@dataclass
class Signals:
    """A log low-passed (zero-phase), its speeds and accelerations by finite differences of the
    filtered angles (or of the filtered logged speeds), the torques filtered alike; edges
    dropped, decimated (`prepare`).  phi_measured False: a link-side log's phi, reconstructed
    from its torque T by the model file's spring law (`spring_deflection`)."""
    theta: np.ndarray
    phi: np.ndarray
    dtheta: np.ndarray
    dphi: np.ndarray
    ddtheta: np.ndarray
    ddphi: np.ndarray
    tau: np.ndarray | None
    T: np.ndarray | None
    t: np.ndarray
    phi_measured: bool = True
    i: np.ndarray | None = None     # the motor currents, filtered as tau, where logged

    def state(self):
        return [self.theta, self.phi, self.dtheta, self.dphi, self.ddtheta, self.ddphi]


def prepare(log: Log, fc: float, decimate: int | None = None, arm: Arm | None = None) -> Signals:
    """Zero-phase low-pass of angles and torques alike, derivatives, edges dropped, decimated
    (by default to one row every 1 / (2 fc)).  A link-side log needs `arm`: its phi is
    theta + the spring's deflection under the logged T."""
    decimate = decimate or max(1, int(0.5 / (fc * log.dt)))
    sos = scipy.signal.butter(4, fc, fs=1.0 / log.dt, output="sos")
    lp = lambda x: scipy.signal.sosfiltfilt(sos, x, axis=1)
    d = lambda x: np.gradient(x, log.dt, axis=1)
    theta = lp(log.theta)
    T = None if log.T is None else lp(log.T)
    if log.phi is not None:
        phi = lp(log.phi)
    elif arm is not None and T is not None:
        phi = theta + spring_deflection(arm, T.T).T       # (samples, n) broadcasts against k1
    else:
        raise LogError(f"{log.path}: no column phi_1..phi_{log.n}, and no arm given to reconstruct it from T")
    dtheta = lp(log.dtheta) if log.dtheta is not None else d(theta)
    dphi = lp(log.dphi) if log.dphi is not None else d(phi)
    # a logged torque is the command held on [t_k, t_k+1): centred at t_k + dt/2, so at t_k it is
    # the mean of two neighbours (a half-sample delay otherwise biases the rotor inertias: +3.7 %
    # on the elbow's at its 30 Hz SEA mode in the synthetic test)
    held = lambda x: np.concatenate([x[:, :1], 0.5 * (x[:, 1:] + x[:, :-1])], axis=1)
    keep = slice(int(EDGE_S / log.dt), len(log.t) - int(EDGE_S / log.dt), decimate)
    cut = lambda x: None if x is None else x[:, keep]
    return Signals(theta[:, keep], phi[:, keep], dtheta[:, keep], dphi[:, keep], d(dtheta)[:, keep],
                   d(dphi)[:, keep], cut(None if log.tau is None else lp(held(log.tau))), cut(T), log.t[keep],
                   log.phi is not None, cut(None if log.i is None else lp(held(log.i))))


# ----------------------------------------------------------------------------- rows

@dataclass
class Rows:
    """Stacked rows, one block per kind and joint: A th = y."""
    A: np.ndarray
    y: np.ndarray
    block: np.ndarray           # block index of every row
    labels: list                # name of every block: tau_j, spring_j, T_j
    t: np.ndarray               # time of every row


def row_kinds(log: Log) -> tuple:
    """The rows a log's columns give: motor-torque rows (phi, tau), spring rows (phi: the link
    equations driven by the measured deflection), link-torque rows (T)."""
    return tuple(k for k, has in (("tau", log.tau is not None), ("spring", log.phi is not None),
                                  ("T", log.T is not None)) if has)


def base_kinds(logs: list) -> tuple:
    """The row kinds whose column space the base parameters are computed in: every kind some
    log has (a torque sensor beside motor-torque and spring rows adds its offsets)."""
    kinds = {k for log in logs for k in row_kinds(log)}
    return tuple(k for k in ("tau", "spring", "T") if k in kinds)


def load_loss_column(arm: Arm, theta, phi, dtheta, dphi, T=None, spring=None) -> np.ndarray:
    """d tau / d c1 per joint and sample (n, count): -|T| tanh(dphi / eps) / mu, |T| smoothed as
    the model's (ABS_SMOOTH), T the logged SEA torque, else the spring law's at `spring` (a model;
    default the arm's)."""
    from rscasadi.dynamics.arm import ABS_SMOOTH
    if T is None:
        T = spring_torque((spring or arm.model), theta, phi, dtheta, dphi)
    load = np.sqrt(T ** 2 + ABS_SMOOTH ** 2) - ABS_SMOOTH
    return -load * np.tanh(dphi / arm.model.column("eps")[:, None]) / arm.model.column("gear_ratio")[:, None]


def stribeck_column(arm: Arm, dphi) -> np.ndarray:
    """d tau / d s per joint and sample (n, count): -exp(-(dphi / v_s)^2) tanh(dphi / eps) / mu,
    at the model file's Stribeck speed v_s."""
    m = arm.model
    fall = np.exp(-(dphi / m.column("v_stribeck")[:, None]) ** 2)
    return -fall * np.tanh(dphi / m.column("eps")[:, None]) / m.column("gear_ratio")[:, None]


def rows(arm: Arm, sig: Signals, unknowns: Unknowns, reduced: bool = False, spring=None) -> Rows:
    """The regression rows of one filtered log: Y th = [tau; T] for every sample and joint, as
    far as the log's columns go (`row_kinds`); the gears' load-dependent losses with the logged T
    or the spring law of `spring` (a model; default the arm's)."""
    n, count = arm.n, sig.t.size
    Y = over_samples(regressor(arm, reduced=reduced), *sig.state())[0].reshape(2 * n, count, -1) @ unknowns.E
    if unknowns.load_losses():
        w = load_loss_column(arm, sig.theta, sig.phi, sig.dtheta, sig.dphi, T=sig.T if sig.phi_measured else None,
                             spring=spring)
        for k, j in unknowns.load_losses():
            Y[j, :, k] = w[j]
    if unknowns.stribeck():
        w = stribeck_column(arm, sig.dphi)
        for k, j in unknowns.stribeck():
            Y[j, :, k] = w[j]
    if unknowns.torque_constants() and sig.i is not None:   # Y th - (kt - kt_file) i = kt_file i
        K = unknowns.kt_change(arm.model)
        for j in range(n):
            Y[j] -= sig.i[j][:, None] * K[j][None, :]
    Ys = over_samples(spring_regressor(arm), *sig.state()[:4])[0].reshape(n, count, -1) @ unknowns.E
    # near a velocity reversal the Coulomb term c tanh(dphi / eps) jumps within milliseconds, and
    # the filtered torque no longer equals the loss at the filtered speed: those rows are left out
    eps = arm.model.column("eps")
    moving = [np.abs(sig.dphi[j]) > REVERSAL * eps[j] for j in range(n)]
    blocks = []
    if sig.tau is not None:
        blocks += [(f"tau_{j + 1}", Y[j][moving[j]], sig.tau[j][moving[j]], sig.t[moving[j]]) for j in range(n)]
    if sig.phi_measured:
        blocks += [(f"spring_{j + 1}", Y[n + j] - Ys[j], np.zeros(count), sig.t) for j in range(n)]
    if sig.T is not None:
        for j in range(n):
            A = Y[n + j].copy()
            A[:, [k for k, jj in unknowns.offsets() if jj == j]] = 1.0           # T_j logged = T_j + offset_j
            blocks.append((f"T_{j + 1}", A, sig.T[j], sig.t))
    return Rows(np.vstack([b[1] for b in blocks]), np.concatenate([b[2] for b in blocks]),
                np.concatenate([np.full(len(b[2]), i) for i, b in enumerate(blocks)]), [b[0] for b in blocks],
                np.concatenate([b[3] for b in blocks]))


def check_moving(rows_: Rows, arm: Arm, path) -> None:
    """Refuse a log in which a joint's motor hardly turns: its torque rows (kept outside the
    Coulomb reversal band) are too few to fit or to predict that joint's torque."""
    if "tau_1" not in rows_.labels:              # a link-side log: the rank check covers its motion
        return
    for j, jt in enumerate(arm.model.joints):
        b = rows_.labels.index(f"tau_{j + 1}")
        count = int(np.sum(rows_.block == b))
        if count < MIN_ROWS:
            raise LogError(f"{path}: column 'phi_{j + 1}': joint {jt.name}'s motor hardly turns ({count} of "
                           f"{int(np.sum(rows_.block == rows_.labels.index('spring_1')))} samples outside its Coulomb "
                           f"band, at least {MIN_ROWS} needed): the log does not excite this joint")


def combine(parts: list[Rows]) -> Rows:
    """The rows of several logs stacked into one regression."""
    return Rows(np.vstack([r.A for r in parts]), np.concatenate([r.y for r in parts]),
                np.concatenate([r.block for r in parts]), parts[0].labels, np.concatenate([r.t for r in parts]))


# ----------------------------------------------------------------------------- estimation

@dataclass
class LeastSquares:
    """The weighted least-squares estimate of the base parameters and its covariance."""
    base: BaseParameters
    beta: np.ndarray
    info: np.ndarray            # Fisher information of beta (inverse covariance)
    sigma: np.ndarray           # residual standard deviation of every block
    condition: float
    cov_segments: np.ndarray | None = None     # the spread of beta over resampled stretches of the logs
    cov_filter: np.ndarray | None = None       # how far beta moves with the filter's cut-off

    @property
    def cov_noise(self) -> np.ndarray:
        """The inverse of the information (what the noise alone allows), computed in equilibrated
        coordinates (its diagonal spans many decades: a spring's k3 column is psi^3)."""
        d = 1.0 / np.sqrt(np.maximum(np.diag(self.info), 1e-300))
        return d[:, None] * np.linalg.inv(d[:, None] * self.info * d[None, :]) * d[None, :]

    @property
    def cov(self) -> np.ndarray:
        """The covariance reported: the noise's, or the segment bootstrap's where it is larger
        along a direction (model error and filtering make stretches of the log disagree more
        than white noise would): both are positive semidefinite, and their elementwise larger
        diagonal is kept with the noise's correlations."""
        cov = self.cov_noise
        if self.cov_segments is not None:
            scale = np.sqrt(np.maximum(np.diag(self.cov_segments), np.diag(cov)) / np.maximum(np.diag(cov), 1e-300))
            cov = scale[:, None] * cov * scale[None, :]
        return cov if self.cov_filter is None else cov + self.cov_filter

    def std_of(self, c) -> float | None:
        """The standard deviation of c . th: the larger of the noise's and the segment
        bootstrap's variance, plus the cut-off's (the estimate's move between two cut-offs)."""
        d = self.base.functional(c)
        if d is None:
            return None
        var = d @ self.cov_noise @ d
        if self.cov_segments is not None:
            var = max(var, d @ self.cov_segments @ d)
        if self.cov_filter is not None:
            var += d @ self.cov_filter @ d
        return float(np.sqrt(max(var, 0.0)))


def structural_base(arm: Arm, unknowns: Unknowns, samples: int = 200, reduced: bool = False,
                    kinds=("tau", "spring")) -> BaseParameters:
    """The base parameters of th in rows of `kinds` (`base_kinds`), from random samples: what
    no data with those columns can separate; `unidentifiable` names what they do not see at all."""
    W = stacked(arm, random_samples(arm, samples, np.random.default_rng(0)), kinds, reduced) @ unknowns.E
    rows_per = W.shape[0] // samples
    if "T" in kinds and unknowns.offsets():                # the T rows (the last n of each sample) see offsets
        for k, j in unknowns.offsets():
            W[rows_per - arm.n + j::rows_per, k] = 1.0
    if "tau" in kinds and unknowns.load_losses():          # the tau rows (the first n) see the load losses
        theta, phi, dtheta, dphi = random_samples(arm, samples, np.random.default_rng(0))[:4]
        w = load_loss_column(arm, theta, phi, dtheta, dphi)
        for k, j in unknowns.load_losses():
            W[j::rows_per, k] = w[j]
    if "tau" in kinds and unknowns.stribeck():             # and the Stribeck excesses
        dphi = random_samples(arm, samples, np.random.default_rng(0))[3]
        w = stribeck_column(arm, dphi)
        for k, j in unknowns.stribeck():
            W[j::rows_per, k] = w[j]
    if "tau" in kinds and unknowns.torque_constants():     # and the currents (any: a motor's own column)
        currents, K = np.random.default_rng(1).normal(size=(arm.n, samples)), unknowns.kt_change(arm.model)
        for j in range(arm.n):
            W[j::rows_per] -= currents[j][:, None] * K[j][None, :]
    return base_of(W, unknowns.names, rtol=1e-9)


def excitation_rank(rows_: Rows, base: BaseParameters, rtol: float = 1e-10) -> int:
    """How many base parameters the rows determine (numerical rank of the equilibrated columns)."""
    A = rows_.A[:, base.independent]
    A = A / np.maximum(np.linalg.norm(A, axis=0), 1e-300)
    if A.shape[0] < A.shape[1]:
        return A.shape[0]
    return int(np.linalg.matrix_rank(A, tol=rtol * np.sqrt(A.shape[0])))


def least_squares(rows_: Rows, base: BaseParameters, th_nominal: np.ndarray, bootstrap: bool = True) -> LeastSquares:
    """Weighted least squares in the base parameters.  Each block (a joint's motor-torque rows,
    its spring rows, ...) is weighted by 1 / its residual RMS, re-estimated twice; the weights
    start from, and are floored at 1e-4 of, the block's torque under the nominal model, so that
    the homogeneous spring rows (T - T_spring = 0) cannot pull the estimate to zero."""
    Ab = rows_.A[:, base.independent]
    nb = len(rows_.labels)
    size = np.array([max(np.sqrt(np.mean((rows_.A[rows_.block == b] @ th_nominal) ** 2)), 1e-12) for b in range(nb)])
    sigma = size.copy()
    for _ in range(3):
        w = 1.0 / sigma[rows_.block]
        beta, *_ = np.linalg.lstsq(Ab * w[:, None], rows_.y * w, rcond=None)
        res = Ab @ beta - rows_.y
        sigma = np.array([max(np.sqrt(np.mean(res[rows_.block == b] ** 2)), 1e-4 * size[b]) for b in range(nb)])
    w = 1.0 / sigma[rows_.block]
    Aw = Ab * w[:, None]
    dof = max(Aw.shape[0] - Aw.shape[1], 1)
    res_w = Aw @ beta - rows_.y * w
    s2 = float(np.sum(res_w ** 2) / dof) * _correlation_inflation(res_w, rows_.block)
    sv = np.linalg.svd(Aw / np.linalg.norm(Aw, axis=0), compute_uv=False)
    return LeastSquares(base, beta, Aw.T @ Aw / s2, sigma, float(sv[0] / sv[-1]),
                        segment_bootstrap(Aw, rows_.y * w, rows_.t) if bootstrap else None)


SEGMENTS = 12            # stretches of the logs the bootstrap resamples
UNCERTAIN = 0.3          # a parameter whose std exceeds this fraction of its estimate is flagged
FILTER_PROBE = 0.8       # the second cut-off, as a fraction of the first, whose estimate tells the filter's effect
WEAK_CONDITION = 200.0   # a log whose regression is worse conditioned is warned about
BOOTSTRAP = 200          # resamples


def segment_bootstrap(Aw: np.ndarray, yw: np.ndarray, t: np.ndarray, seed: int = 0) -> np.ndarray | None:
    """The covariance of the weighted least-squares estimate over SEGMENTS stretches of the logs
    drawn with replacement (a block bootstrap: each stretch keeps its filtered, coloured
    residual whole, so model error that differs along the motion shows as spread); None where
    a resample cannot determine every combination."""
    edges = np.quantile(t, np.linspace(0, 1, SEGMENTS + 1))
    seg = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, SEGMENTS - 1)
    G = np.array([Aw[seg == k].T @ Aw[seg == k] for k in range(SEGMENTS)])
    g = np.array([Aw[seg == k].T @ yw[seg == k] for k in range(SEGMENTS)])
    d = 1.0 / np.sqrt(np.maximum(np.diag(G.sum(0)), 1e-300))            # equilibrated, as cov_noise
    rng, betas = np.random.default_rng(seed), []
    for _ in range(BOOTSTRAP):
        counts = np.bincount(rng.integers(SEGMENTS, size=SEGMENTS), minlength=SEGMENTS)
        Gb, gb = np.tensordot(counts, G, 1), counts @ g
        try:
            betas.append(d * np.linalg.solve(d[:, None] * Gb * d[None, :], d * gb))
        except np.linalg.LinAlgError:
            return None
    return np.cov(np.array(betas).T)


def _correlation_inflation(res, block) -> float:
    """(1 + rho) / (1 - rho) for the lag-1 correlation rho of the residuals within blocks: filtered
    noise is not white, and the variance of a mean of AR(1) samples grows by this factor."""
    num = den = 0.0
    for b in np.unique(block):
        r = res[block == b]
        num, den = num + float(r[1:] @ r[:-1]), den + float(r @ r)
    rho = min(max(num / max(den, 1e-300), 0.0), 0.95)
    return (1 + rho) / (1 - rho)


def _pseudo_inertia(v):
    """J = [[tr(I)/2 1 - I, h], [h^T, m]] from the ten parameters (I about the frame origin);
    linear in v, so numbers and cvxpy expressions alike (Wensing, Kim and Slotine 2017, eq. 6)."""
    m, h = v[0], [v[1], v[2], v[3]]
    I = [[v[4], v[7], v[8]], [v[7], v[5], v[9]], [v[8], v[9], v[6]]]
    half = 0.5 * (v[4] + v[5] + v[6])
    return [[(half if r == c else 0) - I[r][c] for c in range(3)] + [h[r]] for r in range(3)] + [h + [m]]


FIT_MARGIN = 1e-4     # every body's pseudo-inertia at least this fraction of its nominal diagonal


def physical_fit(arm: Arm, unknowns: Unknowns, ls: LeastSquares, th_nominal: np.ndarray) -> tuple[np.ndarray, str]:
    """The physically consistent th closest to the base estimate in its information metric, with
    a weak prior on the model file's values for the directions the data cannot see.  Convex:
    every body's pseudo-inertia J(th) >= 0 is a linear matrix inequality (Wensing, Kim and
    Slotine 2017), k1 > 0 and k3, d, b, c >= 0; the cost is quadratic.  Its optimum is unique,
    so it does not depend on a start point or on the machine."""
    import cvxpy as cp
    model, m = arm.model, len(unknowns.names)
    scale = prior_scale(unknowns, th_nominal)
    x = cp.Variable(m)                                    # th = scale * x: every unknown of size ~1
    p = unknowns.E @ cp.multiply(scale, x)
    p_nom = unknowns.E @ th_nominal
    cons = []
    firsts = [j * PER_JOINT + 10 * i for j in range(model.n) for i in range(len(BODIES))]
    firsts += [payload_slice(model).start] if model.payload is not None else []
    for first in firsts:
        J = cp.bmat(_pseudo_inertia([p[first + k] for k in range(10)]))
        d = np.sqrt(np.maximum(np.diag(np.array(_pseudo_inertia(list(p_nom[first:first + 10])))), 1e-300))
        Dinv = np.diag(1.0 / d)                          # congruence: each body's J on the scale of its nominal
        cons.append(Dinv @ J @ Dinv - FIT_MARGIN * np.eye(4) >> 0)
    for j, jt in enumerate(model.joints):
        for attr in ACTUATOR + ("gear_loss.c1", "gear_loss.stribeck"):
            if f"{jt.name}.{attr}" in unknowns.names:
                k = unknowns.names.index(f"{jt.name}.{attr}")
                cons.append(x[k] >= (1e-3 if attr == "sea.k1" else 0.0))
    for k, _ in unknowns.torque_constants():              # kt > 0: th = kt - kt_file, scaled by kt_file
        cons.append(x[k] >= 1e-3 - 1.0)
    d = 1.0 / np.sqrt(np.maximum(np.diag(ls.info), 1e-300))
    W = np.linalg.cholesky(d[:, None] * ls.info * d[None, :]).T / d[None, :]     # W^T W = info
    data = W @ ls.base.P @ np.diag(scale)
    cost = cp.sum_squares(data @ x - W @ ls.beta) + cp.sum_squares((x - th_nominal / scale) / PRIOR)
    problem = cp.Problem(cp.Minimize(cost), cons)
    with warnings.catch_warnings():         # cvxpy warns of reduced accuracy; the status below says it
        warnings.simplefilter("ignore", UserWarning)
        problem.solve(solver=cp.CLARABEL)
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or x.value is None:
        raise CheckError(f"the physically consistent fit failed: Clarabel reports {problem.status}")
    status = "converged" if problem.status == cp.OPTIMAL else "converged (to Clarabel's reduced tolerances)"
    return scale * np.asarray(x.value), status


def prior_scale(unknowns: Unknowns, th_nominal, floor: float = 0.0) -> np.ndarray:
    """A size for every unknown: its nominal magnitude, and for zero nominals that of its kind in
    the same body (first moments: mass x 5 cm; inertias: the body's largest moment; k3: the cubic
    term that doubles k1 at 5 cm of deflection).  `floor`: every size at least this fraction of
    its kind's, so that a value a URDF writes as round-off (a product of inertia of 6e-8 kg m^2
    beside moments of 1e-3) is sized as its kind, not as 1e-8 (the excitation design's scaling)."""
    th_nominal = np.asarray(th_nominal, float)
    scale = np.abs(th_nominal).copy()
    for k, (name, kind) in enumerate(zip(unknowns.names, unknowns.kinds)):
        same = [i for i, kd in enumerate(unknowns.kinds) if kd[:3] == kind[:3]]
        q = name.rsplit(".", 1)[1]
        if q in ("mx", "my", "mz"):
            mass = th_nominal[next(i for i in same if unknowns.names[i].endswith(".mass"))]
            size = 0.05 * abs(mass)
        elif q.startswith("I"):
            size = max(abs(th_nominal[i]) for i in same if unknowns.names[i].rsplit(".", 1)[1].startswith("I"))
        elif q == "k3":
            k1 = th_nominal[unknowns.names.index(name.replace("sea.k3", "sea.k1"))]
            size = abs(k1) / 0.05 ** 2
        elif k in unknowns.shift:                         # a torque constant's change: the file's kt
            size = abs(unknowns.shift[k])
        elif scale[k] > 0:
            continue
        else:                                             # a loss (b, c, d) with nominal 0
            size = 1.0
        scale[k] = size if scale[k] == 0 else max(scale[k], floor * size)
    return np.maximum(scale, 1e-12)


# ----------------------------------------------------------------------------- the model

def identified_model(arm: Arm, unknowns: Unknowns, th: np.ndarray) -> ArmModel:
    """The model file's arm with the identified parameters `th` in place of the nominal ones."""
    import dataclasses
    p = unknowns.E @ th
    joints = []
    for j, jt in enumerate(arm.model.joints):
        base = j * PER_JOINT
        bodies = {b: body_from_parameters(p[base + 10 * i: base + 10 * (i + 1)]) for i, b in enumerate(BODIES)}
        act = {a: float(v) for a, v in zip(ACTUATOR_ATTR, p[base + 30: base + PER_JOINT])}
        act.update({"c1": float(th[k]) for k, jj in unknowns.load_losses() if jj == j})
        act.update({"stribeck": float(th[k]) for k, jj in unknowns.stribeck() if jj == j})
        if unknowns.torque_constants():
            act["torque_constant"] = float(jt.torque_constant + unknowns.kt_change(arm.model)[j] @ th)
        joints.append(dataclasses.replace(jt, **act, **bodies))
    held = arm.model.payload
    if held is not None:
        held = dataclasses.replace(held, body=body_from_parameters(p[payload_slice(arm.model)]))
    return dataclasses.replace(arm.model, joints=tuple(joints), payload=held, name=arm.model.name + "-identified")


def predict(rows_: Rows, th: np.ndarray) -> dict:
    """Per block: RMS of the measured torque, RMS of the prediction error, their ratio."""
    out, pred = {}, rows_.A @ th
    for b, label in enumerate(rows_.labels):
        sel = rows_.block == b
        if label.startswith("spring"):
            continue
        rms, err = float(np.sqrt(np.mean(rows_.y[sel] ** 2))), float(np.sqrt(np.mean((pred[sel] - rows_.y[sel]) ** 2)))
        out[label] = {"rms": rms, "error_rms": err, "relative": err / max(rms, 1e-300)}
    return out


@dataclass
class Identification:
    """An identification: the unknowns, the least-squares estimate, the physically consistent
    parameters `th` and the nominal ones."""
    unknowns: Unknowns
    ls: LeastSquares
    th: np.ndarray
    th_nominal: np.ndarray
    model: ArmModel
    cutoff_hz: float
    cutoff_why: str
    rows: Rows
    fit_status: str = "converged"
    sensors: str = ""               # the columns the logs had, in words
    kinds: tuple = ()               # the row kinds the base parameters were computed in
    cutoff_scores: dict | None = None   # cross_validated_cutoff's {cut-off: score}, where it chose

    def std(self) -> np.ndarray:
        out = np.full(len(self.th), np.nan)
        for k in range(len(self.th)):
            s = self.ls.std_of(np.eye(len(self.th))[k])
            out[k] = np.nan if s is None else s
        return out

    def combination(self, c) -> tuple[float, float | None]:
        """The estimate of c . th and its standard deviation (None if not identifiable)."""
        c = np.asarray(c, float)
        return float(c @ self.th), self.ls.std_of(c)


def kt_scale(logs: list[Log]) -> str | None:
    """How the logs determine the motors' torque constants (`Unknowns.of`): None without currents;
    "sensor" where a torque sensor's T fixes the scale; else "ratios": currents give tau = kt i
    only up to a scale that every other parameter shares (kt, the inertias, springs and losses
    times one factor predict the same motions), so only the torque constants' ratios are found."""
    if not any(lg.i is not None for lg in logs):
        return None
    return "sensor" if any(lg.T is not None for lg in logs) else "ratios"


def identify(arm: Arm, logs: list[Log], reduced: bool = False, fc: float | None = None) -> Identification:
    """Everything from logs to a physically consistent model."""
    unknowns = Unknowns.of(arm.model, sensor_offsets=any(log.T is not None for log in logs),
                           torque_constants=kt_scale(logs))
    th_nominal = unknowns.from_p(arm.parameters()[1][:n_linear(arm.model)])
    short = [lg.path for lg in logs if lg.t[-1] - lg.t[0] <= 4 * EDGE_S]
    if short:
        raise LogError(f"{', '.join(short)}: column 't': shorter than {4 * EDGE_S:g} s, too short to filter and "
                       f"excite the parameters")
    base = structural_base(arm, unknowns, reduced=reduced, kinds=base_kinds(logs))
    scores = None
    if fc is not None:
        why = f"{fc:.1f} Hz, set by the user"
    elif all(lg.link_side for lg in logs) and (cv := cross_validated_cutoff(arm, logs, unknowns, base, th_nominal,
                                                                           reduced)) is not None:
        fc, why, scores = cv
    else:
        fc, why = cutoff_hz(arm, logs[0])
    signals = [prepare(log, fc, arm=arm) for log in logs]
    rows_ = combine([rows(arm, sig, unknowns, reduced) for sig in signals])
    excited = excitation_rank(rows_, base)
    if excited < base.rank:
        raise LogError(f"{', '.join(lg.path for lg in logs)}: the logged motion determines only {excited} of the "
                       f"{base.rank} identifiable parameter combinations: log a longer or richer motion "
                       f"(rscasadi excite designs one)")
    check_moving(rows_, arm, ", ".join(lg.path for lg in logs))
    # a load-dependent gear loss c1 |T| is linear in c1 once T is known: the logged T where there
    # is one, else the spring law's T, at the model file's spring first, then at the identified one
    # (a fixed point: LOAD_PASSES passes, each a least-squares fit and a physical one)
    iterate = bool(unknowns.load_losses()) and any(lg.T is None for lg in logs)
    spring = None
    for _ in range(LOAD_PASSES if iterate else 1):
        if spring is not None:                         # the first pass takes the rows above
            rows_ = combine([rows(arm, sig, unknowns, reduced, spring) for sig in signals])
        ls = least_squares(rows_, base, th_nominal)
        # what filtering does to the estimate: again at FILTER_PROBE times the cut-off
        probe = combine([rows(arm, prepare(log, FILTER_PROBE * fc, arm=arm), unknowns, reduced, spring)
                         for log in logs])
        moved = ls.beta - least_squares(probe, base, th_nominal, bootstrap=False).beta
        ls.cov_filter = np.outer(moved, moved)
        th, status = physical_fit(arm, unknowns, ls, th_nominal)
        spring = identified_model(arm, unknowns, th)
    sensors = "; ".join(sorted({log.describe() for log in logs}))
    return Identification(unknowns, ls, th, th_nominal, identified_model(arm, unknowns, th), fc, why, rows_, status,
                          sensors, base_kinds(logs), scores)


# ----------------------------------------------------------------------------- command

def reflected_inertia(unknowns: Unknowns, model: ArmModel, j: int) -> np.ndarray:
    """c with c . th = B_j = Izz_O(S_j) + mu_j^2 Izz_O(F_j)."""
    jt, c = model.joints[j], np.zeros(len(unknowns.names))
    c[unknowns.names.index(f"{jt.name}.slow_rotor.Izz")] = 1.0
    c[unknowns.names.index(f"{jt.name}.fast_rotor.Izz")] = jt.gear_ratio ** 2
    return c


def report(ident: Identification, arm: Arm, validation: dict | None, log_files: list) -> dict:
    """The identification's report (report.json): base parameters with their standard deviations,
    the physical fit, the held-out validation if any, and the logs used."""
    std = ident.std()
    u = ident.unknowns
    base = [{"combination": line.split(" = ", 1)[1], "estimate": float(b), "std": float(np.sqrt(ident.ls.cov[i, i]))}
            for i, (line, b) in enumerate(zip(ident.ls.base.explain(), ident.ls.beta))]
    reflected = {}
    for j, jt in enumerate(arm.model.joints):
        est, s = ident.combination(reflected_inertia(u, arm.model, j))
        reflected[jt.name] = {"nominal": float(reflected_inertia(u, arm.model, j) @ ident.th_nominal),
                              "estimate": est, "std": s}
    residual = {label: float(s) for label, s in zip(ident.rows.labels, ident.ls.sigma)}
    uncertain = {name: float(s / abs(est)) for name, est, s in zip(u.names, u.values(ident.th), std)
                 if np.isfinite(s) and abs(est) > 0 and s > UNCERTAIN * abs(est)}
    warnings = []
    if ident.ls.condition > WEAK_CONDITION:
        warnings.append(f"a weak log: condition number {ident.ls.condition:.3g} > {WEAK_CONDITION:g} (a designed "
                        "excitation gives about 40): the estimates can be far off their standard deviations; log "
                        "a longer, richer motion (rscasadi excite designs one)")
    if uncertain:
        warnings.append(f"{len(uncertain)} parameters uncertain by more than {UNCERTAIN:.0%} of their estimate "
                        f"(report.json: uncertain): " + ", ".join(sorted(uncertain, key=uncertain.get, reverse=True)[:6]))
    parameters = {name: {"nominal": float(nom), "estimate": float(est), "std": None if np.isnan(s) else float(s)}
                  for name, nom, est, s in zip(u.names, u.values(ident.th_nominal), u.values(ident.th), std)}
    if u.torque_constants():                              # every motor's, the last one's too where it follows
        K = u.kt_change(arm.model)
        for j, jt in enumerate(arm.model.joints):
            parameters[f"{jt.name}.torque_constant"] = {"nominal": jt.torque_constant,
                                                         "estimate": float(jt.torque_constant + K[j] @ ident.th),
                                                         "std": ident.ls.std_of(K[j])}
    return {
        "warnings": warnings, "uncertain": uncertain,
        "model": str(arm.model.path), "logs": [str(f) for f in log_files],
        "sensors": ident.sensors, "rows": list(ident.kinds),
        "undetermined": {"parameters": ident.ls.base.unidentifiable,
                         "why": f"no effect on what the logs measure ({ident.sensors}): kept at the model file's "
                                "values"},
        "cutoff_hz": ident.cutoff_hz, "cutoff_why": ident.cutoff_why, "cutoff_cross_validation": ident.cutoff_scores,
        "condition_number": ident.ls.condition, "physical_fit": ident.fit_status, "base_parameters": base,
        "parameters": parameters,
        "reflected_rotor_inertia": reflected,
        "residual_rms": residual,
        "fit": predict(ident.rows, ident.th),
        "validation": validation,
        "notes": "std: the larger of the weighted least squares' noise covariance (inflated for the residual's "
                 "colour) and the spread over resampled stretches of the logs (a segment bootstrap, which model "
                 "error widens), plus how far the estimate moves when the cut-off is lowered by 20 % (filtering); "
                 "null where a parameter is identifiable only in combination with others (see base_parameters). "
                 "Balanced rotors are identified as balanced (mass, mz, Ixx = Iyy, Izz).",
    }


CUTOFF_FACTORS = (0.5, 0.7, 1.0, 1.4, 2.0)   # the cut-offs the held-out check tries, times the chosen one
CUTOFF_BETTER = 0.8                          # another cut-off this much better in the check is warned about


def cutoff_check(arm: Arm, logs: list, val_log: Log, ident: "Identification", reduced: bool = False) -> list:
    """Whether the chosen cut-off is near the best: the base parameters estimated (least squares)
    with the logs filtered at CUTOFF_FACTORS times it, each predicting the held-out log filtered
    at the chosen cut-off (one target for all: a lower cut-off would otherwise win by smoothing
    its own target).  [{factor, cutoff_hz, held_out_worst}] of the worst column's relative RMS error."""
    base, fc0 = ident.ls.base, ident.cutoff_hz
    val = rows(arm, prepare(val_log, fc0, arm=arm), ident.unknowns, reduced, ident.model)
    out = []
    for factor in CUTOFF_FACTORS:
        fc = factor * fc0
        if fc >= 0.45 / min(lg.dt for lg in logs):
            continue
        fit = combine([rows(arm, prepare(lg, fc, arm=arm), ident.unknowns, reduced, ident.model) for lg in logs])
        beta = least_squares(fit, base, ident.th_nominal, bootstrap=False).beta
        pred = val.A[:, base.independent] @ beta                # = A th for every th of these base parameters
        worst = max(float(np.sqrt(np.mean((pred[val.block == b] - val.y[val.block == b]) ** 2)
                                  / max(np.mean(val.y[val.block == b] ** 2), 1e-300)))
                    for b, label in enumerate(val.labels) if not label.startswith("spring"))
        out.append({"factor": factor, "cutoff_hz": fc, "held_out_worst": worst})
    return out


FRICTION_SHARE = 0.25    # a link-side residual this much smaller with b dtheta + c tanh(dtheta / eps) is named


def friction_hints(arm: Arm, logs: list, ident: "Identification", reduced: bool = False) -> list:
    """Joints of link-side logs whose model file declares no [joints.link_loss] but whose torques
    a viscous and a Coulomb link loss would explain: the least-squares fit in the base parameters
    again with those two columns added to the joint's rows leaves FRICTION_SHARE less of its
    squared residual, both terms dissipative.  One line each, naming the joint, the loss it
    looks like and the table to declare."""
    hints: list = []
    if not all(lg.link_side for lg in logs):
        return hints
    eps, base = arm.model.column("eps"), ident.ls.base
    parts = [(rows(arm, sig, ident.unknowns, reduced, ident.model), sig)
             for sig in (prepare(lg, ident.cutoff_hz, arm=arm) for lg in logs)]
    A = np.vstack([rw.A[:, base.independent] for rw, _ in parts])
    y = np.concatenate([rw.y for rw, _ in parts])
    plain = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
    for j, jt in enumerate(arm.model.joints):
        if "link_loss" in jt.declared:
            continue
        mine = np.concatenate([rw.block == rw.labels.index(f"T_{j + 1}") for rw, _ in parts])
        speed = np.zeros(len(y))
        speed[mine] = np.concatenate([sig.dtheta[j] for _, sig in parts])      # a T_j row per sample
        extra = np.column_stack([speed, np.where(mine, np.tanh(speed / eps[j]), 0.0)])    # T = ... + the loss
        coef = np.linalg.lstsq(np.hstack([A, extra]), y, rcond=None)[0]
        share = 1.0 - float(np.sum((y - np.hstack([A, extra]) @ coef)[mine] ** 2) / max(np.sum(plain[mine] ** 2), 1e-300))
        if share >= FRICTION_SHARE and np.all(coef[-2:] >= 0):
            hints.append(f"joint {jt.name}: a link-side friction (about b = {coef[-2]:.3g} N m s/rad, c = "
                         f"{coef[-1]:.3g} N m) would take {100 * share:.0f} % of its torque residual, and the model "
                         f"file declares none: add [joints.link_loss] (b, c) for {jt.name} and identify again")
    return hints


def _grouped(names: list) -> str:
    """Parameter names shortened: an attribute undetermined at every joint named once."""
    joints = sorted({name.split(".", 1)[0] for name in names})
    attrs = sorted({name.split(".", 1)[1] for name in names}, key=[n.split(".", 1)[1] for n in names].index)
    every = [a for a in attrs if len(joints) > 1 and all(f"{j}.{a}" in names for j in joints)]
    rest = [name for name in names if name.split(".", 1)[1] not in every]
    parts = ([f"{', '.join(every)} of every joint"] if every else []) + rest[:6]
    return "; ".join(parts) + (f" and {len(rest) - 6} more (report.json: undetermined)" if len(rest) > 6 else "")


def plot(out: Path, rows_: Rows, th: np.ndarray, title: str):
    """Measured against predicted torques of every joint, written to `out`.png."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    taus = ([b for b, label in enumerate(rows_.labels) if label.startswith("tau")]
            or [b for b, label in enumerate(rows_.labels) if label.startswith("T_")])
    fig, axes = plt.subplots(len(taus), 1, figsize=(8, 2.2 * len(taus)), sharex=True, squeeze=False)
    pred = rows_.A @ th
    for ax, b in zip(axes[:, 0], taus):
        sel = rows_.block == b
        ax.plot(rows_.t[sel], rows_.y[sel], ".", ms=2, label="measured (filtered)")
        ax.plot(rows_.t[sel], pred[sel], ".", ms=2, label="identified model")
        ax.set_ylabel(f"{rows_.labels[b]} (N m)")
    axes[0, 0].legend(fontsize=8)
    axes[0, 0].set_title(title)
    axes[-1, 0].set_xlabel("t (s)")
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=110)
    fig.savefig(out.with_suffix(".pdf"))
    plt.close(fig)


def run(model_file, log_files, out, validate=None, cutoff=None, explain=False, reduced=False, log=print) -> tuple[dict, Identification]:
    """`rscasadi identify`: fit the model to the logs, check it on a held-out log if given, and
    write the identified model file, its report and figures into `out`; returns (report, ident)."""
    check_writable(out)
    arm = load(model_file)
    require_sea(arm.model, "rscasadi identify")
    logs = [motor_torques(read_log(f, arm.n), arm.model) for f in log_files]
    val_log = motor_torques(read_log(validate, arm.n), arm.model) if validate else None
    if val_log is not None:                          # refused before the work, not after it
        fc = cutoff or cutoff_hz(arm, logs[0])[0]
        held_out = rows(arm, prepare(val_log, fc, arm=arm), Unknowns.of(arm.model, any(lg.T is not None for lg in logs)),
                        reduced)
        check_moving(held_out, arm, validate)
    if explain:
        u = Unknowns.of(arm.model, any(lg.T is not None for lg in logs), torque_constants=kt_scale(logs))
        fc = cutoff or cutoff_hz(arm, logs[0])[0]
        th_nominal = u.from_p(arm.parameters()[1][:n_linear(arm.model)])
        ls = least_squares(combine([rows(arm, prepare(lg, fc, arm=arm), u, reduced) for lg in logs]),
                           structural_base(arm, u, reduced=reduced, kinds=base_kinds(logs)), th_nominal)
        for line in ls.base.explain():
            log(line)
        log(f"{ls.base.rank} base parameters of {len(u.names)}; not identifiable at all: "
            f"{', '.join(ls.base.unidentifiable) or 'none'}")
    log(f"identifying {arm.model.name} from {len(logs)} log(s) ...")
    ident = identify(arm, logs, reduced=reduced, fc=cutoff)
    log(f"cut-off {ident.cutoff_why}")
    if kt_scale(logs) == "ratios":
        log("torque constants: their ratios from the currents; their mean held at the model file's (currents alone "
            "cannot tell a scale shared by every parameter; a joint torque sensor T_j in the log would)")
    log(f"{ident.ls.base.rank} base parameters, condition number {ident.ls.condition:.3g}; "
        f"physically consistent fit {ident.fit_status}")
    undetermined = ident.ls.base.unidentifiable
    if undetermined:
        log(f"{len(undetermined)} parameters have no effect on what the logs measure ({ident.sensors}), kept at "
            f"the model file's values: {_grouped(undetermined)}")
    validation: dict | None = None
    val_rows = None
    if val_log is not None:
        sig = prepare(val_log, ident.cutoff_hz, arm=arm)
        val_rows = rows(arm, sig, ident.unknowns, reduced, ident.model)
        validation = {"log": str(validate), "prediction": predict(val_rows, ident.th),
                      "nominal": predict(val_rows, ident.th_nominal)}
        worst = max(v["relative"] for v in validation["prediction"].values())
        nominal = max(v["relative"] for v in validation["nominal"].values())
        log(f"validation on {validate}: worst relative RMS error {worst:.3%} (the model file's: {nominal:.3%})")
        check = cutoff_check(arm, logs, val_log, ident, reduced)
        validation["cutoff_check"] = check
        mine = next(c["held_out_worst"] for c in check if c["factor"] == 1.0)
        best = min(check, key=lambda c: c["held_out_worst"])
        log("cut-off check (least squares at each cut-off, held-out worst error): " + ", ".join(
            f"{c['cutoff_hz']:.1f} Hz {c['held_out_worst']:.2%}" for c in check))
    here = lambda f: os.path.relpath(Path(f).resolve(), Path(out).resolve())   # paths as seen from DIR
    if validation:
        validation["log"] = here(validate)
    rep = report(ident, arm, validation, [here(f) for f in log_files])
    rep["model"] = here(model_file)
    if validation and best["held_out_worst"] < CUTOFF_BETTER * mine:
        rep["warnings"].append(f"the cut-off {best['cutoff_hz']:.1f} Hz predicts the held-out log better than the "
                               f"chosen {ident.cutoff_hz:.1f} Hz ({best['held_out_worst']:.2%} against {mine:.2%} "
                               f"worst error): try --cutoff {best['cutoff_hz']:.1f}")
    rep["warnings"] += friction_hints(arm, logs, ident, reduced)
    for warning in rep["warnings"]:
        log(f"warning: {warning}")
    with fresh_directory(out) as tmp:
        (tmp / "model.toml").write_text(f"# identified by rscasadi identify from {', '.join(rep['logs'])}\n"
                                         + to_toml(document(ident.model)))
        write_json(tmp / "report.json", rep, indent=2)
        first = prepare(logs[0], ident.cutoff_hz, arm=arm)
        plot(tmp / "fit", rows(arm, first, ident.unknowns, reduced, ident.model), ident.th,
             f"identification log {Path(log_files[0]).name}")
        if val_rows is not None:
            plot(tmp / "validation", val_rows, ident.th, f"held-out log {Path(validate).name}")
    log(f"wrote {Path(out) / 'model.toml'}, report.json and figures")
    return rep, ident
