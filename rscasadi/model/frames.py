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

from rscasadi.model.checks import _body, _Ctx, _number, _table, _vector, orientation
from rscasadi.model.types import BASE, BODY_KEYS, Capsule, Collision, Frame, Payload, rotation_document, rpy_matrix

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
                raise ValueError(f"{model.path}: frame {f.name!r} would take the place of the link-list form's own "
                                 "frame of that name")
            continue
        parent = BASE if f.body == 0 else model.joints[f.body - 1].name
        doc[f.name] = {"parent": parent, "xyz": [float(v) for v in f.p], **rotation_document(f.R, "rpy", "R")}
    return doc


def payload(ctx, raw, frames: tuple) -> Payload | None:
    """The [payload] table: `frame` (a frame on a moving link) and the body's mass, com and
    inertia (about the com) in that frame, as a link's."""
    if raw is None:
        return None
    t = _table(ctx, "payload", raw, BODY_KEYS | {"frame"}, ("frame",) + tuple(sorted(BODY_KEYS)))
    known = {f.name: f for f in frames}
    if not isinstance(t["frame"], str) or t["frame"] not in known:
        ctx.fail("payload.frame", f"no frame {t['frame']!r} (frames: {', '.join(known)})")
    if known[t["frame"]].body == 0:
        ctx.fail("payload.frame", f"frame {t['frame']!r} is on the fixed base: a payload rides on a moving link")
    return Payload(t["frame"], _body(ctx, "payload", {k: t[k] for k in BODY_KEYS}))


def payload_document(model) -> dict | None:
    """The [payload] table of `model`, or None."""
    if model.payload is None:
        return None
    b = model.payload.body
    I = b.inertia
    return {"frame": model.payload.frame, "mass": float(b.mass), "com": [float(c) for c in b.com],
            "inertia": [float(I[0, 0]), float(I[1, 1]), float(I[2, 2]), float(I[0, 1]), float(I[0, 2]), float(I[1, 2])]}


COLLISION_KEYS = {"margin", "tip", "links"}


def collision(ctx, raw, joints, frames: tuple, default_tip: str | None, urdf: dict | None = None) -> Collision | None:
    """The [collision] table: `links` (a frame name -> the capsule radius of the link that
    carries it), `margin` (m), `tip` (the frame where the last link's capsule ends).  A link's
    capsule runs from its joint's origin to the next joint's origin (the last link's to `tip`),
    unless the URDF gives that link cylinders or spheres (`urdf`: link name -> capsules (a, b, r)
    in its frame), which are then its geometry; `"urdf"` instead of a radius asks for them."""
    if raw is None:
        return None
    urdf = urdf or {}
    t = _table(ctx, "collision", raw, COLLISION_KEYS, ("links",))
    known = {f.name: f for f in frames}
    n = len(joints)
    margin = _number(ctx, "collision.margin", t.get("margin", 0.0), nonneg=True)
    tip = t.get("tip", default_tip)
    links = _table(ctx, "collision.links", t["links"], set(t["links"]))
    capsules, bodies = [], {}
    for name, radius in links.items():
        fld = f"collision.links.{name}"
        if name not in known:
            ctx.fail(fld, f"no frame {name!r} (frames: {', '.join(known)})")
        frame = known[name]
        body = frame.body
        if body == 0:
            ctx.fail(fld, f"{name!r} is on the fixed base, which does not move")
        if body in bodies:
            ctx.fail(fld, f"{bodies[body]!r} of the same link has its geometry already")
        bodies[body] = name
        if name in urdf:                                                  # the URDF's cylinders and spheres
            if radius != "urdf":
                _number(ctx, fld, radius, positive=True)
            capsules += [Capsule(name, body, frame.R @ a + frame.p, frame.R @ b + frame.p, r) for a, b, r in urdf[name]]
            continue
        if radius == "urdf":
            ctx.fail(fld, f"the URDF gives {name!r} no cylinder or sphere <collision> (boxes and meshes are not "
                          "read): give a capsule radius")
        r = _number(ctx, fld, radius, positive=True)
        if body < n:
            end = np.asarray(joints[body].origin_xyz, float)               # the next joint's origin
        else:
            if tip is None or tip not in known:
                ctx.fail("collision.tip", f"the last link's capsule needs the frame where it ends, got {tip!r}")
            if known[tip].body != n:
                ctx.fail("collision.tip", f"frame {tip!r} is not on the last link")
            end = np.asarray(known[tip].p, float)
        capsules.append(Capsule(name, body, np.zeros(3), end, r))
    return Collision(margin, tuple(capsules), tip, {k: v for k, v in links.items()})


def collision_document(model) -> dict | None:
    """The [collision] table of `model`, or None."""
    c = model.collision
    if c is None:
        return None
    return {"margin": c.margin, **({"tip": c.tip} if c.tip else {}), "links": dict(c.links)}


def holding(model, frame=None, mass=None, com=None, inertia=None):
    """`model` with its payload set or changed: fields not given keep the model's payload's (a
    model without one needs them all); `inertia` as in a model file (Ixx, Iyy, Izz, Ixy, Ixz,
    Iyz, about the com).  A ValueError names the field."""
    import dataclasses

    from rscasadi.model.types import Body, inertia_problem
    old = model.payload
    if old is None and None in (frame, mass, com, inertia):
        raise ValueError(f"payload: {model.path} holds none, so give frame, mass, com and inertia")
    frame = old.frame if frame is None else frame
    known = {f.name: f for f in model.frames}
    if frame not in known or known[frame].body == 0:
        raise ValueError(f"payload.frame: no frame {frame!r} on a moving link of {model.path}")
    mass = old.body.mass if mass is None else float(mass)
    if not np.isfinite(mass) or mass <= 0:
        raise ValueError(f"payload.mass: must be > 0, got {mass!r}")
    com = old.body.com if com is None else np.asarray(com, float)
    if inertia is None:
        I = old.body.inertia
    else:
        ixx, iyy, izz, ixy, ixz, iyz = (float(v) for v in inertia)
        I = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    problem = inertia_problem(I)
    if com.shape != (3,) or not np.all(np.isfinite(com)) or problem:
        raise ValueError(f"payload: {'com is not 3 finite numbers' if not problem else 'inertia ' + problem}")
    return dataclasses.replace(model, payload=Payload(frame, Body(mass, com, I)))


def with_collision(model, raw: dict, where):
    """`model` with its [collision] table replaced by `raw` (as a problem file may give it); errors
    name `where` and the field."""
    import dataclasses
    tip = model.collision.tip if model.collision is not None else model.extra.get("tip_link_name")
    return dataclasses.replace(model, collision=collision(_Ctx(where), raw, model.joints, model.frames, tip,
                                                          model.extra.get("collision_geometry")))
