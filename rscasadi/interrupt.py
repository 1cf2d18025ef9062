"""Ctrl-C inside a solver.  While IPOPT runs, CasADi catches the KeyboardInterrupt that Python
raises and IPOPT returns (`NonIpopt_Exception_Thrown` or `User_Requested_Stop`) as if it had
merely failed; the caller must stop too, not take the stop for a result.  `install()` puts a
SIGINT handler in place that remembers the interrupt (and raises KeyboardInterrupt as Python's
own does), so that `raise_if_interrupted` can tell an interrupt from a failure."""
from __future__ import annotations

import signal

_state = {"interrupted": False}


def _handler(signum, frame):
    _state["interrupted"] = True
    raise KeyboardInterrupt


def install():
    """Remember every Ctrl-C from now on (the command line does this at its start)."""
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _handler)


def happened() -> bool:
    """Whether Ctrl-C came since `install()` (and was not yet raised by raise_if_interrupted)."""
    return _state["interrupted"]


def raise_if_interrupted(stats: dict):
    """KeyboardInterrupt if the solve that produced `stats` was stopped by the user."""
    if _state["interrupted"] or stats.get("return_status") == "User_Requested_Stop":
        _state["interrupted"] = False                  # told once
        raise KeyboardInterrupt
