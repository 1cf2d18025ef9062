"""What every generated controller shares: the input guard (templates/rscasadi_guard.h: the one
failure policy, its boxes checked before a controller acts), numbers written as C, and the
boxes a task-space reference must lie in."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from rscasadi.errors import InvalidArgument

GUARD = Path(__file__).with_name("templates") / "rscasadi_guard.h"
POSITION_BOUND = 10.0        # m: a frame's reference position, per axis
VELOCITY_BOUND = 20.0        # m/s: a frame's reference velocity, per axis
ROTATION_BOUND = 1.0 + 1e-6  # an entry of a reference rotation matrix


def guard_source() -> dict:
    """The guard header, as a source for the one build step (file name -> text)."""
    return {GUARD.name: GUARD.read_text()}


def c_numbers(values) -> str:
    """Numbers as a C initialiser list: round-trip exact, INFINITY for an infinite bound."""
    out = []
    for v in np.ravel(np.asarray(values, float)):
        if np.isnan(v):
            raise InvalidArgument("a NaN cannot be a controller's constant")
        out.append(repr(float(v)) if np.isfinite(v) else ("INFINITY" if v > 0 else "-INFINITY"))
    return ", ".join(out) or "0.0"


def c_words(values) -> str:
    """The same numbers for a header comment (short, 'inf' for none)."""
    return ", ".join(f"{v:.4g}" for v in np.ravel(np.asarray(values, float)))


def boxes(values: dict, words: bool = False) -> dict:
    """Named bounds as C initialisers (c_numbers), or with `words` as a header comment's numbers."""
    return {k: (c_words if words else c_numbers)(v) for k, v in values.items()}


def task_reference_bounds(rows: int, frames: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of a task-space reference column: per frame p (3), v (3) and, with 15 rows a frame,
    vec(R) (9)."""
    block = rows // frames
    hi = np.tile(np.concatenate([np.full(3, POSITION_BOUND), np.full(3, VELOCITY_BOUND),
                                 np.full(block - 6, ROTATION_BOUND)]), frames)
    return -hi, hi


# the return codes every controller shares (rscasadi_guard.h; each header names them with its prefix)
COLLISION, NOT_FINITE, FAILED, TOO_STIFF, BAD_ARGUMENT, BAD_MEASUREMENT, BAD_REFERENCE, NOT_INITIALISED = 1, 2, 3, 4, 5, 6, 7, 8
CODE_NAMES = {0: "OK", 1: "COLLISION", 2: "NOT_FINITE", 3: "FAILED", 4: "TOO_STIFF", 5: "BAD_ARGUMENT",
              6: "BAD_MEASUREMENT", 7: "BAD_REFERENCE", 8: "NOT_INITIALISED"}
STIFFNESS_BOUND = 1e6        # N/m, N m/rad: the largest stiffness an impedance step takes
DAMPING_RATIO_BOUND = 10.0   # the largest damping ratio it takes


def within(v, lo, hi) -> bool:
    """rscasadi_within in Python: v of lo's length with lo <= v <= hi everywhere (NaN is outside)."""
    v = np.asarray(v, float).ravel()
    return v.shape == np.shape(lo) and bool(np.all((v >= lo) & (v <= hi)))


def clamp(tau, limit) -> np.ndarray:
    """rscasadi_clamp in Python: within +-limit, a value that is not finite 0."""
    tau = np.asarray(tau, float).ravel()
    return np.clip(np.where(np.isfinite(tau), tau, 0.0), -limit, limit)
