"""A generated controller through ctypes: its library and manifest.json, its state struct in
memory this object owns, and every array checked against the manifest's sizes before C sees it
(C cannot tell a short array from a long one: it would read or write past its end)."""
from __future__ import annotations

import ctypes
import json
from pathlib import Path

import numpy as np

from rscasadi.errors import Error

_DP = ctypes.POINTER(ctypes.c_double)


class ControllerError(Error, ValueError):
    """An array of the wrong length or type for a generated controller, a controller that cannot
    be loaded, or an init that C refused (`code`: its return code); the message names the
    argument and the manifest's size, or the code."""

    def __init__(self, message: str, code: int | None = None):
        super().__init__(message)
        self.code = code


class CompiledController:
    """The generated controller in `directory` (its manifest.json names the library): `stem`'s
    (or the manifest's "symbol", the generator's prefix) `<stem>_sizeof`, `<stem>_init`,
    `<stem>_step_seconds`; `self.sizes` from the manifest.
    init(x) -> 0, or ControllerError naming the code C refused it with (the controller stays
    uninitialised); seconds(): the last step's duration in C.  CODES: the return codes' names."""

    CODES: dict = {}

    def __init__(self, directory, stem: str, sizes: dict | None = None):
        directory = Path(directory)
        try:
            self.manifest = json.loads((directory / "manifest.json").read_text())
            self.lib = ctypes.CDLL(str(directory / self.manifest["library"]))
            self.sizes = self.manifest["sizes"] if sizes is None else sizes
            stem = self.manifest.get("symbol", stem)                   # the generator's prefix, if any
            sizeof, self._init = getattr(self.lib, f"{stem}_sizeof"), getattr(self.lib, f"{stem}_init")
        except (OSError, ValueError, KeyError, AttributeError) as exc:
            raise ControllerError(f"{directory}: not a generated controller ({exc})") from None
        self.stem = stem
        sizeof.restype = ctypes.c_size_t
        self.state = np.zeros(-(-sizeof() // 8))                       # 8-byte aligned
        self.c = ctypes.c_void_p(self.state.ctypes.data)
        self._seconds = getattr(self.lib, f"{stem}_step_seconds", None)
        if self._seconds is not None:
            self._seconds.restype = ctypes.c_double

    def array(self, name: str, value, size: int | None = None) -> np.ndarray:
        """`value` as a contiguous float64 array of the manifest's size for `name` (or `size`);
        ControllerError for another length or a type that is not a real number."""
        size = int(np.prod(self.sizes[name])) if size is None else size
        a = np.asarray(value)
        if a.dtype.kind not in "fiu":
            raise ControllerError(f"{self.stem}: {name} must be real numbers, got an array of {a.dtype}")
        a = np.ascontiguousarray(a, dtype=np.float64).ravel()
        if a.size != size:
            raise ControllerError(f"{self.stem}: {name} must have {size} values (manifest.json), got {a.size}")
        return a

    @staticmethod
    def ptr(a: np.ndarray):
        return a.ctypes.data_as(_DP)

    def init(self, x) -> int:
        return self.started(self._init(self.c, self.ptr(self.array("x", x))))

    def started(self, code: int) -> int:
        """0, or ControllerError for an init's nonzero code."""
        if code != 0:
            raise ControllerError(f"{self.stem}_init refused the measurement: {self.CODES.get(code, code)}", code)
        return 0

    def seconds(self) -> float:
        return self._seconds(self.c)
