"""Expected link trajectories (the analogue of the paper's Fig. 5), read from TOML.

    model = "arm3.toml"            # relative to this file
    period = 2.0                   # s
    duration = 2.0                 # s
    start = [0.0, 0.3, -0.5]       # rad, theta at t = 0
    amplitude = [0.8, 0.6, -0.9]   # rad

theta_j(t) = start_j + amplitude_j * (1 - cos(2 pi t / period))^2 / 4: it starts at rest with
zero acceleration and jerk (so a spring-consistent static equilibrium is a valid start),
reaches start + amplitude at period / 2 and comes back.  Derivatives come from CasADi's AD.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from ..model.modelfile import ModelFileError, read_toml

KEYS = {"model", "period", "duration", "start", "amplitude"}


@dataclass
class Trajectory:
    model_path: Path
    period: float
    duration: float
    start: np.ndarray
    amplitude: np.ndarray

    def __post_init__(self):
        t = ca.SX.sym("t")
        w = 2 * np.pi / self.period
        q = ca.DM(self.start) + ca.DM(self.amplitude) * (1 - ca.cos(w * t)) ** 2 / 4
        derivs = [q]
        for _ in range(4):
            derivs.append(ca.jacobian(derivs[-1], t))
        self._f = ca.Function("theta_d", [t], derivs)

    def __call__(self, t):
        """theta and its first four derivatives at the times t: five arrays (n, len(t))."""
        t = np.atleast_1d(np.asarray(t, float))
        out = self._f.map(len(t))(t[None, :])
        return [np.array(o) for o in out]


def load_trajectory(path) -> Trajectory:
    path = Path(path)
    data = read_toml(path, "trajectory")
    for key in data:
        if key not in KEYS:
            raise ModelFileError(f"{path}: field '{key}': unknown key (allowed: {', '.join(sorted(KEYS))})")
    for key in KEYS:
        if key not in data:
            raise ModelFileError(f"{path}: field '{key}': missing required field")
    for key in ("period", "duration"):
        if isinstance(data[key], bool) or not isinstance(data[key], (int, float)) or not data[key] > 0:
            raise ModelFileError(f"{path}: field '{key}': must be a number > 0, got {data[key]!r}")
    vecs = {}
    for key in ("start", "amplitude"):
        v = data[key]
        if not isinstance(v, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            raise ModelFileError(f"{path}: field '{key}': expected a list of numbers, got {v!r}")
        vecs[key] = np.array(v, float)
    if len(vecs["start"]) != len(vecs["amplitude"]):
        raise ModelFileError(f"{path}: field 'amplitude': {len(vecs['amplitude'])} entries, 'start' has "
                             f"{len(vecs['start'])}")
    return Trajectory((path.parent / data["model"]).resolve(), float(data["period"]), float(data["duration"]),
                      vecs["start"], vecs["amplitude"])
