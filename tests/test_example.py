"""The example C controller: builds with -Werror, runs, equals its Python twin, valgrind-clean."""
import shutil
import subprocess

import numpy as np
import pytest

import rscasadi
from conftest import ROOT, build_example, cc

pytestmark = pytest.mark.skipif(cc() is None, reason="no C compiler")
PERIOD, KP, KD, H = 2.0, 0.5, 0.05, 1e-3


@pytest.fixture(scope="module")
def controller(built, tmp_path_factory):
    return build_example("controller", tmp_path_factory.mktemp("example") / "controller", {built[0]: "rscasadi_arm"})


@pytest.fixture(scope="module")
def controller7(panda_built, tmp_path_factory):
    """The same source built on the Panda's library: ARM_NQ = 7."""
    return build_example("controller", tmp_path_factory.mktemp("example") / "controller7", {panda_built: "rscasadi_arm"})


def amplitudes(n):
    return np.array([(0.5 + 0.1 * (i % 3)) * (-1.0 if i % 3 == 2 else 1.0) for i in range(n)])


def python_twin(arm, seconds):
    """The same loop as examples/controller.c, on the symbolic Functions."""
    from rscasadi.codegen import step_functions
    inv, kk, (step, _) = arm.inverse_dynamics(), arm.model.column("k1"), step_functions(arm)
    n, A = arm.n, amplitudes(arm.n)
    w = 2 * 3.14159265358979323846 / PERIOD

    def desired(t):
        return A * (1 - np.cos(w * t)), A * w * np.sin(w * t), A * w * w * np.cos(w * t)
    th, dth, ddth = desired(0.0)
    T = np.array(inv(th, th, dth, dth, ddth, ddth)[1]).ravel()
    x, rows = np.concatenate([th, th + T / kk, np.zeros(2 * n)]), []
    for k in range(int(seconds / H + 0.5)):
        th, dth, ddth = desired(k * H)
        T = np.array(inv(th, th, dth, dth, ddth, ddth)[1]).ravel()
        ph = th + T / kk
        tau = np.array(inv(th, ph, dth, dth, ddth, ddth)[0]).ravel()
        tau -= KP * (ph - x[n:2 * n]) + KD * (dth - x[3 * n:])
        if k % 10 == 0:
            rows.append(np.concatenate([[k * H], x[:n], tau]))
        x = np.array(step(x, tau, H)).ravel()
    return np.array(rows)


def c_rows(exe, seconds):
    run = subprocess.run([str(exe), seconds], capture_output=True, text=True, check=True)
    lines = run.stdout.splitlines()
    return np.array([[float(v) for v in line.split()] for line in lines if not line.startswith("#")]), \
        float(lines[-1].split("=")[1].split()[0])


def test_example_equals_python(controller, arm3):
    rows, max_err = c_rows(controller, "2.0")
    py_rows = python_twin(arm3, 2.0)
    assert rows.shape == py_rows.shape == (200, 7)
    assert np.max(np.abs(rows - py_rows)) < 1e-9
    assert np.ptp(rows[:, 2]) > 1.0, "the shoulder pitch must actually move"
    assert max_err < 0.01                       # feedforward + small PD tracks within 10 mrad


def test_the_same_source_runs_a_7_joint_arm(controller7):
    """Built on the Panda's header the example is a 7-joint controller (ARM_NQ, ARM_K1): its
    rows have 1 + 2 * 7 numbers and equal the Python twin on the Panda."""
    panda = rscasadi.load(ROOT / "problems" / "panda_sea.toml")
    rows, max_err = c_rows(controller7, "0.3")
    py_rows = python_twin(panda, 0.3)
    assert rows.shape == py_rows.shape == (30, 15)
    assert np.max(np.abs(rows - py_rows)) < 1e-8 * max(1.0, np.abs(py_rows).max())
    assert max_err < 0.05


@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind not installed")
def test_example_is_valgrind_clean(controller):
    run = subprocess.run(["valgrind", "-q", "--error-exitcode=9", "--leak-check=full", str(controller), "0.1"],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert "ERROR SUMMARY" not in run.stderr or "0 errors" in run.stderr


def test_example_usage_errors(controller):
    run = subprocess.run([str(controller), "1", "2"], capture_output=True, text=True)
    assert run.returncode == 2 and "usage" in run.stderr
    run = subprocess.run([str(controller), "np.float64(1.0)"], capture_output=True, text=True)
    assert run.returncode == 2 and "SECONDS" in run.stderr and run.stdout == ""
