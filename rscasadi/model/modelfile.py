"""The TOML model file (docs/user-guide/model.md section 4): parse and validate into an `ArmModel`, and
write any model back as a link-list document.

Every rule is enforced with a `ModelFileError` that names the file, the joint and the field.
"""
from __future__ import annotations

import copy
import dataclasses
import hashlib
import os
import pickle
import re
from pathlib import Path

import numpy as np

from rscasadi.files import cache_dir, sources_digest
from rscasadi.model.checks import (ACTUATOR_KEYS, _body, _Ctx, _number, _table, _vector,  # noqa: F401
                                   actuator, field_checker, joint_context, orientation, read_toml)
from rscasadi.model.collision import collision, collision_document
from rscasadi.model.kinds import KINDS
from rscasadi.model.frames import contacts, frames_document, link_frames, payload, payload_document, user_frames
from rscasadi.model.types import (BASE, BODIES, BODY_KEYS, DEFAULT_GRAVITY, JOINT_KEYS, TOP_KEYS, ArmModel,  # noqa: F401
                                  Body, Joint, ModelFileError, inertia_problem, rotation_document, rpy_matrix,
                                  rpy_of)

def _joint(path, idx, raw, names) -> Joint:
    ctx = joint_context(path, idx, raw)
    t = _table(ctx, "", raw, JOINT_KEYS, ("name", "origin_xyz", "link"))
    if "origin_rpy" not in t and "origin_R" not in t:
        ctx.fail("origin_rpy", "missing required field (or origin_R, a rotation matrix)")
    rpy, R = orientation(ctx, t, "origin_rpy", "origin_R")
    act = actuator(ctx, {k: v for k, v in t.items()}, names)
    kind, jtype = KINDS[act["kind"]], t.get("type", "revolute")
    if jtype not in ("revolute", "prismatic"):
        ctx.fail("type", f"expected \"revolute\" or \"prismatic\", got {jtype!r}")
    if jtype not in kind.fits:
        ctx.fail("type", f"a {kind.name} joint cannot be {jtype} (a {kind.name} joint models "
                         f"{', '.join(kind.fits)} joints)")
    return Joint(origin_xyz=_vector(ctx, "origin_xyz", t["origin_xyz"], 3),
                 origin_rpy=rpy if R is None else (rpy_of(R) if rpy_of(R) is not None else np.full(3, np.nan)),
                 origin_R=R, link=_body(ctx, "link", t["link"]), type=jtype, **act)


def _parents(path, raw_joints, joints) -> tuple:
    """Each joint's parent index from its `parent` (a joint given before it, or "base"; absent:
    the joint before it, a chain); every parent that names no such joint, in one message."""
    index = {jt.name: j for j, jt in enumerate(joints)}
    parents, bad = [], []
    for j, raw in enumerate(raw_joints):
        name = raw.get("parent", BASE if j == 0 else joints[j - 1].name)
        if name == BASE:
            parents.append(-1)
        elif isinstance(name, str) and index.get(name, j) < j:
            parents.append(index[name])
        else:
            where = ("comes after it: list every joint after its parent" if name in index
                     else f"is no joint (joints: {', '.join(index)}, or {BASE!r})")
            bad.append(f"[[joints]] {joints[j].name!r}: parent {name!r} {where}")
    if bad:
        raise ModelFileError(f"{path}: " + "; ".join(bad))
    return () if parents == list(range(-1, len(joints) - 1)) else tuple(parents)


def parse(data: dict, path: str = "<memory>") -> ArmModel:
    """Validate a decoded TOML document (docs/user-guide/model.md section 4) into an ArmModel."""
    ctx = _Ctx(path)
    if isinstance(data, dict) and "urdf" in data:
        from rscasadi.model.urdf import parse_urdf_form
        return parse_urdf_form(data, path)
    _table(ctx, "", data, TOP_KEYS, ("name", "joints"))
    if not isinstance(data["name"], str) or not data["name"].strip():
        ctx.fail("name", f"expected a non-empty string, got {data['name']!r}")
    gravity = _vector(ctx, "gravity", data.get("gravity", list(DEFAULT_GRAVITY)), 3)
    raw_joints = data["joints"]
    if not isinstance(raw_joints, list) or not raw_joints:
        ctx.fail("joints", "expected at least one [[joints]] table")
    joints: list = []
    for idx, raw in enumerate(raw_joints):
        joints.append(_joint(path, idx, raw, {jt.name for jt in joints} | {BASE}))
    model = ArmModel(data["name"], gravity, tuple(joints), path, parents=_parents(path, raw_joints, joints),
                     base=_floating_base(ctx, data))
    frames = user_frames(ctx, data.get("frames"), link_frames(model))
    touching, soles = contacts(ctx, data.get("contacts"), frames, model.floating)
    return dataclasses.replace(model, frames=frames, payload=payload(ctx, data.get("payload"), frames),
                               contacts=touching, soles=soles,
                               collision=collision(ctx, data.get("collision"), model.joints, frames, None,
                                                   parents=model.parents))


def _floating_base(ctx, data: dict) -> Body | None:
    """The [base] body of a model with `floating = true`; None for a fixed base."""
    floating = data.get("floating", False)
    if not isinstance(floating, bool):
        ctx.fail("floating", f"expected true or false, got {floating!r}")
    if floating and "base" not in data:
        ctx.fail("base", "a floating base needs its body: [base] mass, com, inertia (in the base frame)")
    if "base" in data and not floating:
        ctx.fail("base", "a [base] body is only read with floating = true (a fixed base is the world)")
    return _body(ctx, "base", data["base"]) if floating else None


_READ: dict = {}       # (path, resolved) -> (the files' stamps, the model): read once while unchanged


def _stamps(files) -> tuple:
    """What says a file is unchanged: a digest of its bytes (None: unreadable).  Not its time:
    a file rewritten within the clock's tick keeps it."""
    def one(f):
        try:
            return hashlib.sha256(Path(f).read_bytes()).hexdigest()
        except OSError:
            return None
    return tuple((str(f), one(f)) for f in files)


def read(path) -> ArmModel:
    """Read and validate a model file.  A file read again unchanged (and its URDF, for the URDF
    form) is not parsed again, in this process nor in the next (the cache directory keeps the
    parsed model): every round of an OCP's refinement and every command reads it, and the
    Panda's URDF form takes 0.8 s to parse in a new process (yourdfpy, scipy and the tree).
    Each call returns its own copy."""
    key = (str(Path(path)), str(Path(path).resolve()))      # the model names the file as it was given
    hit = _READ.get(key)
    if hit is not None and _stamps(f for f, _ in hit[0]) == hit[0]:
        return copy.deepcopy(hit[1])
    before = _stamps([key[1]])                               # the file as parsed, not as changed since
    kept = _cached(key, before)
    if kept is None:
        model = parse(read_toml(path), str(Path(path)))
        kept = (before + (_stamps([model.extra["urdf"]]) if "urdf" in model.extra else ()), model)
        _keep(key, kept)
    while len(_READ) >= 16:
        _READ.pop(next(iter(_READ)))
    _READ[key] = kept
    return copy.deepcopy(kept[1])


_PARSER: list = []


def _parser() -> str:
    """A digest of this package's sources and of the versions of the libraries a parsed model
    depends on: a model is kept only for the parser that made it."""
    if not _PARSER:
        from importlib.metadata import version
        versions = " ".join(version(lib) for lib in ("yourdfpy", "numpy"))
        _PARSER.append(sources_digest(*sorted(Path(__file__).parent.glob("*.py"))) + versions)
    return _PARSER[0]


def _entry(key, before) -> Path:
    name = hashlib.sha256(repr((key, before, _parser())).encode()).hexdigest()[:24]
    return cache_dir() / "models" / f"{name}.pickle"


def _cached(key, before):
    """(stamps, model) kept by an earlier process for this file as it is now (and its URDF, whose
    digest is checked here), or None."""
    if before[0][1] is None:
        return None
    try:
        with open(_entry(key, before), "rb") as fh:
            stamps, model = pickle.load(fh)
    except Exception:                    # none, or unreadable (truncated, another Python's): parse
        return None
    return (stamps, model) if _stamps(f for f, _ in stamps) == stamps and isinstance(model, ArmModel) else None


def _keep(key, kept):
    """Keep a parsed model for the next process (whole or not at all; a cache that cannot be
    written only costs the next process the parse)."""
    if kept[0][0][1] is None:
        return
    entry = _entry(key, kept[0][:1])
    try:
        entry.parent.mkdir(parents=True, exist_ok=True)
        tmp = entry.with_name(f"{entry.name}.{os.getpid()}.tmp")
        tmp.write_bytes(pickle.dumps(kept))
        os.replace(tmp, entry)
    except OSError:
        pass


# ----------------------------------------------------------------------------- writing

def _toml_key(k: str) -> str:
    """A bare key if it is one (letters, digits, _ and -), else a quoted one."""
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else _toml_value(k)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        escaped = "".join(c if c.isprintable() and c not in '"\\' else f"\\u{ord(c):04x}" for c in v)
        return '"' + escaped + '"'
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    return repr(float(v))


def to_toml(doc: dict) -> str:
    """TOML text of a model document (top-level scalars and arrays, [[joints]] of inline tables)."""
    lines = [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in doc.items() if k != "joints" or not v]
    for jt in doc.get("joints", []):
        lines += ["", "[[joints]]"] + [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in jt.items()]
    return "\n".join(lines) + "\n"


def body_document(body: Body) -> dict:
    """A body as the model file writes it: mass, com, inertia (Ixx, Iyy, Izz, Ixy, Ixz, Iyz)."""
    I = body.inertia
    return {"mass": float(body.mass), "com": [float(c) for c in body.com],
            "inertia": [float(I[0, 0]), float(I[1, 1]), float(I[2, 2]), float(I[0, 1]), float(I[0, 2]), float(I[1, 2])]}


def link_side_document(jt) -> dict:
    """A joint's link_loss and counterbalance (a spring joint's: spring) tables, where the file
    gave them or they are not zero."""
    out = {}
    if "link_loss" in jt.declared or jt.link_b or jt.link_c:
        out["link_loss"] = {"b": jt.link_b, "c": jt.link_c}
    if jt.kind == "spring":
        out["spring"] = {"k": jt.cb_k, "theta0": jt.cb_theta0}
    elif "counterbalance" in jt.declared or jt.cb_k:
        out["counterbalance"] = {"k": jt.cb_k, "theta0": jt.cb_theta0}
    return out


def actuator_document(jt) -> dict:
    """A joint's kind and, as far as its kind has them, gear ratio, SEA and gear loss."""
    kind = jt.joint_kind
    out: dict = {} if kind.name == "sea" else {"kind": kind.name}
    if kind.rotors:
        out["gear_ratio"] = jt.gear_ratio
    if kind.motor:
        out["sea"] = {"k1": jt.k1, "k3": jt.k3, "d": jt.d}
    if kind.rotors:
        out["gear_loss"] = {"b": jt.b, "c": jt.c, "eps": jt.eps,
                            **({"c1": jt.c1} if jt.c1 or "gear_loss.c1" in jt.declared else {}),
                            **({"stribeck": jt.stribeck, "v_stribeck": jt.v_stribeck}
                               if jt.stribeck or "gear_loss.stribeck" in jt.declared else {})}
    return out


def parent_name(model: ArmModel, j: int) -> str:
    """The name of the joint whose link carries joint j, or "base"."""
    p = model.parent[j]
    return BASE if p < 0 else model.joints[p].name


def document(model: ArmModel) -> dict:
    """The link-list form (docs/user-guide/model.md section 4) of any model, URDF-based ones included."""
    joints = []
    for j, jt in enumerate(model.joints):
        limits = {k: (list(v) if isinstance(v, tuple) else v) for k, v in jt.limits.items()}
        joints.append({"name": jt.name, **({"parent": parent_name(model, j)} if model.parents else {}),
                       **({"type": jt.type} if jt.type != "revolute" else {}),
                       "origin_xyz": [float(x) for x in jt.origin_xyz],
                       **rotation_document(jt.R, "origin_rpy", "origin_R"), **actuator_document(jt),
                       **link_side_document(jt),
                       **({"torque_constant": jt.torque_constant} if jt.torque_constant is not None else {}),
                       **({"limits": limits} if limits else {}),
                       **{b: body_document(getattr(jt, b)) for b in BODIES
                          if b == "link" or jt.joint_kind.rotors}})
    frames, held, shape = frames_document(model), payload_document(model), collision_document(model)
    floating = {"floating": True, "base": body_document(model.base)} if model.base is not None else {}
    if model.contacts:
        size = {f: [lx, ly] for f, lx, ly in model.soles}
        floating["contacts"] = [{"frame": f, "kind": k, **({"size": size[f]} if f in size else {})}
                                for f, k in model.contacts]
    return {"name": model.name, "gravity": [float(g) for g in model.gravity], **floating,
            **({"frames": frames} if frames else {}),
            **({"payload": held} if held else {}), **({"collision": shape} if shape else {}), "joints": joints}
