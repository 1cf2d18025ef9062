"""The complete rotor-separated model as MuJoCo's MJCF, exact in MuJoCo's own terms.

Per joint j, inside the body of the link that carries it (the world for a joint on the base), at
the joint frame J_j:
  - the link j (a hinge about z: theta_j) with its subtree;
  - the slow rotor S_j (a hinge about z: phi_j) and the fast rotor F_j (a hinge about z), both
    on the parent as in the paper; the gear is a joint equality, fast = -mu_j slow (the fast
    rotor turns the other way at mu_j times the rate, as in rscasadi.dynamics.recursions);
  - the series spring and its damper: a fixed tendon of length phi_j - theta_j with stiffness k1
    and damping d (the link feels +k1 (phi - theta), the slow rotor the opposite);
  - the gear loss b dphi: the slow rotor's joint damping;
  - the link-side viscous loss link_b dtheta and the counterbalance spring cb_k (theta - theta0):
    the link hinge's damping, stiffness and springref;
  - the motor: an actuator on the fast rotor, its torque tau_j the model's motor torque (through
    the gear the slow side receives -mu_j tau_j, as in the model), ctrlrange the torque limit.
Joints of other kinds (rscasadi.model.kinds): a geared joint's rotors are bodies as an SEA's, the
slow one held to the link by a second equality (slow = theta) instead of the spring; a spring
joint is its link hinge's stiffness and springref; a direct joint's motor acts on its link hinge;
a free joint is its link hinge alone.  A prismatic joint's link is a slide along z instead of
a hinge (its ref a distance; no rotors).  In the reduced and armature files a geared joint's rotors
are welded and their spin inertia is the link hinge's armature.
Inertias are each body's own (mass, centre of mass, inertia about it, in the joint or link frame;
`inertiafromgeom` off, so geometry never changes them).  The model's frames are sites on their
links (named as the frames); the payload is a body welded to its frame's link (MuJoCo folds its
inertia into the link's, as the model does); the collision capsules ([collision] and the
payload's sphere) are geoms on their links, of contype 2 and conaffinity 1: they touch what a
user adds to the world (MuJoCo's default geoms, contype = conaffinity = 1) and never each other,
as the model's capsules are only ever checked against obstacles.  Meshes are not written: the
capsules are the geometry.
The model starts at rest: every hinge's `ref` (MuJoCo's qpos0, with its body's frame turned by
it, so that qpos stays the model's angle) is the rest pose, the links at the angle nearest 0
inside their range (`rest_pose`) and the rotors where the springs hold them statically, and the
keyframe "rest" adds the motor torques that hold it (mj_resetDataKeyframe(m, d, 0)).
A floating robot (floating = true) is one body `base` on a free joint (MuJoCo's qpos [x, y, z,
qw, qx, qy, qz], qvel [v in world axes; w in the base frame]: rscasadi.dynamics.floating.to_mujoco)
carrying the tree; the world gets a floor (a plane at z = 0) and each point contact a sphere of
FOOT_RADIUS at its frame's origin, each flat contact one at each corner of its sole (`size`), that
touch the floor and nothing else (contype and conaffinity 4 on the floor, the feet only colliding
with it); the base starts level, the lowest foot on the
floor, the links at their rest pose, standing (`floating_rest`): the keyframe's torques hold it
for an instant, but an SEA under a constant motor torque has no stiffness, so standing longer
takes a controller.
MuJoCo keeps the gear only as a constraint it solves softly: the file asks for RK4 at 1 ms and
an equality nearly hard (solimp 0.9999), under which its motion follows the complete model
(tests/test_mujoco.py). Not expressed, and refused by name: a cubic spring term (k3), Coulomb
loss on the gear (c) or the link (link_loss c; MuJoCo's frictionloss is another law).
"""
from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from rscasadi.errors import InvalidArgument
from rscasadi.files import fresh_directory, safe_name, write_text

TIMESTEP = 1e-3
FOOT_RADIUS = 0.005                         # m: the sphere of a point contact in MuJoCo
FLOOR = '<geom name="floor" type="plane" size="0 0 1" contype="4" conaffinity="4"/>'
SOLIMP = "0.9999 0.9999 0.001 0.5 2"       # the gear's equality, nearly hard
SOLREF = "0.002 1"


def _quat(R) -> str:
    """A rotation matrix as MuJoCo's quaternion (w x y z)."""
    R = np.asarray(R, float)
    w = np.sqrt(max(0.0, 1.0 + np.trace(R))) / 2
    if w > 1e-6:
        q = [w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)]
    else:                                                     # a half turn: from the largest diagonal
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = np.sqrt(max(0.0, 1.0 + R[i, i] - R[j, j] - R[k, k])) * 2
        q = [0.0] * 4
        q[0], q[1 + i] = (R[k, j] - R[j, k]) / s, s / 4
        q[1 + j], q[1 + k] = (R[j, i] + R[i, j]) / s, (R[k, i] + R[i, k]) / s
    return " ".join(repr(float(v)) for v in q)


def _rz(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _hinge_frame(pos, R, ref: float) -> str:
    """A hinge body's pos and quat for a joint whose qpos0 is `ref`: the body frame is R turned
    by ref about z, so that at qpos = q it is R Rz(q), as with ref 0 (MuJoCo turns a hinge's body
    by qpos - qpos0)."""
    return f'pos="{_numbers(pos)}" quat="{_quat(np.asarray(R, float) @ _rz(ref))}"'


def _link_frame(jt, ref: float) -> str:
    """A link body's pos and quat at qpos0 = `ref`: a hinge's (`_hinge_frame`), or a slide's,
    moved by ref along z of J (MuJoCo slides a body by qpos - qpos0)."""
    if jt.joint_motion.turns:
        return _hinge_frame(jt.origin_xyz, jt.R, ref)
    R = np.asarray(jt.R, float)
    return f'pos="{_numbers(np.asarray(jt.origin_xyz, float) + R[:, 2] * ref)}" quat="{_quat(R)}"'


REST_MARGIN = 0.05        # the rest angle keeps this fraction of its range from either end


def rest_pose(model) -> np.ndarray:
    """Each link's rest angle: 0 where it lies inside the joint's range, else the nearest angle
    inside it, REST_MARGIN of the range from its end."""
    theta = np.zeros(len(model.joints))
    for j, jt in enumerate(model.joints):
        lim = jt.limits.get("theta")
        if lim is not None and np.all(np.isfinite(lim)):
            lo, hi = float(lim[0]), float(lim[1])
            if not lo <= 0.0 <= hi:
                margin = REST_MARGIN * (hi - lo)
                theta[j] = float(np.clip(0.0, lo + margin, hi - margin))
    return theta


def rest_state(model, variant: str = "complete") -> tuple:
    """(theta, phi, tau) of the rest the export starts in: the links at `rest_pose` (the joints
    without an input where they rest), the motors where the springs hold the links statically
    (the reduced model's for "reduced"), and the motor torques that hold them still
    (dynamics.statics.rest).  "armature": no spring; the rotors welded at their zero angle, the
    motors carry the link torque through the gear (tau = -T / mu)."""
    from rscasadi.dynamics.arm import Arm
    from rscasadi.dynamics.statics import rest
    arm = Arm(model)
    if variant != "armature":
        return rest(arm, rest_pose(model), reduced=variant == "reduced")
    theta, _, _ = rest(arm, rest_pose(model), phi=np.zeros(arm.m))                 # rotors at their zero angle
    z, zm = np.zeros(arm.n), np.zeros(arm.m)
    T = np.array(arm.inverse_dynamics()(theta, zm, z, zm, z, zm)[1]).ravel()[model.actuated]
    geared = np.array([bool(model.joints[j].joint_kind.rotors) for j in model.actuated])
    return theta, theta[model.motors], np.where(geared, -T / model.column("gear_ratio")[model.actuated], T)


def floating_rest(model) -> tuple:
    """(theta, phi, tau) a floating robot's export starts in: the links at `rest_pose`; standing
    on its point contacts where it can (dynamics.stance.stand: the springs deflected, the torques
    that hold it, level at `standing_height`), else the springs relaxed and no torque."""
    from rscasadi.dynamics.floating import FloatingRobot
    from rscasadi.dynamics.stance import StandingError, stand
    theta = rest_pose(model)
    if model.contacts:
        try:
            s = stand(FloatingRobot(model), theta, np.r_[0, 0, standing_height(model, theta), 0, 0, 0, 1])
            return theta, s.q[7 + model.n:], s.tau
        except StandingError:
            pass
    return theta, theta[model.motors], np.zeros(len(model.actuated))


def standing_height(model, theta) -> float:
    """The base's height, level, at which the lowest point contact's sphere touches the floor
    (0 without contacts)."""
    from rscasadi.dynamics.floating import FloatingRobot
    if not model.contacts:
        return 0.0
    robot = FloatingRobot(model)
    q = np.r_[0, 0, 0, 0, 0, 0, 1, theta, theta[model.motors]]
    low = min(float(np.asarray(robot.frame_placement(f)(q)[1])[2, 0]) for f, _ in model.contacts)
    return FOOT_RADIUS - low


def _torque_limits(model) -> np.ndarray:
    """Each input's torque limit (the actuated joints'; N m; inf where the model file gives none)."""
    return np.array([model.joints[j].limits.get("tau", np.inf) for j in model.actuated], float)


def _numbers(v) -> str:
    return " ".join(repr(float(x)) for x in np.ravel(v))


def _inertial(body, indent: str) -> str:
    """A body's <inertial>: its mass, centre of mass and inertia about it (fullinertia)."""
    I = np.asarray(body.inertia, float)
    mass = max(float(body.mass), 1e-9)
    full = [I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]
    if float(body.mass) <= 0 or max(abs(v) for v in full) == 0:
        full = [1e-12, 1e-12, 1e-12, 0.0, 0.0, 0.0]               # a massless point (a tool frame)
    return f'{indent}<inertial pos="{_numbers(body.com)}" mass="{mass!r}" fullinertia="{_numbers(full)}"/>\n'


def _attached(model, body: int, indent: str) -> list:
    """What rides on body `body` (0: the world) besides its joint: the frames as sites, the
    collision capsules as geoms (a capsule of zero length as a sphere), the payload as a body."""
    from rscasadi.model.collision import capsules
    out = [f'{indent}<site name={quoteattr(safe_name(f.name))} pos="{_numbers(f.p)}" quat="{_quat(f.R)}" size="0.005"/>'
           for f in model.frames if f.body == body]
    for i, c in enumerate(capsules(model)):
        if c.body != body:
            continue
        shape = (f'type="sphere" pos="{_numbers(c.a)}"' if np.allclose(c.a, c.b) else
                 f'type="capsule" fromto="{_numbers(np.r_[c.a, c.b])}"')
        out.append(f'{indent}<geom name={quoteattr(safe_name(f"capsule{i}_{c.link}"))} {shape} '
                   f'size="{float(c.radius)!r}" contype="2" conaffinity="1" group="3"/>')
    soles = {frame: (lx, ly) for frame, lx, ly in model.soles}
    for frame, kind in model.contacts:                        # the feet: they touch the floor alone
        f = model.frame(frame)
        if f.body != body:
            continue
        corners = ([np.zeros(3)] if kind == "point" else       # a sole: a sphere at each corner
                   [np.array([sx * soles[frame][0] / 2, sy * soles[frame][1] / 2, 0.0]) for sx in (1, -1) for sy in (1, -1)])
        for i, corner in enumerate(corners):
            name = "contact_" + frame + (f"_{i}" if kind == "flat" else "")
            out.append(f'{indent}<geom name={quoteattr(safe_name(name))} type="sphere" pos="{_numbers(f.p + f.R @ corner)}" '
                       f'size="{FOOT_RADIUS!r}" contype="4" conaffinity="0"/>')
    held = model.payload
    if held is not None and model.frame(held.frame).body == body:
        f = model.frame(held.frame)
        out += [f'{indent}<body name="payload" pos="{_numbers(f.p)}" quat="{_quat(f.R)}">',
                _inertial(held.body, indent + "  ").rstrip("\n"), f"{indent}</body>"]
    return out


def check_exportable(model) -> None:
    """Refuse, naming the joint, what MJCF cannot hold exactly."""
    problems = [f"{jt.name}: k3 = {jt.k3:g} (a cubic spring; a tendon's is linear)" for jt in model.joints if jt.k3]
    problems += [f"{jt.name}: gear_loss c = {jt.c:g} (Coulomb loss; MuJoCo's frictionloss is another law)"
                 for jt in model.joints if jt.c]
    problems += [f"{jt.name}: link_loss c = {jt.link_c:g} (Coulomb loss; MuJoCo's frictionloss is another law)"
                 for jt in model.joints if jt.link_c]
    problems += [f"{jt.name}: gear_loss c1 = {jt.c1:g} (a loss growing with the transmitted torque; MJCF has none)"
                 for jt in model.joints if jt.c1]
    problems += [f"{jt.name}: gear_loss stribeck = {jt.stribeck:g} (static friction falling with speed; MJCF has none)"
                 for jt in model.joints if jt.stribeck]
    soles = {frame for frame, _, _ in model.soles}
    problems += [f"contact {frame}: a flat contact without its sole's size (give [[contacts]] size = [lx, ly])"
                 for frame, kind in model.contacts if kind == "flat" and frame not in soles]
    if problems:
        raise InvalidArgument(f"{model.path}: cannot be exported to MuJoCo exactly: " + "; ".join(problems))


VARIANTS = ("complete", "reduced", "armature")


def mujoco_xml(model, variant: str = "complete") -> str:
    """The MJCF text of `model` (an ArmModel): see the module's docstring.  `variant`:
    "complete", the rotor-separated model; "reduced", the DLR/Spong reduced model
    (Arm.reduced_forward_dynamics): the rotors welded to their parent links at their zero angle,
    each motor coordinate phi_j a hinge of its own on the world with the spin inertia
    B_j = Izz(S_j) + mu_j^2 Izz(F_j), the spring between it and the link, the motor on it (gear
    -mu_j); "armature", the rigid-joint model MuJoCo users write for a geared motor: no spring,
    B_j as the joint's armature, the rotors welded, the gear loss as joint damping, the motor on
    the joint (gear -mu_j)."""
    if variant not in VARIANTS:
        raise InvalidArgument(f"mujoco_xml: variant must be one of {', '.join(VARIANTS)}, got {variant!r}")
    armature, reduced = variant == "armature", variant == "reduced"
    check_exportable(model)
    if reduced:                        # the reduced model's own refusal (unbalanced rotors), by name
        from rscasadi.dynamics.arm import Arm
        Arm(model).mass_matrix(reduced=True)
    names = [safe_name(jt.name) for jt in model.joints]
    theta0, phi0, tau0 = floating_rest(model) if model.floating else rest_state(model, variant)
    g = np.asarray(model.gravity, float)
    lines = [f'<mujoco model={quoteattr(safe_name(model.name))}>',
             f'  <option timestep="{TIMESTEP!r}" integrator="RK4" gravity="{_numbers(g)}"/>',
             '  <compiler angle="radian" autolimits="true" inertiafromgeom="false"/>',
             '  <worldbody>']
    inner = "    "
    if model.floating:                 # the base: a body on a free joint, the tree inside it
        lines += ["    " + FLOOR, f'    <body name="base" pos="0 0 {standing_height(model, theta0)!r}">',
                  '      <freejoint name="base"/>', _inertial(model.base, "      ").rstrip("\n")]
        inner = "      "
    lines += _attached(model, 0, inner)

    motor_of = model.motor_of

    def joint_bodies(j: int, indent: str) -> list:
        jt, name, kind = model.joints[j], names[j], model.joints[j].joint_kind
        theta = jt.limits.get("theta")
        welded = bool(kind.rotors) and (armature or (kind.rotors == "link" and variant != "complete"))
        rigid = f' armature="{float(jt.rotor_inertia)!r}"' if welded else ""
        damping = jt.link_b + (jt.b if welded else 0.0)
        link_side = (f' damping="{float(damping)!r}"' if damping else "") + (
            f' stiffness="{float(jt.cb_k)!r}" springref="{float(jt.cb_theta0)!r}"' if jt.cb_k else "")
        out = [f'{indent}<body name="{name}_link" {_link_frame(jt, theta0[j])}>',
               _inertial(jt.link, indent + "  ").rstrip("\n"),
               f'{indent}  <joint name="{name}" type="{"hinge" if jt.joint_motion.turns else "slide"}" axis="0 0 1" '
               f'ref="{float(theta0[j])!r}"{rigid}{link_side}'
               + (f' range="{theta[0]!r} {theta[1]!r}"' if theta is not None and np.all(np.isfinite(theta)) else "")
               + "/>"] + _attached(model, j + 1, indent + "  ")
        for child in model.children(j):
            out += joint_bodies(child, indent + "  ")
        out.append(f"{indent}</body>")
        if not kind.rotors:
            return out
        turns = phi0[motor_of[j]] if kind.motor else theta0[j]           # what the rotors turn with
        for part, suffix, damping, gear in (("slow_rotor", "slow", jt.b, 1.0), ("fast_rotor", "fast", 0.0, -jt.gear_ratio)):
            ref = float(gear * turns) if variant == "complete" else 0.0
            out += [f'{indent}<body name="{name}_{suffix}" {_hinge_frame(jt.origin_xyz, jt.R, ref)}>',
                    _inertial(getattr(jt, part), indent + "  ").rstrip("\n")]
            if variant == "complete":
                out.append(f'{indent}  <joint name="{name}_{suffix}" type="hinge" axis="0 0 1" ref="{ref!r}" '
                           f'damping="{float(damping)!r}"/>')
            out.append(f"{indent}</body>")
        return out

    for root in model.children(-1):
        lines += joint_bodies(root, inner)
    if model.floating:
        lines.append("    </body>")
    if reduced:                         # each motor coordinate on its own, its spin inertia B_j
        for i, j in enumerate(model.motors):
            n, jt = names[j], model.joints[j]
            B = float(jt.rotor_inertia)
            lines += [f'    <body name="{n}_motor" {_hinge_frame(np.zeros(3), np.eye(3), phi0[i])}>',
                      f'      <inertial pos="0 0 0" mass="1.0" diaginertia="{B!r} {B!r} {B!r}"/>',
                      f'      <joint name="{n}_motor" type="hinge" axis="0 0 1" ref="{float(phi0[i])!r}" damping="{float(jt.b)!r}"/>',
                      "    </body>"]
    lines += ["  </worldbody>"]
    limits = _torque_limits(model)
    key = [f'  <keyframe>\n    <key name="rest" ctrl="{_numbers(np.clip(tau0, -limits, limits))}"/>\n  </keyframe>']
    kinds = model.kinds
    if not armature:
        equal = [f'    <joint name="{names[j]}_gear" joint1="{names[j]}_fast" joint2="{names[j]}_slow" '
                 f'polycoef="0 {-float(jt.gear_ratio)!r} 0 0 0" solimp="{SOLIMP}" solref="{SOLREF}"/>'
                 for j, jt in enumerate(model.joints) if kinds[j].rotors and not reduced]
        equal += [f'    <joint name="{names[j]}_drive" joint1="{names[j]}_slow" joint2="{names[j]}" '
                  f'polycoef="0 1 0 0 0" solimp="{SOLIMP}" solref="{SOLREF}"/>'
                  for j in range(model.n) if kinds[j].rotors == "link" and not reduced]
        lines += ["  <equality>"] + equal + ["  </equality>"] if equal else []
        motor = "motor" if reduced else "slow"              # the joint of phi_j
        springs = [f'    <fixed name="{names[j]}_spring" stiffness="{float(model.joints[j].k1)!r}" '
                   f'damping="{float(model.joints[j].d)!r}" springlength="0">\n'
                   f'      <joint joint="{names[j]}_{motor}" coef="1"/>\n      <joint joint="{names[j]}" coef="-1"/>\n'
                   f'    </fixed>' for j in model.motors]
        lines += ["  <tendon>"] + springs + ["  </tendon>"] if springs else []
    lines.append("  <actuator>")
    for j, tau in zip(model.actuated, limits):
        n, jt, kind = names[j], model.joints[j], kinds[j]
        limit = f' ctrlrange="{-float(tau)!r} {float(tau)!r}"' if np.isfinite(tau) else ""
        if not kind.rotors:                                   # direct: the torque on the joint
            on = f'"{n}" gear="1.0"'
        elif armature or (reduced and not kind.motor):        # through the gear onto the link
            on = f'"{n}" gear="{-float(jt.gear_ratio)!r}"'
        elif reduced:
            on = f'"{n}_motor" gear="{-float(jt.gear_ratio)!r}"'
        else:
            on = f'"{n}_fast" gear="1"'
        lines.append(f'    <motor name="{n}_motor" joint={on}{limit}/>')
    lines += ["  </actuator>"] + key + ["</mujoco>"]
    return "\n".join(lines) + "\n"


def gear_map(arm, m) -> np.ndarray:
    """T: the model's (theta, phi) velocities to MuJoCo's (link, slow, fast per joint, in MuJoCo's
    order; link and motor in the reduced file) for the file `mujoco_xml` wrote: MuJoCo's
    q = T (theta, phi), the fast rotor -mu times what the rotors turn with (an SEA's phi, a
    geared joint's theta)."""
    n, model = arm.n, arm.model
    T = np.zeros((m.nv, n + arm.m))
    motor_of = model.motor_of
    names = {m.joint(i).name for i in range(m.njnt)}
    for j, jt in enumerate(model.joints):
        name = safe_name(jt.name)
        T[m.joint(name).dofadr[0], j] = 1.0
        col = n + motor_of[j] if j in motor_of else j
        if name + "_slow" in names:
            T[m.joint(name + "_slow").dofadr[0], col] = 1.0
            T[m.joint(name + "_fast").dofadr[0], col] = -float(jt.gear_ratio)
        elif name + "_motor" in names:
            T[m.joint(name + "_motor").dofadr[0], col] = 1.0
    return T


def mujoco_state(robot, m, q, v) -> tuple:
    """MuJoCo's qpos and qvel of a floating robot's q and v (rscasadi.dynamics.floating) in the
    file `mujoco_xml` wrote: the free joint's by `to_mujoco`, the hinges' through `gear_map`."""
    from rscasadi.dynamics.floating import to_mujoco
    q, v = np.asarray(q, float), np.asarray(v, float)
    T = gear_map(robot, m)
    qpos, qvel = np.zeros(m.nq), T @ v[6:]
    qpos[:7], qvel[:6] = to_mujoco(q[:7], v[:6])
    qpos[7:] = (T @ q[7:])[6:]                     # each hinge's qpos follows its dof (after the free joint's)
    return qpos, qvel


def state_from_mujoco(robot, m, qpos, qvel) -> tuple:
    """The inverse of `mujoco_state`: q and v from MuJoCo's qpos and qvel (the hinges' by the
    least-squares inverse of `gear_map`, exact while the gear's equality holds)."""
    from rscasadi.dynamics.floating import from_mujoco
    back = np.linalg.pinv(gear_map(robot, m))
    base_q, base_v = from_mujoco(qpos[:7], qvel[:6])
    return np.r_[base_q, back @ np.r_[np.zeros(6), qpos[7:]]], np.r_[base_v, back @ qvel]


def with_world(xml: str, world: str) -> str:
    """The MJCF text `xml` with `world` (MJCF elements: geoms, bodies) added to its worldbody."""
    return xml.replace("  <worldbody>\n", "  <worldbody>\n" + world.rstrip("\n") + "\n", 1)


def contact_wrench(m, d, frame: str):
    """[force; moment] (world axes, moment about the site `frame`'s origin) of every contact on
    the arm's geoms (group 3), as the world exerts it on the arm."""
    import mujoco
    origin, total, f6 = d.site_xpos[m.site(frame).id], np.zeros(6), np.zeros(6)
    for i in range(d.ncon):
        c = d.contact[i]
        mine = [g for g in (c.geom1, c.geom2) if m.geom_group[g] == 3]
        if len(mine) != 1:
            continue
        mujoco.mj_contactForce(m, d, i, f6)
        force = c.frame.reshape(3, 3).T @ f6[:3]                     # on geom2, from geom1
        force = force if mine[0] == c.geom2 else -force
        total += np.r_[force, np.cross(c.pos - origin, force)]
    return total


def mujoco_plant(arm, dt: float, world: str = "", frame: str | None = None, push=None):
    """(x, tau, t) -> (x after dt, wrench): the arm exported (`mujoco_xml`) and simulated by
    MuJoCo at its own timestep, for rscasadi.sim.loop.run_loop (x = theta, phi, dtheta, dphi).
    `world`: MJCF elements added to the worldbody (a table: its geoms collide with the arm's
    capsules); `frame`: the wrench the contacts exert on the arm at that frame after each sample
    (6 x 1, `contact_wrench`), else None; `push(t)`: a wrench [force; moment] (world axes, at
    `frame`'s origin) applied to the frame's body through every MuJoCo step of the sample that
    starts at t (mj_applyFT), and added to the wrench returned."""
    import mujoco
    m = mujoco.MjModel.from_xml_string(with_world(mujoco_xml(arm.model), world))
    d = mujoco.MjData(m)
    T = gear_map(arm, m)
    back, steps, n = np.linalg.pinv(T), int(round(dt / m.opt.timestep)), arm.n + arm.m
    if steps < 1 or abs(steps * m.opt.timestep - dt) > 1e-12:
        raise InvalidArgument(f"mujoco_plant: dt = {dt!r} s must be a whole number of MuJoCo's {m.opt.timestep!r} s steps")
    if frame is not None:
        m.site(safe_name(frame))                                     # a KeyError now, not mid-run
    if push is not None and frame is None:
        raise InvalidArgument("mujoco_plant: push needs the frame it acts at")

    def plant(x, tau, t):
        d.qpos[:], d.qvel[:], d.ctrl[:] = T @ x[:n], T @ x[n:], tau
        applied = np.zeros(6) if push is None else np.asarray(push(t), float)
        for _ in range(steps):
            d.qfrc_applied[:] = 0.0
            if applied.any():
                mujoco.mj_kinematics(m, d)                           # where the frame is now
                site = m.site(safe_name(frame))
                mujoco.mj_applyFT(m, d, applied[:3], applied[3:], d.site_xpos[site.id], int(site.bodyid[0]),
                                  d.qfrc_applied)
            mujoco.mj_step(m, d)
        d.qfrc_applied[:] = 0.0
        wrench = None
        if frame is not None:
            mujoco.mj_forward(m, d)                                  # the contacts at the new state
            wrench = (contact_wrench(m, d, safe_name(frame)) + applied)[:, None]
        return np.r_[back @ d.qpos, back @ d.qvel], wrench
    return plant


def export_mujoco(model_file, out, log=print, variant: str = "complete") -> Path:
    """`rscasadi export mujoco MODEL --out DIR [--reduced | --armature]`: DIR/model.xml (whole or
    not at all) of the `variant` (mujoco_xml)."""
    from rscasadi.dynamics.arm import load
    arm = load(model_file)
    text = mujoco_xml(arm.model, variant)
    if arm.model.floating:
        with fresh_directory(Path(out)) as tmp:
            write_text(tmp / "model.xml", text)
        log(f"wrote {Path(out) / 'model.xml'}: {arm.n} joints on a free-flying base, a floor, "
            f"{len(arm.model.contacts)} feet (RK4 at {TIMESTEP * 1e3:g} ms); starts standing where it can "
            "(keyframe 'rest': the torques that hold the rest pose)")
        return Path(out) / "model.xml"
    with fresh_directory(Path(out)) as tmp:
        write_text(tmp / "model.xml", text)
    what = {"armature": "rigid joints with the rotors as armature (for comparison)",
            "reduced": "the DLR/Spong reduced model: rotors welded, each motor coordinate a joint of its own",
            "complete": "each a link, a slow and a fast rotor, the gear an equality, the spring a tendon"
            if arm.model.all_sea else "the rotors as bodies, each gear an equality, each SEA's spring a tendon"}[variant]
    theta, _, tau = rest_state(arm.model, variant)
    weak = [f"{arm.model.joints[j].name} ({abs(t):.3g} N m, limit {lim:g})"
            for j, t, lim in zip(arm.model.actuated, tau, _torque_limits(arm.model))
            if abs(t) > lim]
    log(f"wrote {Path(out) / 'model.xml'}: {arm.n} joints, {what} (RK4 at {TIMESTEP * 1e3:g} ms); starts at rest "
        f"(keyframe 'rest': links at {_numbers(np.round(theta, 4))} rad, the springs deflected)")
    if weak:
        log(f"note: the motors cannot hold the rest pose at {', '.join(weak)}: the keyframe's torques are the limits, "
            "and the arm moves from it")
    return Path(out) / "model.xml"


def compare_variants(arm, trajectory) -> dict:
    """The feedforward torques of `trajectory` (rscasadi.sim.simulation.feedforward), held over
    each MuJoCo step, open loop, applied to each export of `arm` and to rscasadi's CVODES replay:
    the largest link-angle difference (rad) of each variant's MuJoCo motion from the replay
    ("reduced": None for an arm with unbalanced rotors, which that model cannot hold)."""
    import mujoco
    from rscasadi.sim.simulation import feedforward, simulate
    n = arm.n
    t = np.arange(int(round(trajectory.duration / TIMESTEP)) + 1) * TIMESTEP
    ff = feedforward(arm, trajectory, t)
    ours = simulate(arm, ff["x0"], t, ff["tau"], interpolation="constant")["theta"]
    balanced = all(getattr(jt, part).balanced for jt in arm.model.joints for part in ("slow_rotor", "fast_rotor"))
    runs = {}
    for variant in VARIANTS:
        if variant == "reduced" and not balanced:
            continue
        m = mujoco.MjModel.from_xml_string(mujoco_xml(arm.model, variant))
        d = mujoco.MjData(m)
        T = gear_map(arm, m)                           # armature: the links alone (no motor coordinates)
        q = n + arm.m
        d.qpos[:], d.qvel[:] = T @ ff["x0"][:q], T @ ff["x0"][q:]
        back, worst = np.linalg.pinv(T), 0.0
        for k in range(len(t) - 1):
            d.ctrl[:] = ff["tau"][:, k]
            mujoco.mj_step(m, d)
            worst = max(worst, float(np.max(np.abs((back @ d.qpos)[:n] - ours[:, k + 1]))))
        runs[variant] = worst
    return {"seconds": float(t[-1]), "timestep": TIMESTEP, "complete": runs["complete"],
            "reduced": runs.get("reduced"), "armature": runs["armature"]}
