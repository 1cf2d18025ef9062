"""Ctrl-C and SIGTERM inside a solver or a write.  While IPOPT runs, CasADi catches the
KeyboardInterrupt that Python raises and IPOPT returns (`NonIpopt_Exception_Thrown` or
`User_Requested_Stop`) as if it had merely failed; the caller must stop too, not take the stop
for a result.  `install()` puts SIGINT and SIGTERM handlers in place that remember the signal
and raise KeyboardInterrupt (as Python's own SIGINT handler does), so that every `finally` runs
(temporary directories are removed, nothing half-written is kept) and `raise_if_interrupted` can
tell an interrupt from a failure; `terminated()` tells a SIGTERM from a Ctrl-C.

A command (`install(command=True)`) owns its process: from the first signal on, what native
libraries print about the evaluation the signal broke into (SUNDIALS' "rhs failed:
KeyboardInterrupt", CasADi's dump of the function's inputs) goes to /dev/null and the command's
own last line goes through `say` to the real stderr; a second signal ends the process at once."""
from __future__ import annotations

import os
import signal

_state: dict = {"interrupted": False, "terminated": False, "command": False, "stderr": -1}


def _handler(signum, frame):
    if _state["interrupted"] and _state["command"]:
        os._exit(143 if _state["terminated"] or signum == signal.SIGTERM else 130)
    _state["interrupted"] = True
    _state["terminated"] = _state["terminated"] or signum == signal.SIGTERM
    if _state["command"] and _state["stderr"] < 0:
        _state["stderr"] = os.dup(2)
        quiet = os.open(os.devnull, os.O_WRONLY)
        os.dup2(quiet, 2)
        os.close(quiet)
    raise KeyboardInterrupt


def say(line: str):
    """Write one line to the user's stderr (the real one, also after a command's first signal)."""
    fd = _state["stderr"] if _state["stderr"] >= 0 else 2
    os.write(fd, (line + "\n").encode())


def install(command: bool = False):
    """Remember every Ctrl-C and SIGTERM from now on (the command line does this at its start,
    with command=True: see the module's note)."""
    _state["command"] = _state["command"] or command
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
