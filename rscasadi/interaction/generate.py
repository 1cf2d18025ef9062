"""The interaction controllers as C: the momentum observer (`rscasadi controller observer MODEL
--gain K --out DIR`) and the impedance controller (`rscasadi controller impedance MODEL --frame F
| --joint-space --out DIR`).  Their CasADi Functions generated to C, the code around them from the
template files in `templates/` (the state in a caller's struct), compiled once per source by the
one build step, and described by a manifest."""
from __future__ import annotations

import ctypes
import re
import shutil
import tempfile
from pathlib import Path
from string import Template

import casadi as ca
import numpy as np

from rscasadi.dynamics.arm import Arm, load
from rscasadi.files import fresh_directory, write_json
from rscasadi.interaction.observer import observer_terms
from rscasadi.native.build import cached_library, compiler

TEMPLATES = Path(__file__).with_name("templates")


def _generate(function: ca.Function, stem: str, header: dict, body: dict, out, opt: str, log, manifest: dict) -> dict:
    """The C of `function` (its own file, with a header) and of the templates rscasadi_<stem>.h and
    .c (substituted with `header` and `body`, the work sizes added), compiled once per source by
    the one build step, written into `out` whole with `manifest`."""
    gen = ca.CodeGenerator(f"{function.name()}.c", {"with_header": True})
    gen.add(function)
    with tempfile.TemporaryDirectory() as d:
        gen.generate(d + "/")
        sources = {name: (Path(d) / name).read_text() for name in (f"{function.name()}.c", f"{function.name()}.h")}
    header = {**header, "sz_w": function.sz_w() + 1, "sz_iw": function.sz_iw() + 1}
    sources[f"rscasadi_{stem}.h"] = Template((TEMPLATES / f"rscasadi_{stem}.h").read_text()).substitute(header)
    sources[f"rscasadi_{stem}.c"] = Template((TEMPLATES / f"rscasadi_{stem}.c").read_text()).substitute(body)
    out = Path(out)
    with fresh_directory(out, "manifest.json") as tmp:
        for name, text in sources.items():
            (tmp / name).write_text(text)
        cc = compiler()
        lib = cached_library(sources, [opt, "-std=c99"], name=stem, what=f"the {stem} ({opt})", log=log, cc=cc)
        shutil.copy2(lib, tmp / f"librscasadi_{stem}.so")
        manifest = {**manifest, "header": f"rscasadi_{stem}.h", "library": f"librscasadi_{stem}.so",
                    "sources": sorted(k for k in sources if k.endswith(".c")), "compiler": cc + [opt]}
        write_json(tmp / "manifest.json", manifest, indent=2)
    log(f"wrote {out / f'librscasadi_{stem}.so'}, rscasadi_{stem}.h and manifest.json")
    return manifest


def _model_name(arm: Arm) -> str:
    """The model file's name for a C comment: only characters that cannot end one."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", Path(str(arm.model.path)).name)


def generate_observer(model, out, gain, sample_time: float = 1e-3, threshold: float = np.inf, opt: str = "-O2",
                      log=print) -> dict:
    """Write the observer's C, header, library and manifest for `model` (a model file or an Arm)
    into `out` (whole or not at all): gain K (1/s, one number or 2n) at `sample_time` (s), the
    collision flag above `threshold` (N m, any link)."""
    arm = model if isinstance(model, Arm) else load(model)
    n = arm.n
    K = np.broadcast_to(np.asarray(gain, float), (2 * n)).copy()
    if not np.all(np.isfinite(K)) or not np.all(K > 0) or not (sample_time > 0) or K.max() * sample_time >= 1.0:
        raise ValueError(f"observer: gain {gain!r} 1/s and sample time {sample_time!r} s need K > 0 and K dt < 1")
    header = {"model": _model_name(arm), "n": n, "nq": 2 * n, "nx": 4 * n, "dt": repr(float(sample_time)),
              "gain": ", ".join(f"{k:g}" for k in np.unique(K))}
    if not threshold > 0:
        raise ValueError(f"observer: --threshold {threshold!r} N m must be > 0")
    header["threshold"] = f"{threshold:g}" if np.isfinite(threshold) else "none (INFINITY)"
    body = {"dt": repr(float(sample_time)), "gains": ", ".join(repr(float(k)) for k in K),
            "threshold": repr(float(threshold)) if np.isfinite(threshold) else "INFINITY"}
    manifest = {"model": str(arm.model.path),
                "api": {"observer_sizeof": [], "observer_init": ["obs", "x_measured"],
                        "observer_step": ["obs", "x_measured", "tau_applied", "r_out"],
                        "observer_step_seconds": ["obs"]},
                "sizes": {"x": 4 * n, "tau": n, "r": 2 * n}, "gain": K.tolist(), "sample_time": sample_time,
                "threshold": threshold if np.isfinite(threshold) else None}
    return _generate(observer_terms(arm), "observer", header, body, out, opt, log, manifest)


def generate_impedance(model, out, frame: str | None, design: str = "motor", opt: str = "-O2", log=print) -> dict:
    """Write the impedance controller's C, header, library and manifest for `model` into `out`
    (whole or not at all): Cartesian at `frame`, or in joint space when frame is None; `design`
    "motor" (passive) or "link" (as `impedance_law`)."""
    from rscasadi.interaction.impedance import impedance_law
    from rscasadi.model.checks import identifier
    arm = model if isinstance(model, Arm) else load(model)
    if frame is not None and frame not in arm.frames():
        raise ValueError(f"--frame: {arm.model.path} has no frame {frame!r} (frames: {', '.join(arm.frames())})")
    if design not in ("motor", "link"):
        raise ValueError(f"--design {design!r}: choose motor or link")
    n = arm.n
    nref, nk = (12, 6) if frame is not None else (n, n)
    limits = [jt.limits.get("tau", np.inf) for jt in arm.model.joints]
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
              "nref_k": nk}
    body = {"limits": ", ".join(repr(float(v)) if np.isfinite(v) else "INFINITY" for v in limits),
            "passive": int(design == "motor")}
    reference = "pose_desired" if cartesian else "q_desired"
    manifest = {"model": str(arm.model.path), "frame": frame, "design": design,
                "api": {"impedance_sizeof": [], "impedance_init": ["c", "x_measured"],
                        "impedance_step": ["c", "x_measured", reference, "stiffness", "damping_ratio", "tau_out"],
                        "impedance_step_seconds": ["c"]},
                "sizes": {"x": 4 * n, reference: nref, "stiffness": nk, "damping_ratio": nk, "tau": n}}
    return _generate(impedance_law(arm, frame, design=design), "impedance", header, body, out, opt, log, manifest)


class _Compiled:
    """A generated library through ctypes, its state struct in memory this object owns:
    init(x) -> code, seconds(): the last step's duration measured in C."""

    def __init__(self, directory, stem: str):
        self.lib = ctypes.CDLL(str(Path(directory) / f"librscasadi_{stem}.so"))
        sizeof = getattr(self.lib, f"{stem}_sizeof")
        sizeof.restype = ctypes.c_size_t
        self.state = np.zeros(-(-sizeof() // 8))                       # 8-byte aligned
        self.c = ctypes.c_void_p(self.state.ctypes.data)
        self.p = ctypes.POINTER(ctypes.c_double)
        self._init, self._seconds = getattr(self.lib, f"{stem}_init"), getattr(self.lib, f"{stem}_step_seconds")
        self._seconds.restype = ctypes.c_double

    def _ptr(self, a):
        return a.ctypes.data_as(self.p)

    def init(self, x) -> int:
        return self._init(self.c, self._ptr(np.ascontiguousarray(x, float)))

    def seconds(self) -> float:
        return self._seconds(self.c)


class CompiledObserver(_Compiled):
    """One generated observer through ctypes, its `observer_t` in memory this object owns:
    init(x), step(x, tau) -> (r, flag)."""

    def __init__(self, directory):
        super().__init__(directory, "observer")

    def step(self, x, tau):
        x, tau = np.ascontiguousarray(x, float), np.ascontiguousarray(tau, float)
        r = np.zeros(len(x) // 2)
        return r, self.lib.observer_step(self.c, self._ptr(x), self._ptr(tau), self._ptr(r))


class CompiledImpedance(_Compiled):
    """One generated impedance controller through ctypes: step(x, reference, stiffness,
    damping_ratio) -> (tau, flag)."""

    def __init__(self, directory):
        super().__init__(directory, "impedance")

    def step(self, x, reference, stiffness, damping_ratio):
        args = [np.ascontiguousarray(v, float) for v in (x, reference, stiffness, damping_ratio)]
        tau = np.zeros(len(args[0]) // 4)
        return tau, self.lib.impedance_step(self.c, *[self._ptr(a) for a in args], self._ptr(tau))
