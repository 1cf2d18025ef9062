"""Ctrl-C on every long command: one line of ours (CasADi may add its own warning line when
IPOPT is the one interrupted), exit 130, nothing half-written in --out; nothing the native
libraries print about the evaluation the signal broke into.  (The sweep's own test
is in test_sweep.py.)"""
import os
import signal
import subprocess
import sys

import pytest

from conftest import ROOT

CASES = {                                            # command, a line it prints while working
    "ocp": (["ocp", "problems/ocp_min_effort.toml"], "iter"),
    "ocp replay": (["ocp", "problems/ocp_min_effort.toml"], "total"),     # in SUNDIALS, which prints its own error
    "excite": (["excite", "problems/arm3.toml", "--period", "6", "--harmonics", "3"], "start"),
    "paper": (["paper"], ""),
    "codegen": (["codegen", "problems/panda_sea.toml", "--frames", "panda_link4"], ""),
    "mpc": (["mpc", "problems/mpc_arm3.toml", "--study", "1"], "MPC"),
}


@pytest.mark.parametrize("name", CASES)
def test_ctrl_c_prints_one_line_and_keeps_nothing(name, tmp_path):
    args, marker = CASES[name]
    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, "-m", "rscasadi.cli", *args, "--out", str(out)], cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    for line in p.stdout:
        if marker in line:
            os.killpg(p.pid, signal.SIGINT)
            break
    _, err = p.communicate(timeout=300)
    lines = [ln for ln in err.strip().splitlines() if "KeyboardInterruptException" not in ln]
    assert p.returncode == 130, err
    assert lines == ["rscasadi: interrupted; nothing half-written was kept"], err
    assert not out.exists() or not any(out.iterdir()), sorted(out.rglob("*"))


ENDLESS_FATROP = """
import sys
import rscasadi.ocp.solvers as solvers
plain = solvers.options
def endless(*args, **kwargs):                       # a fatrop solve that would run for an hour
    opts = plain(*args, **kwargs)
    opts["fatrop"].update(tol=1e-300, max_iter=10 ** 6, acceptable_iter=10 ** 6)
    return opts
solvers.options = endless
from rscasadi.cli import entry
entry(sys.argv[1:])
"""


def test_ctrl_c_stops_a_fatrop_solve_within_a_second(tmp_path):
    """The default solver (fatrop through its C interface) in a solve that would not end: Ctrl-C
    at its 20th iteration stops the command within a second, exit 130, one line, nothing kept."""
    import time
    out = tmp_path / "out"
    script = tmp_path / "endless.py"
    script.write_text(ENDLESS_FATROP)
    p = subprocess.Popen([sys.executable, str(script), "ocp", str(ROOT / "problems" / "ocp_min_time.toml"),
                          "--out", str(out)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    for line in p.stdout:
        if line.strip().startswith("20 "):               # fatrop's 20th iteration
            break
    sent = time.perf_counter()
    os.killpg(p.pid, signal.SIGINT)
    try:
        _, err = p.communicate(timeout=60)
    finally:
        p.kill()
    took = time.perf_counter() - sent
    assert p.returncode == 130, err[-2000:]
    assert err.strip().splitlines() == ["rscasadi: interrupted; nothing half-written was kept"], err[-2000:]
    assert took < 5.0, f"stopped {took:.2f} s after Ctrl-C"    # a solve of an hour; 0.02-0.09 s measured
    assert not out.exists() or not any(out.iterdir())
