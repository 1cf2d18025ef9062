"""What a task is made of, stated once for the OCP and the MPC: where a frame must end (`Goal`),
what the arm must keep clear of (`Obstacle`), what it holds (`Payload`), and the joints' limits
(`Limits`, the model's: a limit the model does not give is no limit).  Each object checks itself
against the arm (`check`) and round-trips through the dict that solution.json and the studies
write (`to_dict`, `from_dict`); `rscasadi.task.read` parses them from the fields the OCP and the
MPC problem files share.  A tool path is `rscasadi.task.toolpath.ToolPath`."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rscasadi.errors import InvalidArgument
from rscasadi.model.limits import limit_arrays
from rscasadi.model.types import ModelFileError

PAYLOAD_KEYS = ("frame", "mass", "com", "inertia", "radius")


def _frame_names(model) -> list:
    return [f.name for f in model.frames]


@dataclass
class Goal:
    """Where a frame must end, at rest: its origin at `position` (m, world) and, if `R` is given,
    its rotation R; the configuration is the solver's choice within the joint limits.  The
    replay must reach it within `position_tol` (m) and `angle_tol` (rad)."""
    frame: str
    position: np.ndarray
    R: np.ndarray | None = None
    position_tol: float = 1e-3
    angle_tol: float = 1e-2

    def __post_init__(self):
        self.position = np.asarray(self.position, float).ravel()
        self.R = None if self.R is None else np.asarray(self.R, float)

    @classmethod
    def from_rpy(cls, frame: str, position, rpy=None, **tolerances) -> "Goal":
        """The goal as the problem file writes it: the rotation by roll, pitch, yaw (rad, URDF
        convention), or none."""
        from rscasadi.model.types import rpy_matrix
        return cls(frame, position, None if rpy is None else rpy_matrix(np.asarray(rpy, float)), **tolerances)

    def check(self, model, where="<task>", fld: str = "goal") -> "Goal":
        """The frame exists on `model` and the goal is not more conditions than its joints."""
        if self.frame not in _frame_names(model):
            raise ModelFileError(f"{where}: field '{fld}.frame': {model.path} has no frame {self.frame!r} "
                                 f"(frames: {', '.join(_frame_names(model))})")
        rows = 3 if self.R is None else 6
        if rows > model.n:
            raise ModelFileError(f"{where}: field '{fld}': {'a position' if self.R is None else 'a pose'} is "
                                 f"{rows} conditions, more than the {model.n} joints can meet "
                                 "in general" + ("; give the position alone (no rpy)" if model.n >= 3 else ""))
        return self

    def to_dict(self) -> dict:
        """As solution.json writes it."""
        return {"frame": self.frame, "position": self.position.tolist(),
                "R": None if self.R is None else self.R.tolist(),
                "position_tol": self.position_tol, "angle_tol": self.angle_tol}

    @staticmethod
    def from_dict(d: dict) -> "Goal":
        return Goal(d["frame"], d["position"], d.get("R"), d.get("position_tol", 1e-3), d.get("angle_tol", 1e-2))


def goals_of(data) -> list:
    """The goal dicts of a solution.json's "goal": none, one (a dict) or several (a list)."""
    goal = data.get("goal") if isinstance(data, dict) else None
    return [] if not goal else [goal] if isinstance(goal, dict) else list(goal)


@dataclass
class Obstacle:
    """A sphere (`center`, `radius`) or an axis-aligned box (`center`, `size`), in the world
    frame (m); the arm's capsules ([collision] of the model file) must keep their margin from it."""
    kind: str
    center: np.ndarray
    radius: float = 0.0
    size: np.ndarray | None = None

    def __post_init__(self):
        self.center = np.asarray(self.center, float).ravel()
        self.size = None if self.size is None else np.asarray(self.size, float).ravel()

    def check(self, model, where="<task>") -> "Obstacle":
        """The arm has capsules that can keep clear of it."""
        if model.collision is None:
            raise ModelFileError(f"{where}: field 'obstacles': {model.path} has no [collision] table "
                                 "(the capsules of the links that must keep clear)")
        return self

    def to_dict(self) -> dict:
        """As solution.json and the studies' results write it."""
        return {"kind": self.kind, "center": self.center.tolist(), "radius": self.radius,
                "size": None if self.size is None else self.size.tolist()}

    @staticmethod
    def from_dict(d: dict) -> "Obstacle":
        return Obstacle(d["kind"], d["center"], d["radius"], d.get("size"))


@dataclass
class Payload:
    """What the arm holds, set on the model or changing the model's own [payload]: fields left
    None keep the model's (a model without a payload needs frame, mass, com and inertia;
    `inertia` as in a model file: Ixx, Iyy, Izz, Ixy, Ixz, Iyz about the com; `radius` its
    collision sphere's)."""
    frame: str | None = None
    mass: float | None = None
    com: list | None = None
    inertia: list | None = None
    radius: float | None = None

    def check(self, model, where="<task>"):
        """`model` holding it; a ModelFileError names the field and `where`."""
        from rscasadi.model.frames import holding
        try:
            return holding(model, **self.to_dict())
        except (ValueError, TypeError) as exc:
            raise ModelFileError(f"{where}: field '{str(exc).split(':')[0]}': "
                                 f"{str(exc).split(':', 1)[-1].strip()}") from None

    def to_dict(self) -> dict:
        """The fields given, as the problem files write them."""
        return {k: getattr(self, k) for k in PAYLOAD_KEYS if getattr(self, k) is not None}

    @staticmethod
    def from_dict(d: dict) -> "Payload":
        unknown = set(d) - set(PAYLOAD_KEYS)
        if unknown:
            raise InvalidArgument(f"payload: unknown key {sorted(unknown)[0]!r} (allowed: {', '.join(PAYLOAD_KEYS)})")
        return Payload(**d)


def holding_payload(model, payload: dict | Payload | None, where="<task>"):
    """`model` with a task's payload (a Payload or its dict) set, or `model` itself if none."""
    if payload is None:
        return model
    return (payload if isinstance(payload, Payload) else Payload.from_dict(payload)).check(model, where)


@dataclass(frozen=True)
class Limits:
    """The joints' limits (`rscasadi.model.limits.limit_arrays`): per joint `tau`, `psi`, `dphi`
    (inf where none) and the link-angle range `theta_lo`, `theta_hi` (-inf, inf where none)."""
    tau: np.ndarray
    psi: np.ndarray
    dphi: np.ndarray
    theta_lo: np.ndarray
    theta_hi: np.ndarray

    @staticmethod
    def of(model) -> "Limits":
        return Limits(**limit_arrays(model))

    def narrowed(self, margin: float) -> "Limits":
        """Every psi and dphi limit less `margin` of it, each finite link-angle range narrowed by
        `margin` of its width at both ends (the reserve an OCP holds at its collocation points);
        the motor torques keep theirs."""
        width = self.theta_hi - self.theta_lo
        inset = margin * np.where(np.isfinite(width), width, 0.0) / 2
        return Limits(self.tau, (1 - margin) * self.psi, (1 - margin) * self.dphi,
                      self.theta_lo + inset, self.theta_hi - inset)

    def to_dict(self) -> dict:
        return {k: getattr(self, k).tolist() for k in ("tau", "psi", "dphi", "theta_lo", "theta_hi")}

    @staticmethod
    def from_dict(d: dict) -> "Limits":
        return Limits(**{k: np.asarray(v, float) for k, v in d.items()})
