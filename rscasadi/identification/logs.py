"""Logs of an FS-SEA arm: what it measures, as CSV.

Header `t,theta_1..theta_n,phi_1..phi_n,tau_1..tau_n`, optionally followed by `T_1..T_n` (a
torque sensor on the SEA output); joints numbered base to tip; SI units (s, rad, N m);
uniform sampling.  `phi` is the slow-side angle: the motor encoder divided by the gear ratio.
`tau` is the motor torque (motor side).  Every defect is refused naming the file and column.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rscasadi.model.modelfile import ModelFileError


class LogError(ModelFileError):
    """A log file is not what an FS-SEA arm measures."""


@dataclass
class Log:
    """A log (docs/user-guide/logs.md): time, link and motor angles, motor torques, and SEA
    torques if a torque sensor was logged; arrays are (n, N)."""
    path: str
    t: np.ndarray
    theta: np.ndarray          # (n, N)
    phi: np.ndarray
    tau: np.ndarray
    T: np.ndarray | None = None

    @property
    def dt(self) -> float:
        return float(self.t[1] - self.t[0])

    @property
    def n(self) -> int:
        return self.theta.shape[0]


def header(n: int, torque_sensor: bool = False) -> list[str]:
    """The columns of a log of an n-joint arm: t, theta_j, phi_j, tau_j [, T_j]."""
    cols = ["t"] + [f"{q}_{j}" for q in ("theta", "phi", "tau") for j in range(1, n + 1)]
    return cols + ([f"T_{j}" for j in range(1, n + 1)] if torque_sensor else [])


def write_log(path, log: Log):
    """Write `log` as CSV with the header `header` gives."""
    import io
    from rscasadi.files import write_text
    n = log.n
    data = [log.t, *log.theta, *log.phi, *log.tau] + ([*log.T] if log.T is not None else [])
    rows = np.vstack(data).T
    text = io.StringIO(newline="")
    w = csv.writer(text)
    w.writerow(header(n, log.T is not None))
    w.writerows([[repr(float(v)) for v in row] for row in rows])
    write_text(path, text.getvalue())                     # whole or not at all


def read_log(path, n: int, min_samples: int = 50) -> Log:
    """Read and check a log for an n-joint arm."""
    path = Path(path)
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise LogError(f"{path}: cannot read log: {exc.strerror}") from exc
    except (UnicodeDecodeError, csv.Error) as exc:
        raise LogError(f"{path}: not a CSV text file: {exc}") from exc
    if not rows:
        raise LogError(f"{path}: empty log (expected the header {','.join(header(n))})")
    cols = [c.strip() for c in rows[0]]
    for want in (header(n), header(n, True)):
        if cols == want:
            break
    else:
        expected = header(n)
        missing = [c for c in expected if c not in cols]
        extra = [c for c in cols if c not in header(n, True)]
        what = (f"missing column {missing[0]!r}" if missing else f"unexpected column {extra[0]!r}" if extra
                else "columns out of order")
        raise LogError(f"{path}: header: {what}; expected {','.join(expected)} (optionally ,T_1..T_{n}) "
                       f"for a {n}-joint arm")
    body = rows[1:]
    if len(body) < min_samples:
        raise LogError(f"{path}: only {len(body)} samples; at least {min_samples} are needed to estimate "
                       f"velocities and accelerations and excite the parameters")
    data = np.empty((len(body), len(cols)))
    for i, row in enumerate(body):
        if len(row) != len(cols):
            raise LogError(f"{path}: line {i + 2}: {len(row)} values, the header has {len(cols)}")
        for k, v in enumerate(row):
            try:
                data[i, k] = float(v)
            except ValueError:
                raise LogError(f"{path}: line {i + 2}, column {cols[k]!r}: not a number: {v!r}") from None
    bad = ~np.isfinite(data)
    if bad.any():
        i, k = np.argwhere(bad)[0]
        raise LogError(f"{path}: line {i + 2}, column {cols[k]!r}: {data[i, k]} (NaN or infinite); "
                       f"{int(bad.sum())} such values in all")
    t = data[:, 0]
    dt = np.diff(t)
    if np.any(dt <= 0):
        i = int(np.argmax(dt <= 0))
        raise LogError(f"{path}: column 't': time does not increase at line {i + 3} ({t[i]} then {t[i + 1]})")
    if np.max(np.abs(dt - np.median(dt))) > 1e-6 * max(1.0, np.median(dt)) + 1e-3 * np.median(dt):
        i = int(np.argmax(np.abs(dt - np.median(dt))))
        raise LogError(f"{path}: column 't': sampling is not uniform (step {dt[i]:.6g} s at line {i + 3}, "
                       f"median {np.median(dt):.6g} s); resample the log first")
    blocks = [data[:, 1 + k * n: 1 + (k + 1) * n].T for k in range(len(cols) // n)]
    return Log(str(path), t, blocks[0], blocks[1], blocks[2], blocks[3] if len(blocks) > 3 else None)
