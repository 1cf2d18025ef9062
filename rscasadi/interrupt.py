"""Ctrl-C and SIGTERM inside a solver or a write.  While IPOPT runs, CasADi catches the
KeyboardInterrupt that Python raises and IPOPT returns (`NonIpopt_Exception_Thrown` or
`User_Requested_Stop`) as if it had merely failed; the caller must stop too, not take the stop
for a result.  `install()` puts SIGINT and SIGTERM handlers in place that remember the signal
and raise KeyboardInterrupt (as Python's own SIGINT handler does), so that every `finally` runs
(temporary directories are removed, nothing half-written is kept) and `raise_if_interrupted` can
tell an interrupt from a failure; `terminated()` tells a SIGTERM from a Ctrl-C."""
from __future__ import annotations

import signal

_state = {"interrupted": False, "terminated": False}


def _handler(signum, frame):
    _state["interrupted"] = True
    _state["terminated"] = _state["terminated"] or signum == signal.SIGTERM
    raise KeyboardInterrupt


def install():
    """Remember every Ctrl-C and SIGTERM from now on (the command line does this at its start)."""
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _handler)
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, _handler)


def happened() -> bool:
    """Whether Ctrl-C or SIGTERM came since `install()` (and was not yet raised by raise_if_interrupted)."""
    return _state["interrupted"]


def terminated() -> bool:
    """Whether the signal that came was SIGTERM."""
    return _state["terminated"]


def raise_if_interrupted(stats: dict):
    """KeyboardInterrupt if the solve that produced `stats` was stopped by the user."""
    if _state["interrupted"] or stats.get("return_status") == "User_Requested_Stop":
        _state["interrupted"] = False                  # told once
        raise KeyboardInterrupt
