"""Physical parameters as numbers or as symbolic inputs.

The parameter vector p of an arm, in this order:

- for each joint j (base to tip), for each of its bodies (link, slow_rotor, fast_rotor), the ten
  inertial parameters that the dynamics is linear in: mass m, first moment m c (`mx, my, mz`),
  and the inertia about the body-frame origin (`Ixx, Iyy, Izz, Ixy, Ixz, Iyz`), all in the
  body's own frame (docs/user-guide/model.md section 2);
- then its actuator: `sea.k1, sea.k3, sea.d, gear_loss.b, gear_loss.c`;
- if the model holds a payload, its ten inertial parameters in its frame (`payload.mass`,
  `payload.mx`, ..., `payload.Iyz`);
- last, `gravity.x, gravity.y, gravity.z`.

Names are dotted: "elbow_pitch.link.mass", "elbow_pitch.fast_rotor.Izz", "elbow_pitch.sea.k1".
Everything before gravity is p_lin: inverse dynamics is linear in it (with eps, the gear ratios
and gravity fixed).  Gear ratios and eps are not in p: identification keeps them fixed.  A
design study or a sweep may also free a gear ratio ("elbow_pitch.gear_ratio", `designable`):
the equations are exact for any value of it (it scales the fast rotor's spin, its reflected
inertia and the motor torque).

`Physics` holds what the recursions read (spatial inertias, actuator columns, gravity), either
as numbers from the model file or as CasADi expressions of p.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

# Which of an arm's parameters a generated library, an optimal-control NLP or an MPC takes as
# inputs (one option, one type, everywhere): "none", the model's numbers folded into the code;
# "all", every parameter of p; "family", the parameters not zero in the model (the zeros
# folded: every arm with the same zeros, at about the constant code's speed).  An Arm's
# Functions take that p when asked (`parametric=True`): the Arm's `free` parameters.
PARAMETRIC = ("none", "all", "family")
# an optimal-control problem and an MPC take "none" or "family": "all" would make the model's
# zeros variables of the NLP and inputs of the controller, for nothing a family cannot do
PROBLEM_PARAMETRIC = ("none", "family")

from rscasadi.spatial import Xup, spatial_inertia
from rscasadi.model.modelfile import BODIES, ArmModel, Body
from rscasadi.errors import InvalidArgument

INERTIAL = ("mass", "mx", "my", "mz", "Ixx", "Iyy", "Izz", "Ixy", "Ixz", "Iyz")
ACTUATOR = ("sea.k1", "sea.k3", "sea.d", "gear_loss.b", "gear_loss.c", "link_loss.b", "link_loss.c",
            "counterbalance.k")
ACTUATOR_ATTR = ("k1", "k3", "d", "b", "c", "link_b", "link_c", "cb_k")
CONSTANTS = ("eps", "gear_ratio", "cb_theta0", "c1", "stribeck", "v_stribeck")   # per-joint numbers the dynamics read that p does not hold
GRAVITY = ("gravity.x", "gravity.y", "gravity.z")
PER_JOINT = len(BODIES) * len(INERTIAL) + len(ACTUATOR)


def body_parameters(body: Body) -> np.ndarray:
    """m, m c, I_O (about the frame origin): the ten parameters of eq. (11)."""
    I, h = body.inertia_origin, body.mass * body.com
    return np.r_[body.mass, h, I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]


def body_from_parameters(v) -> Body:
    """The inverse of body_parameters: mass, centre of mass and inertia about it."""
    m, h = float(v[0]), np.asarray(v[1:4], float)
    I_O = np.array([[v[4], v[7], v[8]], [v[7], v[5], v[9]], [v[8], v[9], v[6]]], float)
    c = h / m if m != 0.0 else np.zeros(3)                  # a massless body (an empty payload) has no centre
    return Body(m, c, I_O - m * (c @ c * np.eye(3) - np.outer(c, c)))


def spatial_from_parameters(v):
    """Eq. (11) from the ten parameters: [[I_O, (m c)~], [-(m c)~, m 1]] (numbers or SX)."""
    m, hx, hy, hz, ixx, iyy, izz, ixy, ixz, iyz = (v[i] for i in range(10))
    H = ca.vertcat(ca.horzcat(0, -hz, hy), ca.horzcat(hz, 0, -hx), ca.horzcat(-hy, hx, 0))
    I_O = ca.vertcat(ca.horzcat(ixx, ixy, ixz), ca.horzcat(ixy, iyy, iyz), ca.horzcat(ixz, iyz, izz))
    return ca.vertcat(ca.horzcat(I_O, H), ca.horzcat(-H, m * ca.SX.eye(3)))


def names(model: ArmModel) -> list[str]:
    """The names of the parameter vector p, in its order (docs/user-guide/model.md section 6)."""
    out = []
    for jt in model.joints:
        out += [f"{jt.name}.{body}.{q}" for body in BODIES for q in INERTIAL]
        out += [f"{jt.name}.{a}" for a in ACTUATOR]
    if model.payload is not None:
        out += [f"payload.{q}" for q in INERTIAL]
    return out + list(GRAVITY)


def nominal(model: ArmModel) -> np.ndarray:
    """The model's values of the parameter vector p."""
    out: list = []
    for jt in model.joints:
        out += [body_parameters(getattr(jt, body)) for body in BODIES]
        out.append([getattr(jt, a) for a in ACTUATOR_ATTR])
    if model.payload is not None:
        out.append(body_parameters(model.payload.body))
    return np.concatenate(out + [model.gravity])


def payload_slice(model: ArmModel) -> slice:
    """Where the payload's ten parameters are in p (an empty slice without a payload)."""
    start = model.n * PER_JOINT
    return slice(start, start + (10 if model.payload is not None else 0))


def _with_payload(model: ArmModel, inertias: list, M_payload):
    """The link that holds the payload gets its spatial inertia, moved from its frame to the link's."""
    if model.payload is None:
        return inertias
    frame = model.frame(model.payload.frame)
    X = Xup(ca.DM(frame.R), frame.p)
    link = inertias[frame.body - 1]
    M = X.T @ M_payload @ X
    link["link"] = (ca.DM(link["link"]) + M) if isinstance(M, ca.DM) else link["link"] + M
    if isinstance(link["link"], ca.DM):
        link["link"] = np.array(link["link"])
    return inertias


def designable(model: ArmModel) -> list[str]:
    """Names a design study or a sweep may free: p's, and each joint's gear ratio."""
    return names(model) + [f"{jt.name}.gear_ratio" for jt in model.joints]


def _gear_joint(model: ArmModel, name: str):
    """The joint index of a gear-ratio name, or None."""
    for j, jt in enumerate(model.joints):
        if name == f"{jt.name}.gear_ratio":
            return j
    return None


def gear_ratios(model: ArmModel, free: list | None = None, p=None):
    """The gear-ratio column: the model file's numbers, with the ones named in `free` the
    matching entries of p."""
    mu = [float(v) for v in model.column("gear_ratio")]
    if not free or not any(_gear_joint(model, name) is not None for name in free):
        return ca.DM(mu)
    S = ca.MX if isinstance(p, ca.MX) else ca.SX
    entries = [S(v) for v in mu]
    for k, name in enumerate(free):
        j = _gear_joint(model, name)
        if j is not None:
            entries[j] = p[k]
    return ca.vertcat(*entries)


def geared_limits(limits: dict, mu_old: float, mu_new: float) -> dict:
    """A joint's limits behind another gear ratio, the same motor: its speed limit mu dphi is
    kept, so the slow-side limit dphi scales by mu_old / mu_new (tau, the motor torque, and psi
    stay)."""
    if mu_new == mu_old or "dphi" not in limits:
        return limits
    return {**limits, "dphi": limits["dphi"] * mu_old / mu_new}


def value(model: ArmModel, name: str) -> float:
    """The model file's value of a designable parameter."""
    j = _gear_joint(model, name)
    return float(model.joints[j].gear_ratio) if j is not None else float(nominal(model)[names(model).index(name)])


def n_linear(model: ArmModel) -> int:
    """Length of p_lin, the leading part of p that inverse dynamics is linear in."""
    return payload_slice(model).stop


@dataclass
class Physics:
    """What the recursions read: per joint the spatial inertias {link, slow_rotor, fast_rotor}
    (6x6), the actuator columns k1, k3, d, b, c, link_b, link_c, cb_k (n x 1), the constants eps,
    gear_ratio, cb_theta0 and c1, and
    gravity.  `symbolic` says whether they are expressions of p (then every rotor is written in
    its spinning frame, exact for any p, except the rotors (j, part) in `balanced`, balanced for
    every p) or the model file's numbers."""
    inertias: list
    columns: dict
    gravity: object
    symbolic: bool
    balanced: frozenset = frozenset()

    @staticmethod
    def constant(model: ArmModel) -> "Physics":
        cols = {a: ca.DM(model.column(a)) for a in ACTUATOR_ATTR + CONSTANTS}
        inertias = [{b: spatial_inertia(getattr(jt, b)) for b in BODIES} for jt in model.joints]
        held = ca.DM(spatial_inertia(model.payload.body)) if model.payload is not None else None
        return Physics(_with_payload(model, inertias, held), cols, np.asarray(model.gravity, float), False)

    @staticmethod
    def of(model: ArmModel, p) -> "Physics":
        """Physics as expressions of p (an SX or MX column of len(names(model)))."""
        n, inertias, act = model.n, [], []
        for j in range(n):
            base = j * PER_JOINT
            inertias.append({b: spatial_from_parameters(p[base + 10 * i: base + 10 * (i + 1)])
                             for i, b in enumerate(BODIES)})
            act.append(p[base + 30: base + PER_JOINT])
        cols = {a: ca.vertcat(*[act[j][i] for j in range(n)]) for i, a in enumerate(ACTUATOR_ATTR)}
        cols.update({a: ca.DM(model.column(a)) for a in CONSTANTS})
        held = payload_slice(model)
        inertias = _with_payload(model, inertias, spatial_from_parameters(p[held.start:held.stop])
                                 if model.payload is not None else None)
        return Physics(inertias, cols, p[held.stop: held.stop + 3], True)

    def rotor_inertia(self, j: int):
        """B_j = Izz_O(S_j) + mu_j^2 Izz_O(F_j)."""
        M = self.inertias[j]
        return M["slow_rotor"][2, 2] + self.columns["gear_ratio"][j] ** 2 * M["fast_rotor"][2, 2]

    @staticmethod
    def partial(model: ArmModel, free: list, p, tie_balanced: bool = False) -> "Physics":
        """Physics with only the parameters named in `free` symbolic (p, one entry each) and the
        rest the model file's numbers.  When only actuator constants (sea.*, gear_loss.*) or
        gravity are free, the inertias stay numbers and the rotors stay in the joint frame, so
        the expressions are as compact as the constant version's.  tie_balanced: a rotor balanced
        in the model whose Iyy is not free takes Iyy = Ixx (tied_balanced), so it stays balanced
        for every p and is written in the joint frame."""
        all_names, values = names(model), nominal(model)
        idx = {k: all_names.index(name) for k, name in enumerate(free) if _gear_joint(model, name) is None}
        S = ca.MX if isinstance(p, ca.MX) else ca.SX
        n_lin = n_linear(model)
        cheap = all(i >= n_lin or (i < model.n * PER_JOINT and i % PER_JOINT >= len(BODIES) * len(INERTIAL))
                    for i in idx.values())
        if not cheap:
            entries = [S(v) for v in values]
            for k, i in idx.items():
                entries[i] = p[k]
            tied = tied_balanced(model, free) if tie_balanced else {}
            for iyy, ixx in tied.items():
                entries[all_names.index(iyy)] = entries[all_names.index(ixx)]
            phys = Physics.of(model, ca.vertcat(*entries))
            phys.balanced = frozenset(tuple(name.rsplit(".", 2)[:2]) for name in tied)
        else:
            phys = Physics.constant(model)
            for k, i in idx.items():
                if i >= n_lin:
                    g = [S(float(v)) for v in np.array(phys.gravity).ravel()] if not isinstance(
                        phys.gravity, (ca.SX, ca.MX)) else ca.vertsplit(phys.gravity)
                    g[i - n_lin] = p[k]
                    phys.gravity = ca.vertcat(*g)
                else:
                    j, a = divmod(i, PER_JOINT)
                    attr = ACTUATOR_ATTR[a - len(BODIES) * len(INERTIAL)]
                    col = [S(float(v)) for v in np.array(phys.columns[attr]).ravel()] if isinstance(
                        phys.columns[attr], ca.DM) else ca.vertsplit(phys.columns[attr])
                    col[j] = p[k]
                    phys.columns[attr] = ca.vertcat(*col)
        phys.columns["gear_ratio"] = gear_ratios(model, free, p)     # the file's, or free ones
        return phys


def tied_balanced(model: ArmModel, free: list) -> dict:
    """{Iyy name: Ixx name} of the rotors balanced in the model (Ixx = Iyy about the joint axis,
    centre on it, no products) whose Iyy, mx, my and products are not in `free`: tied, they stay
    balanced for every value of the free parameters."""
    out, freed = {}, set(free)
    for jt in model.joints:
        for part in ("slow_rotor", "fast_rotor"):
            key = f"{jt.name}.{part}."
            if getattr(jt, part).balanced and not freed & {key + a for a in ("Iyy", "mx", "my", "Ixy", "Ixz", "Iyz")}:
                out[key + "Iyy"] = key + "Ixx"
    return out


def family(model: ArmModel) -> tuple[list, dict]:
    """The parameters that define an arm of this model's family, and the tied ones: p without the
    parameters that are zero in the model (folded: balanced rotors' centres, products of inertia,
    k3, gravity off z) and without the Iyy of its balanced rotors (tied to Ixx: such a rotor stays
    balanced and is written in the joint frame).  Arm(model, free, tie_balanced=True) takes them."""
    nonzero = [k for k, v in zip(names(model), nominal(model)) if v != 0]
    tied = tied_balanced(model, [k for k in nonzero if not k.endswith(".Iyy")])
    return [k for k in nonzero if k not in tied], tied


def check_names(model: ArmModel, wanted, where: str) -> list:
    """The names in `wanted`, each a designable name of the model, or an error naming it."""
    known = designable(model)
    for name in wanted:
        if name not in known:
            close = [k for k in known if k.split(".")[-1] == str(name).split(".")[-1]][:4]
            raise InvalidArgument(f"{where}: '{name}' is not a parameter of {model.path}"
                             + (f" (e.g. {', '.join(close)})" if close else ""))
    return list(wanted)


def with_values(model: ArmModel, values: dict) -> ArmModel:
    """The same arm with the named parameters set (names as in `designable(model)`)."""
    import dataclasses
    if not values:
        return model
    p = nominal(model)
    all_names, gears = names(model), {}
    for name, v in values.items():
        j = _gear_joint(model, name)
        if j is not None:
            gears[j] = float(v)
        else:
            p[all_names.index(name)] = float(v)
    joints = []
    for j, jt in enumerate(model.joints):
        base = j * PER_JOINT
        bodies = {b: body_from_parameters(p[base + 10 * i: base + 10 * (i + 1)]) for i, b in enumerate(BODIES)}
        act = dict(zip(ACTUATOR_ATTR, p[base + 30: base + PER_JOINT]))
        changed = {b: bodies[b] for b in BODIES
                   if any(f"{jt.name}.{b}.{q}" in values for q in INERTIAL)}
        mu = gears.get(j, jt.gear_ratio)
        joints.append(dataclasses.replace(jt, **changed, **{a: float(v) for a, v in act.items()},
                                          gear_ratio=mu, limits=geared_limits(jt.limits, jt.gear_ratio, mu)))
    held = payload_slice(model)
    payload = model.payload
    if payload is not None and any(name.startswith("payload.") for name in values):
        payload = dataclasses.replace(payload, body=body_from_parameters(p[held]))
    return dataclasses.replace(model, joints=tuple(joints), payload=payload, gravity=p[held.stop:].copy())
