"""The nonlinear MPC generated to C: equal to its CasADi Function, and better than feedforward +
PD on a plant with a heavier tip and quantised encoders (a short run; the full one is
benchmarks/bench_mpc.py)."""
import numpy as np
import pytest

from rscasadi.cli import main
from rscasadi.control.mpc import CompiledMPC, closed_loop, hold_function, load_mpc_problem, rti_function
from rscasadi.control.ocp import rest_state
from rscasadi.dynamics.arm import load
from rscasadi.model.modelfile import ModelFileError

from conftest import ROOT

PROBLEM = ROOT / "problems" / "mpc_arm3.toml"


@pytest.fixture(scope="module")
def mpc_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("mpc") / "arm3"
    assert main(["mpc", str(PROBLEM), "--out", str(out), "--opt=-O1"]) in (0, None)
    return out


def test_generated_c_equals_the_casadi_function(mpc_dir):
    p = load_mpc_problem(PROBLEM)
    arm = load(p.model_path)
    rti, hold = rti_function(arm, p), hold_function(arm, p)
    c = CompiledMPC(mpc_dir)
    rng = np.random.default_rng(3)
    x = rest_state(arm, [0.1, 0.4, -0.6])
    c.init(x)
    U = np.array(hold(x))
    for _ in range(5):                                   # the C keeps its torque plan between steps
        ref = np.vstack([x[:3, None] + rng.normal(0, 0.05, (3, p.horizon)), rng.normal(0, 0.2, (3, p.horizon))])
        tau_c, _, flag = c.step(x, ref)
        tau_py, U = (np.array(v) for v in rti(x, ref, U))
        assert flag == 0 and np.max(np.abs(tau_c - tau_py.ravel())) < 1e-12
        x = x + rng.normal(0, 1e-3, x.shape)
    assert np.all(np.abs(tau_c) <= np.array([jt.limits["tau"] for jt in arm.model.joints]) + 1e-12)


def test_mpc_beats_feedforward_and_pd_under_mismatch(mpc_dir):
    res = closed_loop(PROBLEM, mpc_dir, duration=0.4, log=lambda m: None)
    mpc, pd = res["MPC (C)"], res["feedforward + PD"]
    assert mpc["max_limit_violation"] == 0.0
    assert mpc["max_error"] < pd["max_error"] / 3            # the full 2 s run: 13x (bench_mpc)
    assert res["feedforward"]["max_error"] > pd["max_error"]  # no feedback: the heavier tip drifts


@pytest.mark.parametrize("text,field", [
    ('model = "arm3.toml"\nhorizon = 0\n', "horizon"),
    ('model = "arm3.toml"\ninterval = -1.0\n', "interval"),
    ('model = "arm3.toml"\n[weights]\nspeed = 1.0\n', "weights.speed"),
    ('model = "arm3.toml"\ncolour = 1\n', "colour"),
])
def test_bad_mpc_problem_names_the_field(tmp_path, text, field):
    path = tmp_path / "bad_mpc.toml"
    path.write_text(text)
    with pytest.raises(ModelFileError, match=rf"bad_mpc\.toml: field '{field}'"):
        load_mpc_problem(path)


@pytest.fixture(scope="module")
def mpc_example(built, mpc_dir, tmp_path_factory):
    import subprocess
    from conftest import cc
    arm_dir, exe = built[0], tmp_path_factory.mktemp("mpc_example") / "mpc_example"
    subprocess.run([cc(), "-std=c99", "-Wall", "-Wextra", "-Werror", "-O2", f"-I{arm_dir}", f"-I{mpc_dir}",
                    str(ROOT / "examples" / "mpc.c"), f"-L{arm_dir}", f"-L{mpc_dir}", "-lrscasadi_arm",
                    "-lrscasadi_mpc", f"-Wl,-rpath,{arm_dir}", f"-Wl,-rpath,{mpc_dir}", "-lm", "-o", str(exe)],
                   check=True)
    return exe


def test_mpc_example_tracks_within_limits(mpc_example):
    import subprocess
    run = subprocess.run([str(mpc_example), "0.01", "1.0"], capture_output=True, text=True, check=True)
    rows = np.array([[float(v) for v in line.split()] for line in run.stdout.splitlines() if not line.startswith("#")])
    assert rows.shape == (100, 7)
    assert np.all(np.abs(rows[:, 4:]) <= np.array([0.6, 0.6, 0.4]) + 1e-12)     # the torque limits
    assert np.ptp(rows[:, 2]) > 0.1, "the shoulder pitch must move"
    max_err = float(run.stdout.splitlines()[-1].split("=")[1].split()[0])
    assert max_err < 1e-3


def test_mpc_example_is_valgrind_clean_and_refuses_bad_arguments(mpc_example):
    import shutil
    import subprocess
    if shutil.which("valgrind") is not None:
        run = subprocess.run(["valgrind", "-q", "--error-exitcode=9", "--leak-check=full", str(mpc_example), "0.01",
                              "0.52"], capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
    run = subprocess.run([str(mpc_example), "fast"], capture_output=True, text=True)
    assert run.returncode == 2 and "argument 1" in run.stderr and run.stdout == ""
