"""The task's fields as the OCP and the MPC problem files write them, parsed once: `[goal]`,
`[path]`, `[[obstacles]]`, `[payload]`.  Each reader takes `fail(field, message)` (the file's
error, `rscasadi.model.checks.field_checker`) and the raw TOML value, and returns the task object
or calls `fail` naming the field and the entry."""
from __future__ import annotations

import numpy as np

from rscasadi.task.objects import PAYLOAD_KEYS, Goal, Obstacle
from rscasadi.task.toolpath import ToolPath

PATH_KEYS = {"frame", "points", "circle", "speed", "tolerance"}
CIRCLE_KEYS = {"center", "radius", "normal", "turns"}
GOAL_KEYS = {"frame", "position", "rpy", "tolerance"}


def number(fail, fld, v, positive: bool):
    """A number (a positive one if asked), or fail naming the field."""
    if isinstance(v, bool) or not isinstance(v, (int, float, np.floating)) or not np.isfinite(v) or (positive and v <= 0):
        fail(fld, f"must be a{' positive' if positive else ''} number, got {v!r}")
    return float(v)


def vector3(fail, fld, v, positive: bool = False) -> np.ndarray:
    """Three numbers (positive ones if asked), or an error naming the field and the entry."""
    if not isinstance(v, list) or len(v) != 3:
        fail(fld, f"expected a list of 3 numbers, got {v!r}")
    return np.array([number(fail, f"{fld}[{i}]", x, positive) for i, x in enumerate(v)])


def read_path(fail, t: dict) -> ToolPath:
    """The [path] table: frame, points (a polyline) or circle = { center, radius, normal, turns },
    speed (m/s; not for min_time), tolerance (m)."""
    for key in t:
        if key not in PATH_KEYS:
            fail(f"path.{key}", f"unknown key (allowed: {', '.join(sorted(PATH_KEYS))})")
    if "frame" not in t:
        fail("path.frame", "missing required field")
    if ("points" in t) == ("circle" in t):
        fail("path", "give points (a polyline) or a circle = { center, radius, normal }, one of them")
    if not isinstance(t["frame"], str):
        fail("path.frame", f"expected the name of a frame, got {t['frame']!r}")
    speed = number(fail, "path.speed", t["speed"], True) if "speed" in t else None
    tolerance = number(fail, "path.tolerance", t.get("tolerance", 1e-3), True)
    if "circle" in t:
        c = t["circle"]
        if not isinstance(c, dict) or set(c) - CIRCLE_KEYS or not {"center", "radius", "normal"} <= set(c):
            fail("path.circle", f"expected {{ center, radius, normal[, turns] }}, got {c!r}")
        normal = vector3(fail, "path.circle.normal", c["normal"])
        if not np.any(normal):
            fail("path.circle.normal", "must not be [0, 0, 0]")
        return ToolPath(t["frame"], speed=speed, tolerance=tolerance, center=vector3(fail, "path.circle.center", c["center"]),
                        radius=number(fail, "path.circle.radius", c["radius"], True), normal=normal,
                        turns=number(fail, "path.circle.turns", c.get("turns", 1.0), True))
    if not isinstance(t["points"], list) or len(t["points"]) < 2:
        fail("path.points", f"expected a list of at least two points, got {t['points']!r}")
    points = np.array([vector3(fail, f"path.points[{i}]", v) for i, v in enumerate(t["points"])])
    return ToolPath(t["frame"], points, speed, tolerance)


def read_goal(fail, t: dict, fld: str = "goal") -> Goal:
    """A [goal] table (or one of [[goal]], named `fld`): frame, position, optional rpy (URDF
    convention) and tolerance."""
    if not isinstance(t, dict):
        fail(fld, f"expected a table, got {t!r}")
    for key in t:
        if key not in GOAL_KEYS:
            fail(f"{fld}.{key}", f"unknown key (allowed: {', '.join(sorted(GOAL_KEYS))})")
    for key in ("frame", "position"):
        if key not in t:
            fail(f"{fld}.{key}", "missing required field")
    if not isinstance(t["frame"], str):
        fail(f"{fld}.frame", f"expected the name of a frame, got {t['frame']!r}")
    vec = {key: vector3(fail, f"{fld}.{key}", t[key]) for key in ("position", "rpy") if key in t}
    tol = t.get("tolerance", {})
    if not isinstance(tol, dict) or set(tol) - {"position", "angle"}:
        fail(f"{fld}.tolerance", f"expected {{ position = m, angle = rad }}, got {tol!r}")
    return Goal.from_rpy(t["frame"], vec["position"], vec.get("rpy"),
                         **{f"{k}_tol": number(fail, f"{fld}.tolerance.{k}", v, True) for k, v in tol.items()})


def read_obstacles(fail, raw) -> tuple:
    """[[obstacles]]: each a sphere = { center, radius } or a box = { center, size }."""
    if not isinstance(raw, list):
        fail("obstacles", "expected [[obstacles]] tables")
    out = []
    for i, entry in enumerate(raw):
        if not isinstance(entry, dict) or len(entry) != 1 or next(iter(entry)) not in ("sphere", "box"):
            fail(f"obstacles[{i}]", f"expected sphere = {{ center, radius }} or box = {{ center, size }}, got {entry!r}")
        kind, t = next(iter(entry.items()))
        need = {"center", "radius"} if kind == "sphere" else {"center", "size"}
        if not isinstance(t, dict) or set(t) != need:
            fail(f"obstacles[{i}].{kind}", f"expected the keys {', '.join(sorted(need))}, got {t!r}")
        vec = {key: vector3(fail, f"obstacles[{i}].{kind}.{key}", t[key], positive=key == "size")
               for key in ("center", "size") if key in t}
        radius = number(fail, f"obstacles[{i}].{kind}.radius", t["radius"], True) if kind == "sphere" else 0.0
        out.append(Obstacle(kind, vec["center"], radius, vec.get("size")))
    return tuple(out)


def read_payload(fail, raw) -> dict:
    """[payload]: frame, mass, com, inertia, radius (each optional where the model holds one)."""
    if not isinstance(raw, dict) or not raw or set(raw) - set(PAYLOAD_KEYS):
        fail("payload", f"expected a table of {', '.join(sorted(PAYLOAD_KEYS))}, got {raw!r}")
    return dict(raw)
