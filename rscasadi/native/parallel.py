"""Threads for generated C: OpenMP, when the C compiler has it.

The NLP's per-interval functions are mapped over the intervals with CasADi's "openmp" map (a
`#pragma omp parallel for`, static schedule: interval k runs on the same thread at every call,
so a per-thread cache keyed by k stays warm); `openmp_flags` says how to compile it, `set_threads`
how many threads the calling thread's next parallel loops use.  Without OpenMP the pragma is
ignored and the loops run serially: same results, one core.

GNU OpenMP's thread pool does not survive fork(): a child forked after a loop on more than one
thread hangs in its own next loop on more than one (measured; on one thread it runs).  So such a
child runs its loops on one thread, whatever it asks for (with a warning).

Between loops GNU OpenMP's idle threads spin GOMP_SPINCOUNT times before they sleep: 300 000 by
default, milliseconds of a core, and a thread that waits at a loop's end for a thread the system
has descheduled spins as long.  A solver's loops come every few milliseconds with serial work
between them, so on a machine with one core busy elsewhere the Panda's minimum-time solve on two
threads took 3.8-4.0 s against 2.0-2.3 s with 10 000 spins (and 2.0-2.2 s on one thread); on a
quiet machine 1.3-1.5 s either way (2026-11-27, 2-core Xeon VM).  So where this process loads
GNU OpenMP (`set_threads`), it does so with SPIN_COUNT spins unless the user set GOMP_SPINCOUNT or
OMP_WAIT_POLICY; the variable is read once, at the load, and is not left in the environment.  A
process that loaded GNU OpenMP before (a threaded MPC controller's library) keeps its setting.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
import subprocess
import tempfile
import warnings
from pathlib import Path

_PROBE = "#include <omp.h>\nint rsc_probe(void) { int n = 0;\n#pragma omp parallel\n n = omp_get_num_threads(); return n; }\n"


@functools.lru_cache(maxsize=None)
def openmp_flags(cc: tuple) -> tuple:
    """("-fopenmp",) if compiler `cc` builds and links an OpenMP shared library, else ()."""
    with tempfile.TemporaryDirectory() as d:
        src = Path(d) / "probe.c"
        src.write_text(_PROBE)
        run = subprocess.run([*cc, "-fopenmp", "-fPIC", "-shared", str(src), "-o", str(Path(d) / "probe.so")],
                             capture_output=True, text=True)
    return ("-fopenmp",) if run.returncode == 0 else ()


def available_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:                              # not Linux
        return os.cpu_count() or 1


SPIN_COUNT = "10000"        # GOMP_SPINCOUNT at the load: tens of microseconds, then the threads sleep


@functools.lru_cache(maxsize=None)
def _runtime():
    name = ctypes.util.find_library("gomp")
    ours = not ({"GOMP_SPINCOUNT", "OMP_WAIT_POLICY"} & set(os.environ))
    if ours:
        os.environ["GOMP_SPINCOUNT"] = SPIN_COUNT
    try:
        for candidate in ([name] if name else []) + ["libgomp.so.1"]:
            try:
                return ctypes.CDLL(candidate)
            except OSError:
                continue
        return None
    finally:
        if ours:
            os.environ.pop("GOMP_SPINCOUNT", None)


_state = {"pool": False, "forked": False}     # this process asked for > 1 thread; forked after that


def _after_fork_in_child():
    _state["forked"] = _state["forked"] or _state["pool"]


if hasattr(os, "register_at_fork"):                # POSIX
    os.register_at_fork(after_in_child=_after_fork_in_child)


def threads_now() -> int:
    """The threads the calling thread's next OpenMP loops use (1 without an OpenMP runtime).  A
    thread's setting is its own: work handed to another thread takes this number with it."""
    omp = _runtime()
    return 1 if omp is None else int(omp.omp_get_max_threads())


def set_threads(n: int) -> int:
    """The threads (n >= 1) the calling thread's OpenMP loops use from now on; returns what the
    runtime will use (1 without an OpenMP runtime, or in a child forked after a threaded loop)."""
    omp = _runtime()
    if omp is None:
        return 1
    if _state["forked"] and n > 1:
        warnings.warn(f"this process was forked after a solve on more than one thread: GNU OpenMP cannot start "
                      f"threads in it, so it solves on one (asked for {n}); spawn processes to use threads there")
        n = 1
    omp.omp_set_num_threads(ctypes.c_int(int(n)))
    got = int(omp.omp_get_max_threads())
    _state["pool"] = _state["pool"] or got > 1
    return got
