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

import numpy as np
from scipy.spatial.transform import Rotation

from rscasadi.spatial import spatial_inertia, transform_inertia
from rscasadi.model.checks import ACTUATOR_KEYS, _Ctx, _number, _table, _vector, actuator, joint_context
from rscasadi.model.frames import collision, payload, user_frames
from rscasadi.model.types import DEFAULT_GRAVITY, ArmModel, Body, Frame, Joint, ModelFileError, inertia_problem, rpy_of

URDF_TOP_KEYS = {"name", "urdf", "tip", "locked", "gravity", "joints", "frames", "payload", "collision"}
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


def _load(path, ctx):
    import yourdfpy
    try:
        return yourdfpy.URDF.load(str(path), load_meshes=False, build_scene_graph=False,
                                  load_collision_meshes=False, build_collision_scene_graph=False)
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
    problem = inertia_problem(I)
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
    actuators = {}
    for idx, raw in enumerate(raw_joints):
        jctx = joint_context(path, idx, raw)
        t = _table(jctx, "", raw, ACTUATOR_KEYS, ("name", "gear_ratio", "sea", "slow_rotor", "fast_rotor"))
        act = actuator(jctx, t, set(actuators))
        if act["name"] not in joints_by_name:
            jctx.fail("name", f"no joint {act['name']!r} in {urdf_path}")
        if act["name"] in locked:
            jctx.fail("name", f"joint {act['name']!r} is both actuated and locked")
        actuators[act["name"]] = (idx, act)

    chain, bodies, tip_body = _cut_chain(robot, urdf_path, joints_by_name, links_by_name, locked, actuators,
                                         data.get("tip"), ctx)
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
    extra = {"urdf": str(urdf_path), "tip_link": tip_body, "locked": dict(locked),
             "links": [b["links"] for b in bodies]}
    # each URDF link's frame on its chain body: L_j = L_urdf R_a, so a pose T in L_urdf is R_a^T T in L_j
    frames = tuple(Frame(name, b, axes[b].T @ T[:3, :3], axes[b].T @ T[:3, 3])
                   for b, body in enumerate(bodies) for name, T in zip(body["links"], body["T_links"]))
    frames = user_frames(ctx, data.get("frames"), frames)
    tip_link = data.get("tip") or next((lk for lk in reversed(bodies[-1]["links"])), None)
    extra["tip_link_name"] = tip_link                          # where the last link's capsule ends by default
    extra["collision_geometry"] = {lk: geometry for b in bodies for lk in b["links"]
                                   if (geometry := _collision_primitives(urdf_path, links_by_name[lk]))}
    return ArmModel(data["name"], gravity, tuple(joints), path, extra, frames=frames,
                    payload=payload(ctx, data.get("payload"), frames),
                    collision=collision(ctx, data.get("collision"), joints, frames, tip_link,
                                        extra["collision_geometry"]))


def _collision_primitives(urdf_path, link) -> list:
    """A URDF link's <collision> cylinders and spheres as capsules (a, b, radius) in the link's
    frame: a cylinder's axis is its z, and the capsule of its radius over its length holds it;
    a sphere is a capsule of no length.  Boxes and meshes are left out (None of them: [])."""
    out = []
    for c in link.collisions or ():
        T = np.asarray(c.origin if c.origin is not None else np.eye(4), float)
        g = c.geometry
        if g is None or not np.all(np.isfinite(T)):
            continue
        if g.cylinder is not None:
            r, length = float(g.cylinder.radius), float(g.cylinder.length)
            half = T[:3, :3] @ np.array([0.0, 0.0, length / 2])
            out.append((T[:3, 3] - half, T[:3, 3] + half, r))
        elif g.sphere is not None:
            out.append((T[:3, 3].copy(), T[:3, 3].copy(), float(g.sphere.radius)))
    for a, b, r in out:
        if not (np.isfinite(r) and r > 0 and np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            raise ModelFileError(f"{urdf_path}: link {link.name!r}, <collision>: a cylinder or sphere with a "
                                 f"radius that is not a positive number ({r!r})")
    return out


def _cut_chain(robot, urdf_path, joints_by_name, links_by_name, locked, actuators, tip, ctx):
    """Walk the URDF tree from its root: the chain of moving joints, and for every chain body
    (0 = base, j = link of moving joint j) its merged spatial inertia in its URDF frame, the
    names of the links merged into it, and (T_joint) the transform from it to the origin of
    the next moving joint."""
    children = {}
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
    bodies = [{"M": np.zeros((6, 6)), "links": [], "T_joint": None, "T_links": []}]
    chain = []
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
            if jt.type == "fixed" or jt.name in locked:
                motion = np.eye(4) if jt.type == "fixed" else _joint_motion(urdf_path, jt, float(locked[jt.name]))
                stack.append((jt.child, b, T @ origin @ motion))
                continue
            if jt.type not in MOVING:
                ctx.fail("urdf", f"{urdf_path}: joint {jt.name!r} is {jt.type}: only revolute and continuous "
                                 f"joints can be actuated (lock it under 'locked' to hold it fixed)")
            if jt.name not in actuators:
                ctx.fail("joints", f"{urdf_path}: joint {jt.name!r} ({jt.type}) moves but has no [[joints]] "
                                   f"entry and is not locked")
            if bodies[b]["T_joint"] is not None:
                ctx.fail("urdf", f"{urdf_path}: link {link_name!r} is a branch point (moving joints "
                                 f"{bodies[b]['next']!r} and {jt.name!r}): only serial chains are supported; "
                                 f"lock one branch")
            bodies[b]["T_joint"], bodies[b]["next"] = T @ origin, jt.name
            chain.append(jt)
            bodies.append({"M": np.zeros((6, 6)), "links": [], "T_joint": None, "T_links": []})
            stack.append((jt.child, len(bodies) - 1, np.eye(4)))
    if not chain:
        ctx.fail("joints", f"{urdf_path} has no moving joint to actuate")
    if tip is not None and tip_body != len(bodies) - 1:
        beyond = [jt.name for jt in chain[tip_body:]]
        ctx.fail("tip", f"joints {beyond} lie beyond the tip link {tip!r}: lock them or move the tip")
    return chain, bodies, tip_body
