"""The MPC problem file (docs/user-guide/mpc.md): the model, the reference, horizon, sampling and
weights, checked field by field."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rscasadi.model.checks import field_checker, read_toml

TOP = {"model", "trajectory", "sample_time", "horizon", "interval", "substeps", "sqp_iterations", "qp_iterations",
       "weights"}
WEIGHTS = {"theta": 1e5, "dtheta": 1.0, "tau": 1e-3, "limits": 1e5}
SOFT = 0.9                   # penalties start at this fraction of the psi and dphi limits
LINE_SEARCH = (1.0, 0.5, 0.25, 0.125)   # step sizes tried when sqp_iterations > 1


@dataclass
class MPCProblem:
    path: Path
    model_path: Path
    trajectory: Path | None = None
    sample_time: float = 1e-3
    horizon: int = 10
    interval: float = 0.01
    substeps: int = 5
    sqp_iterations: int = 1
    qp_iterations: int = 16
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
    for key, lo in (("horizon", 1), ("substeps", 1), ("sqp_iterations", 1), ("qp_iterations", 1)):
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
