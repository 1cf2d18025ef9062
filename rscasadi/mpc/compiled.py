"""The generated C controller, loaded through ctypes."""
from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np


class CompiledMPC:
    """One generated C controller through ctypes, its `mpc_t` in memory this object owns:
    init(x), step(x, reference) -> (tau, seconds measured in C, flag), step_to(x, target),
    set_payload_mass(m), set_parameters(p), set_posture(theta).  Several may share one library."""

    def __init__(self, directory):
        self.lib = ctypes.CDLL(str(Path(directory) / "librscasadi_mpc.so"))
        self.lib.mpc_step_seconds.restype = ctypes.c_double
        self.lib.mpc_sizeof.restype = ctypes.c_size_t
        self.lib.mpc_set_payload_mass.argtypes = [ctypes.c_void_p, ctypes.c_double]
        self.c_double_p = ctypes.POINTER(ctypes.c_double)
        self.state = np.zeros(-(-self.lib.mpc_sizeof() // 8))       # the mpc_t, 8-byte aligned
        self.c = ctypes.c_void_p(self.state.ctypes.data)

    def _p(self, a):
        return a.ctypes.data_as(self.c_double_p)

    def init(self, x, parameters=None):
        """mpc_init, or mpc_init_parameters with the arm's `parameters` (manifest.json's names)."""
        x = self._p(np.ascontiguousarray(x, float))
        if parameters is None:
            assert self.lib.mpc_init(self.c, x) == 0
        else:
            assert self.lib.mpc_init_parameters(self.c, x, self._p(np.ascontiguousarray(parameters, float))) == 0

    def step(self, x, reference):
        """reference: rows x N, a column per interval end (theta_ref over dtheta_ref; in task
        space p_ref, v_ref [, vec(R_ref)])."""
        return self._call(self.lib.mpc_step, x, np.asarray(reference, float).T.ravel())

    def step_to(self, x, target):
        return self._call(self.lib.mpc_step_to, x, np.asarray(target, float).ravel())

    def set_payload_mass(self, mass: float) -> int:
        return self.lib.mpc_set_payload_mass(self.c, float(mass))

    def set_parameters(self, p) -> int:
        """The arm's parameters (manifest.json "parameters": names in order), from the next step on."""
        return self.lib.mpc_set_parameters(self.c, self._p(np.ascontiguousarray(p, float)))

    def set_posture(self, theta) -> int:
        return self.lib.mpc_set_posture(self.c, self._p(np.ascontiguousarray(theta, float)))

    def _call(self, fn, x, data):
        tau = np.zeros(len(x) // 4)
        x, data = np.ascontiguousarray(x, float), np.ascontiguousarray(data, float)
        flag = fn(self.c, self._p(x), self._p(data), self._p(tau))
        return tau, self.lib.mpc_step_seconds(self.c), flag
