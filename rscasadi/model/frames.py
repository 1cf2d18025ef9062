"""Frames of an arm: each link's own frame, and user frames from the model file's [frames] table
placed on a parent frame (xyz, and rpy as in URDF):

    [frames]
    tool = { parent = "panda_link8", xyz = [0.0, 0.0, 0.1034], rpy = [0.0, 0.0, -0.785398] }

A link-list model's frames are `base` (the world frame) and one per joint, named as the joint,
on the link it moves (that link's frame, whose z is the joint's axis).  A URDF-based model's are
the URDF's links, each where the URDF places its link frame, those merged into a parent link by
a fixed or locked joint too.
"""
from __future__ import annotations

import numpy as np

from rscasadi.model.checks import _body, _number, _table, _vector, orientation
from rscasadi.model.types import BASE, BODY_KEYS, Frame, Payload, rotation_document, rpy_matrix
from rscasadi.errors import InvalidArgument

FRAME_KEYS = {"parent", "xyz", "rpy", "R"}


def link_frames(model) -> tuple:
    """`base` and a frame per joint, on the link it moves (a link-list model's own frames)."""
    return (Frame(BASE, 0, np.eye(3), np.zeros(3)),) + tuple(
        Frame(jt.name, j + 1, np.eye(3), np.zeros(3)) for j, jt in enumerate(model.joints))


def user_frames(ctx, raw, frames: tuple) -> tuple:
    """`frames` and the [frames] table's, each placed on its parent (which may be a user frame
    given before or after it); errors name the file and the field."""
    if raw is None:
        return frames
    table = _table(ctx, "frames", raw, set(raw))
    known = {f.name: f for f in frames}
    pending = {}
    for name, entry in table.items():
        fld = f"frames.{name}"
        if name in known:
            ctx.fail(fld, f"a frame {name!r} exists already (a link's frame)")
        t = _table(ctx, fld, entry, FRAME_KEYS, ("parent",))
        if not isinstance(t["parent"], str):
            ctx.fail(f"{fld}.parent", f"expected the name of a frame, got {t['parent']!r}")
        xyz = _vector(ctx, f"{fld}.xyz", t.get("xyz", [0.0, 0.0, 0.0]), 3)
        rpy, R = orientation(ctx, t, "rpy", "R", f"{fld}.")
        pending[name] = (t["parent"], xyz, rpy_matrix(rpy) if R is None else R)
    out = dict(known)
    while pending:
        ready = [name for name, (parent, *_) in pending.items() if parent in out]
        if not ready:
            name, (parent, *_) = next(iter(pending.items()))
            problem = ("parents form a cycle" if parent in pending
                       else f"no frame {parent!r} (frames: {', '.join(out)})")
            ctx.fail(f"frames.{name}.parent", problem)
        for name in ready:
            parent, xyz, R = pending.pop(name)
            f = out[parent]
            out[name] = Frame(name, f.body, f.R @ R, f.p + f.R @ xyz, user=True)
    return tuple(out.values())


def frames_document(model) -> dict:
    """The [frames] table of the link-list form of `model`: every frame that is not one of that
    form's own (base and the joints' names), placed on its body's own frame; so a URDF-based
    model written as a link list keeps its URDF links' frames."""
    own = {f.name: f for f in link_frames(model)}
    doc = {}
    for f in model.frames:
        if f.name in own:
            mine = own[f.name]
            if f.body != mine.body or not (np.allclose(f.R, mine.R, atol=1e-12) and np.allclose(f.p, mine.p, atol=1e-12)):
                raise InvalidArgument(f"{model.path}: frame {f.name!r} would take the place of the link-list form's own "
                                 "frame of that name")
            continue
        parent = BASE if f.body == 0 else model.joints[f.body - 1].name
        doc[f.name] = {"parent": parent, "xyz": [float(v) for v in f.p], **rotation_document(f.R, "rpy", "R")}
    return doc


def payload(ctx, raw, frames: tuple) -> Payload | None:
    """The [payload] table: `frame` (a frame on a moving link) and the body's mass, com and
    inertia (about the com) in that frame, as a link's; `radius` (m, optional) the sphere about
    its com that must keep clear of obstacles."""
    if raw is None:
        return None
    t = _table(ctx, "payload", raw, BODY_KEYS | {"frame", "radius"}, ("frame",) + tuple(sorted(BODY_KEYS)))
    known = {f.name: f for f in frames}
    if not isinstance(t["frame"], str) or t["frame"] not in known:
        ctx.fail("payload.frame", f"no frame {t['frame']!r} (frames: {', '.join(known)})")
    if known[t["frame"]].body == 0:
        ctx.fail("payload.frame", f"frame {t['frame']!r} is on the fixed base: a payload rides on a moving link")
    radius = _number(ctx, "payload.radius", t["radius"], positive=True) if "radius" in t else None
    return Payload(t["frame"], _body(ctx, "payload", {k: t[k] for k in BODY_KEYS}), radius)


CONTACT_KINDS = ("point", "flat")


def contacts(ctx, raw, frames: tuple, floating: bool) -> tuple:
    """The [[contacts]] tables of a floating robot: `frame` (any frame) and `kind`, point (the
    default) or flat, a flat one optionally its sole's `size = [lx, ly]` (m, along the frame's x
    and y, centred on its origin) (docs/user-guide/floating.md); every bad entry named in one
    message.  Returns the contacts ((frame, kind), ...) and the soles ((frame, lx, ly), ...)."""
    if raw is None:
        return (), ()
    if not floating:
        ctx.fail("contacts", "contacts are a floating robot's (floating = true); a fixed base is the world")
    if not isinstance(raw, list) or not all(isinstance(c, dict) for c in raw):
        ctx.fail("contacts", f"expected [[contacts]] tables (frame, kind), got {raw!r}")
    known = {f.name for f in frames}
    out: list = []
    bad: list = []
    soles: list = []
    for i, c in enumerate(raw):
        extra = set(c) - {"frame", "kind", "size"}
        frame, kind, size = c.get("frame"), c.get("kind", "point"), c.get("size")
        sized = (isinstance(size, list) and len(size) == 2
                 and all(isinstance(x, (int, float)) and not isinstance(x, bool) and x > 0 and np.isfinite(x)
                         for x in size))
        if extra:
            bad.append(f"contacts[{i}]: unknown keys {sorted(extra)} (frame, kind, size)")
        elif size is not None and (kind != "flat" or not sized):
            bad.append(f"contacts[{i}] ({frame!r}): size is a flat contact's sole, two lengths > 0 (m), got {size!r}")
        elif frame not in known:
            bad.append(f"contacts[{i}]: no frame {frame!r}")
        elif kind not in CONTACT_KINDS:
            bad.append(f"contacts[{i}] ({frame!r}): kind {kind!r} is not point or flat")
        elif frame in [f for f, _ in out]:
            bad.append(f"contacts[{i}]: {frame!r} given twice")
        else:
            out.append((frame, kind))
            if size is not None:
                soles.append((frame, float(size[0]), float(size[1])))
    if bad:
        ctx.fail("contacts", "; ".join(bad))
    return tuple(out), tuple(soles)


def payload_document(model) -> dict | None:
    """The [payload] table of `model`, or None."""
    if model.payload is None:
        return None
    b = model.payload.body
    I = b.inertia
    return {"frame": model.payload.frame, "mass": float(b.mass), "com": [float(c) for c in b.com],
            "inertia": [float(I[0, 0]), float(I[1, 1]), float(I[2, 2]), float(I[0, 1]), float(I[0, 2]), float(I[1, 2])],
            **({"radius": float(model.payload.radius)} if model.payload.radius is not None else {})}


def holding(model, frame=None, mass=None, com=None, inertia=None, radius=None):
    """`model` with its payload set or changed: fields not given keep the model's payload's (a
    model without one needs them all but `radius`); `inertia` as in a model file (Ixx, Iyy, Izz,
    Ixy, Ixz, Iyz, about the com); `radius` its collision sphere's.  A ValueError names the field."""
    import dataclasses

    from rscasadi.model.types import Body, inertia_problem
    old = model.payload
    if old is None and None in (frame, mass, com, inertia):
        raise InvalidArgument(f"payload: {model.path} holds none, so give frame, mass, com and inertia")
    frame = old.frame if frame is None else frame
    known = {f.name: f for f in model.frames}
    if frame not in known or known[frame].body == 0:
        raise InvalidArgument(f"payload.frame: no frame {frame!r} on a moving link of {model.path}")
    mass = old.body.mass if mass is None else float(mass)
    if not np.isfinite(mass) or mass <= 0:
        raise InvalidArgument(f"payload.mass: must be > 0, got {mass!r}")
    com = old.body.com if com is None else np.asarray(com, float)
    if inertia is None:
        I = old.body.inertia
    else:
        ixx, iyy, izz, ixy, ixz, iyz = (float(v) for v in inertia)
        I = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    problem = inertia_problem(I)
    if com.shape != (3,) or not np.all(np.isfinite(com)) or problem:
        raise InvalidArgument(f"payload: {'com is not 3 finite numbers' if not problem else 'inertia ' + problem}")
    radius = old.radius if radius is None and old is not None else radius
    if radius is not None and not (isinstance(radius, (int, float)) and np.isfinite(radius) and radius > 0):
        raise InvalidArgument(f"payload.radius: must be a number > 0, got {radius!r}")
    return dataclasses.replace(model, payload=Payload(frame, Body(mass, com, I), None if radius is None else float(radius)))
