"""Code generation: the arm's Functions as plain C99 (CasADi's standard interface), compiled
into one shared library, described by DIR/manifest.json, and loaded back with casadi.external.

Nothing from a model file reaches C or the compiler: the function names are fixed, the
optional prefix must be a C identifier, and the compiler runs from an argument list.
Compiled libraries are cached by a hash of their sources, compiler and flags.
"""
from __future__ import annotations

import ctypes
import json
import os
import tempfile
from pathlib import Path

import casadi as ca
import numpy as np

from rscasadi.dynamics.feedforward import feedforward_functions
from rscasadi.dynamics.arm import Arm
from rscasadi.dynamics.floating import FloatingRobot, load_robot
from rscasadi.model.parameters import PARAMETRIC, tied_balanced
from rscasadi.dynamics.kinematics import REFERENCES
from rscasadi.model.parameters import gear_ratios
from rscasadi.model.checks import identifier
from rscasadi.files import OutputError, safe_name
from rscasadi.native.generate import C_IDENTIFIER, package
from rscasadi.codegen.step_kernel import kernel_source
from rscasadi.native.build import OPT_LEVELS, BuildError, compiler, native_flags
from rscasadi.native.loader import CompiledController, ControllerError
from rscasadi.errors import InvalidArgument

LIBRARY = "librscasadi_arm.so"
HEADER = "rscasadi_arm.h"                  # ours (templates/), including CasADi's:
CASADI_HEADER = "rscasadi_arm_functions.h"


class CodegenError(BuildError, OutputError):
    """Generating or compiling the C code failed; nothing was left half-written."""


def _renamed(f: ca.Function, name: str, outs=None, out_names=None) -> ca.Function:
    """f under a new name, outputs after common-subexpression elimination (ca.cse)."""
    if not f.is_a("SXFunction"):
        return ca.Function(name, f.mx_in(), f.call(f.mx_in()), f.name_in(), out_names or f.name_out())
    ins = f.sx_in()
    outs = f.call(ins) if outs is None else outs(*ins)
    return ca.Function(name, ins, ca.cse(list(outs)), f.name_in(), out_names or f.name_out())


def rk4(f, x, h):
    """One classical Runge-Kutta step of dx/dt = f(x); returns x_next and the stage points."""
    k1 = f(x)
    k2 = f(x + h / 2 * k1)
    k3 = f(x + h / 2 * k2)
    k4 = f(x + h * k3)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4), (x, x + h / 2 * k1, x + h / 2 * k2, x + h * k3)


def rhs(arm: Arm, parametric: bool = False) -> ca.Function:
    """The state equation as a compact SX Function: (x, tau[, p]) -> dx/dt, x = (theta, phi, dtheta, dphi)."""
    x, tau = ca.SX.sym("x", 2 * arm.nq), ca.SX.sym("tau", arm.u)
    p = [ca.SX.sym("p", arm.n_p)] if parametric else []
    q = arm.split_state(x)
    xdot = ca.vertcat(q[2], q[3], *arm.forward_dynamics(parametric=parametric)(*q, tau, *p))
    return ca.Function("rhs", [x, tau] + p, ca.cse([xdot]), ["x", "tau"] + ["p"] * len(p), ["xdot"])


def rk4_step(arm: Arm, parametric: bool = False, prefix: str = "") -> ca.Function:
    """step: (x, tau, h[, p]) -> x_next, one classical RK4 step of the complete model."""
    f = rhs(arm, parametric)
    x, tau, h = ca.MX.sym("x", 2 * arm.nq), ca.MX.sym("tau", arm.u), ca.MX.sym("h")
    p = [ca.MX.sym("p", arm.n_p)] if parametric else []
    return ca.Function(prefix + "step", [x, tau, h] + p, [rk4(lambda z: f(z, tau, *p), x, h)[0]],
                       ["x", "tau", "h"] + ["p"] * len(p), ["x_next"])


def step_functions(arm: Arm, prefix: str = "", fd_jacobian: ca.Function | None = None, parametric: bool = False,
                   expand: bool | None = None):
    """step: (x, tau, h[, p]) -> x_next, one RK4 step of the complete model; step_jacobian: (x, tau,
    h[, p]) -> A = dx_next/dx, B = dx_next/dtau by the chain rule through the four stages,
    dk_i = J_i d(stage point)/d(x, tau), using the structure of J_i = d xdot/d(x, tau): its top
    half (d theta/dt = dtheta, ...) only copies the speed rows, so only its bottom half, the
    forward-dynamics Jacobian F_i (2n x 5n), multiplies:

        dk_i = [dX_i[speeds]; F_i[:, x] dX_i + [0 | F_i[:, tau]]],   dX_i = [1 0] + c_i h dk_{i-1}

    With the small SX forward-dynamics Jacobian (`expand`, the default when it is SX) the whole
    Function becomes straight-line SX: 0.9 us instead of 7.5 us at n = 3.  Past it (the
    implicit-function route), F_i is never formed: with dk_i = [S_i; B_i], the speed rows
    S_i = [0 1 0] + c_i h B_{i-1}, and B_i = M_i^-1 ([-dr/dx | dQ/dtau] - c_i h dr/dx dk_{i-1})
    (Arm.acceleration_sensitivity): the sparse residual Jacobian times dk_{i-1}, no identity
    added to a dense matrix (n = 12: 206 -> ~100 us)."""
    nq, nx, f = arm.nq, 2 * arm.nq, rhs(arm, parametric)
    fd_jacobian = fd_jacobian or forward_dynamics_jacobian(arm, parametric, prefix + "forward_dynamics_jacobian")
    x, tau, h = ca.MX.sym("x", nx), ca.MX.sym("tau", arm.u), ca.MX.sym("h")
    p = [ca.MX.sym("p", arm.n_p)] if parametric else []
    _, stages = rk4(lambda z: f(z, tau, *p), x, h)
    I = ca.DM.eye(nx + arm.u)[:nx, :]                                # d x / d(x, tau)
    small = arm.forward_dynamics(parametric=parametric).n_instructions() <= AD_JACOBIAN_LIMIT
    S: list = []                                                     # dk_i = [S_i; B_i]
    B: list = []
    for xi, c in zip(stages, (0.0, 0.5, 0.5, 1.0)):
        if small:                                                    # F_i = d(ddtheta, ddphi)/d(x, tau)
            dX = I + c * h * ca.vertcat(S[-1], B[-1]) if S else ca.MX(I)
            F = ca.densify(fd_jacobian(*arm.split_state(xi), tau, *p))
            B.append(ca.mtimes(F[:, :nx], ca.densify(dX)) + ca.horzcat(ca.MX.zeros(nq, nx), F[:, nx:]))
        else:
            B.append(arm.acceleration_sensitivity(arm.split_state(xi), tau, ca.vertcat(S[-1], B[-1]) if S else None,
                                                  c * h, *p))
        S.append(I[nq:, :] + c * h * B[-2] if S else ca.MX(I[nq:, :]))
    weights = (1, 2, 2, 1)
    dnext = I + h / 6 * ca.vertcat(sum(w * Si for w, Si in zip(weights, S)), sum(w * Bi for w, Bi in zip(weights, B)))
    names = ["x", "tau", "h"] + ["p"] * len(p)
    step = rk4_step(arm, parametric, prefix)
    step_jac = ca.Function(prefix + "step_jacobian", [x, tau, h] + p, [dnext[:, :nx], dnext[:, nx:]],
                           names, ["A", "B"])
    if expand if expand is not None else small:
        step_jac = step_jac.expand(prefix + "step_jacobian", {"cse": True})
    return step, step_jac


AD_JACOBIAN_LIMIT = 1000   # forward-dynamics SX instructions above which the Jacobian comes from the
                           # implicit-function theorem (AD through the sweep: 1165 at n = 3, 27 535 at n = 6)


def _ad_jacobian(f: ca.Function, ins, parametric: bool):
    """The dense Jacobian of all outputs of f with respect to its inputs but p, by SX AD."""
    wrt = ins[:-1] if parametric else ins
    return ca.densify(ca.jacobian(ca.vertcat(*f.call(list(ins))), ca.vertcat(*wrt)))


IMPLICIT_SX_LIMIT = 30000  # SX instructions of the straight-line implicit-function route above which
                           # its MX graph is generated instead (8.6k at n = 6, 20.7k on the Panda, 54.6k at
                           # n = 12: at 7 joints 2.3 us against the MX graph's 4.7 us, -O3, 2026-11-24)


def _implicit_sx(arm: Arm, parametric: bool) -> ca.Function:
    """The implicit-function route as one straight-line SX Function: forward dynamics, the
    residual's Jacobian and a symbolic LDL^T of the sparse M, M J = [-dr/dx | dQ/dtau]."""
    x = [ca.SX.sym(name, arm._size(name)) for name in ("theta", "phi", "dtheta", "dphi")]
    tau = ca.SX.sym("tau", arm.u)
    p = [ca.SX.sym("p", arm.n_p)] if parametric else []
    ddtheta, ddphi = arm.forward_dynamics(parametric=parametric)(*x, tau, *p)
    Jr = arm.residual_jacobian(parametric=parametric)(*x, ddtheta, ddphi, *p)
    rhs = ca.horzcat(-Jr, arm.input_matrix(gear_ratios(arm.model, arm.free, *p)))
    D, Lt, perm = ca.ldl(arm.mass_matrix(parametric=parametric)(x[0], x[1], *p))
    return ca.Function("forward_dynamics_jacobian", x + [tau] + p, [ca.ldl_solve(rhs, D, Lt, perm)],
                       ["theta", "phi", "dtheta", "dphi", "tau"] + ["p"] * len(p), ["jacobian"], {"cse": True})


def forward_dynamics_jacobian(arm: Arm, parametric: bool = False, name: str = "forward_dynamics_jacobian"):
    """The faster route to d(ddtheta, ddphi)/d(x, tau) for this arm: plain SX AD for small
    forward dynamics (compact straight-line code), the implicit-function theorem past
    AD_JACOBIAN_LIMIT instructions (AD through the sweep explodes with n): straight-line SX
    while it stays below IMPLICIT_SX_LIMIT instructions, an MX graph of SX pieces above."""
    fd = arm.forward_dynamics(parametric=parametric)
    if fd.n_instructions() > AD_JACOBIAN_LIMIT:
        sx = _implicit_sx(arm, parametric)
        return _renamed(sx if sx.n_instructions() <= IMPLICIT_SX_LIMIT else arm.forward_dynamics_jacobian(parametric=parametric),
                        name)
    return _renamed(fd, name, lambda *ins: [_ad_jacobian(fd, ins, parametric)], ["jacobian"])


def frame_functions(arm: Arm, frames=(), external=(), parametric: bool = False) -> dict:
    """The task-space Functions by public name: per frame its placement, its Jacobian in the
    three references, its velocity and dJ/dt dtheta (local_world_aligned), the centre of mass;
    with `external`, the dynamics taking a wrench at each of those frames."""
    fns = {}
    for frame in frames:
        fs = [arm.frame_placement(frame, parametric=parametric),
              *[arm.frame_jacobian(frame, ref, parametric=parametric) for ref in REFERENCES],
              arm.frame_velocity(frame, "local_world_aligned", parametric=parametric),
              arm.frame_jacobian_dot_times_v(frame, parametric=parametric)]
        fns.update({f.name(): f for f in fs})
    if frames:
        fns["center_of_mass"] = arm.center_of_mass(parametric=parametric)
    if external:
        fns["forward_dynamics_external"] = arm.forward_dynamics(parametric=parametric, external=external)
        fns["inverse_dynamics_external"] = arm.inverse_dynamics(parametric=parametric, external=external)
    return fns


def check_frames(arm: Arm, frames, external):
    """Every frame named exists (the error names the option and the frame) and maps to a C
    identifier that no other frame maps to."""
    for option, names in (("--frames", frames), ("--external", external)):
        for name in names:
            if name not in arm.frames():
                raise CodegenError(f"{option}: {arm.model.path} has no frame {name!r} "
                                   f"(frames: {', '.join(arm.frames())})")
            try:
                identifier(name)
            except ValueError as exc:
                raise CodegenError(f"{option}: {exc}") from None
    idents = [identifier(name) for name in set(frames) | set(external)]
    if len(set(idents)) != len(idents):
        raise CodegenError(f"--frames/--external: {sorted(set(frames) | set(external))} are not distinct "
                           "as C identifiers")


def functions(arm: Arm, prefix: str = "", parametric: bool = False, frames=(), external=()) -> tuple[dict, dict]:
    """The Functions to generate, by their public name; and those omitted, with the reason.
    parametric: every Function takes the parameter vector p as its last input; frames, external:
    the task-space Functions (frame_functions)."""
    p = f"{prefix}_" if prefix else ""
    fns, omitted = {}, {}
    for name, f in frame_functions(arm, frames, external, parametric).items():
        fns[name] = _renamed(f, p + name)
    for name in ("forward_dynamics", "inverse_dynamics", "energy"):
        fns[name] = _renamed(getattr(arm, name)(parametric=parametric), p + name)
    for name in ("reduced_forward_dynamics", "reduced_inverse_dynamics"):
        try:
            fns[name] = _renamed(getattr(arm, name)(parametric=parametric), p + name)
        except ValueError as exc:                  # unbalanced rotors: the reduced model does not apply
            omitted[name] = str(exc)
    inv = arm.inverse_dynamics(parametric=parametric)
    fns["forward_dynamics_jacobian"] = forward_dynamics_jacobian(arm, parametric, p + "forward_dynamics_jacobian")
    fns["inverse_dynamics_jacobian"] = _renamed(inv, p + "inverse_dynamics_jacobian",
                                                lambda *ins: [_ad_jacobian(inv, ins, parametric)], ["jacobian"])
    fns["step"], fns["step_jacobian"] = step_functions(arm, p, fns["forward_dynamics_jacobian"], parametric)
    if arm.model.all_sea:
        for f in feedforward_functions(arm, parametric=parametric):  # the paper's feedforward, on line
            fns[f.name()] = _renamed(f, p + f.name())
    else:
        omitted["feedforward_init"] = omitted["feedforward_step"] = (
            "the paper's feedforward (eqs. 33-35) drives SEAs; this robot has joints of other kinds")
    return fns, omitted


FEEDFORWARD = "rscasadi_feedforward"
TEMPLATES = Path(__file__).with_name("templates")
ACCELERATION_BOUND = 1e3         # rad/s^2: the largest desired link acceleration the feedforward takes
STEP_BOUNDS = (1e-6, 0.1)        # s: the sample times it takes


def feedforward_controller(arm: Arm, fns: dict, prefix: str) -> dict:
    """The sources of the guarded feedforward (templates/rscasadi_feedforward.*: ff_init, ff_step
    around the library's feedforward_init and feedforward_step, with the controllers' failure
    policy) and the guard header: file name -> text."""
    from string import Template
    from rscasadi.model.limits import limit_arrays, measurement_bounds
    from rscasadi.native.controller import c_numbers, c_words, guard_source
    n, p = arm.n, f"{prefix}_" if prefix else ""
    lo, hi = measurement_bounds(arm.model)
    tau = limit_arrays(arm.model)["tau"]
    parts = [fns[k] for k in ("feedforward_init", "feedforward_step", "inverse_dynamics")]
    values = {"n": n, "p": p, "P": p.upper(), "model": safe_name(Path(str(arm.model.path)).name),
              "tau_limits": c_words(tau), "tau_max": c_numbers(tau), "theta_lo": c_words(lo[:n]),
              "theta_hi": c_words(hi[:n]), "speed": c_words(hi[2 * n:3 * n]), "theta_lo_c": c_numbers(lo[:n]),
              "theta_hi_c": c_numbers(hi[:n]), "speed_c": c_numbers(hi[2 * n:3 * n]), "accel": repr(ACCELERATION_BOUND),
              "h_lo": repr(STEP_BOUNDS[0]), "h_hi": repr(STEP_BOUNDS[1]), "header": FEEDFORWARD + ".h",
              "sz_w": max(f.sz_w() for f in parts) + 1, "sz_iw": max(f.sz_iw() for f in parts) + 1}
    return {name: Template((TEMPLATES / name).read_text()).substitute(values)
            for name in (FEEDFORWARD + ".h", FEEDFORWARD + ".c")} | guard_source()


def floating_functions(robot: FloatingRobot, prefix: str = "", frames=()) -> tuple[dict, dict]:
    """A floating robot's Functions to generate (docs/user-guide/floating.md), by public name: the
    free and contact dynamics and their parts, the contact dynamics' Jacobian, momentum, integrate,
    and per frame its placement and Jacobians; the contacts are the model file's [[contacts]]."""
    p = f"{prefix}_" if prefix else ""
    names = ["forward_dynamics", "inverse_dynamics", "mass_matrix", "nonlinear_effects", "generalized_forces",
             "energy", "integrate", "center_of_mass", "centroidal_momentum", "centroidal_momentum_matrix"]
    fns = {name: getattr(robot, name)() for name in names}
    omitted = {"step": "a floating robot's steps depend on its contacts: integrate its contact dynamics",
               "feedforward_init": "the paper's feedforward drives a fixed-base arm of SEAs"}
    if robot.model.contacts:
        for name in ("contact_dynamics", "contact_dynamics_jacobian", "contact_jacobian", "contact_drift",
                     "contact_inverse_dynamics", "impact"):
            fns[name] = getattr(robot, name)()
    else:
        omitted["contact_dynamics"] = "the model file has no [[contacts]]"
    for frame in frames:
        for f in (robot.frame_placement(frame), *[robot.frame_jacobian(frame, ref) for ref in ("local", "local_world_aligned")]):
            fns[f.name()] = f
    return {name: _renamed(f, p + name) for name, f in fns.items()}, omitted


def floating_macros(robot: FloatingRobot, prefix: str) -> str:
    """A floating robot's sizes as C macros: PREFIX_ROBOT_NQ (q), _NV (v), _NU (tau), _NC (contact rows)."""
    from rscasadi.dynamics.contacts import contact_set
    p = f"{prefix}_" if prefix else ""
    nc = sum(c.rows for c in contact_set(robot.model)) if robot.model.contacts else 0
    return (f"\n/* The robot on its floating base: its sizes (docs/user-guide/floating.md). */\n"
            f"#define {p}ROBOT_NQ {robot.nq}                 /* q = (base xyz, quaternion xyzw, theta, phi) */\n"
            f"#define {p}ROBOT_NV {robot.nv}                 /* v = (base [v; w] in its frame, dtheta, dphi) */\n"
            f"#define {p}ROBOT_NU {robot.u}                 /* torque inputs tau (the actuated joints) */\n"
            f"#define {p}ROBOT_NC {nc}                 /* contact rows of the model file's [[contacts]] */\n"
            f"#define {p}ROBOT_NJ {robot.n}                 /* joints */\n\n")


def arm_macros(arm: Arm, prefix: str) -> str:
    """The arm's size and the model file's numbers as C macros, so programs are written for any
    arm: PREFIX_ARM_NQ (joints), _NX (state entries), and initialisers of ARM_NQ numbers."""
    from rscasadi.model.limits import limit_arrays
    m, p = arm.model, f"{prefix}_" if prefix else ""
    tau = limit_arrays(m)["tau"]

    def numbers(v):
        return "{" + ", ".join(repr(float(x)) for x in v) + "}"
    return (f"\n/* The arm: its size and its model file's numbers (initialisers of {p}ARM_NQ entries). */\n"
            f"#define {p}ARM_NQ {m.n}                 /* joints */\n"
            f"#define {p}ARM_NM {arm.m}                 /* motor coordinates phi (the SEA joints) */\n"
            f"#define {p}ARM_NU {arm.u}                 /* torque inputs tau (the actuated joints) */\n"
            f"#define {p}ARM_NX {2 * arm.nq}             /* state x = (theta, phi, dtheta, dphi) */\n"
            f"#define {p}ARM_GEAR_RATIO {numbers(m.column('gear_ratio'))}  /* mu: motor turns per link turn */\n"
            f"#define {p}ARM_K1 {numbers(m.column('k1'))}  /* SEA stiffness, N m/rad */\n"
            f"#define {p}ARM_TAU_MAX {numbers(np.where(np.isfinite(tau), tau, 0.0)[m.actuated])}  /* each input's "
            "torque limit, N m; 0: none */\n\n")


def arm_header(arm: Arm | FloatingRobot, prefix: str, declarations: list) -> str:
    """The library's header (templates/rscasadi_arm.h): CasADi's declarations included, the arm's
    macros (arm_macros) and the structured kernels' `declarations`."""
    from string import Template
    macros = floating_macros(arm, prefix) if isinstance(arm, FloatingRobot) else arm_macros(arm, prefix)
    return Template((TEMPLATES / HEADER).read_text()).substitute(
        model=safe_name(Path(str(arm.model.path)).name), GUARD=f"{prefix.upper()}_RSCASADI_ARM_H" if prefix
        else "RSCASADI_ARM_H", casadi_header=CASADI_HEADER, macros=macros,
        declarations="".join(declarations))


def _io(f: ca.Function, out: bool):
    n = f.n_out() if out else f.n_in()
    sp = f.sparsity_out if out else f.sparsity_in
    names = f.name_out() if out else f.name_in()
    return [{"name": names[i], "rows": sp(i).size1(), "cols": sp(i).size2()} for i in range(n)]



# the Functions that, past straight-line SX (an MX graph of SX pieces), are generated as a structured C kernel
# (codegen.step_kernel) of this method: on a 20-joint tree of SEAs the forward dynamics' Jacobian 30 us
# against the MX graph's 98-103 us (-O3, this processor; 2026-11-29, 2-core Xeon VM; results/bench_trees.md)
KERNELS = {"step_jacobian": "rk4", "forward_dynamics_jacobian": "fd_jacobian"}


def generate(model, out, prefix: str | None = None, opt: str = "-O3", log=print, parametric: str = "none",
             native: bool = False, frames=(), external=(), only=None) -> dict:
    """Write C sources, one header, one shared library and manifest.json into `out`.
    parametric (model.parameters.PARAMETRIC): "none", the model's numbers in the C; "all", every
    function takes the parameter vector p (manifest "parameters") last, so one library serves
    every arm with the same joints, axes, gear ratios and eps; "family": p holds only the
    parameters not zero in this model, the zeros are folded: every arm with the same zeros, at
    about the constant C's speed (Compiled.parameters_of checks an arm against it).
    native: compile for this machine's processor (native_flags()); the sources stay portable C99.
    frames, external: frame names whose kinematics, and at which wrenches, the library gets
    (frame_functions); a frame's name enters C only as a C identifier (model.checks.identifier).
    only: the public names of the Functions to generate (default: all), for a controller that
    needs a few; an unknown name is refused, listing those there are."""
    prefix = prefix or ""
    if prefix and not C_IDENTIFIER.match(prefix):
        raise CodegenError(f"prefix {prefix!r} is not a C identifier ([A-Za-z_][A-Za-z0-9_]*, at most 63)")
    if opt not in OPT_LEVELS:
        raise CodegenError(f"optimisation flag {opt!r} not one of {' '.join(OPT_LEVELS)}")
    arm = model if isinstance(model, (Arm, FloatingRobot)) else load_robot(model)
    if isinstance(parametric, bool) or parametric not in PARAMETRIC:
        raise CodegenError(f"parametric {parametric!r} not one of {', '.join(PARAMETRIC)}")
    frames, external = list(frames), list(external)
    if isinstance(arm, FloatingRobot):
        if parametric != "none" or external:
            raise CodegenError(f"{arm.model.path}: a floating robot's C takes the model's numbers (no --parametric) "
                               "and no --external wrenches (its contacts are the model file's [[contacts]])")
        for frame in frames:
            arm.model.frame(frame)
    else:
        if parametric == "family":
            arm = Arm.family(arm.model)
        check_frames(arm, frames, external)
    out = Path(out).resolve()
    try:
        cc = compiler()
    except BuildError as exc:
        raise CodegenError(str(exc)) from None
    flags = [opt, "-std=c99"] + (native_flags() if native else [])
    takes_p = parametric != "none"
    fns, omitted = (floating_functions(arm, prefix, frames) if isinstance(arm, FloatingRobot)
                    else functions(arm, prefix, takes_p, frames, external))
    if only is not None:
        unknown = [name for name in only if name not in fns]
        if unknown or not only:
            raise CodegenError(f"only: {', '.join(map(repr, unknown)) or 'nothing'} is not a Function of "
                               f"{arm.model.path} (there are: {', '.join(fns)})")
        omitted.update({name: "not asked for (only)" for name in fns if name not in only})
        fns = {name: f for name, f in fns.items() if name in only}
    header_gen = ca.CodeGenerator(CASADI_HEADER.removesuffix(".h"), {"with_header": True})
    texts: dict[str, str] = {}
    kernels = {}                                    # name -> step_kernel.Kernel
    with tempfile.TemporaryDirectory() as d:
        for name, f in fns.items():
            gen = ca.CodeGenerator(f"{f.name()}.c", {"with_header": False})
            method = KERNELS.get(name) if isinstance(arm, Arm) and not f.is_a("SXFunction") else None
            if method is not None:                  # past straight-line SX: the structured kernel instead
                kernels[name] = kernel_source(arm, f.name(), takes_p, method=method)
                for g in kernels[name].functions:
                    gen.add(g)
            else:
                gen.add(f)
                header_gen.add(f)
            gen.generate(d + os.sep)
            texts[f"{f.name()}.c"] = (Path(d) / f"{f.name()}.c").read_text() + (kernels[name].body if name in kernels else "")
        header_gen.generate(d + os.sep)                # only its header is used
        texts[CASADI_HEADER] = (Path(d) / CASADI_HEADER).read_text()
    sources = [file for file in texts if file.endswith(".c")]
    texts[HEADER] = arm_header(arm, prefix, [k.header for k in kernels.values()])
    guarded = (not takes_p and isinstance(arm, Arm) and arm.model.all_sea     # the feedforward, guarded
               and {"feedforward_init", "feedforward_step", "inverse_dynamics"} <= set(fns))
    if guarded and isinstance(arm, Arm):
        texts.update(feedforward_controller(arm, fns, prefix))
    manifest = {
        "model": str(getattr(arm.model, "path", "")),
        "header": HEADER,
        "headers": [HEADER, CASADI_HEADER],           # the one to include, and CasADi's, which it includes
        "sources": sources + ([FEEDFORWARD + ".c"] if guarded else []),
        "controllers": {"feedforward": {"header": FEEDFORWARD + ".h", "type": f"{prefix + '_' if prefix else ''}ff_t",
                                        "init": f"{prefix + '_' if prefix else ''}ff_init",
                                        "step": f"{prefix + '_' if prefix else ''}ff_step"}} if guarded else {},
        "functions": {name: {"symbol": f.name(), "inputs": _io(f, False), "outputs": _io(f, True),
                             "n_instructions": kernels[name].n_instructions if name in kernels else f.n_instructions()}
                      for name, f in fns.items()},
        "kernels": {name: "structured C kernel (step_kernel.py); n_instructions: the SX of one stage "
                          "point (forward dynamics and M's factors, then dr/dx" + (", which it evaluates at "
                          "the four points at once)" if KERNELS[name] == "rk4" else ")") for name in kernels},
        "omitted": omitted,
        "parametric": parametric,
        "frames": {name: identifier(name) for name in frames},
        "external": {"frames": external, "wrench": "[force; moment] at the frame's origin, world axes"}
                    if external else None,
        "parameters": _parameters(arm) if takes_p and isinstance(arm, Arm) else None,
        "prefix": prefix,
    }
    # the library is built from the functions' sources (and the feedforward's, which includes the
    # headers): the parametric library of another arm, its macros in the header aside, is a cache hit
    built = texts if not takes_p else {file: texts[file] for file in sources}
    try:
        return package(out, texts, flags, LIBRARY, manifest, log, cc, name="arm", what=f"{len(sources)} sources",
                       built=built)
    except BuildError as exc:
        raise CodegenError(str(exc)) from None


def _parameters(arm: Arm) -> dict:
    """The manifest's parameters: p's names and nominal values, and the family's zeros."""
    names, values = arm.parameters()
    free = names if arm.free is None else arm.free
    tied = tied_balanced(arm.model, free) if arm.tie_balanced else {}
    nominal = dict(zip(names, values.tolist()))
    return {"names": free, "nominal": [nominal[k] for k in free], "tied": tied,
            "zero": [k for k in names if k not in set(free) and k not in tied]}


class Compiled:
    """A compiled arm: its Functions (casadi.external) by public name."""

    def __init__(self, directory):
        self.directory = Path(directory)
        try:
            self.manifest = json.loads((self.directory / "manifest.json").read_text())
        except (OSError, ValueError) as exc:
            raise CodegenError(f"{self.directory}: no readable manifest.json ({exc})") from exc
        lib = str(self.directory / self.manifest["library"])
        self.functions = {name: ca.external(info["symbol"], lib)
                          for name, info in self.manifest["functions"].items()}

    def parameters_of(self, arm: Arm) -> np.ndarray:
        """p for `arm` in this parametric library's order; ValueError naming the parameter if the
        arm is not of the library's family (a number where the family has a zero)."""
        info = self.manifest.get("parameters")
        if not info:
            raise InvalidArgument(f"{self.directory}: not a parametric library (rscasadi codegen --parametric)")
        names, values = arm.parameters()
        value = dict(zip(names, values.tolist()))
        missing = [k for k in info["names"] + info.get("zero", []) if k not in value]
        if missing:
            raise InvalidArgument(f"{arm.model.path}: has no parameter {missing[0]!r} of the library in {self.directory}")
        for k in info.get("zero", []):
            if value[k] != 0:
                raise InvalidArgument(f"{arm.model.path}: parameter {k!r} is {value[k]:g}, but the library in "
                                 f"{self.directory} folds it to 0 (its family); generate one with --parametric all")
        for k, like in info.get("tied", {}).items():
            if value[k] != value[like]:
                raise InvalidArgument(f"{arm.model.path}: parameter {k!r} is {value[k]:g}, not {like!r} "
                                 f"({value[like]:g}): the library in {self.directory} keeps that rotor balanced "
                                 "(its family); generate one with --parametric all")
        return np.array([value[k] for k in info["names"]])

    def __getitem__(self, name) -> ca.Function:
        return self.functions[name]

    def __iter__(self):
        return iter(self.functions)


def load_compiled(directory) -> Compiled:
    """Load DIR/manifest.json's library back through casadi.external."""
    return Compiled(directory)


class CompiledFeedforward(CompiledController):
    """The guarded feedforward of a generated (constant) arm library through ctypes, its ff_t in
    memory this object owns: init(theta_d, dtheta_d, ddtheta_d) -> tau (ControllerError if
    refused), step(theta_d, dtheta_d, ddtheta_d, h) -> (tau, code): the controllers' failure policy
    (templates/rscasadi_feedforward.h)."""

    CODES = {0: "ok", 2: "FF_NOT_FINITE", 3: "FF_FAILED", 5: "FF_BAD_ARGUMENT", 7: "FF_BAD_REFERENCE",
             8: "FF_NOT_INITIALISED"}

    def __init__(self, directory):
        manifest = json.loads((Path(directory) / "manifest.json").read_text())
        if not manifest.get("controllers", {}).get("feedforward"):
            raise ControllerError(f"{directory}: a parametric library has no guarded feedforward")
        n = manifest["functions"]["feedforward_init"]["inputs"][0]["rows"]
        prefix = f"{manifest['prefix']}_" if manifest.get("prefix") else ""
        super().__init__(directory, f"{prefix}ff", sizes={"theta_d": n, "dtheta_d": n, "ddtheta_d": n, "tau": n})
        self._step = getattr(self.lib, f"{prefix}ff_step")
        self._step.argtypes = [ctypes.c_void_p] + [ctypes.POINTER(ctypes.c_double)] * 3 + [ctypes.c_double,
                                                                                           ctypes.POINTER(ctypes.c_double)]

    def _sample(self, theta_d, dtheta_d, ddtheta_d):
        return [self.ptr(self.array(k, v)) for k, v in zip(("theta_d", "dtheta_d", "ddtheta_d"), (theta_d, dtheta_d, ddtheta_d))]

    def init(self, theta_d, dtheta_d, ddtheta_d) -> np.ndarray:  # type: ignore[override]  # from a reference sample
        tau = np.zeros(self.sizes["tau"])
        self.started(self._init(self.c, *self._sample(theta_d, dtheta_d, ddtheta_d), self.ptr(tau)))
        return tau

    def step(self, theta_d, dtheta_d, ddtheta_d, h: float):
        if not isinstance(h, (int, float, np.integer, np.floating)) or isinstance(h, bool):
            raise ControllerError(f"{self.stem}: h must be a number of seconds, got {h!r}")
        tau = np.zeros(self.sizes["tau"])
        return tau, self._step(self.c, *self._sample(theta_d, dtheta_d, ddtheta_d), float(h), self.ptr(tau))
