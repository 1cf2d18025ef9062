"""Logs of an FS-SEA arm: what its sensors measure, as CSV.

The header names the columns, in any order: `t` and the link angles `theta_1..theta_n` always;
then whichever of these groups the robot has, each for every joint:

| group | what | needs |
|---|---|---|
| `phi_j` | slow-side motor angle: the motor encoder divided by the gear ratio | |
| `tau_j` | motor torque (motor side), the command held on [t_k, t_k+1) | `phi_j` |
| `i_j` | motor current (A), instead of tau_j: tau_j = kt_j i_j, kt_j the model file's `torque_constant` | `phi_j` |
| `T_j` | SEA output or joint torque sensor | |
| `dtheta_j`, `dphi_j` | measured speeds, used instead of differentiated angles | `theta_j`, `phi_j` |

At least one torque group (`tau`, `i` or `T`).  Joints are numbered base to tip; SI units (s, rad,
N m); uniform sampling.  Every defect is refused naming the file and column.
"""
from __future__ import annotations

import csv
import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rscasadi.model.modelfile import ModelFileError

GROUPS = ("theta", "phi", "tau", "i", "T", "dtheta", "dphi")   # the order a written log keeps
NEEDS = {"tau": "phi", "i": "phi", "dphi": "phi"}              # a group that means nothing without another
WHAT = {"theta": "link angle", "phi": "slow-side motor angle", "tau": "motor torque", "i": "motor current",
        "T": "SEA or joint torque", "dtheta": "link speed", "dphi": "slow-side motor speed"}


class LogError(ModelFileError):
    """A log file is not what an FS-SEA arm measures."""


@dataclass
class Log:
    """A log (docs/user-guide/logs.md): time and link angles, and whichever of motor angles,
    motor torques, SEA/joint torques and measured speeds the robot logged; arrays are (n, N),
    None where not logged."""
    path: str
    t: np.ndarray
    theta: np.ndarray          # (n, N)
    phi: np.ndarray | None = None
    tau: np.ndarray | None = None
    i: np.ndarray | None = None
    T: np.ndarray | None = None
    dtheta: np.ndarray | None = None
    dphi: np.ndarray | None = None

    @property
    def dt(self) -> float:
        return float(self.t[1] - self.t[0])

    @property
    def n(self) -> int:
        return self.theta.shape[0]

    @property
    def groups(self) -> tuple:
        """The column groups logged, in GROUPS' order."""
        return tuple(g for g in GROUPS if getattr(self, g) is not None)

    @property
    def link_side(self) -> bool:
        """Link angles and joint torques only: no motor angle (a sold SEA or torque-sensing arm)."""
        return self.phi is None

    def describe(self) -> str:
        return ", ".join(f"{WHAT[g]} ({g}_j)" for g in self.groups)


def header(n: int, torque_sensor: bool = False, groups: tuple | None = None) -> list[str]:
    """The columns of a log of an n-joint arm: t, then each group's j = 1..n (by default theta,
    phi, tau [, T])."""
    groups = groups or (("theta", "phi", "tau") + (("T",) if torque_sensor else ()))
    return ["t"] + [f"{g}_{j}" for g in GROUPS if g in groups for j in range(1, n + 1)]


def write_log(path, log: Log):
    """Write `log` as CSV, its groups in GROUPS' order."""
    import io
    from rscasadi.files import write_text
    groups = log.groups
    rows = np.vstack([log.t] + [row for g in groups for row in getattr(log, g)]).T
    text = io.StringIO(newline="")
    w = csv.writer(text)
    w.writerow(header(log.n, groups=groups))
    w.writerows([[repr(float(v)) for v in row] for row in rows])
    write_text(path, text.getvalue())                     # whole or not at all


def column_groups(path, cols: list, n: int) -> dict:
    """{group: [column index of joint 1..n]} from a header, every defect refused by name."""
    expected = (f"t,theta_1..theta_{n} and any of the groups phi_j, tau_j (or i_j), T_j, dtheta_j, dphi_j "
                f"(j = 1..{n}) for a {n}-joint arm")
    seen: set = set()
    where: dict[str, dict[int, int]] = {}
    unexpected: list = []
    for k, c in enumerate(cols):
        if c in seen:
            raise LogError(f"{path}: header: column {c!r} appears twice")
        seen.add(c)
        if c == "t":
            continue
        group, _, j = c.rpartition("_")
        if group not in GROUPS or not j.isdigit() or not 1 <= int(j) <= n:
            unexpected.append((c, group))
            continue
        where.setdefault(group, {})[int(j)] = k
    for need in ("t", "theta_1"):
        if need not in seen:
            raise LogError(f"{path}: header: missing column {need!r}; expected {expected}")
    for g, js in where.items():
        missing = [j for j in range(1, n + 1) if j not in js]
        if missing:
            raise LogError(f"{path}: header: missing column '{g}_{missing[0]}' ({WHAT[g]}s are logged for joints "
                           f"{', '.join(str(j) for j in sorted(js))}: a group is logged for every joint or none)")
    for c, group in unexpected:
        hint = (" (a motor current is i_j)" if group == "current" else f" (this arm has {n} joints)" if group in GROUPS
                else "")
        raise LogError(f"{path}: header: unexpected column {c!r}{hint}; expected {expected}")
    if "tau" in where and "i" in where:
        raise LogError(f"{path}: header: both motor torques (tau_j) and motor currents (i_j): give one")
    for g, need in NEEDS.items():
        if g in where and need not in where:
            raise LogError(f"{path}: header: column '{g}_1' ({WHAT[g]}) needs '{need}_1..{need}_{n}' "
                           f"({WHAT[need]}), which the log lacks")
    if "tau" not in where and "i" not in where and "T" not in where:
        raise LogError(f"{path}: header: no torque column: identification needs tau_1..tau_{n} (motor torque), "
                       f"i_1..i_{n} (motor current) "
                       f"or T_1..T_{n} (SEA or joint torque); expected {expected}")
    return {g: [where[g][j] for j in range(1, n + 1)] for g in GROUPS if g in where}


def read_log(path, n: int, min_samples: int = 50) -> Log:
    """Read and check a log for an n-joint arm."""
    from rscasadi.files import check_input_size
    path = Path(path)
    check_input_size(path, "log")
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
    groups = column_groups(path, cols, n)
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
    return Log(str(path), t, **{g: data[:, idx].T for g, idx in groups.items()})


def motor_torques(log: Log, model) -> Log:
    """The log with its motor currents as motor torques too, tau_j = kt_j i_j (kt_j the model's
    `torque_constant`, N m/A; the currents kept, for identification to correct kt where a torque
    sensor fixes the scale); a log without currents as it is.  Refused, naming the joints, where
    the model gives no torque constant."""
    if log.i is None:
        return log
    missing = [jt.name for jt in model.joints if jt.torque_constant is None]
    if missing:
        raise LogError(f"{log.path}: column 'i_1' (motor current) needs each joint's torque_constant (N m/A, motor "
                       f"side) in the model file {model.path}: none for {', '.join(missing)}")
    kt = np.array([jt.torque_constant for jt in model.joints])
    return dataclasses.replace(log, tau=kt[:, None] * log.i)
