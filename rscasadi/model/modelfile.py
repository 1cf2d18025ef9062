"""The TOML model file of MODEL.md section 4: parse, validate, and hold the constant model.

Everything here is plain data (numpy); the recursions read it and never change it.
Every rule of MODEL.md section 4 is enforced with a `ModelFileError` that names the
file, the joint and the field.
"""
from __future__ import annotations

import math
import tomllib
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

DEFAULT_GRAVITY = (0.0, 0.0, -9.81)
TOP_KEYS = {"name", "gravity", "joints"}
JOINT_KEYS = {"name", "origin_xyz", "origin_rpy", "gear_ratio", "sea", "gear_loss", "limits",
              "link", "slow_rotor", "fast_rotor"}
BODY_KEYS = {"mass", "com", "inertia"}
SEA_KEYS = {"k1", "k3", "d"}
GEAR_LOSS_KEYS = {"b", "c", "eps"}
LIMIT_KEYS = {"tau", "dphi", "psi", "theta"}
BODIES = ("link", "slow_rotor", "fast_rotor")


class ModelFileError(ValueError):
    """A model file breaks a rule of MODEL.md section 4."""


def rpy_matrix(rpy) -> np.ndarray:
    """URDF convention: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


@dataclass(frozen=True)
class Body:
    """A rigid body's inertial parameters in its own frame."""
    mass: float
    com: np.ndarray          # (3,) centre of mass in the body frame
    inertia: np.ndarray      # (3, 3) about the centre of mass

    @property
    def inertia_origin(self) -> np.ndarray:
        """Inertia about the frame origin (parallel-axis theorem): I_O = I_C + m (p.p 1 - p p^T)."""
        p = self.com
        return self.inertia + self.mass * (p @ p * np.eye(3) - np.outer(p, p))

    @staticmethod
    def from_spatial(M: np.ndarray) -> "Body":
        """The inverse of eq. (11): mass, centre of mass and inertia about it from a 6x6 M."""
        m = M[3, 3]
        com = np.array([M[2, 4], M[0, 5], M[1, 3]]) / m
        return Body(m, com, M[:3, :3] - m * (com @ com * np.eye(3) - np.outer(com, com)))

    @property
    def balanced(self) -> bool:
        """Centre of mass on the z axis and inertia symmetric about it (MODEL.md section 3)."""
        I = self.inertia
        return (self.com[0] == 0.0 and self.com[1] == 0.0 and I[0, 0] == I[1, 1]
                and I[0, 1] == 0.0 and I[0, 2] == 0.0 and I[1, 2] == 0.0)


@dataclass(frozen=True)
class Joint:
    name: str
    origin_xyz: np.ndarray   # J_j origin in the parent frame
    origin_rpy: np.ndarray
    gear_ratio: float        # mu_j
    k1: float
    k3: float
    d: float
    b: float
    c: float
    eps: float
    limits: dict
    link: Body
    slow_rotor: Body
    fast_rotor: Body

    origin_R: np.ndarray | None = None   # J_j's rotation when it came from a URDF (else from origin_rpy)

    @property
    def R(self) -> np.ndarray:
        """Rotation of J_j relative to the parent frame; the round-off of exact right angles
        (cos(pi/2) = 6e-17) is set to 0 so that symbolic code folds it away."""
        R = rpy_matrix(self.origin_rpy) if self.origin_R is None else np.array(self.origin_R, dtype=float)
        R[np.abs(R) < 1e-15] = 0.0
        return R

    @property
    def rotor_inertia(self) -> float:
        """B_j = Izz_O(S_j) + mu_j^2 Izz_O(F_j) (MODEL.md section 3)."""
        return float(self.slow_rotor.inertia_origin[2, 2]
                     + self.gear_ratio ** 2 * self.fast_rotor.inertia_origin[2, 2])


@dataclass(frozen=True)
class ArmModel:
    """The constant description of an n-joint FS-SEA arm; joints base to tip."""
    name: str
    gravity: np.ndarray
    joints: tuple
    path: str = "<memory>"
    extra: dict = field(default_factory=dict, compare=False)

    @property
    def n(self) -> int:
        return len(self.joints)

    def column(self, attr: str) -> np.ndarray:
        """One joint parameter as an (n,) array, e.g. column('gear_ratio')."""
        return np.array([getattr(jt, attr) for jt in self.joints], dtype=float)


# ----------------------------------------------------------------------------- validation

class _Ctx:
    """Where we are in the file, for error messages."""

    def __init__(self, path, joint=None):
        self.path, self.joint = path, joint

    def fail(self, fld: str, problem: str):
        where = f"{self.path}: "
        if self.joint is not None:
            idx, name = self.joint
            where += f"joint {idx + 1}" + (f" ({name!r})" if name else "") + ", "
        raise ModelFileError(f"{where}field '{fld}': {problem}")


def _number(ctx, fld, value, *, positive=False, nonneg=False):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        ctx.fail(fld, f"expected a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        ctx.fail(fld, f"must be finite, got {value!r}")
    if positive and value <= 0.0:
        ctx.fail(fld, f"must be > 0, got {value!r}")
    if nonneg and value < 0.0:
        ctx.fail(fld, f"must be >= 0, got {value!r}")
    return value


def _vector(ctx, fld, value, size):
    if not isinstance(value, list) or len(value) != size:
        ctx.fail(fld, f"expected a list of {size} numbers, got {value!r}")
    return np.array([_number(ctx, f"{fld}[{i}]", v) for i, v in enumerate(value)])


def _table(ctx, fld, value, allowed, required=()):
    if not isinstance(value, dict):
        ctx.fail(fld, f"expected a table, got {value!r}")
    for key in value:
        if key not in allowed:
            ctx.fail(f"{fld}.{key}" if fld else key, f"unknown key (allowed: {', '.join(sorted(allowed))})")
    for key in required:
        if key not in value:
            ctx.fail(f"{fld}.{key}" if fld else key, "missing required field")
    return value


def inertia_problem(inertia: np.ndarray, rtol: float = 1e-12) -> str | None:
    """Why a 3x3 inertia about the centre of mass is not physical, or None."""
    if not np.all(np.isfinite(inertia)):
        return "has a value that is not finite"
    eig = np.linalg.eigvalsh(inertia)
    if eig[0] <= 0.0:
        return f"not positive definite (principal moments {eig.tolist()})"
    if eig[2] > eig[0] + eig[1] + rtol * eig[-1]:
        return f"principal moments {eig.tolist()} break the triangle inequality"
    return None


def _body(ctx, fld, value) -> Body:
    t = _table(ctx, fld, value, BODY_KEYS, BODY_KEYS)
    mass = _number(ctx, f"{fld}.mass", t["mass"], positive=True)
    com = _vector(ctx, f"{fld}.com", t["com"], 3)
    ixx, iyy, izz, ixy, ixz, iyz = _vector(ctx, f"{fld}.inertia", t["inertia"], 6)
    inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    problem = inertia_problem(inertia)
    if problem:
        ctx.fail(f"{fld}.inertia", problem)
    return Body(mass, com, inertia)


ACTUATOR_KEYS = {"name", "gear_ratio", "sea", "gear_loss", "limits", "slow_rotor", "fast_rotor"}


def joint_context(path, idx, raw) -> _Ctx:
    name = raw.get("name") if isinstance(raw, dict) else None
    return _Ctx(path, (idx, name if isinstance(name, str) else None))


def actuator(ctx, t: dict, names) -> dict:
    """The actuator part of a [[joints]] table, common to both forms of the file: name, gear
    ratio, SEA, gear loss, limits and the two rotor bodies (given in J_j, z = joint axis)."""
    name = t.get("name")
    if not isinstance(name, str) or not name.strip():
        ctx.fail("name", f"expected a non-empty string, got {name!r}")
    if name in names:
        ctx.fail("name", f"duplicate joint name {name!r}")
    sea = _table(ctx, "sea", t["sea"], SEA_KEYS, ("k1",))
    loss = _table(ctx, "gear_loss", t.get("gear_loss", {}), GEAR_LOSS_KEYS)
    lim_raw = _table(ctx, "limits", t.get("limits", {}), LIMIT_KEYS)
    limits = {key: _number(ctx, f"limits.{key}", lim_raw[key], positive=True)
              for key in ("tau", "dphi", "psi") if key in lim_raw}
    if "theta" in lim_raw:
        lo, hi = _vector(ctx, "limits.theta", lim_raw["theta"], 2)
        if not lo < hi:
            ctx.fail("limits.theta", f"lower bound {lo} must be below upper bound {hi}")
        limits["theta"] = (float(lo), float(hi))
    return dict(
        name=name,
        gear_ratio=_number(ctx, "gear_ratio", t["gear_ratio"], positive=True),
        k1=_number(ctx, "sea.k1", sea["k1"], positive=True),
        k3=_number(ctx, "sea.k3", sea.get("k3", 0.0), nonneg=True),
        d=_number(ctx, "sea.d", sea.get("d", 0.0), nonneg=True),
        b=_number(ctx, "gear_loss.b", loss.get("b", 0.0), nonneg=True),
        c=_number(ctx, "gear_loss.c", loss.get("c", 0.0), nonneg=True),
        eps=_number(ctx, "gear_loss.eps", loss.get("eps", 0.01), positive=True),
        limits=limits,
        slow_rotor=_body(ctx, "slow_rotor", t["slow_rotor"]),
        fast_rotor=_body(ctx, "fast_rotor", t["fast_rotor"]),
    )


def _joint(path, idx, raw, names) -> Joint:
    ctx = joint_context(path, idx, raw)
    t = _table(ctx, "", raw, JOINT_KEYS,
               ("name", "origin_xyz", "origin_rpy", "gear_ratio", "sea", "link", "slow_rotor", "fast_rotor"))
    return Joint(origin_xyz=_vector(ctx, "origin_xyz", t["origin_xyz"], 3),
                 origin_rpy=_vector(ctx, "origin_rpy", t["origin_rpy"], 3),
                 link=_body(ctx, "link", t["link"]), **actuator(ctx, t, names))


def parse(data: dict, path: str = "<memory>") -> ArmModel:
    """Validate a decoded TOML document (MODEL.md section 4) into an ArmModel."""
    ctx = _Ctx(path)
    if isinstance(data, dict) and "urdf" in data:
        from .urdf import parse_urdf_form
        return parse_urdf_form(data, path)
    _table(ctx, "", data, TOP_KEYS, ("name", "joints"))
    if not isinstance(data["name"], str) or not data["name"].strip():
        ctx.fail("name", f"expected a non-empty string, got {data['name']!r}")
    gravity = _vector(ctx, "gravity", data.get("gravity", list(DEFAULT_GRAVITY)), 3)
    raw_joints = data["joints"]
    if not isinstance(raw_joints, list) or not raw_joints:
        ctx.fail("joints", "expected at least one [[joints]] table")
    joints = []
    for idx, raw in enumerate(raw_joints):
        joints.append(_joint(path, idx, raw, {jt.name for jt in joints}))
    return ArmModel(data["name"], gravity, tuple(joints), path)


def field_checker(path, d: dict, allowed):
    """For a document read from `path`: refuse keys not in `allowed`, and return fail(field,
    message), which raises the ModelFileError naming file and field."""
    def fail(fld, msg):
        raise ModelFileError(f"{path}: field '{fld}': {msg}")
    for key in d:
        if key not in allowed:
            fail(key, f"unknown key (allowed: {', '.join(sorted(allowed))})")
    return fail


def read_toml(path, kind: str = "model") -> dict:
    """A TOML document, or a ModelFileError that names the file (kind: model, problem, trajectory)."""
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except OSError as exc:
        raise ModelFileError(f"{path}: cannot read {kind} file: {exc.strerror}") from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ModelFileError(f"{path}: not valid TOML: {exc}") from exc


def read(path) -> ArmModel:
    """Read and validate a model file."""
    return parse(read_toml(path), str(Path(path)))


# ----------------------------------------------------------------------------- writing

def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    return repr(float(v))


def to_toml(doc: dict) -> str:
    """TOML text of a model document (top-level scalars and arrays, [[joints]] of inline tables)."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in doc.items() if k != "joints" or not v]
    for jt in doc.get("joints", []):
        lines += ["", "[[joints]]"] + [f"{k} = {_toml_value(v)}" for k, v in jt.items()]
    return "\n".join(lines) + "\n"


def body_document(body: Body) -> dict:
    I = body.inertia
    return {"mass": float(body.mass), "com": [float(c) for c in body.com],
            "inertia": [float(I[0, 0]), float(I[1, 1]), float(I[2, 2]), float(I[0, 1]), float(I[0, 2]), float(I[1, 2])]}


def rpy_of(R) -> np.ndarray | None:
    """Roll, pitch, yaw (URDF convention) of a rotation, or None where scipy's angles do not give
    R back to 1e-12 (a gimbal lock it resolves badly)."""
    from scipy.spatial.transform import Rotation
    with warnings.catch_warnings():                                  # gimbal lock: checked below
        warnings.simplefilter("ignore")
        rpy = Rotation.from_matrix(R).as_euler("xyz")
    return rpy if np.max(np.abs(rpy_matrix(rpy) - R)) <= 1e-12 else None


def document(model: ArmModel) -> dict:
    """The link-list form (docs/model.md section 4) of any model, URDF-based ones included."""
    joints = []
    for jt in model.joints:
        rpy = rpy_of(jt.R)
        if rpy is None:
            raise ModelFileError(f"{model.path}: joint {jt.name!r}: its rotation has no exact roll-pitch-yaw")
        limits = {k: (list(v) if isinstance(v, tuple) else v) for k, v in jt.limits.items()}
        joints.append({"name": jt.name, "origin_xyz": [float(x) for x in jt.origin_xyz],
                       "origin_rpy": [float(x) for x in rpy], "gear_ratio": jt.gear_ratio,
                       "sea": {"k1": jt.k1, "k3": jt.k3, "d": jt.d},
                       "gear_loss": {"b": jt.b, "c": jt.c, "eps": jt.eps}, **({"limits": limits} if limits else {}),
                       **{b: body_document(getattr(jt, b)) for b in BODIES}})
    return {"name": model.name, "gravity": [float(g) for g in model.gravity], "joints": joints}
