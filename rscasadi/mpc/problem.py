"""The MPC problem file (docs/user-guide/mpc.md): the model, the reference, horizon, sampling and
weights, checked field by field."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rscasadi.model.checks import field_checker, read_toml
from rscasadi.model.types import ModelFileError

TOP = {"model", "trajectory", "sample_time", "horizon", "interval", "substeps", "sqp_iterations", "qp_iterations",
       "weights"}
WEIGHTS = {"theta": 1e5, "dtheta": 1.0, "tau": 1e-3, "limits": 1e5}
SOFT = 0.9                   # penalties start at this fraction of the psi and dphi limits
LINE_SEARCH = (1.0, 0.5, 0.25, 0.125)   # step sizes tried when sqp_iterations > 1


@dataclass
class MPCProblem:
    """An MPC problem: the `model` and the reference `trajectory`, the controller's `sample_time`,
    a horizon of `horizon` intervals of `interval` s with `substeps` RK4 steps each, the SQP
    iterations per sample (1: the real-time iteration) and the QP's interior-point iterations,
    and the cost `weights` (theta, dtheta, tau, limits).  Build it in Python or read it with
    `load_mpc_problem`; `check()` applies the file's rules.  `path`: the file it came from."""
    model: Path
    trajectory: Path | None = None
    sample_time: float = 1e-3
    horizon: int = 10
    interval: float = 0.01
    substeps: int = 5
    sqp_iterations: int = 1
    qp_iterations: int = 16
    weights: dict = field(default_factory=lambda: dict(WEIGHTS))
    path: Path | None = None

    def __post_init__(self):
        self.model = Path(self.model)
        self.trajectory = None if self.trajectory is None else Path(self.trajectory)
        self.weights = {**WEIGHTS, **self.weights}

    def check(self) -> "MPCProblem":
        """The problem file's rules on the object; a `ModelFileError` names the field."""
        where = str(self.path) if self.path is not None else "<MPCProblem>"

        def fail(fld, msg):
            raise ModelFileError(f"{where}: field '{fld}': {msg}")
        for key in ("sample_time", "interval"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v <= 0:
                fail(key, f"must be a positive number, got {v!r}")
        for key in ("horizon", "substeps", "sqp_iterations", "qp_iterations"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                fail(key, f"must be an integer >= 1, got {v!r}")
        for key, v in self.weights.items():
            if key not in WEIGHTS:
                fail(f"weights.{key}", f"unknown weight (allowed: {', '.join(WEIGHTS)})")
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v < 0:
                fail(f"weights.{key}", f"must be a number >= 0, got {v!r}")
        return self


def load_mpc_problem(path) -> MPCProblem:
    """Read and check an MPC problem file (docs/user-guide/mpc.md); errors name the field."""
    path = Path(path)
    d = read_toml(path, "MPC problem")
    fail = field_checker(path, d, TOP)
    if not isinstance(d.get("model"), str):
        fail("model", "missing, or not the path of a model file")
    if "trajectory" in d and not isinstance(d["trajectory"], str):
        fail("trajectory", "expected the path of a trajectory file")
    if not isinstance(d.get("weights", {}), dict):
        fail("weights", "expected a table")
    fields = {k: d[k] for k in TOP - {"model", "trajectory", "weights"} if k in d}
    return MPCProblem((path.parent / d["model"]).resolve(),
                      (path.parent / d["trajectory"]).resolve() if "trajectory" in d else None,
                      weights=dict(d.get("weights", {})), path=path, **fields).check()


def mpc_problem(problem) -> MPCProblem:
    """`problem` itself (checked) if an MPCProblem, else the problem file it names."""
    return problem.check() if isinstance(problem, MPCProblem) else load_mpc_problem(problem)
