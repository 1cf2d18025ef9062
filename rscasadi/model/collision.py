"""The arm's collision geometry: capsules on its links, and the payload's sphere.

    [collision]
    margin = 0.02                                # m, kept from every obstacle
    tip = "tool"                                 # where the last link's default capsule ends
    links = { upper_arm = 0.05, hand = "urdf" }  # per link: a capsule radius, or "urdf"
    pairs = [["left_forearm", "right_forearm"], ["left_hand", "torso"]]   # links kept apart
    [[collision.capsules]]                       # added on any link, in a frame's coordinates
    frame = "tool"
    a = [0.0, 0.0, 0.0]
    b = [0.0, 0.0, 0.12]
    radius = 0.03

`pairs` names links (by a frame on each) whose capsules must keep the margin from each other as
well as from the obstacles: two arms of a tree, an arm and the torso.  Each link of a pair must
move relative to the other (not both on the base) and have capsules.

A link given a radius has one capsule from its joint's origin to the next joint's origin (the
last link's to `tip`); a link given "urdf" has the URDF's collision geometry of every URDF link
merged into it (a fixed or locked child's too): a cylinder as the capsule of its radius over its
length, a sphere as a capsule of no length, a box as one to four capsules along its longest
edge, a mesh as the capsule that holds its vertices.  Each holds its shape, so a clearance
measured on the capsules is never more than the true one.  A URDF model without `links` takes
the URDF's geometry of every moving link that has some.  With `links`, the geometry is never
less than the URDF's: every URDF collision shape on a moving link (one `links` names with a
radius, one it leaves out, a hand or finger merged into a link) that the capsules do not hold is
added as its own capsules, and one that cannot be read (a mesh not shipped) is named in the
table's notes (`rscasadi info --collision`) as unchecked.  A mesh
that cannot be read (not shipped, outside the robot's package) is an error naming it: a link
is never left out silently.  A payload with a `radius` adds a sphere of that radius about its
centre of mass.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from rscasadi.model.checks import _Ctx, _number, _table, _vector
from rscasadi.model.meshes import bounding_capsule, mesh_file, vertices
from rscasadi.model.types import Capsule, Collision
from rscasadi.errors import InvalidArgument

COLLISION_KEYS = {"margin", "tip", "links", "capsules", "pairs"}
CAPSULE_KEYS = {"frame", "a", "b", "radius"}
MAX_BOX_CAPSULES = 4


# ----------------------------------------------------------------------------- URDF shapes as capsules

def box_capsules(T: np.ndarray, size) -> list:
    """Capsules (a, b, r) holding a box of edge lengths `size` placed at T: the box is cut across
    its middle edge into k <= 4 slabs of a near-square section, each held by the capsule along
    the longest edge whose radius is its section's half-diagonal."""
    size = np.asarray(size, float)
    order = np.argsort(size)[::-1]                       # longest, middle, shortest edge
    L, W, H = size[order]
    k = int(min(MAX_BOX_CAPSULES, max(1, round(W / H)) if H > 0 else MAX_BOX_CAPSULES))
    r = math.hypot(W / (2 * k), H / 2)
    axis, across = T[:3, :3][:, order[0]], T[:3, :3][:, order[1]]
    out = []
    for i in range(k):
        c = T[:3, 3] + across * W * ((i + 0.5) / k - 0.5)
        out.append((c - axis * L / 2, c + axis * L / 2, max(r, 1e-9)))
    return out


def shape_capsules(urdf_path, shape) -> list:
    """One URDF collision shape (kind, T in its link's frame, data) as capsules in that frame; a
    ValueError says why a mesh cannot be used."""
    kind, T, data = shape
    if kind == "cylinder":
        r, length = data
        half = T[:3, :3] @ np.array([0.0, 0.0, length / 2])
        return [(T[:3, 3] - half, T[:3, 3] + half, r)]
    if kind == "sphere":
        return [(T[:3, 3].copy(), T[:3, 3].copy(), data)]
    if kind == "box":
        return box_capsules(T, data)
    filename, scale = data
    path, why = mesh_file(urdf_path, filename)
    if path is None:
        raise InvalidArgument(why)
    points = (vertices(path) * scale) @ T[:3, :3].T + T[:3, 3]
    return [bounding_capsule(points)]


# ----------------------------------------------------------------------------- the [collision] table

def collision(ctx, raw, joints, frames: tuple, default_tip, urdf: dict | None = None,
              urdf_path=None, parents: tuple = ()) -> Collision | None:
    """The [collision] table (module docstring); `urdf` maps a URDF link's name to its collision
    shapes (none for a link-list model); `default_tip` the frame (or, for a tree, the frames)
    where a leaf link's capsule ends; `parents` the tree (ArmModel.parents)."""
    if raw is None:
        return None
    urdf = urdf or {}
    t = _table(ctx, "collision", raw, COLLISION_KEYS)
    known = {f.name: f for f in frames}
    margin = _number(ctx, "collision.margin", t.get("margin", 0.0), nonneg=True)
    tip = t.get("tip", default_tip)
    if tip is not None and not isinstance(tip, str) and not (isinstance(tip, list) and all(isinstance(x, str) for x in tip)):
        ctx.fail("collision.tip", f"expected the name of a frame (or a list of them, one per leaf link), got {tip!r}")
    parent = tuple(parents) if parents else tuple(range(-1, len(joints) - 1))
    if "links" in t or not urdf:
        links = dict(_table(ctx, "collision.links", t.get("links", {}), set(t.get("links", {}))))
    else:                                        # every moving link the URDF gives geometry
        first: dict = {}
        for f in frames:
            if f.body != 0 and f.name in urdf and urdf[f.name]:
                first.setdefault(f.body, f.name)
        links = {name: "urdf" for name in first.values()}
    capsules: list = []
    bodies: dict = {}
    for name, value in links.items():
        fld = f"collision.links.{name}"
        if name not in known:
            ctx.fail(fld, f"no frame {name!r} (frames: {', '.join(known)})")
        body = known[name].body
        if body == 0:
            ctx.fail(fld, f"{name!r} is on the fixed base, which does not move")
        if body in bodies:
            ctx.fail(fld, f"{bodies[body]!r} of the same link has its geometry already")
        bodies[body] = name
        if value == "urdf":
            capsules += _urdf_geometry(ctx, fld, name, body, frames, urdf, urdf_path)
        else:
            capsules.append(_joint_capsule(ctx, fld, name, body, _number(ctx, fld, value, positive=True),
                                           joints, known, tip, parent))
    for i, entry in enumerate(_list(ctx, "collision.capsules", t.get("capsules", []))):
        capsules.append(_given_capsule(ctx, f"collision.capsules[{i}]", entry, known))
    notes: list = []
    if urdf and "links" in t:
        added, notes = _urdf_not_held(capsules, frames, urdf, urdf_path)
        capsules += added
    if not capsules:
        ctx.fail("collision", "no link has geometry: give `links` (a capsule radius or \"urdf\" per link) or "
                              "[[collision.capsules]]")
    return Collision(margin, tuple(capsules), tip, links, tuple(notes), _pairs(ctx, t.get("pairs", []), known, capsules))


def _pairs(ctx, raw, known: dict, capsules: list) -> tuple:
    """collision.pairs: [[frame, frame], ...], two links with capsules, not the same link, not both
    on the base."""
    out = []
    if not isinstance(raw, list):
        ctx.fail("collision.pairs", f"expected a list of [frame, frame] pairs, got {raw!r}")
    for i, pair in enumerate(raw):
        fld = f"collision.pairs[{i}]"
        if not isinstance(pair, list) or len(pair) != 2 or not all(isinstance(f, str) for f in pair):
            ctx.fail(fld, f"expected two frame names, got {pair!r}")
        for name in pair:
            if name not in known:
                ctx.fail(fld, f"no frame {name!r} (frames: {', '.join(known)})")
            if not any(c.body == known[name].body for c in capsules):
                ctx.fail(fld, f"the link of {name!r} has no capsule: give it geometry under links or capsules")
        if known[pair[0]].body == known[pair[1]].body:
            ctx.fail(fld, f"{pair[0]!r} and {pair[1]!r} are on the same link")
        out.append((pair[0], pair[1]))
    return tuple(out)


def _held(piece, capsule) -> bool:
    """Whether the capsule (a, b, r) `piece` lies inside `capsule` (same body frame): the distance
    to a segment is convex, so both ends' distances to capsule's axis plus r within its radius."""
    a, b, r = piece
    return all(_to_segment(p, capsule.a, capsule.b) + r <= capsule.radius + 1e-12 for p in (a, b))


def _to_segment(p, a, b) -> float:
    p, a, b = (np.asarray(v, float) for v in (p, a, b))
    d = b - a
    s = 0.0 if not d.any() else float(np.clip((p - a) @ d / (d @ d), 0.0, 1.0))
    return float(np.linalg.norm(p - a - s * d))


def _urdf_not_held(given: list, frames, urdf: dict, urdf_path) -> tuple[list, list]:
    """The URDF collision shapes of every moving link that the `given` capsules do not hold, as
    capsules of their own; and notes naming the links whose shapes were added, and the shapes
    that cannot be read (by reason)."""
    added: list = []
    grown: dict = {}
    unread: dict = {}
    for f in frames:
        if f.body == 0 or f.user:
            continue
        for shape in urdf.get(f.name, ()):
            try:
                pieces = [(f.R @ a + f.p, f.R @ b + f.p, float(r)) for a, b, r in shape_capsules(urdf_path, shape)]
            except ValueError as exc:
                unread.setdefault(str(exc), []).append(f"{f.name} ({Path(str(shape[2][0])).name})")
                continue
            own = [c for c in given + added if c.body == f.body]
            if all(any(_held(piece, c) for c in own) for piece in pieces):
                continue
            added += [Capsule(f.name, f.body, a, b, r) for a, b, r in pieces]
            grown.setdefault(f.name, []).append(shape[0])
    notes = [f"URDF link {name!r}: {len(kinds)} collision {'/'.join(sorted(set(kinds)))} shape(s) outside the "
             "capsules given: added" for name, kinds in grown.items()]
    notes += [f"collision meshes of {', '.join(where)}: {why}; not checked against obstacles (give the mesh, or a "
              "capsule that holds it)" for why, where in unread.items()]
    return added, notes


def _list(ctx, fld, value) -> list:
    if not isinstance(value, list):
        ctx.fail(fld, f"expected an array of tables ([[{fld}]]), got {value!r}")
    return value


def _urdf_geometry(ctx, fld, name, body, frames, urdf, urdf_path) -> list:
    """The capsules of every URDF link merged into `body`, in the body's frame."""
    out = []
    for f in frames:
        if f.body != body or f.user:
            continue
        for shape in urdf.get(f.name, ()):
            try:
                pieces = shape_capsules(urdf_path, shape)
            except ValueError as exc:
                ctx.fail(fld, f"URDF link {f.name!r}: collision mesh {shape[2][0]!r} {exc}; give {name!r} a capsule "
                              "radius here instead, or ship the mesh inside the robot's package")
            out += [Capsule(f.name, body, f.R @ a + f.p, f.R @ b + f.p, float(r)) for a, b, r in pieces]
    if not out:
        ctx.fail(fld, f"the URDF gives the link of {name!r} no <collision> geometry: give a capsule radius")
    return out


def _joint_capsule(ctx, fld, name, body, radius, joints, known, tip, parent) -> Capsule:
    """The capsule from the link's joint origin to the origin of the joint it carries (a leaf
    link's to its `tip` frame; a link that carries several joints needs capsules given)."""
    carried = [j for j, p in enumerate(parent) if p == body - 1]
    if len(carried) == 1:
        return Capsule(name, body, np.zeros(3), np.asarray(joints[carried[0]].origin_xyz, float), radius)
    if carried:
        ctx.fail(fld, f"the link of {name!r} carries {len(carried)} joints "
                      f"({', '.join(joints[j].name for j in carried)}): give its capsules under [[collision.capsules]]")
    tips = [tip] if isinstance(tip, str) else list(tip or [])
    mine = [t for t in tips if t in known and known[t].body == body]
    if not mine:
        ctx.fail("collision.tip", f"the capsule of the leaf link {name!r} needs the frame where it ends "
                                  f"(a frame on that link), got {tip!r}")
    return Capsule(name, body, np.zeros(3), np.asarray(known[mine[0]].p, float), radius)


def _given_capsule(ctx, fld, entry, known) -> Capsule:
    t = _table(ctx, fld, entry, CAPSULE_KEYS, ("frame", "radius"))
    name = t["frame"]
    if not isinstance(name, str) or name not in known:
        ctx.fail(f"{fld}.frame", f"no frame {name!r} (frames: {', '.join(known)})")
    f = known[name]
    if f.body == 0:
        ctx.fail(f"{fld}.frame", f"{name!r} is on the fixed base, which does not move")
    a = _vector(ctx, f"{fld}.a", t.get("a", [0.0, 0.0, 0.0]), 3)
    b = _vector(ctx, f"{fld}.b", t.get("b", list(a)), 3)
    r = _number(ctx, f"{fld}.radius", t["radius"], positive=True)
    return Capsule(name, f.body, f.R @ a + f.p, f.R @ b + f.p, r)


def collision_document(model) -> dict | None:
    """The [collision] table of `model` in the form any model file reads back: the margin and
    every capsule, in its body's frame given by the frame it was named by."""
    c = model.collision
    if c is None:
        return None
    known = {f.name: f for f in model.frames}
    out = []
    for cap in c.capsules:
        f = known[cap.link]
        out.append({"frame": cap.link, "a": [float(v) for v in f.R.T @ (cap.a - f.p)],
                    "b": [float(v) for v in f.R.T @ (cap.b - f.p)], "radius": float(cap.radius)})
    return {"margin": c.margin, "links": {}, "capsules": out, **({"pairs": [list(p) for p in c.pairs]} if c.pairs else {})}


def with_collision(model, raw: dict, where):
    """`model` with its [collision] table replaced by `raw` (as a problem file may give it); errors
    name `where` and the field."""
    tip = model.collision.tip if model.collision is not None else model.extra.get("tip_link_name")
    return dataclasses.replace(model, collision=collision(_Ctx(where), raw, model.joints, model.frames, tip,
                                                          model.extra.get("collision_geometry"),
                                                          model.extra.get("urdf"), model.parents))


# ----------------------------------------------------------------------------- what keeps clear

def capsules(model) -> tuple:
    """Every capsule that must keep clear of obstacles: the [collision] table's and the payload's
    sphere (about its centre of mass, when it has a radius)."""
    out = tuple(model.collision.capsules) if model.collision is not None else ()
    held = model.payload
    if held is not None and held.radius is not None:
        f = model.frame(held.frame)
        centre = f.R @ np.asarray(held.body.com, float) + f.p
        out += (Capsule(f"payload ({held.frame})", f.body, centre, centre.copy(), float(held.radius)),)
    return out


def capsule_pairs(model) -> list:
    """Every pair of capsules that must keep the margin from each other: those on the two links of
    each of [collision] pairs."""
    if model.collision is None or not model.collision.pairs:
        return []
    caps = capsules(model)
    out = []
    for a, b in model.collision.pairs:
        body_a, body_b = model.frame(a).body, model.frame(b).body
        out += [(c, d) for c in caps if c.body == body_a for d in caps if d.body == body_b]
    return out


def margin(model) -> float:
    """The model's collision margin in m (0 without a [collision] table)."""
    return model.collision.margin if model.collision is not None else 0.0
