"""Reading and checking documents: every refusal is a `ModelFileError` naming the file, the
joint and the field."""
from __future__ import annotations

import math
import tomllib

import numpy as np

from rscasadi.model.kinds import KINDS, Kind, kind_of
from rscasadi.model.types import (BASE, BODY_KEYS, COUNTERBALANCE_KEYS, GEAR_LOSS_KEYS, LIMIT_KEYS, LINK_LOSS_KEYS,
                                  SEA_KEYS, Body, ModelFileError, inertia_problem)
from rscasadi.errors import InvalidArgument

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


def _rotation(ctx, fld, value) -> np.ndarray:
    """A rotation matrix written as three rows of three numbers: orthonormal to 1e-9, det +1."""
    if not isinstance(value, list) or len(value) != 3:
        ctx.fail(fld, f"expected three rows of three numbers (a rotation matrix), got {value!r}")
    R = np.array([_vector(ctx, f"{fld}[{i}]", row, 3) for i, row in enumerate(value)])
    if np.max(np.abs(R @ R.T - np.eye(3))) > 1e-9 or np.linalg.det(R) < 0:
        ctx.fail(fld, "not a rotation matrix (orthonormal rows, determinant +1, to 1e-9)")
    return R


def orientation(ctx, t: dict, rpy_key: str, matrix_key: str, where: str = ""):
    """(rpy, R): a placement's rotation, given as roll-pitch-yaw or, exactly, as a matrix (the
    form rscasadi writes where no roll-pitch-yaw gives the rotation back exactly); not both."""
    if rpy_key in t and matrix_key in t:
        ctx.fail(f"{where}{matrix_key}", f"give {rpy_key} or {matrix_key}, not both")
    if matrix_key in t:
        return None, _rotation(ctx, f"{where}{matrix_key}", t[matrix_key])
    return _vector(ctx, f"{where}{rpy_key}", t.get(rpy_key, [0.0, 0.0, 0.0]), 3), None


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


ACTUATOR_KEYS = {"name", "kind", "gear_ratio", "sea", "gear_loss", "limits", "slow_rotor", "fast_rotor", "link_loss",
                 "counterbalance", "spring", "torque_constant"}
SPRING_KEYS = {"k", "theta0"}                 # a spring joint's spring: k (theta - theta0)


def _stribeck(ctx, loss: dict) -> dict:
    """gear_loss.stribeck (N m) and its speed v_stribeck (rad/s), given together."""
    if ("stribeck" in loss) != ("v_stribeck" in loss):
        given, missing = ("stribeck", "v_stribeck") if "stribeck" in loss else ("v_stribeck", "stribeck")
        ctx.fail(f"gear_loss.{missing}", f"gear_loss.{given} needs gear_loss.{missing} beside it")
    if "stribeck" not in loss:
        return {}
    return {"stribeck": _number(ctx, "gear_loss.stribeck", loss["stribeck"], nonneg=True),
            "v_stribeck": _number(ctx, "gear_loss.v_stribeck", loss["v_stribeck"], positive=True)}


def joint_context(path, idx, raw) -> _Ctx:
    """The context naming joint idx (and its name, if the raw table has one) of the file at path."""
    name = raw.get("name") if isinstance(raw, dict) else None
    return _Ctx(path, (idx, name if isinstance(name, str) else None))


def joint_kind(ctx, t: dict) -> Kind:
    """The joint's kind (default sea), its required keys present and its refused ones absent."""
    kind = kind_of(t.get("kind", "sea"))
    if kind is None:
        ctx.fail("kind", f"expected one of {', '.join(KINDS)}, got {t.get('kind')!r}")
    for key in kind.refused:
        if key in t:
            ctx.fail(key, f"a {kind.name} joint has no {key}")
    for key in kind.required:
        if key not in t:
            ctx.fail(key, f"missing required field (a {kind.name} joint)")
    return kind


def _limits(ctx, t: dict, kind: Kind) -> dict:
    """limits: tau (an actuated joint's motor), dphi (the slow side's speed: sea, geared), psi (the
    SEA's deflection), theta (the link's range)."""
    allowed = {"theta"} | ({"tau"} if kind.actuated else set()) | ({"dphi"} if kind.rotors else set()) \
        | ({"psi"} if kind.motor else set())
    lim_raw = _table(ctx, "limits", t.get("limits", {}), LIMIT_KEYS)
    for key in lim_raw:
        if key not in allowed:
            ctx.fail(f"limits.{key}", f"a {kind.name} joint has no {key} to limit (allowed: {', '.join(sorted(allowed))})")
    limits = {key: _number(ctx, f"limits.{key}", lim_raw[key], positive=True)
              for key in ("tau", "dphi", "psi") if key in lim_raw}
    if "theta" in lim_raw:
        lo, hi = _vector(ctx, "limits.theta", lim_raw["theta"], 2)
        if not lo < hi:
            ctx.fail("limits.theta", f"lower bound {lo} must be below upper bound {hi}")
        limits["theta"] = (float(lo), float(hi))
    return limits


NO_BODY = Body(0.0, np.zeros(3), np.zeros((3, 3)))     # the rotors of a joint that has none


def actuator(ctx, t: dict, names) -> dict:
    """The actuator part of a [[joints]] table, common to both forms of the file: name, kind,
    gear ratio, SEA, gear loss, limits and the two rotor bodies (given in J_j, z = joint axis)."""
    name = t.get("name")
    if not isinstance(name, str) or not name.strip():
        ctx.fail("name", f"expected a non-empty string, got {name!r}")
    if name in names:
        ctx.fail("name", f"duplicate joint name {name!r}" if name != BASE else
                 f"{BASE!r} names the base frame (and its joint would name its link's frame)")
    kind = joint_kind(ctx, t)
    sea = _table(ctx, "sea", t["sea"], SEA_KEYS, ("k1",)) if kind.motor else {}
    loss = _table(ctx, "gear_loss", t.get("gear_loss", {}), GEAR_LOSS_KEYS)
    if kind.rotors == "link" and "c1" in loss:
        ctx.fail("gear_loss.c1", "a geared joint's gear loss has no load term: the torque its gear carries "
                                 "depends on the acceleration")
    link = _table(ctx, "link_loss", t.get("link_loss", {}), LINK_LOSS_KEYS)
    balance = _table(ctx, "counterbalance", t.get("counterbalance", {}), COUNTERBALANCE_KEYS, ("k",)
                     if "counterbalance" in t else ())
    if "spring" in t:
        spring = _table(ctx, "spring", t["spring"], SPRING_KEYS, ("k",))
        balance = {"k": _number(ctx, "spring.k", spring["k"], positive=True), "theta0": spring.get("theta0", 0.0)}
    return dict(
        name=name,
        kind=kind.name,
        gear_ratio=_number(ctx, "gear_ratio", t["gear_ratio"], positive=True) if kind.rotors else 1.0,
        k1=_number(ctx, "sea.k1", sea["k1"], positive=True) if kind.motor else 0.0,
        k3=_number(ctx, "sea.k3", sea.get("k3", 0.0), nonneg=True),
        d=_number(ctx, "sea.d", sea.get("d", 0.0), nonneg=True),
        b=_number(ctx, "gear_loss.b", loss.get("b", 0.0), nonneg=True),
        c=_number(ctx, "gear_loss.c", loss.get("c", 0.0), nonneg=True),
        eps=_number(ctx, "gear_loss.eps", loss.get("eps", 0.01), positive=True),
        link_b=_number(ctx, "link_loss.b", link.get("b", 0.0), nonneg=True),
        link_c=_number(ctx, "link_loss.c", link.get("c", 0.0), nonneg=True),
        cb_k=_number(ctx, "counterbalance.k", balance.get("k", 0.0), nonneg=True),
        cb_theta0=_number(ctx, "counterbalance.theta0", balance.get("theta0", 0.0)),
        c1=_number(ctx, "gear_loss.c1", loss.get("c1", 0.0), nonneg=True),
        **_stribeck(ctx, loss),
        **({"torque_constant": _number(ctx, "torque_constant", t["torque_constant"], positive=True)}
           if "torque_constant" in t else {}),
        declared=frozenset([key for key in ("link_loss", "counterbalance") if key in t]
                           + (["counterbalance"] if "spring" in t else [])
                           + [f"gear_loss.{key}" for key in ("c1", "stribeck") if key in loss]),
        limits=_limits(ctx, t, kind),
        slow_rotor=_body(ctx, "slow_rotor", t["slow_rotor"]) if kind.rotors else NO_BODY,
        fast_rotor=_body(ctx, "fast_rotor", t["fast_rotor"]) if kind.rotors else NO_BODY,
    )


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
    from rscasadi.files import check_input_size
    check_input_size(path, "model")
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except OSError as exc:
        raise ModelFileError(f"{path}: cannot read {kind} file: {exc.strerror}") from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ModelFileError(f"{path}: not valid TOML: {exc}") from exc


def identifier(name: str, what: str = "frame") -> str:
    """`name` as a C identifier that CasADi accepts in a Function's name: each run of characters
    other than letters and digits becomes one _, none at either end; it must start with a letter
    and have at most 48 characters, else it is refused."""
    import re
    ident = re.sub(r"[^A-Za-z0-9]+", "_", str(name)).strip("_")
    if not ident or not ident[0].isalpha() or len(ident) > 48:
        raise InvalidArgument(f"{what} name {name!r} cannot be made a C identifier (letters, digits and single _, "
                         "starting with a letter, at most 48 characters)")
    return ident
