"""The example C controller: builds with -Werror, runs, equals its Python twin, valgrind-clean."""
import shutil
import subprocess

import numpy as np
import pytest

from conftest import ROOT, build_example, cc

pytestmark = pytest.mark.skipif(cc() is None, reason="no C compiler")
A, PERIOD, KP, KD, H = np.array([0.5, 0.6, -0.7]), 2.0, 0.5, 0.05, 1e-3


@pytest.fixture(scope="module")
def controller(built, tmp_path_factory):
    return build_example("controller", tmp_path_factory.mktemp("example") / "controller", {built[0]: "rscasadi_arm"})


def k1(arm):
    return [repr(float(v)) for v in arm.model.column("k1")]


def python_twin(arm, seconds):
    """The same loop as examples/controller.c, on the symbolic Functions."""
    from rscasadi.codegen import step_functions
    inv, kk, (step, _) = arm.inverse_dynamics(), arm.model.column("k1"), step_functions(arm)
    w = 2 * 3.14159265358979323846 / PERIOD

    def desired(t):
        return A * (1 - np.cos(w * t)), A * w * np.sin(w * t), A * w * w * np.cos(w * t)
    th, dth, ddth = desired(0.0)
    T = np.array(inv(th, th, dth, dth, ddth, ddth)[1]).ravel()
    x, rows = np.concatenate([th, th + T / kk, np.zeros(6)]), []
    for k in range(int(seconds / H + 0.5)):
        th, dth, ddth = desired(k * H)
        T = np.array(inv(th, th, dth, dth, ddth, ddth)[1]).ravel()
        ph = th + T / kk
        tau = np.array(inv(th, ph, dth, dth, ddth, ddth)[0]).ravel()
        tau -= KP * (ph - x[3:6]) + KD * (dth - x[9:12])
        if k % 10 == 0:
            rows.append(np.concatenate([[k * H], x[:3], tau]))
        x = np.array(step(x, tau, H)).ravel()
    return np.array(rows)


def test_example_equals_python(controller, arm3):
    run = subprocess.run([str(controller), *k1(arm3), "2.0"], capture_output=True, text=True, check=True)
    lines = run.stdout.splitlines()
    c_rows = np.array([[float(v) for v in line.split()] for line in lines if not line.startswith("#")])
    py_rows = python_twin(arm3, 2.0)
    assert c_rows.shape == py_rows.shape == (200, 7)
    assert np.max(np.abs(c_rows - py_rows)) < 1e-9
    assert np.ptp(c_rows[:, 2]) > 1.0, "the shoulder pitch must actually move"
    max_err = float(lines[-1].split("=")[1].split()[0])
    assert max_err < 0.01                       # feedforward + small PD tracks within 10 mrad


@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind not installed")
def test_example_is_valgrind_clean(controller, arm3):
    run = subprocess.run(["valgrind", "-q", "--error-exitcode=9", "--leak-check=full", str(controller),
                          *k1(arm3), "0.1"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert "ERROR SUMMARY" not in run.stderr or "0 errors" in run.stderr


def test_example_usage_errors(controller):
    run = subprocess.run([str(controller)], capture_output=True, text=True)
    assert run.returncode == 2 and "usage" in run.stderr
    run = subprocess.run([str(controller), "1200", "np.float64(1000.0)", "600"], capture_output=True, text=True)
    assert run.returncode == 2 and "argument 2" in run.stderr and run.stdout == ""
