"""Ctrl-C on every long command: one line of ours (CasADi may add its own warning line when
IPOPT is the one interrupted), exit 130, nothing half-written in --out.  (The sweep's own test
is in test_sweep.py.)"""
import os
import signal
import subprocess
import sys

import pytest

from conftest import ROOT

CASES = {                                            # command, a line it prints while working
    "ocp": (["ocp", "problems/ocp_min_effort.toml"], "iter"),
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
