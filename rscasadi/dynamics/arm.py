"""The arm object: a model file's constants and its dynamics as named casadi.Functions."""
from __future__ import annotations

import hashlib
import pickle
import threading
from collections import OrderedDict

import casadi as ca
import numpy as np

from rscasadi.dynamics import kinematics, recursions as rec
from rscasadi.model.checks import identifier
from rscasadi.model.kinds import require_sea
from rscasadi.model.modelfile import ArmModel, read
from rscasadi.model.parameters import (Physics, family as parameter_family, gear_ratios, names as parameter_names,
                                       nominal as parameter_nominal)
from rscasadi.errors import InvalidArgument

STATE = ["theta", "phi", "dtheta", "dphi"]
ABS_SMOOTH = 1e-3    # N m: |T| in the load-dependent gear loss is sqrt(T^2 + ABS_SMOOTH^2) - ABS_SMOOTH
SHARED_ARMS = 8      # the arms (model contents, parameter choice) whose Functions this process keeps
_SHARED: OrderedDict = OrderedDict()
_SHARED_LOCK = threading.Lock()


def _shared_functions(model: ArmModel, free, tie_balanced: bool) -> dict:
    """The Functions built so far for arms of this model (by content: its pickle's digest) and
    choice of parameters, shared by every Arm of them in this process: an OCP's refinement rounds,
    guesses and replays build each once (symbolic builds of 0.05-0.3 s each on 7 joints).  The
    SHARED_ARMS most recently used are kept."""
    key = (hashlib.sha256(pickle.dumps(model)).hexdigest(), None if free is None else tuple(free), tie_balanced)
    with _SHARED_LOCK:
        if key in _SHARED:
            _SHARED.move_to_end(key)
        else:
            _SHARED[key] = {}
            while len(_SHARED) > SHARED_ARMS:
                _SHARED.popitem(last=False)
        return _SHARED[key]


class Arm:
    """An n-joint robot of SEA joints and joints of other kinds (rscasadi.model.kinds), a chain or
    a tree. Every method returns a casadi.Function whose inputs and outputs are columns named as
    in docs/user-guide/model.md section 3: theta, dtheta, ddtheta (n: every joint), phi, dphi,
    ddphi (m: the joints with a motor coordinate, `model.motors`), tau (u: the actuated joints,
    `model.actuated`); `coordinates` names the entries of q = (theta, phi).  For an arm of SEAs,
    m = u = n.

    `parametric=True` gives the twin with one more input, p (docs/user-guide/model.md, "Parameters"):
    the same equations with every physical parameter symbolic, equal to the constant version
    at p = arm.parameters()[1].  `Arm(model, free=[names])` makes p only those parameters (in
    that order), the others staying the model file's numbers: compact expressions for design
    studies that free a few constants (Physics.partial); `tie_balanced=True` keeps the model's
    balanced rotors balanced (Iyy = Ixx) and in the joint frame."""

    def __init__(self, model: ArmModel, free: list | None = None, tie_balanced: bool = False):
        self.model = model
        self.n = model.n
        self.m = len(model.motors)               # motor coordinates: phi, dphi, ddphi
        self.u = len(model.actuated)             # torque inputs: tau
        self.free = None if free is None else list(free)
        self.tie_balanced = tie_balanced          # Physics.partial: balanced rotors stay balanced
        self._functions = _shared_functions(model, free, tie_balanced)
        self.physics = Physics.constant(model)

    @staticmethod
    def family(model: ArmModel) -> "Arm":
        """The arm with p made of the parameters that are not zero in its model file
        (model.parameters.family): a zero (a balanced rotor's centre, a product of inertia, k3,
        gravity along x on a level base) is part of the family's structure, folded into the C
        like a constant arm's numbers; a balanced rotor stays one (Iyy = Ixx, in the joint frame)."""
        return Arm(model, free=parameter_family(model)[0], tie_balanced=True)

    def _physics_of(self, p) -> Physics:
        return (Physics.of(self.model, p) if self.free is None
                else Physics.partial(self.model, self.free, p, self.tie_balanced))

    @property
    def n_p(self) -> int:
        """Length of the parametric twins' input p."""
        return len(parameter_names(self.model)) if self.free is None else len(self.free)

    @property
    def coordinates(self) -> list:
        """The names of q = (theta, phi): `<joint>` for every joint, then `<joint>.motor` for each
        joint with a motor coordinate (velocities and accelerations follow the same order)."""
        return self.model.coordinates

    @property
    def inputs(self) -> list:
        """The names of tau's entries: the actuated joints'."""
        return [self.model.joints[j].name for j in self.model.actuated]

    @property
    def nq(self) -> int:
        """The number of coordinates q = (theta, phi): n + m."""
        return self.n + self.m

    def split_state(self, x) -> list:
        """x = (theta, phi, dtheta, dphi) (2 nq entries) as its four parts."""
        n, q = self.n, self.nq
        return ca.vertsplit(x, [0, n, q, q + n, 2 * q])

    def _size(self, name: str) -> int:
        """The length of a Function input or output named `name`."""
        return {"phi": self.m, "dphi": self.m, "ddphi": self.m, "tau": self.u}.get(name, self.n)

    def _at_motors(self, v):
        """The entries of an n-vector at the joints with a motor coordinate (v itself when all have one)."""
        return v if self.m == self.n else v[self.model.motors]

    def __repr__(self):
        return f"Arm({self.model.name!r}, n={self.n}, file={self.model.path!r})"

    def parameters(self) -> tuple[list, np.ndarray]:
        """The ordered parameter names and their nominal values (the model file's numbers)."""
        return parameter_names(self.model), parameter_nominal(self.model)

    # -- actuator laws (docs/user-guide/model.md section 2) ---------------------------------------------
    def sea_torque(self, theta, phi, dtheta, dphi, phys=None):
        """T = T_K(psi) + T_B(dpsi) = k1 psi + k3 psi^3 + d dpsi, psi = phi - theta, per motor
        (theta, dtheta: every joint's; phi, dphi: the motors')."""
        c, sel = (phys or self.physics).columns, self._at_motors
        psi, dpsi = phi - sel(theta), dphi - sel(dtheta)
        return sel(c["k1"]) * psi + sel(c["k3"]) * psi ** 3 + sel(c["d"]) * dpsi

    def gear_loss(self, dphi, phys=None, T=0.0, joints=None):
        """T_B2 = b dphi + (c + c1 |T| + s exp(-(dphi / v_s)^2)) tanh(dphi / eps): the harmonic
        drive's loss grows with the torque T it transmits (the SEA's; |T| smoothed as
        sqrt(T^2 + ABS_SMOOTH^2) - ABS_SMOOTH) and, by s (stribeck), towards rest (Stribeck).
        `joints`: whose gears (default: the motors', dphi their slow sides' speeds)."""
        c = (phys or self.physics).columns
        sel = self._at_motors if joints is None else (lambda v: v[joints])
        load = ca.sqrt(T * T + ABS_SMOOTH ** 2) - ABS_SMOOTH
        static = sel(c["stribeck"]) * ca.exp(-(dphi / sel(c["v_stribeck"])) ** 2)
        return sel(c["b"]) * dphi + (sel(c["c"]) + sel(c["c1"]) * load + static) * ca.tanh(dphi / sel(c["eps"]))

    def link_loss(self, theta, dtheta, phys=None):
        """T_L = link_b dtheta + link_c tanh(dtheta / eps) + cb_k (theta - cb_theta0): what the link
        loses to its bearings and its counterbalance spring, beside the SEA's torque."""
        c = (phys or self.physics).columns
        return c["link_b"] * dtheta + c["link_c"] * ca.tanh(dtheta / c["eps"]) + c["cb_k"] * (theta - c["cb_theta0"])

    def _phi_force(self, phys, x, tau):
        """Q_phi = -T - T_B2 - mu tau per motor (docs/user-guide/model.md section 3)."""
        T = self.sea_torque(*x, phys=phys)
        return -T - self.gear_loss(x[3], phys, T) - self._at_motors(phys.columns["gear_ratio"]) * self._motor_tau(tau)

    def _motor_tau(self, tau):
        """The entries of tau that drive the motors (all of tau when every joint is an SEA)."""
        if self.u == self.m:
            return tau
        at = self.model.input_of
        return tau[[at[j] for j in self.model.motors]]

    def _theta_force(self, phys, x, tau):
        """Q_theta: per joint the generalised force on theta beside the inertial one: the SEA's
        spring (sea), -mu tau - T_B2(dtheta) through a rigid gear (geared), tau (direct), less the
        link side's loss and spring T_L (every kind)."""
        theta, phi, dtheta, dphi = x
        Q = -self.link_loss(theta, dtheta, phys)
        if self.m:
            T = self.sea_torque(*x, phys=phys)
            Q = Q + (T if self.m == self.n else ca.sparsify(ca.DM(_scatter(self.model.motors, self.n))) @ T)
        kinds, mu, at = self.model.kinds, phys.columns["gear_ratio"], self.model.input_of
        geared = [j for j, k in enumerate(kinds) if k.rotors == "link"]
        direct = [j for j, k in enumerate(kinds) if k.actuated and not k.rotors]
        if geared:
            g = self.gear_loss(dtheta[geared], phys, 0.0, geared)
            drive = -mu[geared] * tau[[at[j] for j in geared]] - g
            Q = Q + ca.sparsify(ca.DM(_scatter(geared, self.n))) @ drive
        if direct:
            Q = Q + ca.sparsify(ca.DM(_scatter(direct, self.n))) @ tau[[at[j] for j in direct]]
        return Q

    # -- plumbing ---------------------------------------------------------------------------
    def _function(self, name, ins, outs, build, parametric=False, key=None):
        """The Function `name` built once: build(phys, *inputs); the parametric twin adds p.
        Inputs named f_* are wrenches (6 x 1), the others columns (`_size`)."""
        key = (name, parametric) if key is None else (key, parametric)
        if key not in self._functions:
            args = [ca.SX.sym(i, 6) if i.startswith("f_") else ca.SX.sym(i, self._size(i)) for i in ins]
            if parametric:
                p = ca.SX.sym("p", self.n_p)
                self._functions[key] = ca.Function(name, args + [p], build(self._physics_of(p), *args),
                                                   ins + ["p"], outs)
            else:
                self._functions[key] = ca.Function(name, args, build(self.physics, *args), ins, outs)
        return self._functions[key]

    def _segments(self, reduced, phys):
        self._fixed_base()
        if reduced:
            unbalanced = [f"joint {i + 1} ({jt.name!r}) {part}" for i, jt in enumerate(self.model.joints)
                          for part in ("slow_rotor", "fast_rotor") if not getattr(jt, part).balanced]
            if unbalanced:
                raise InvalidArgument(f"{self.model.path}: the DLR/Spong reduced model assumes balanced rotors "
                                 f"(com on the axis, ixx = iyy, no products of inertia); unbalanced: "
                                 + ", ".join(unbalanced))
        return rec.segments(self.model, phys, reduced)

    def _fixed_base(self) -> None:
        """Refuse a floating model: its dynamics need the base's coordinates (FloatingRobot)."""
        if self.model.floating:
            raise InvalidArgument(f"{self.model.path}: the base floats (floating = true): its dynamics, frames and "
                                  "contacts are rscasadi.FloatingRobot's (rscasadi.load_robot); this capability "
                                  "takes robots on a fixed base")

    def _kin(self, reduced, phys, x):
        segs = self._segments(reduced, phys)
        return segs, rec.kinematics(segs, *x)

    def _inverse(self, reduced, parametric=False, external=()):
        frames, wrench_names = self._external(external)

        def build(phys, theta, phi, dtheta, dphi, ddtheta, ddphi, *f):
            x = (theta, phi, dtheta, dphi)
            segs, kin = self._kin(reduced, phys, x)
            f_ext = kinematics.link_wrenches(self.model, frames, theta, f) if f else None
            T, Qi_phi = rec.inverse_dynamics(segs, kin, ddtheta, ddphi, phys.gravity, f_ext)  # eq. (26)
            T = T + self.link_loss(theta, dtheta, phys)                    # the spring also carries T_L
            return [self._input_torques(phys, x, T, Qi_phi), T]
        name = ("reduced_inverse_dynamics" if reduced else "inverse_dynamics") + ("_external" if external else "")
        return self._function(name, STATE + ["ddtheta", "ddphi"] + wrench_names, ["tau", "T"], build, parametric,
                              key=(name, tuple(external)))

    def _forward(self, reduced, parametric=False, external=()):
        frames, wrench_names = self._external(external)

        def build(phys, theta, phi, dtheta, dphi, tau, *f):
            x = (theta, phi, dtheta, dphi)
            segs, kin = self._kin(reduced, phys, x)
            f_ext = kinematics.link_wrenches(self.model, frames, theta, f) if f else None
            Q_phi = self._phi_force(phys, x, tau) if self.m else ca.DM.zeros(0, 1)
            return list(rec.forward_dynamics(segs, kin, self._theta_force(phys, x, tau), Q_phi, phys.gravity, f_ext))
        name = ("reduced_forward_dynamics" if reduced else "forward_dynamics") + ("_external" if external else "")
        return self._function(name, STATE + ["tau"] + wrench_names, ["ddtheta", "ddphi"], build, parametric,
                              key=(name, tuple(external)))

    def _input_torques(self, phys, x, T, Qi_phi):
        """tau from inverse dynamics: an SEA's motor, eq. (22), -(Q_phi + T + T_B2) / mu; a geared
        joint's, -(T + T_B2(dtheta)) / mu; a direct joint's, T (T: the link torque theta's
        equation needs, with T_L)."""
        mu, parts = phys.columns["gear_ratio"], {}
        if self.m:
            T_s = self.sea_torque(*x, phys=phys)
            tau_m = -(Qi_phi + T_s + self.gear_loss(x[3], phys, T_s)) / self._at_motors(mu)
            if self.m == self.u:
                return tau_m
            parts.update({j: tau_m[i] for j, i in self.model.motor_of.items()})
        for j in self.model.actuated:
            if self.model.joints[j].joint_kind.rotors == "link":
                parts[j] = -(T[j] + self.gear_loss(x[2][j], phys, 0.0, [j])) / mu[j]
            elif j not in parts:
                parts[j] = T[j]
        return ca.vertcat(*[parts[j] for j in self.model.actuated]) if parts else ca.DM.zeros(0, 1)

    def _external(self, external) -> tuple:
        """The frames named in `external` and their wrench inputs' names (f_<frame>)."""
        frames = [self.model.frame(name) for name in external]
        names = [f"f_{identifier(name)}" for name in external]
        if len(set(names)) != len(names):
            raise InvalidArgument(f"external: the frames {list(external)} are not distinct as C identifiers")
        return frames, names

    # -- public Functions -------------------------------------------------------------------
    def inverse_dynamics(self, *, parametric: bool = False, external=()) -> ca.Function:
        """theta, phi, dtheta, dphi, ddtheta, ddphi -> tau (eq. 22), T (eq. 26).  `external`: frame
        names; one more input f_<frame> each, the wrench [force; moment] (6 x 1, world axes) that
        the environment applies at the frame's origin (the links feel J^T f, J local_world_aligned)."""
        return self._inverse(False, parametric, tuple(external))

    def forward_dynamics(self, *, parametric: bool = False, external=()) -> ca.Function:
        """theta, phi, dtheta, dphi, tau -> ddtheta, ddphi: the complete model, one O(n) sweep.
        `external`: as for `inverse_dynamics`, a wrench input per named frame."""
        return self._forward(False, parametric, tuple(external))

    def reduced_inverse_dynamics(self, *, parametric: bool = False, external=()) -> ca.Function:
        """The DLR/Spong reduced model: M_tt ddtheta + C dtheta + g = T; B ddphi + T + T_B2 = -mu tau."""
        return self._inverse(True, parametric, tuple(external))

    def reduced_forward_dynamics(self, *, parametric: bool = False, external=()) -> ca.Function:
        """The DLR/Spong reduced model solved for ddtheta, ddphi (wrench inputs as `forward_dynamics`)."""
        return self._forward(True, parametric, tuple(external))

    # -- frames and kinematics (docs/user-guide/frames.md) -----------------------------------
    def frames(self) -> list:
        """The names of the arm's frames: its links' and the model file's [frames]."""
        return [f.name for f in self.model.frames]

    def _kinematic(self, name, frame, ins, outs, build, parametric, reference=None):
        """A kinematic Function of one frame, named name_<frame>[_<reference>] (C identifiers)."""
        self._fixed_base()
        fr = self.model.frame(frame)
        if reference is not None and reference not in kinematics.REFERENCES:
            raise InvalidArgument(f"reference {reference!r}: choose one of {', '.join(kinematics.REFERENCES)}")
        full = f"{name}_{identifier(frame)}" + (f"_{reference}" if reference else "")
        return self._function(full, ins, outs, lambda phys, *a: build(fr, *a), parametric, key=(full, frame))

    def frame_placement(self, frame: str, *, parametric: bool = False) -> ca.Function:
        """theta -> rotation R (3 x 3), translation p (3 x 1): the frame in the world (base) frame."""
        return self._kinematic("frame_placement", frame, ["theta"], ["rotation", "translation"],
                               lambda fr, theta: list(kinematics.frame_pose(self.model, fr, theta)), parametric)

    def frame_jacobian(self, frame: str, reference: str = "local_world_aligned", *, parametric: bool = False) -> ca.Function:
        """theta -> J (6 x n, rows linear then angular) in `reference`: local_world_aligned,
        local or world, as Pinocchio's ReferenceFrame (docs/user-guide/frames.md)."""
        return self._kinematic("frame_jacobian", frame, ["theta"], ["J"],
                               lambda fr, theta: [kinematics.frame_jacobian(self.model, fr, theta, reference)],
                               parametric, reference)

    def frame_velocity(self, frame: str, reference: str = "local_world_aligned", *, parametric: bool = False) -> ca.Function:
        """theta, dtheta -> v (6 x 1, [linear; angular]) in `reference`."""
        return self._kinematic("frame_velocity", frame, ["theta", "dtheta"], ["v"],
                               lambda fr, theta, dtheta: [kinematics.frame_jacobian(self.model, fr, theta, reference)
                                                          @ dtheta], parametric, reference)

    def frame_acceleration(self, frame: str, reference: str = "local_world_aligned", *,
                           parametric: bool = False) -> ca.Function:
        """theta, dtheta, ddtheta -> a (6 x 1): the classical acceleration in `reference`
        (Pinocchio's getFrameClassicalAcceleration)."""
        return self._kinematic("frame_acceleration", frame, ["theta", "dtheta", "ddtheta"], ["a"],
                               lambda fr, th, dth, ddth: [kinematics.frame_classical_acceleration(self.model, fr, th, dth, ddth, reference)],
                               parametric, reference)

    def frame_jacobian_dot_times_v(self, frame: str, *, parametric: bool = False) -> ca.Function:
        """theta, dtheta -> dJ/dt dtheta (6 x 1) of the local_world_aligned Jacobian."""
        return self._kinematic("frame_jacobian_dot_times_v", frame, ["theta", "dtheta"], ["dJv"],
                               lambda fr, theta, dtheta: [kinematics.jacobian_dot_times_v(self.model, fr, theta,
                                                                                          dtheta)], parametric)

    def center_of_mass(self, *, parametric: bool = False) -> ca.Function:
        """theta, phi -> c (3 x 1): the centre of mass of every moving body, links and rotors (the
        fixed base excluded, as Pinocchio's).  phi matters only for an unbalanced rotor."""
        def build(phys, theta, phi):
            return [kinematics.center_of_mass(self._segments(False, phys), theta, phi)]
        return self._function("center_of_mass", ["theta", "phi"], ["c"], build, parametric)

    def center_of_mass_jacobian(self, *, parametric: bool = False) -> ca.Function:
        """theta, phi -> Jc (3 x 2n) = dc/d(theta, phi) (the phi block is zero for balanced rotors)."""
        def build(phys, theta, phi):
            c = kinematics.center_of_mass(self._segments(False, phys), theta, phi)
            return [ca.jacobian(c, ca.vertcat(theta, phi))]
        return self._function("center_of_mass_jacobian", ["theta", "phi"], ["Jc"], build, parametric)

    def joint_forward_dynamics(self, *, parametric: bool = False) -> ca.Function:
        """Paper eq. (23), flexible-joint forward dynamics:
        theta, phi, dtheta, dphi, tau, ddtheta -> ddphi.  ddtheta gives the parent links'
        spatial accelerations alpha_{k+1} (only the joints inboard of each rotor matter);
        T is the SEA torque of the spring law at the state."""
        def build(phys, theta, phi, dtheta, dphi, tau, ddtheta):
            x = (theta, phi, dtheta, dphi)
            segs, kin = self._kin(False, phys, x)
            return [rec.joint_forward_dynamics(segs, kin, ddtheta, self._phi_force(phys, x, tau), phys.gravity)]
        return self._function("joint_forward_dynamics", STATE + ["tau", "ddtheta"], ["ddphi"], build, parametric)

    def arm_forward_dynamics(self, *, parametric: bool = False) -> ca.Function:
        """Paper eqs. (29)-(32), whole-arm forward dynamics:
        theta, phi, dtheta, dphi, ddphi, ddtheta_guess -> ddtheta.  T is the SEA torque of the
        spring law at the state; ddphi are the rotor accelerations (from eq. 23) and
        ddtheta_guess the predicted link accelerations that form the rotors' spatial
        accelerations in eq. (29).  At the exact ddtheta, ddtheta == ddtheta_guess.  Every joint an SEA."""
        require_sea(self.model, "the paper's whole-arm forward dynamics (eqs. 29-32)")

        def build(phys, theta, phi, dtheta, dphi, ddphi, ddtheta_guess):
            x = (theta, phi, dtheta, dphi)
            segs, kin = self._kin(False, phys, x)
            return [rec.arm_forward_dynamics(segs, kin, self.sea_torque(*x, phys=phys), ddphi, ddtheta_guess,
                                             phys.gravity)]
        return self._function("arm_forward_dynamics", STATE + ["ddphi", "ddtheta_guess"], ["ddtheta"], build,
                              parametric)

    def energy(self, *, parametric: bool = False) -> ca.Function:
        """theta, phi, dtheta, dphi -> E: kinetic + gravitational + the springs' energy (the SEAs',
        the counterbalances' and spring joints')."""
        def build(phys, theta, phi, dtheta, dphi):
            segs, kin = self._kin(False, phys, (theta, phi, dtheta, dphi))
            c, sel = phys.columns, self._at_motors
            spring = ca.sum1(0.5 * c["cb_k"] * (theta - c["cb_theta0"]) ** 2)
            if self.m:
                psi = phi - sel(theta)
                spring += ca.sum1(0.5 * sel(c["k1"]) * psi ** 2 + 0.25 * sel(c["k3"]) * psi ** 4)
            return [rec.energy(segs, kin, phys.gravity) + spring]
        return self._function("energy", STATE, ["E"], build, parametric)

    def _residual_rows(self, phys, x, ddtheta, ddphi, tau):
        """r = M ddq + c - Q, one generalised force per coordinate (docs/user-guide/model.md
        section 3): theta's rows, then phi's."""
        segs, kin = self._kin(False, phys, x)
        T, Qi_phi = rec.inverse_dynamics(segs, kin, ddtheta, ddphi, phys.gravity)
        rows = [T - self._theta_force(phys, x, tau)]
        if self.m:
            rows.append(Qi_phi - self._phi_force(phys, x, tau))
        return ca.vertcat(*rows)

    def residual(self, *, parametric: bool = False) -> ca.Function:
        """theta, phi, dtheta, dphi, ddtheta, ddphi, tau -> r = M ddq + c - Q (n + m): zero exactly
        at the forward dynamics; dr/dtau = -input_matrix."""
        def build(phys, theta, phi, dtheta, dphi, ddtheta, ddphi, tau):
            return [self._residual_rows(phys, (theta, phi, dtheta, dphi), ddtheta, ddphi, tau)]
        return self._function("residual", STATE + ["ddtheta", "ddphi", "tau"], ["r"], build, parametric)

    def residual_jacobian(self, *, parametric: bool = False) -> ca.Function:
        """theta, phi, dtheta, dphi, ddtheta, ddphi -> dr/d(theta, phi, dtheta, dphi) ((n + m) x
        2 (n + m)), where r = M ddq + c - Q without its tau term (the rows of
        docs/user-guide/model.md section 3)."""
        def build(phys, theta, phi, dtheta, dphi, ddtheta, ddphi):
            x = (theta, phi, dtheta, dphi)
            r = self._residual_rows(phys, x, ddtheta, ddphi, ca.DM.zeros(self.u))
            return ca.cse([ca.jacobian(r, ca.vertcat(*x))])
        return self._function("residual_jacobian", STATE + ["ddtheta", "ddphi"], ["jacobian"], build, parametric)

    def forward_dynamics_jacobian(self, *, parametric: bool = False) -> ca.Function:
        """theta, phi, dtheta, dphi, tau -> jacobian = d(ddtheta, ddphi)/d(theta, phi, dtheta, dphi, tau)
        ((n + m) x (2 (n + m) + u); 2n x 5n for SEAs) by the implicit-function theorem on M ddq + c = Q at ddq = forward dynamics:
        M J = [-dr/d(q, dq) | dQ/dtau], one LDL^T solve.  An MX graph calling compact SX
        Functions: its size grows like the inverse-dynamics derivative, not like AD through
        the articulated sweep."""
        key = ("forward_dynamics_jacobian", parametric)
        if key not in self._functions:
            x = [ca.MX.sym(name, self._size(name)) for name in STATE]
            tau = ca.MX.sym("tau", self.u)
            p = [ca.MX.sym("p", self.n_p)] if parametric else []
            J = self.acceleration_sensitivity(x, tau, None, None, *p)
            self._functions[key] = ca.Function("forward_dynamics_jacobian", x + [tau] + p, [J],
                                               STATE + ["tau"] + (["p"] if parametric else []), ["jacobian"])
        return self._functions[key]

    def acceleration_sensitivity(self, x, tau, D=None, s=None, *p):
        """The derivative of the forward dynamics along dX = [1 0] + s D (MX; x the four state parts,
        D 4n x 5n, the state's sensitivity to (x_0, tau) being [1 0] + s D; D None: the
        forward-dynamics Jacobian itself) by the implicit-function theorem:
        M^-1 ([-dr/dx | dQ/dtau] - s dr/dx D).  The sparse residual Jacobian multiplies D; no dense
        forward-dynamics Jacobian is formed."""
        ddtheta, ddphi = self.forward_dynamics(parametric=bool(p))(*x, tau, *p)
        Jr = self.residual_jacobian(parametric=bool(p))(*x, ddtheta, ddphi, *p)
        rhs = ca.horzcat(-Jr, self.input_matrix(gear_ratios(self.model, self.free, *p)))
        if D is not None:
            # (D' Jr')' rather than Jr D: CasADi's dense-times-sparse kernel runs down contiguous
            # columns, 3x faster than its sparse-times-dense one here (n = 12: 6.5 instead of 18 us)
            rhs -= s * ca.mtimes(D.T, Jr.T).T
        return ca.solve(self.mass_matrix(parametric=bool(p))(x[0], x[1], *p), rhs, "ldl")

    def input_places(self) -> list:
        """Per input, in tau's order: (the coordinate it drives, its joint, whether through a gear):
        a motor's phi (sea), a geared link's theta, a direct joint's theta."""
        at_motor, kinds = self.model.motor_of, self.model.kinds
        return [(self.n + at_motor[j] if kinds[j].motor else j, j, bool(kinds[j].rotors)) for j in self.model.actuated]

    def input_matrix(self, mu):
        """dQ/dtau ((n + m) x u): the generalised forces' derivative by the inputs, given the gear
        ratios mu (n): -mu on a motor's phi row (sea) or on theta's row (geared), 1 on theta's
        row (direct)."""
        place = np.zeros((self.n + self.m, self.u))
        for col, (row, _, _) in enumerate(self.input_places()):
            place[row, col] = 1.0
        gains = ca.vertcat(*[-mu[j] if geared else 1.0 for _, j, geared in self.input_places()])
        return ca.mtimes(ca.sparsify(ca.DM(place)), ca.diag(gains))

    def mass_matrix(self, *, reduced: bool = False, parametric: bool = False) -> ca.Function:
        """theta, phi -> M ((n + m) x (n + m), q = (theta, phi)), the Jacobian of the generalized
        inertial forces of the recursion with respect to (ddtheta, ddphi)."""
        def build(phys, theta, phi):
            n, m = self.n, self.m
            ddq = ca.SX.sym("ddq", n + m)
            segs, kin = self._kin(reduced, phys, (theta, phi, ca.DM.zeros(n), ca.DM.zeros(m)))
            Q = ca.vertcat(*rec.inverse_dynamics(segs, kin, ddq[:n], ddq[n:], np.zeros(3)))
            return [ca.jacobian(Q, ddq)]
        name = "reduced_mass_matrix" if reduced else "mass_matrix"
        return self._function(name, ["theta", "phi"], ["M"], build, parametric)


Robot = Arm
"""`Robot` and `Arm` name one class: a robot on a fixed base, a tree of joints of any kind (a serial
arm is the tree with one branch)."""


def _scatter(rows: list, n: int) -> np.ndarray:
    """The n x len(rows) matrix that places a short column's entries at `rows` of an n-column."""
    S = np.zeros((n, len(rows)))
    S[rows, range(len(rows))] = 1.0
    return S


def load(path) -> Arm:
    """Read a model file (docs/user-guide/model.md section 4) and return its Arm."""
    return Arm(read(path))
