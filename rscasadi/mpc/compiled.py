"""The generated C controller, loaded through ctypes."""
from __future__ import annotations

from pathlib import Path

import numpy as np


class CompiledMPC:
    """The generated C controller through ctypes: init(x), step(x, reference) -> tau, seconds
    (the step's duration measured in C, by mpc_step_seconds), flag."""

    def __init__(self, directory):
        import ctypes
        self.lib = ctypes.CDLL(str(Path(directory) / "librscasadi_mpc.so"))
        self.lib.mpc_step_seconds.restype = ctypes.c_double
        self.c_double_p = ctypes.POINTER(ctypes.c_double)

    def _p(self, a):
        return np.ascontiguousarray(a, float).ctypes.data_as(self.c_double_p)

    def init(self, x):
        assert self.lib.mpc_init(self._p(x)) == 0

    def step(self, x, reference):
        """reference: 2n x N (theta_ref over dtheta_ref, a column per interval end)."""
        return self._call(self.lib.mpc_step, x, np.asarray(reference, float).T.ravel())

    def step_to(self, x, theta_target):
        return self._call(self.lib.mpc_step_to, x, np.asarray(theta_target, float))

    def _call(self, fn, x, data):
        tau = np.zeros(len(x) // 4)
        x, data = np.ascontiguousarray(x, float), np.ascontiguousarray(data, float)
        flag = fn(self._p(x), self._p(data), tau.ctypes.data_as(self.c_double_p))
        return tau, self.lib.mpc_step_seconds(), flag
