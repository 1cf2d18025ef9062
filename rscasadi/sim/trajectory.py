"""Expected link trajectories, read from and written to TOML (docs/user-guide/problems.md).

Two kinds, each theta(t) as a CasADi expression whose derivatives come from AD:

    kind = "bump" (the default; the paper's Fig. 5)
    model = "arm3.toml"            # relative to this file
    period = 2.0                   # s
    duration = 2.0                 # s
    start = [0.0, 0.3, -0.5]       # rad, theta at t = 0
    amplitude = [0.8, 0.6, -0.9]   # rad

theta_j(t) = start_j + amplitude_j * (1 - cos(2 pi t / period))^2 / 4: at rest with zero
acceleration and jerk at t = 0, out to start + amplitude at period / 2 and back.

    kind = "fourier" (excitation trajectories, Swevers et al.)
    model = "arm3.toml"
    period = 10.0                  # s: the base frequency is 1 / period
    duration = 10.0                # s
    offset = [0.0, 0.3, -0.5]      # rad
    a = [[...], ...]               # n rows of K sine coefficients (rad/s)
    b = [[...], ...]               # n rows of K cosine coefficients (rad/s)

theta_j(t) = offset_j + sum_l a_jl / (w l) sin(w l t) - b_jl / (w l) cos(w l t), w = 2 pi / period.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from rscasadi.model.modelfile import ModelFileError, read_toml, to_toml

KEYS = {"bump": {"kind", "model", "period", "duration", "start", "amplitude"},
        "fourier": {"kind", "model", "period", "duration", "offset", "a", "b"}}


def bump(t, period, start, amplitude):
    """theta(t) = start + amplitude (1 - cos(2 pi t / period))^2 / 4: at rest with zero
    acceleration and jerk at t = 0 and t = period."""
    w = 2 * np.pi / period
    return ca.DM(start) + ca.DM(amplitude) * (1 - ca.cos(w * t)) ** 2 / 4


def fourier(t, period, offset, a, b):
    """The finite Fourier series; a, b: (n, K) arrays (numbers or CasADi symbols)."""
    w = 2 * np.pi / period
    K = a.shape[1]
    q = ca.DM(offset) if not isinstance(offset, (ca.SX, ca.MX)) else offset
    for l in range(1, K + 1):
        q = q + a[:, l - 1] / (w * l) * ca.sin(w * l * t) - b[:, l - 1] / (w * l) * ca.cos(w * l * t)
    return q


@dataclass
class Trajectory:
    """An expected link trajectory (bump or Fourier): called at times t it gives theta and its first four
    derivatives (each n x len(t))."""
    model_path: Path
    period: float
    duration: float
    start: np.ndarray | None = None
    amplitude: np.ndarray | None = None
    kind: str = "bump"
    offset: np.ndarray | None = None
    a: np.ndarray | None = None
    b: np.ndarray | None = None
    _f: ca.Function = field(init=False, repr=False)

    def __post_init__(self):
        t = ca.SX.sym("t")
        q = (bump(t, self.period, self.start, self.amplitude) if self.kind == "bump"
             else fourier(t, self.period, self.offset, ca.DM(self.a), ca.DM(self.b)))
        derivs = [q]
        for _ in range(4):
            derivs.append(ca.jacobian(derivs[-1], t))
        self._f = ca.Function("theta_d", [t], derivs)

    @property
    def n(self) -> int:
        return len(self.start if self.kind == "bump" else self.offset)

    def __call__(self, t):
        """theta and its first four derivatives at the times t: five arrays (n, len(t))."""
        t = np.atleast_1d(np.asarray(t, float))
        out = self._f.map(len(t))(t[None, :])
        return [np.array(o) for o in out]

    def document(self, model: str) -> dict:
        head = {"kind": self.kind, "model": model, "period": self.period, "duration": self.duration}
        if self.kind == "bump":
            return {**head, "start": list(self.start), "amplitude": list(self.amplitude)}
        return {**head, "offset": list(self.offset), "a": [list(r) for r in self.a], "b": [list(r) for r in self.b]}

    def write(self, path, model: str):
        Path(path).write_text(to_toml(self.document(model)))


def _numbers(path, key, v, shape_hint):
    arr = np.asarray(v, dtype=object)
    try:
        out = np.array(v, dtype=float)
    except (TypeError, ValueError):
        raise ModelFileError(f"{path}: field '{key}': expected {shape_hint} of numbers, got {v!r}") from None
    if arr.dtype == bool or any(isinstance(x, bool) for x in np.ravel(arr)) or not np.all(np.isfinite(out)):
        raise ModelFileError(f"{path}: field '{key}': expected {shape_hint} of finite numbers, got {v!r}")
    return out


def load_trajectory(path) -> Trajectory:
    """Read and check a trajectory file (docs/user-guide/problems.md); errors name the field."""
    path = Path(path)
    data = read_toml(path, "trajectory")
    kind = data.get("kind", "bump")
    if kind not in KEYS:
        raise ModelFileError(f"{path}: field 'kind': must be one of {', '.join(KEYS)}, got {kind!r}")
    keys = KEYS[kind]
    for key in data:
        if key not in keys:
            raise ModelFileError(f"{path}: field '{key}': unknown key (allowed: {', '.join(sorted(keys))})")
    for key in keys - {"kind"}:
        if key not in data:
            raise ModelFileError(f"{path}: field '{key}': missing required field")
    if not isinstance(data["model"], str) or "\0" in data["model"]:
        raise ModelFileError(f"{path}: field 'model': expected a file name, got {data['model']!r}")
    for key in ("period", "duration"):
        if isinstance(data[key], bool) or not isinstance(data[key], (int, float)) or not data[key] > 0:
            raise ModelFileError(f"{path}: field '{key}': must be a number > 0, got {data[key]!r}")
    common = dict(model_path=(path.parent / data["model"]).resolve(), period=float(data["period"]),
                  duration=float(data["duration"]), kind=kind)
    if kind == "bump":
        start, amp = (_numbers(path, k, data[k], "a list") for k in ("start", "amplitude"))
        if start.ndim != 1 or amp.shape != start.shape:
            raise ModelFileError(f"{path}: field 'amplitude': {amp.size} entries, 'start' has {start.size}")
        return Trajectory(start=start, amplitude=amp, **common)
    offset = _numbers(path, "offset", data["offset"], "a list")
    a, b = (_numbers(path, k, data[k], "a list of lists") for k in ("a", "b"))
    if offset.ndim != 1 or a.ndim != 2 or a.shape != b.shape or a.shape[0] != offset.size:
        raise ModelFileError(f"{path}: field 'a': a and b must be {offset.size} rows of equally many "
                             f"coefficients, got shapes {a.shape} and {b.shape}")
    return Trajectory(offset=offset, a=a, b=b, **common)
