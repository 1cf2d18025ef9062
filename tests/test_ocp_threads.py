"""The compiled NLP's loops over the intervals run on OpenMP threads ([solver] threads).  Each
interval's work is independent, the condensing kernel's cache is per thread and interval, and
the static schedule runs interval k on the same thread at every call: the iterates must not
depend on the number of threads.  A race (shared work arrays, a cache entry written by two
threads) would show as different iterates; a library that is not parallel at all would make
that comparison empty, so that is checked too."""
import multiprocessing

import numpy as np
import pytest

from rscasadi.native.build import compiler
from rscasadi.native.parallel import openmp_flags, set_threads
from rscasadi.ocp import load_problem, solve_once
from rscasadi.ocp.sweep import point_problem
from rscasadi.model.modelfile import ModelFileError

from conftest import problem, raw_solve


@pytest.mark.parametrize("case,over", [
    ("condensed_fatrop", {}),
    ("lifted_fatrop", {"transcription": {"condense": False}}),          # SX stage functions mapped
    ("condensed_ipopt", {"solver": {"name": "ipopt"}}),
    ("min_time_fatrop", {"objective": "min_time", "max_duration": 5.0}),
])
def test_the_number_of_threads_changes_no_iterate(pitch_arm, monkeypatch, case, over):
    tr = {"intervals": 17, "compiled": True, **over.get("transcription", {})}      # 17: uneven splits
    path = problem(pitch_arm, f"threads_{case}.toml", **{**over, "transcription": tr})
    out = {}
    for threads in (1, 2, 3):
        p = load_problem(path).replace(threads=threads)
        sol, raw = raw_solve(monkeypatch, p)
        assert sol["success"], sol["status"]
        assert sol["threads"] == threads
        out[threads] = sol, raw
    (a, ra) = out[1]
    for threads in (2, 3):
        b, rb = out[threads]
        assert a["iterations"] == b["iterations"]
        for key in ("x", "lam_g", "lam_x"):
            scale = max(1.0, np.max(np.abs(ra[key])))
            assert np.max(np.abs(ra[key] - rb[key])) <= 1e-12 * scale, (threads, key)


def test_the_compiled_nlp_really_runs_on_threads(pitch_arm):
    # the machines we support have gcc with OpenMP: without it the comparison above is empty
    from rscasadi.ocp.fatrop.driver import driver_library
    assert openmp_flags(tuple(compiler())) == ("-fopenmp",)
    assert set_threads(2) == 2
    path = problem(pitch_arm, "threads_lib.toml", transcription={"intervals": 17, "compiled": True})
    sol = solve_once(load_problem(path).replace(threads=2), print_level=0, log=lambda m: None)
    assert sol["success"] and sol["threads"] == 2 and sol["interface"] == "direct"
    with open(driver_library(lambda m: None), "rb") as fh:   # the driver evaluates the intervals' pieces
        assert b"GOMP_parallel" in fh.read()                # in an OpenMP loop


@pytest.mark.parametrize("value", [-1, 1.5, "four", True])
def test_bad_threads_are_named(pitch_arm, value):
    path = problem(pitch_arm, "threads_bad.toml", solver={"threads": value})
    with pytest.raises(ModelFileError, match=r"threads_bad.toml.*solver\.threads.*integer >= 0"):
        load_problem(path)


def test_threads_default_to_one_and_sweep_points_to_one(pitch_arm):
    p = load_problem(problem(pitch_arm, "threads_default.toml"))
    assert p.solver.threads == 1
    assert point_problem(p.replace(threads=0), {"duration": 1.2}).solver.threads == 1   # not every core
    assert point_problem(p.replace(threads=2), {"duration": 1.2}).solver.threads == 2


def _solve_in_child(path, threads):
    sol = solve_once(load_problem(path).replace(threads=threads), print_level=0, log=lambda m: None)
    return sol["status"], sol["threads"]


def test_a_child_forked_after_a_threaded_solve_solves_on_one_thread(pitch_arm):
    # GNU OpenMP's thread pool does not survive fork(): a child forked after a solve on 2 threads
    # hangs in its own next solve on 2 (measured: without the guard in parallel.set_threads this
    # times out). The child asks for 2 and runs on one; on one, no pool is needed.
    path = problem(pitch_arm, "threads_fork.toml", transcription={"intervals": 17, "compiled": True})
    assert solve_once(load_problem(path).replace(threads=2), print_level=0, log=lambda m: None)["threads"] == 2
    with multiprocessing.get_context("fork").Pool(1) as pool:
        assert pool.apply_async(_solve_in_child, (path, 2)).get(timeout=60) == ("Solve_Succeeded", 1)


_IDLE = """
import json, os, sys, time, ctypes
from rscasadi.native.parallel import set_threads
threads = set_threads(2)
left = os.environ.get("GOMP_SPINCOUNT")
lib = ctypes.CDLL(sys.argv[1])            # a parallel region per call (parallel._PROBE)
lib.rsc_probe()
cpu0 = time.process_time()
for _ in range(60):                       # a solver's rhythm: a loop, then serial work elsewhere
    lib.rsc_probe()
    time.sleep(0.004)
print(json.dumps({"threads": threads, "cpu": time.process_time() - cpu0, "left": left}))
"""


def test_idle_openmp_threads_sleep_soon_unless_the_user_says_otherwise(tmp_path):
    """Where rscasadi loads GNU OpenMP (set_threads) its idle threads spin SPIN_COUNT times, not
    300 000, before they sleep (measured: a busy core elsewhere doubled a 2-thread solve with the
    default): between 60 parallel regions 4 ms apart the process burns several times less CPU than
    with the user's GOMP_SPINCOUNT=300000, which is obeyed; nothing is left in the environment."""
    import json
    import os
    import subprocess
    import sys

    from rscasadi.native.parallel import _PROBE
    if not openmp_flags(tuple(compiler())):
        pytest.skip("no OpenMP in this compiler")
    (tmp_path / "probe.c").write_text(_PROBE)
    lib = tmp_path / "probe.so"
    subprocess.run([*compiler(), "-fopenmp", "-fPIC", "-shared", str(tmp_path / "probe.c"), "-o", str(lib)], check=True)
    env = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}

    def idle(**extra):
        run = subprocess.run([sys.executable, "-c", _IDLE, str(lib)], env={**env, **extra}, capture_output=True,
                             text=True, check=True)
        return json.loads(run.stdout.strip().splitlines()[-1])
    ours, theirs = idle(), idle(GOMP_SPINCOUNT="300000")
    assert ours["threads"] == theirs["threads"] == 2
    assert ours["left"] is None and theirs["left"] == "300000"
    assert ours["cpu"] * 3 < theirs["cpu"], (ours, theirs)
