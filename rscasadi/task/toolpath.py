"""A path for a frame: a polyline or a circle, by arc length s, and its timing.

The geometry is one function of s in two backends, numpy (guesses, targets, the replay's check)
and CasADi (the OCP's constraint when the timing is free); `distance` is the geometric distance
to the path, what the replay measures when the timing is the solver's choice.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np
from rscasadi.errors import InvalidArgument


@dataclass
class ToolPath:
    """A path for `frame`: the polyline `points` (k x 3, world, m), or the circle of `radius`
    about `center` in the plane of `normal`, `turns` times round from `start` (a point on it; by
    default where theta_start puts the frame).  `speed` (m/s): the mean speed of a fixed timing,
    rest to rest, s(t) = L (tau - sin(2 pi tau) / 2 pi), tau = t / T, T = L / speed; None: the
    timing is free (objective min_time).  The replay must stay within `tolerance` (m)."""
    frame: str
    points: np.ndarray | None = None
    speed: float | None = None
    tolerance: float = 1e-3
    center: np.ndarray | None = None
    radius: float = 0.0
    normal: np.ndarray | None = None
    start: np.ndarray | None = None
    turns: float = 1.0

    def __post_init__(self):
        if self.points is not None:
            self.points = np.asarray(self.points, float).reshape(-1, 3)
        for key in ("center", "normal", "start"):
            if getattr(self, key) is not None:
                setattr(self, key, np.asarray(getattr(self, key), float).ravel())

    @property
    def kind(self) -> str:
        return "circle" if self.center is not None else "polyline"

    # -- geometry -------------------------------------------------------------------------------
    def _axes(self):
        """The circle's in-plane unit vectors: e1 towards `start`, e2 = n x e1."""
        n = self.normal / np.linalg.norm(self.normal)
        d = self.start - self.center
        e1 = d - n * (n @ d)
        e1 /= np.linalg.norm(e1)
        return e1, np.cross(n, e1)

    def anchored(self, p) -> "ToolPath":
        """A circle starting at the point nearest p (a polyline: itself)."""
        if self.kind != "circle" or self.start is not None:
            return self
        n = self.normal / np.linalg.norm(self.normal)
        d = np.asarray(p, float).ravel() - self.center
        d = d - n * (n @ d)
        if np.linalg.norm(d) < 1e-9:
            raise InvalidArgument("the frame's start is on the circle's axis: no nearest point")
        return ToolPath(**{**self.to_dict(), "start": self.center + self.radius * d / np.linalg.norm(d)})

    @property
    def length(self) -> float:
        if self.kind == "circle":
            return float(2 * np.pi * self.radius * self.turns)
        return float(np.sum(np.linalg.norm(np.diff(self.points, axis=0), axis=1)))

    def _cumulative(self):
        return np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(self.points, axis=0), axis=1))]

    def position(self, s) -> np.ndarray:
        """The points at arc lengths s (len(s) x 3)."""
        s = np.clip(np.atleast_1d(np.asarray(s, float)), 0.0, self.length)
        if self.kind == "circle":
            e1, e2 = self._axes()
            a = s / self.radius
            return self.center + self.radius * (np.outer(np.cos(a), e1) + np.outer(np.sin(a), e2))
        cum = self._cumulative()
        return np.column_stack([np.interp(s, cum, self.points[:, i]) for i in range(3)])

    def position_symbolic(self, s):
        """The point at arc length s, a CasADi expression (piecewise linear for a polyline)."""
        if self.kind == "circle":
            e1, e2 = self._axes()
            a = s / self.radius
            return ca.DM(self.center) + self.radius * (ca.cos(a) * ca.DM(e1) + ca.sin(a) * ca.DM(e2))
        cum = self._cumulative()
        return ca.vertcat(*[ca.pw_lin(s, ca.DM(cum), ca.DM(self.points[:, i])) for i in range(3)])

    @property
    def end(self) -> np.ndarray:
        return self.position(self.length)[0]

    @property
    def first(self) -> np.ndarray:
        """Where the path starts (a circle not yet anchored: None)."""
        return self.points[0] if self.kind == "polyline" else self.start

    def distance(self, P) -> np.ndarray:
        """The distance of each point of P (k x 3) from the path (its nearest point)."""
        P = np.atleast_2d(np.asarray(P, float))
        if self.kind == "circle":
            n = self.normal / np.linalg.norm(self.normal)
            d = P - self.center
            h = d @ n
            radial = np.linalg.norm(d - np.outer(h, n), axis=1)
            return np.hypot(radial - self.radius, h)
        a, b = self.points[:-1], self.points[1:]
        ab = b - a
        u = np.clip(np.einsum("kij,ij->ki", P[:, None, :] - a, ab) / np.maximum(np.sum(ab * ab, axis=1), 1e-300), 0, 1)
        nearest = a + u[..., None] * ab
        return np.min(np.linalg.norm(P[:, None, :] - nearest, axis=2), axis=1)

    def sample(self, count: int = 200) -> np.ndarray:
        """Points along the path for drawing (count x 3, a polyline: its own points)."""
        return self.points if self.kind == "polyline" else self.position(np.linspace(0.0, self.length, count))

    # -- timing -----------------------------------------------------------------------------------
    @property
    def duration(self) -> float:
        return self.length / self.speed

    def arc_length(self, t) -> np.ndarray:
        """s(t) of the fixed timing: rest to rest in `duration`."""
        tau = np.clip(np.asarray(t, float) / self.duration, 0.0, 1.0)
        return self.length * (tau - np.sin(2 * np.pi * tau) / (2 * np.pi))

    def __call__(self, t) -> np.ndarray:
        """The frame's target positions at the times t (len(t) x 3) of the fixed timing."""
        return self.position(self.arc_length(t))

    # -- files ----------------------------------------------------------------------------------
    def check(self, model, where="<task>") -> "ToolPath":
        """The path's frame is one of `model`'s."""
        from rscasadi.model.types import ModelFileError
        if self.frame not in [f.name for f in model.frames]:
            raise ModelFileError(f"{where}: field 'path.frame': {model.path} has no frame {self.frame!r}")
        return self

    def to_dict(self) -> dict:
        out = {"frame": self.frame, "speed": self.speed, "tolerance": self.tolerance}
        if self.kind == "circle":
            out.update(center=self.center.tolist(), radius=self.radius, normal=self.normal.tolist(),
                       start=None if self.start is None else self.start.tolist(), turns=self.turns)
        else:
            out["points"] = self.points.tolist()
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "ToolPath":
        return cls(**d)
