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
import numpy as np
from scipy.spatial.transform import Rotation

from rscasadi.spatial import spatial_inertia, transform_inertia
from rscasadi.model.checks import ACTUATOR_KEYS, _Ctx, _number, _table, _vector, actuator, joint_context
from rscasadi.model.collision import collision
from rscasadi.model.frames import payload, user_frames
from rscasadi.model.types import DEFAULT_GRAVITY, ArmModel, Body, Frame, Joint, ModelFileError, inertia_problem, rpy_of

URDF_TOP_KEYS = {"name", "urdf", "tip", "locked", "lock_others", "gravity", "joints", "frames", "payload",
                 "collision"}
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


def _link_spatial(urdf_path, link) -> np.ndarray:
    """A URDF link's spatial inertia about its frame origin (6x6); zero if it has no mass."""
    inertial = link.inertial
    if inertial is None or inertial.mass is None or inertial.mass == 0.0:
        return np.zeros((6, 6))
    where = f"{urdf_path}: link {link.name!r}, <inertial>"
    if not np.isfinite(inertial.mass) or inertial.mass < 0.0:
        raise ModelFileError(f"{where}: mass must be >= 0, got {inertial.mass!r}")
    I = np.asarray(inertial.inertia if inertial.inertia is not None else np.zeros((3, 3)), float)
    problem = inertia_problem(I, point_mass=True)          # the merged body's is checked positive definite
    if problem:
        raise ModelFileError(f"{where}: inertia {problem}")
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
        if not isinstance(data[key], str) or not data[key].strip():
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
        t = _table(jctx, "", raw, ACTUATOR_KEYS, ("name", "gear_ratio", "sea", "slow_rotor", "fast_rotor"))
        act = actuator(jctx, t, set(actuators))
        if act["name"] not in joints_by_name:
            jctx.fail("name", f"no joint {act['name']!r} in {urdf_path}")
        if act["name"] in locked:
            jctx.fail("name", f"joint {act['name']!r} is both actuated and locked")
        actuators[act["name"]] = (idx, act)

    lock_others = _number(ctx, "lock_others", data.get("lock_others", 0.0))
    chain, bodies, tip_body, held_at = _cut_chain(robot, urdf_path, joints_by_name, links_by_name, locked,
                                                  actuators, data.get("tip"), ctx, lock_others)
    order = [act_name for act_name in actuators]
    if [jt.name for jt in chain] != order:
        ctx.fail("joints", f"[[joints]] must list the chain's moving joints base to tip: "
                           f"{[jt.name for jt in chain]}, got {order}")
    joints, R_prev, axes = [], np.eye(3), [np.eye(3)]
    for j, ujoint in enumerate(chain):
        idx, act = actuators[ujoint.name]
        jctx = joint_context(path, idx, {"name": ujoint.name})
        T_acc = bodies[j]["T_joint"]                          # parent body's URDF frame -> joint origin
        R_a = axis_rotation(_axis(urdf_path, ujoint))
        R_J = R_prev.T @ T_acc[:3, :3] @ R_a
        R_J[np.abs(R_J) < 1e-15] = 0.0
        M = bodies[j + 1]["M"]
        if M[3, 3] <= 0.0:
            jctx.fail("link", f"the link moved by joint {ujoint.name!r} ({', '.join(bodies[j + 1]['links'])} in "
                              f"{urdf_path}) has no mass: give it an <inertial>")
        M_ours = transform_inertia(M, R_a.T, np.zeros(3))     # from L_urdf to L_j = L_urdf R_a
        link = Body.from_spatial(M_ours)
        problem = inertia_problem(link.inertia, 1e-9)
        if problem:
            jctx.fail("link", f"merged inertia of {', '.join(bodies[j + 1]['links'])} {problem}")
        limits = dict(act.pop("limits"))
        lim = ujoint.limit
        if "theta" not in limits and ujoint.type == "revolute" and lim is not None \
                and lim.lower is not None and lim.upper is not None and np.isfinite([lim.lower, lim.upper]).all() \
                and lim.lower < lim.upper:
            limits["theta"] = (float(lim.lower), float(lim.upper))
        rpy = rpy_of(R_J)                               # informative only: origin_R is what counts
        joints.append(Joint(origin_xyz=R_prev.T @ T_acc[:3, 3], origin_rpy=np.full(3, np.nan) if rpy is None else rpy,
                            link=link,
                            limits=limits, origin_R=R_J, **act))
        R_prev = R_a
        axes.append(R_a)
    extra = {"urdf": str(urdf_path), "tip_link": tip_body, "locked": held_at,
             "links": [b["links"] for b in bodies]}
    # each URDF link's frame on its chain body: L_j = L_urdf R_a, so a pose T in L_urdf is R_a^T T in L_j
    frames = tuple(Frame(name, b, axes[b].T @ T[:3, :3], axes[b].T @ T[:3, 3])
                   for b, body in enumerate(bodies) for name, T in zip(body["links"], body["T_links"]))
    frames = user_frames(ctx, data.get("frames"), frames)
    tip_link = data.get("tip") or next((lk for lk in reversed(bodies[-1]["links"])), None)
    extra["tip_link_name"] = tip_link                          # where the last link's capsule ends by default
    extra["collision_geometry"] = {lk: shapes for b in bodies for lk in b["links"]
                                   if (shapes := _collision_shapes(urdf_path, links_by_name[lk]))}
    return ArmModel(data["name"], gravity, tuple(joints), path, extra, frames=frames,
                    payload=payload(ctx, data.get("payload"), frames),
                    collision=collision(ctx, data.get("collision"), joints, frames, tip_link,
                                        extra["collision_geometry"], urdf_path))


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


def _cut_chain(robot, urdf_path, joints_by_name, links_by_name, locked, actuators, tip, ctx, lock_others: float = 0.0):
    """Walk the URDF tree from its root: the chain of moving joints on the path from the root to
    the tip (`tip`, else the child link of the deepest actuated joint), and for every chain body
    (0 = base, j = link of moving joint j) its merged spatial inertia in its URDF frame, the
    names of the links merged into it, and (T_joint) the transform from it to the origin of
    the next moving joint.  Moving joints off that path (a whole robot's head, other arm,
    fingers) are held at their [locked] position, else at `lock_others`: those hanging from the
    fixed base cannot move the chain, those hanging from its links add their mass there."""
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
    if tip is not None and (not isinstance(tip, str) or tip not in links_by_name):
        ctx.fail("tip", f"no link {tip!r} in {urdf_path}")
    # where no tip is given the chain ends below the deepest actuated joint (whatever their order
    # in the file: the order is checked by the caller, with its own message)
    target = tip if tip is not None else max((joints_by_name[name].child for name in actuators),
                                             key=lambda link: len(_path_joints(robot, links_by_name, link)))
    on_path = {jt.name for jt in _path_joints(robot, links_by_name, target)}
    off = [name for name in actuators if name not in on_path]
    if off:
        ctx.fail("joints", f"{urdf_path}: {', '.join(repr(n) for n in off)} not on the path from {roots[0]!r} to the "
                           f"tip {target!r}: actuate the joints of one chain (tip = its last link)")
    held = lambda jt: jt.type not in MOVING + ("prismatic",) or jt.name in actuators or jt.name in locked  # noqa: E731
    unlisted = [jt.name for jt in _path_joints(robot, links_by_name, target) if not held(jt)]
    if tip is None:                     # where the chain ends is not said: the joints below it must be
        below, todo = [], [target]
        while todo:
            for jt in children.get(todo.pop(), []):
                below += [] if held(jt) else [jt.name]
                todo.append(jt.child)
        unlisted += below
    if unlisted:
        ctx.fail("joints", f"{urdf_path}: the moving joints {', '.join(repr(n) for n in unlisted)} on the path from "
                           f"{roots[0]!r} to the chain's last link {target!r}{' or below it' if tip is None else ''} "
                           "have no [[joints]] entry and are not locked: give each an actuator, hold it under "
                           "[locked], or end the chain at a link with tip = \"LINK\" (every moving joint off the "
                           "path from the root to the tip is then held at lock_others)")
    bodies: list[dict[str, Any]] = [{"M": np.zeros((6, 6)), "links": [], "T_joint": None, "T_links": []}]
    chain, held_at = [], {}                                   # held_at: every held moving joint's position
    tip_body = None
    stack = [(roots[0], 0, np.eye(4))]                        # (link, chain body, transform body frame -> link)
    while stack:
        link_name, b, T = stack.pop()
        bodies[b]["links"].append(link_name)
        bodies[b]["T_links"].append(T)
        if link_name == tip:
            tip_body = b
        if b > 0:
            bodies[b]["M"] = bodies[b]["M"] + transform_inertia(_link_spatial(urdf_path, links_by_name[link_name]),
                                                                T[:3, :3], T[:3, 3])
        for jt in children.get(link_name, []):
            origin = _origin(urdf_path, jt)
            if jt.name in locked and jt.type not in MOVING + ("prismatic",):
                ctx.fail(f"locked.{jt.name}", f"{urdf_path}: joint {jt.name!r} is {jt.type}: only revolute, "
                                              f"continuous and prismatic joints can be locked")
            if jt.name in actuators and jt.type not in MOVING:
                ctx.fail("urdf", f"{urdf_path}: joint {jt.name!r} is {jt.type}: only revolute and continuous "
                                 f"joints can be actuated (lock it under 'locked' to hold it fixed)")
            if jt.name not in actuators:                          # fixed, locked, or off the chain: held
                if jt.type in MOVING + ("prismatic",):
                    held_at[jt.name] = float(locked.get(jt.name, lock_others))
                    motion = _joint_motion(urdf_path, jt, held_at[jt.name])
                else:                                             # fixed (floating, planar: at their origin)
                    motion = np.eye(4)
                stack.append((jt.child, b, T @ origin @ motion))
                continue
            bodies[b]["T_joint"], bodies[b]["next"] = T @ origin, jt.name
            chain.append(jt)
            bodies.append({"M": np.zeros((6, 6)), "links": [], "T_joint": None, "T_links": []})
            stack.append((jt.child, len(bodies) - 1, np.eye(4)))
    if tip is not None and tip_body != len(bodies) - 1:
        beyond = [jt.name for jt in chain[tip_body:]]
        ctx.fail("tip", f"joints {beyond} lie beyond the tip link {tip!r}: lock them or move the tip")
    return chain, bodies, tip_body, held_at
