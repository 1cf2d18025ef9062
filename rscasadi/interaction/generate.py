"""The interaction controllers as C: the momentum observer (`rscasadi controller observer MODEL
--gain K --out DIR`) and the impedance controller (`rscasadi controller impedance MODEL --frame F
| --joint-space --out DIR`), through the one controller pipeline (rscasadi.native.generate):
their CasADi Functions generated to C, the code around them from the template files in
`templates/` (the state in a caller's struct), and a manifest."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from rscasadi.dynamics.arm import Arm, load
from rscasadi.files import safe_name
from rscasadi.interaction.observer import observer_terms
from rscasadi.dynamics.statics import holding_torque
from rscasadi.model.limits import limit_arrays, measurement_bounds, torque_bounds
from rscasadi.interaction.impedance import impedance_boxes
from rscasadi.native.controller import DAMPING_RATIO_BOUND, STIFFNESS_BOUND, boxes, c_numbers, c_words
from rscasadi.native.generate import function_name, write_controller
from rscasadi.native.loader import CompiledController
from rscasadi.errors import InvalidArgument
from rscasadi.model.kinds import require_sea

TEMPLATES = Path(__file__).with_name("templates")


def _model_name(arm: Arm) -> str:
    """The model file's name for a C comment: only characters that cannot end one."""
    return safe_name(Path(str(arm.model.path)).name)


def generate_observer(model, out, gain, sample_time: float = 1e-3, threshold: float = np.inf, opt: str = "-O2",
                      log=print, prefix: str = "") -> dict:
    """Write the observer's C, header, library and manifest for `model` (a model file or an Arm)
    into `out` (whole or not at all): gain K (1/s, one number or 2n) at `sample_time` (s), the
    collision flag above `threshold` (N m, any link); `prefix`: before every C symbol and file
    (rscasadi.native.generate.symbols)."""
    arm = model if isinstance(model, Arm) else load(model)
    require_sea(arm.model, "the observer")
    n = arm.n
    K = np.broadcast_to(np.asarray(gain, float), (2 * n)).copy()
    if not np.all(np.isfinite(K)) or not np.all(K > 0) or not (sample_time > 0) or K.max() * sample_time >= 1.0:
        raise InvalidArgument(f"observer: gain {gain!r} 1/s and sample time {sample_time!r} s need K > 0 and K dt < 1")
    header = {"model": _model_name(arm), "n": n, "nq": 2 * n, "nx": 4 * n, "dt": repr(float(sample_time)),
              "gain": ", ".join(f"{k:g}" for k in np.unique(K))}
    if not threshold > 0:
        raise InvalidArgument(f"observer: --threshold {threshold!r} N m must be > 0")
    header["threshold"] = f"{threshold:g}" if np.isfinite(threshold) else "none (INFINITY)"
    x_lo, x_hi = measurement_bounds(arm.model)
    box = {"x_lo": x_lo, "x_hi": x_hi, "tau_lo": -torque_bounds(arm.model), "tau_hi": torque_bounds(arm.model)}
    header.update(boxes(box, words=True))
    body = {"dt": repr(float(sample_time)), "gains": ", ".join(repr(float(k)) for k in K),
            "threshold": repr(float(threshold)) if np.isfinite(threshold) else "INFINITY", **boxes(box)}
    manifest = {"model": str(arm.model.path),
                "api": {"sizeof": [], "init": ["obs", "x_measured"], "step": ["obs", "x_measured", "tau_applied", "r_out"],
                        "step_seconds": ["obs"]},
                "sizes": {"x": 4 * n, "tau": n, "r": 2 * n}, "gain": K.tolist(), "sample_time": sample_time,
                "threshold": threshold if np.isfinite(threshold) else None,
                "guard": {k: v.tolist() for k, v in box.items()}}
    return write_controller("observer", prefix, [observer_terms(arm, function_name("observer", prefix, "terms"))],
                            TEMPLATES, header, body, out, [opt, "-std=c99"], manifest, log)


def generate_impedance(model, out, frame: str | None, design: str = "motor", opt: str = "-O2", log=print,
                       prefix: str = "") -> dict:
    """Write the impedance controller's C, header, library and manifest for `model` into `out`
    (whole or not at all): Cartesian at `frame`, or in joint space when frame is None; `design`
    "motor" (passive) or "link" (as `impedance_law`); `prefix`: before every C symbol and file
    (rscasadi.native.generate.symbols)."""
    from rscasadi.interaction.impedance import impedance_law
    from rscasadi.model.checks import identifier
    arm = model if isinstance(model, Arm) else load(model)
    require_sea(arm.model, "the impedance controller")
    if frame is not None and frame not in arm.frames():
        raise InvalidArgument(f"--frame: {arm.model.path} has no frame {frame!r} (frames: {', '.join(arm.frames())})")
    if design not in ("motor", "link"):
        raise InvalidArgument(f"--design {design!r}: choose motor or link")
    n = arm.n
    nref, nk = (12, 6) if frame is not None else (n, n)
    limits = limit_arrays(arm.model)["tau"]
    box = impedance_boxes(arm.model, frame)
    texts = {"motor": "on motor positions, q_bar(phi) solves phi = q_bar + psi(T(q_bar)) and\n"
                      " * the motors ask the springs for T(q_bar) - D dphi: passive, and at rest the stiffness seen\n"
                      " * is the commanded one, the springs' compliance included.",
             "link": "on the measured link angles, the springs are asked for T(theta) - D dtheta\n"
                     " * by a torque loop: stiffer than the springs allow the passive design, not shown passive."}
    cartesian = frame is not None
    header = {"model": _model_name(arm), "n": n, "nx": 4 * n, "nref": nref, "nk": nk, "design": design,
              "design_text": texts[design], "space": "Cartesian" if cartesian else "joint-space",
              "at": f" at frame {identifier(frame)}" if cartesian else "",
              "reference": "p (3, world, m) then R (9, column-major)" if cartesian else f"q_desired ({n}, rad)",
              "stiffness": (f"translational N/m (3), rotational N m/rad (3{'' if n >= 6 else '; not used below 6 joints'})"
                            if cartesian else f"N m/rad ({n})"),
              "nref_k": nk, "tau_limits": c_words(limits), "k_max": f"{STIFFNESS_BOUND:g}",
              "z_max": f"{DAMPING_RATIO_BOUND:g}", **boxes({k: box[k] for k in ("x_lo", "x_hi", "ref_lo", "ref_hi")}, True)}
    body = {"limits": c_numbers(limits), "passive": int(design == "motor"), **boxes(box)}
    reference = "pose_desired" if cartesian else "q_desired"
    manifest = {"model": str(arm.model.path), "frame": frame, "design": design,
                "api": {"sizeof": [], "init": ["c", "x_measured"],
                        "step": ["c", "x_measured", reference, "stiffness", "damping_ratio", "tau_out"],
                        "step_seconds": ["c"]},
                "sizes": {"x": 4 * n, reference: nref, "stiffness": nk, "damping_ratio": nk, "tau": n},
                "guard": {k: v.tolist() for k, v in box.items()}}
    name = lambda what: function_name("impedance", prefix, what)
    return write_controller("impedance", prefix, [impedance_law(arm, frame, design=design, name=name("law")),
                                                  holding_torque(arm, name("hold"))],
                            TEMPLATES, header, body, out, [opt, "-std=c99"], manifest, log)


class CompiledObserver(CompiledController):
    """One generated observer through ctypes, its `observer_t` in memory this object owns:
    init(x) -> 0 (ControllerError if refused), step(x, tau) -> (r, code)."""

    CODES = {0: "ok", 1: "OBSERVER_COLLISION", 2: "OBSERVER_NOT_FINITE", 3: "OBSERVER_FAILED",
             5: "OBSERVER_BAD_ARGUMENT", 6: "OBSERVER_BAD_MEASUREMENT", 7: "OBSERVER_BAD_TORQUE",
             8: "OBSERVER_NOT_INITIALISED"}

    def __init__(self, directory):
        super().__init__(directory, "observer")

    def step(self, x, tau):
        x, tau = self.array("x", x), self.array("tau", tau)
        r = np.zeros(self.sizes["r"])
        return r, getattr(self.lib, f"{self.stem}_step")(self.c, self.ptr(x), self.ptr(tau), self.ptr(r))


class CompiledImpedance(CompiledController):
    """One generated impedance controller through ctypes: init(x) -> 0 (ControllerError if
    refused), step(x, reference, stiffness, damping_ratio) -> (tau, code)."""

    CODES = {0: "ok", 2: "IMPEDANCE_NOT_FINITE", 3: "IMPEDANCE_FAILED", 4: "IMPEDANCE_TOO_STIFF",
             5: "IMPEDANCE_BAD_ARGUMENT", 6: "IMPEDANCE_BAD_MEASUREMENT", 7: "IMPEDANCE_BAD_REFERENCE",
             8: "IMPEDANCE_NOT_INITIALISED"}

    def __init__(self, directory):
        super().__init__(directory, "impedance")
        self.reference = "pose_desired" if "pose_desired" in self.sizes else "q_desired"

    def step(self, x, reference, stiffness, damping_ratio):
        args = [self.array(name, v) for name, v in
                zip(("x", self.reference, "stiffness", "damping_ratio"), (x, reference, stiffness, damping_ratio))]
        tau = np.zeros(self.sizes["tau"])
        return tau, getattr(self.lib, f"{self.stem}_step")(self.c, *[self.ptr(a) for a in args], self.ptr(tau))
