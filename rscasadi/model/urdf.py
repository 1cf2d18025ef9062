"""URDF-based model files (docs/user-guide/model.md, "URDF form"): links, joint placements and axes from
a URDF, the actuators (gear, SEA, losses, rotors, limits) from the model file.

The URDF is parsed by yourdfpy (meshes never loaded).  The tree is cut into the serial chain
of moving joints; every link hanging on a chain link through fixed or locked joints is merged
into it (spatial inertias add, eq. 11 moved by eq. 8).  A URDF joint turns its child about an
arbitrary axis a; our joints turn about z, so each joint frame J_j is the URDF joint frame
turned by R_a (the shortest rotation taking z to a) and link j's frame is the URDF child
frame turned by the same R_a: L_j = L_urdf R_a.
"""
from __future__ import annotations

from pathlib import Path

from typing import Any
import warnings

import numpy as np
from scipy.spatial.transform import Rotation

from rscasadi.spatial import spatial_inertia, transform_inertia
from rscasadi.model.checks import ACTUATOR_KEYS, _Ctx, _number, _table, _vector, actuator, joint_context
from rscasadi.model.collision import collision
from rscasadi.model.frames import contacts, payload, user_frames
from rscasadi.model.kinds import KINDS
from rscasadi.model.types import DEFAULT_GRAVITY, ArmModel, Body, Frame, Joint, ModelFileError, inertia_problem, rpy_of

URDF_TOP_KEYS = {"name", "urdf", "tip", "tips", "locked", "lock_others", "gravity", "joints", "frames", "payload",
                 "collision", "floating", "contacts"}
MOVING = ("revolute", "continuous")


def axis_rotation(axis) -> np.ndarray:
    """R_a: the shortest rotation taking z to the unit joint axis a (the identity for a = z)."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    if np.allclose(a, [0, 0, 1], atol=1e-15):
        return np.eye(3)
    if np.allclose(a, [0, 0, -1], atol=1e-15):
        return np.diag([1.0, -1.0, -1.0])
    R = Rotation.align_vectors([a], [[0.0, 0.0, 1.0]])[0].as_matrix()
    R[np.abs(R) < 1e-15] = 0.0
    return R


def _homogeneous(R, p):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


SNAP = 1e-8      # rad: an angle this close to a multiple of pi/2 is that multiple (CAD writes 1.57079632679 or 1.57079633)


def snap_angle(a: float) -> float:
    """a, or the multiple of pi/2 within SNAP of it (exactly as np.pi / 2 * k)."""
    k = round(a / (np.pi / 2))
    return float(np.pi / 2 * k) if abs(a - np.pi / 2 * k) <= SNAP else float(a)


def snapped(path) -> tuple:
    """The URDF's text with every <origin rpy> angle within SNAP of a multiple of pi/2 snapped
    to it (an exported 1.57079632679 rad rotation has entries of 5e-12 where 0 is meant: no
    folding, 64 % more instructions, and no exact roll-pitch-yaw to write back); and how many
    angles were snapped."""
    from lxml import etree
    tree = etree.parse(str(path), etree.XMLParser(remove_blank_text=True))
    count = 0
    for origin in tree.iter("origin"):
        rpy = origin.get("rpy")
        if rpy is None:
            continue
        try:
            angles = [float(v) for v in rpy.split()]
        except ValueError:
            continue                                              # yourdfpy names the bad value
        new = [snap_angle(a) for a in angles]
        count += sum(a != b for a, b in zip(angles, new))
        origin.set("rpy", " ".join(repr(a) for a in new))
    return etree.tostring(tree), count


def _load(path, ctx):
    import io

    import yourdfpy

    from rscasadi.files import check_input_size
    check_input_size(path, "model")
    try:
        text, _ = snapped(path)
        return yourdfpy.URDF.load(io.BytesIO(text), load_meshes=False, build_scene_graph=False,
                                  load_collision_meshes=False, build_collision_scene_graph=False,
                                  mesh_dir=str(Path(path).parent))
    except OSError as exc:
        ctx.fail("urdf", f"cannot read URDF {path}: {exc.strerror or exc}")
    except Exception as exc:                                     # lxml syntax errors, missing elements
        ctx.fail("urdf", f"{path} is not a valid URDF: {type(exc).__name__}: {exc}")


def _link_spatial(urdf_path, link, odd: list | None = None) -> np.ndarray:
    """A URDF link's spatial inertia about its frame origin (6x6); zero if it has no mass.  A link
    whose moments break the triangle inequality (no rigid body has them: a CAD export's round
    numbers) is kept as given, its name added to `odd`."""
    inertial = link.inertial
    if inertial is None or inertial.mass is None or inertial.mass == 0.0:
        return np.zeros((6, 6))
    where = f"{urdf_path}: link {link.name!r}, <inertial>"
    if not np.isfinite(inertial.mass) or inertial.mass < 0.0:
        raise ModelFileError(f"{where}: mass must be >= 0, got {inertial.mass!r}")
    I = np.asarray(inertial.inertia if inertial.inertia is not None else np.zeros((3, 3)), float)
    problem = inertia_problem(I, point_mass=True, triangle=False)   # the merged body's is checked whole
    if problem:
        raise ModelFileError(f"{where}: inertia {problem}")
    if odd is not None and inertia_problem(I, point_mass=True):
        odd.append(link.name)
    T = np.asarray(inertial.origin if inertial.origin is not None else np.eye(4), float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ModelFileError(f"{where}: <origin> is not finite numbers")
    body = Body(float(inertial.mass), np.zeros(3), I)
    return transform_inertia(spatial_inertia(body), T[:3, :3], T[:3, 3])


def _axis(urdf_path, joint) -> np.ndarray:
    """A joint's unit axis (URDF default: x), or a ModelFileError naming the joint."""
    a = np.asarray(joint.axis if joint.axis is not None else [1.0, 0.0, 0.0], float).ravel()
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.linalg.norm(a) < 1e-9:
        raise ModelFileError(f"{urdf_path}: joint {joint.name!r}, <axis>: expected 3 finite numbers, not all "
                             f"zero, got {joint.axis!r}")
    return a / np.linalg.norm(a)


def _origin(urdf_path, joint) -> np.ndarray:
    T = np.asarray(joint.origin if joint.origin is not None else np.eye(4), float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ModelFileError(f"{urdf_path}: joint {joint.name!r}, <origin>: not finite numbers")
    return T


def _joint_motion(urdf_path, joint, q) -> np.ndarray:
    """The 4x4 motion of a locked joint at q about/along its axis."""
    a = _axis(urdf_path, joint)
    if joint.type == "prismatic":
        return _homogeneous(np.eye(3), a * q)
    return _homogeneous(Rotation.from_rotvec(a * q).as_matrix(), np.zeros(3))


def parse_urdf_form(data: dict, path: str) -> ArmModel:
    """Validate a URDF-based model file into an ArmModel (same object as the link-list form)."""
    from pathlib import Path
    ctx = _Ctx(path)
    _table(ctx, "", data, URDF_TOP_KEYS, ("name", "urdf", "joints"))
    for key in ("name", "urdf"):
        if not isinstance(data[key], str) or not data[key].strip() or "\0" in data[key]:
            ctx.fail(key, f"expected a non-empty string, got {data[key]!r}")
    gravity = _vector(ctx, "gravity", data.get("gravity", list(DEFAULT_GRAVITY)), 3)
    urdf_path = (Path(path).parent / data["urdf"]) if path != "<memory>" else Path(data["urdf"])
    if not urdf_path.is_file():
        ctx.fail("urdf", f"URDF file {urdf_path} not found")
    robot = _load(urdf_path, ctx)
    joints_by_name = {jt.name: jt for jt in robot.robot.joints}
    links_by_name = {lk.name: lk for lk in robot.robot.links}
    raw_locked = data.get("locked", {})
    if not isinstance(raw_locked, dict):
        ctx.fail("locked", f"expected a table of joint names and positions, got {raw_locked!r}")
    locked = _table(ctx, "locked", raw_locked, set(joints_by_name) | set(raw_locked))
    for name, value in locked.items():
        if name not in joints_by_name:
            ctx.fail(f"locked.{name}", f"no joint {name!r} in {urdf_path}")
        _number(ctx, f"locked.{name}", value)
    raw_joints = data["joints"]
    if not isinstance(raw_joints, list) or not raw_joints:
        ctx.fail("joints", "expected at least one [[joints]] table")
    actuators: dict = {}
    for idx, raw in enumerate(raw_joints):
        jctx = joint_context(path, idx, raw)
        t = _table(jctx, "", raw, ACTUATOR_KEYS, ("name",))
        act = actuator(jctx, t, set(actuators))
        if act["name"] not in joints_by_name:
            jctx.fail("name", f"no joint {act['name']!r} in {urdf_path}")
        if act["name"] in locked:
            jctx.fail("name", f"joint {act['name']!r} is both actuated and locked")
        actuators[act["name"]] = (idx, act)

    misfits = [f"{name!r} is {joints_by_name[name].type}, which a {act['kind']} joint cannot model"
               f" (a {act['kind']} joint models {', '.join(KINDS[act['kind']].fits)} joints)"
               for name, (_, act) in actuators.items() if joints_by_name[name].type not in KINDS[act["kind"]].fits]
    if misfits:
        ctx.fail("joints", f"{urdf_path}: " + "; ".join(misfits) + " (hold a joint fixed under [locked])")
    lock_others = _number(ctx, "lock_others", data.get("lock_others", 0.0))
    if "tip" in data and "tips" in data:
        ctx.fail("tips", "give tip (one chain) or tips (a tree), not both")
    if "tips" in data and (not isinstance(data["tips"], list) or not data["tips"]):
        ctx.fail("tips", f"expected a list of link names, got {data['tips']!r}")
    placement, bodies, held_at = _cut_tree(robot, urdf_path, joints_by_name, links_by_name, locked, actuators,
                                           data.get("tips", data.get("tip")), ctx, lock_others)
    order = list(actuators)
    parents = [placement[name][0] - 1 for name in order]
    late = [f"{name!r} before {order[p]!r}" for j, (name, p) in enumerate(zip(order, parents)) if p >= j]
    if late:
        if len(set(parents)) == len(parents):                 # one chain: each body carries one joint
            depth = sorted(order, key=lambda name: len(_path_joints(robot, links_by_name, joints_by_name[name].child)))
            ctx.fail("joints", f"[[joints]] must list the chain's moving joints base to tip: {depth}, got {order}")
        ctx.fail("joints", "[[joints]] must list every joint after the joint that carries it: " + ", ".join(late))
    joints, axes = [], [np.eye(3)]
    for j, name in enumerate(order):
        ujoint, (idx, act) = joints_by_name[name], actuators[name]
        jctx = joint_context(path, idx, {"name": name})
        T_acc = placement[name][1]                             # parent body's URDF frame -> joint origin
        R_prev = axes[parents[j] + 1]
        R_a = axis_rotation(_axis(urdf_path, ujoint))
        R_J = R_prev.T @ T_acc[:3, :3] @ R_a
        R_J[np.abs(R_J) < 1e-15] = 0.0
        M = bodies[j + 1]["M"]
        if M[3, 3] <= 0.0:
            jctx.fail("link", f"the link moved by joint {name!r} ({', '.join(bodies[j + 1]['links'])} in "
                              f"{urdf_path}) has no mass: give it an <inertial>")
        M_ours = transform_inertia(M, R_a.T, np.zeros(3))     # from L_urdf to L_j = L_urdf R_a
        link = Body.from_spatial(M_ours)
        problem = inertia_problem(link.inertia, 1e-9)
        if problem:
            jctx.fail("link", f"merged inertia of {', '.join(bodies[j + 1]['links'])} {problem}")
        limits = dict(act.pop("limits"))
        lim = ujoint.limit
        if "theta" not in limits and ujoint.type in ("revolute", "prismatic") and lim is not None \
                and lim.lower is not None and lim.upper is not None and np.isfinite([lim.lower, lim.upper]).all() \
                and lim.lower < lim.upper:
            limits["theta"] = (float(lim.lower), float(lim.upper))
        rpy = rpy_of(R_J)                               # informative only: origin_R is what counts
        joints.append(Joint(origin_xyz=R_prev.T @ T_acc[:3, 3], origin_rpy=np.full(3, np.nan) if rpy is None else rpy,
                            link=link, limits=limits, origin_R=R_J,
                            type="prismatic" if ujoint.type == "prismatic" else "revolute", **act))
        axes.append(R_a)
    tips = data.get("tips") or ([data["tip"]] if "tip" in data else [])
    extra = {"urdf": str(urdf_path), "locked": held_at, "links": [b["links"] for b in bodies]}
    # each URDF link's frame on its tree body: L_j = L_urdf R_a, so a pose T in L_urdf is R_a^T T in L_j
    frames = tuple(Frame(name, b, axes[b].T @ T[:3, :3], axes[b].T @ T[:3, 3])
                   for b, body in enumerate(bodies) for name, T in zip(body["links"], body["T_links"]))
    frames = user_frames(ctx, data.get("frames"), frames)
    leaves = [b for b in range(1, len(bodies)) if b - 1 not in parents]
    ends = tips or [next((lk for lk in reversed(bodies[b]["links"])), None) for b in leaves]
    tip_link = ends[0] if len(ends) == 1 else ends
    extra["tip_link_name"] = tip_link                          # where a leaf link's capsule ends by default
    extra["collision_geometry"] = {lk: shapes for b in bodies for lk in b["links"]
                                   if (shapes := _collision_shapes(urdf_path, links_by_name[lk]))}
    tree = () if parents == list(range(-1, len(order) - 1)) else tuple(parents)
    touching, soles = contacts(ctx, data.get("contacts"), frames, data.get("floating") is True)
    return ArmModel(data["name"], gravity, tuple(joints), path, extra, frames=frames,
                    base=_base_body(ctx, data.get("floating", False), bodies[0], urdf_path),
                    contacts=touching, soles=soles,
                    payload=payload(ctx, data.get("payload"), frames), parents=tree,
                    collision=collision(ctx, data.get("collision"), joints, frames, tip_link,
                                        extra["collision_geometry"], urdf_path, parents=tree))


def _base_body(ctx, floating, body: dict, urdf_path) -> Body | None:
    """With `floating = true`, the root link and the links fixed to it as the base's body."""
    if not isinstance(floating, bool):
        ctx.fail("floating", f"expected true or false, got {floating!r}")
    if not floating:
        return None
    if body["M"][3, 3] <= 0.0:
        ctx.fail("floating", f"the base ({', '.join(body['links'])} in {urdf_path}) has no mass: a floating base "
                             "needs an <inertial>")
    base = Body.from_spatial(body["M"])
    problem = inertia_problem(base.inertia, 1e-9)
    if problem:
        ctx.fail("floating", f"merged inertia of the base ({', '.join(body['links'])}) {problem}")
    return base


def _collision_shapes(urdf_path, link) -> list:
    """A URDF link's <collision> shapes (kind, T in the link's frame, data): ("cylinder", T,
    (radius, length)), ("sphere", T, radius), ("box", T, size), ("mesh", T, (file name, scale));
    read as capsules only where [collision] asks for them (rscasadi.model.collision)."""
    out = []
    shape: tuple
    sizes: Any
    for c in link.collisions or ():
        T = np.asarray(c.origin if c.origin is not None else np.eye(4), float)
        g = c.geometry
        if g is None or not np.all(np.isfinite(T)):
            continue
        if g.cylinder is not None:
            shape, sizes = ("cylinder", T, (float(g.cylinder.radius), float(g.cylinder.length))), [g.cylinder.radius]
        elif g.sphere is not None:
            shape, sizes = ("sphere", T, float(g.sphere.radius)), [g.sphere.radius]
        elif g.box is not None:
            shape, sizes = ("box", T, np.asarray(g.box.size, float)), list(np.ravel(g.box.size))
        elif g.mesh is not None:
            scale = np.ones(3) if g.mesh.scale is None else np.broadcast_to(np.asarray(g.mesh.scale, float), 3).copy()
            shape, sizes = ("mesh", T, (str(g.mesh.filename), scale)), list(np.abs(scale))
        else:
            continue
        sizes = np.asarray(sizes, float)
        if sizes.size == 0 or not (np.all(np.isfinite(sizes)) and np.all(sizes > 0)):
            raise ModelFileError(f"{urdf_path}: link {link.name!r}, <collision>: a {shape[0]} whose sizes are not "
                                 f"positive numbers ({sizes.tolist()!r})")
        out.append(shape)
    return out


def _path_joints(robot, links_by_name, target: str) -> list:
    """The joints on the path from the URDF's root link to `target`, root first."""
    parent_joint = {jt.child: jt for jt in robot.robot.joints}
    path, link = [], target
    while link in parent_joint:
        path.append(parent_joint[link])
        link = parent_joint[link].parent
    return path[::-1]


def _cut_tree(robot, urdf_path, joints_by_name, links_by_name, locked, actuators, tips, ctx, lock_others: float = 0.0):
    """Walk the URDF tree from its root: the tree of moving joints on the paths from the root to
    the tips (`tips`, else the child links of the actuated joints), and for every body of that
    tree (0 = base, then one per moving joint in the order of `actuators`) its merged spatial
    inertia in its URDF frame, the names of the links merged into it; per moving joint the body
    that carries it and the transform from that body's frame to the joint's origin.  Moving joints
    off those paths (a whole robot's head, other arm, fingers) are held at their [locked]
    position, else at `lock_others`: those hanging from the fixed base cannot move the tree, those
    hanging from its links add their mass there."""
    children: dict = {}
    for jt in robot.robot.joints:
        if jt.parent not in links_by_name or jt.child not in links_by_name:
            missing = jt.parent if jt.parent not in links_by_name else jt.child
            ctx.fail("urdf", f"{urdf_path}: joint {jt.name!r} names link {missing!r}, which is not defined")
        children.setdefault(jt.parent, []).append(jt)
    child_links = {jt.child for jt in robot.robot.joints}
    roots = [lk for lk in links_by_name if lk not in child_links]
    if len(roots) != 1:
        ctx.fail("urdf", f"{urdf_path}: expected one root link, found {roots}")
    field = "tips" if isinstance(tips, list) else "tip"
    given = tips if isinstance(tips, list) else ([] if tips is None else [tips])
    for tip in given:
        if not isinstance(tip, str) or tip not in links_by_name:
            ctx.fail(field, f"no link {tip!r} in {urdf_path}")
    targets = given or [joints_by_name[name].child for name in actuators]
    on_path = {jt.name for t in targets for jt in _path_joints(robot, links_by_name, t)}
    held = lambda jt: jt.type not in MOVING + ("prismatic",) or jt.name in actuators or jt.name in locked  # noqa: E731
    off = [name for name in actuators if name not in on_path]
    below_tip = [name for name in off if any(t in {jt.child for jt in _path_joints(robot, links_by_name,
                                                                                    joints_by_name[name].child)}
                                             for t in given)]
    if below_tip:
        ctx.fail(field, f"joints {below_tip} lie beyond the tip link(s) {given}: lock them or move the tip")
    if off:
        ctx.fail("joints", f"{urdf_path}: {', '.join(repr(n) for n in off)} not on the paths from {roots[0]!r} to "
                           f"the tips {given}: add their last links to tips, or lock them")
    unlisted = [jt.name for t in targets for jt in _path_joints(robot, links_by_name, t) if not held(jt)]
    if not given:                       # where the tree ends is not said: the joints below it must be
        below, todo = [], list(dict.fromkeys(targets))
        while todo:
            for jt in children.get(todo.pop(), []):
                below += [] if held(jt) or jt.name in on_path else [jt.name]
                todo.append(jt.child)
        unlisted += below
    unlisted = list(dict.fromkeys(unlisted))
    if unlisted:
        ends = targets if given else [max(targets, key=lambda t: len(_path_joints(robot, links_by_name, t)))]
        ctx.fail("joints", f"{urdf_path}: the moving joints {', '.join(repr(n) for n in unlisted)} on the paths from "
                           f"{roots[0]!r} to {', '.join(repr(t) for t in ends)}{' or below them' if not given else ''} "
                           "have no [[joints]] entry and are not locked: give each an actuator, hold it under "
                           "[locked], or end the tree at its last links with tip = \"LINK\" or tips = [\"LINK\", ...] "
                           "(every moving joint off the paths from the root to the tips is then held at lock_others)")
    index = {name: k + 1 for k, name in enumerate(actuators)}        # joint name -> its body
    bodies: list[dict[str, Any]] = [{"M": np.zeros((6, 6)), "links": [], "T_links": []} for _ in range(len(index) + 1)]
    placement, held_at = {}, {}                               # held_at: every held moving joint's position
    stack = [(roots[0], 0, np.eye(4))]                        # (link, tree body, transform body frame -> link)
    odd: list = []                                            # links whose moments no rigid body has
    while stack:
        link_name, b, T = stack.pop()
        bodies[b]["links"].append(link_name)
        bodies[b]["T_links"].append(T)
        bodies[b]["M"] = bodies[b]["M"] + transform_inertia(_link_spatial(urdf_path, links_by_name[link_name], odd),
                                                            T[:3, :3], T[:3, 3])
        for jt in children.get(link_name, []):
            origin = _origin(urdf_path, jt)
            if jt.name in locked and jt.type not in MOVING + ("prismatic",):
                ctx.fail(f"locked.{jt.name}", f"{urdf_path}: joint {jt.name!r} is {jt.type}: only revolute, "
                                              f"continuous and prismatic joints can be locked")
            if jt.name not in actuators:                          # fixed, locked, or off the tree: held
                if jt.type in MOVING + ("prismatic",):
                    held_at[jt.name] = float(locked.get(jt.name, lock_others))
                    motion = _joint_motion(urdf_path, jt, held_at[jt.name])
                else:                                             # fixed (floating, planar: at their origin)
                    motion = np.eye(4)
                stack.append((jt.child, b, T @ origin @ motion))
                continue
            placement[jt.name] = (b, T @ origin)
            stack.append((jt.child, index[jt.name], np.eye(4)))
    if odd:
        warnings.warn(f"{urdf_path}: the inertias of links {', '.join(repr(n) for n in odd)} break the triangle "
                      "inequality (no rigid body has such principal moments); kept as given, merged into the "
                      "bodies that carry them, which are checked whole", stacklevel=3)
    return placement, bodies, held_at
