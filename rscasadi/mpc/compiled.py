"""The generated C MPC, loaded through ctypes (native.loader: every array checked against the
manifest's sizes)."""
from __future__ import annotations

import ctypes

import numpy as np

from rscasadi.native.loader import CompiledController, ControllerError

CODES = {0: "ok", 2: "MPC_NOT_FINITE", 3: "MPC_FAILED", 4: "MPC_NO_PAYLOAD", 5: "MPC_BAD_ARGUMENT",
         6: "MPC_BAD_MEASUREMENT", 7: "MPC_BAD_REFERENCE", 8: "MPC_NOT_INITIALISED"}


class CompiledMPC(CompiledController):
    """One generated C controller through ctypes, its `mpc_t` in memory this object owns:
    init(x) -> code, step(x, reference) -> (tau, seconds measured in C, code), or in two phases
    prepare(reference) -> code then feedback(x) -> (tau, seconds, code), step_to(x, target),
    set_payload_mass(m), set_parameters(p), set_posture(theta) -> code.  The codes and what tau
    is then: the header's failure policy (CODES names them).  Several may share one library."""

    CODES = CODES

    def __init__(self, directory):
        super().__init__(directory, "mpc")
        self.fn = {k: getattr(self.lib, f"{self.stem}_{k}") for k in ("init", "init_parameters", "step", "step_to",
                                                                       "step_seconds", "set_payload_mass",
                                                                       "set_parameters", "set_posture", "prepare",
                                                                       "feedback", "feedback_seconds")}
        self.fn["set_payload_mass"].argtypes = [ctypes.c_void_p, ctypes.c_double]
        self.fn["step_seconds"].restype = self.fn["feedback_seconds"].restype = ctypes.c_double
        self.n = self.sizes["tau"]

    def init(self, x, parameters=None) -> int:
        """mpc_init, or mpc_init_parameters with the arm's `parameters` (manifest.json's names):
        0, or ControllerError with the code C refused them with (the controller stays
        uninitialised)."""
        x = self.ptr(self.array("x", x))
        if parameters is None:
            return self.started(self.fn["init"](self.c, x))
        p = self.array("parameters", parameters, len(self.manifest["parameters"]["names"]))
        return self.started(self.fn["init_parameters"](self.c, x, self.ptr(p)))

    def step(self, x, reference):
        """reference: rows x N, a column per interval end (theta_ref over dtheta_ref; in task
        space p_ref, v_ref [, vec(R_ref)])."""
        return self._call(self.fn["step"], x, self._reference(reference))

    def prepare(self, reference) -> int:
        """mpc_prepare: everything of the next step that needs no measurement (the reference as
        in `step`); 0 or a code (the next feedback's)."""
        return self.fn["prepare"](self.c, self.ptr(self._reference(reference)))

    def _reference(self, reference) -> np.ndarray:
        """The reference (rows x N, manifest.json) as C takes it, column after column."""
        rows, N = self.sizes["reference"]
        ref = np.asarray(reference)
        if ref.shape != (rows, N):
            raise ControllerError(f"mpc: reference must be {rows} x {N} (manifest.json), got shape {ref.shape}")
        return self.array("reference", ref.T)

    def feedback(self, x):
        """mpc_feedback: the prepared step from the measured state: (tau, seconds in C, code)."""
        tau = np.zeros(self.n)
        flag = self.fn["feedback"](self.c, self.ptr(self.array("x", x)), self.ptr(tau))
        return tau, self.fn["feedback_seconds"](self.c), flag

    def step_to(self, x, target):
        return self._call(self.fn["step_to"], x, self.array("target", target))

    def set_payload_mass(self, mass: float) -> int:
        if not isinstance(mass, (int, float, np.integer, np.floating)) or isinstance(mass, bool):
            raise ControllerError(f"mpc: the payload's mass must be a number, got {mass!r}")
        return self.fn["set_payload_mass"](self.c, float(mass))

    def set_parameters(self, p) -> int:
        """The arm's parameters (manifest.json "parameters": names in order), from the next step on."""
        return self.fn["set_parameters"](self.c, self.ptr(self.array("parameters", p, len(self.manifest["parameters"]["names"]))))

    def set_posture(self, theta) -> int:
        joints = self.sizes.get("joints", self.n)
        return self.fn["set_posture"](self.c, self.ptr(self.array("theta", theta, joints)))

    def _call(self, fn, x, data):
        tau = np.zeros(self.n)
        x = self.array("x", x)
        flag = fn(self.c, self.ptr(x), self.ptr(data), self.ptr(tau))
        return tau, self.fn["step_seconds"](self.c), flag
