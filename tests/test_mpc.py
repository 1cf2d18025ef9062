"""The nonlinear MPC generated to C: equal to its CasADi Function, its QP step against an
independent QP solver (qpOASES), better than feedforward + PD on a plant with a heavier tip and
on the true arm when built from the identified model (short runs; the full ones are
benchmarks/bench_mpc.py), and its SQP mode reaching a target pose within the limits."""
import json
import re
import subprocess
import sys

import casadi as ca
import numpy as np
import pytest

from rscasadi.cli import main
import rscasadi.mpc as M
from rscasadi.mpc import CompiledMPC, closed_loop, hold_function, load_mpc_problem, rti_function
from rscasadi.ocp import rest_state
from rscasadi.dynamics.arm import load
from rscasadi.model.modelfile import ModelFileError
from rscasadi.sim.sensors import LINK_COUNTS

from conftest import ROOT

PROBLEM = ROOT / "problems" / "mpc_arm3.toml"


def split_step(arm, p):
    """The generated step's CasADi reference: (x, reference, X, U, params) -> (tau, X_next, U_next)
    through mpc_prepare's and mpc_feedback's Functions (the real-time iteration, split)."""
    from rscasadi.mpc.formulation import feedback_function, prepare_function
    prepare = prepare_function(arm, p)
    feedback = feedback_function(arm, p, prepare)
    return lambda x, ref, X, U, params: feedback(x, X, U, *prepare(ref, X, U, params))


@pytest.fixture(scope="module")
def mpc_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("mpc") / "arm3"          # for any processor: valgrind runs it (test_mpc_example_*)
    assert main(["mpc", str(PROBLEM), "--out", str(out), "--opt=-O1", "--no-native"]) in (0, None)
    return out


def test_generated_c_equals_the_casadi_function(mpc_dir):
    """mpc_step is mpc_prepare then mpc_feedback: the C equals those two CasADi Functions chained."""
    from rscasadi.mpc.formulation import feedback_function, prepare_function
    p = load_mpc_problem(PROBLEM)
    arm = load(p.model)
    prepare, hold = prepare_function(arm, p), hold_function(arm, p)
    feedback = feedback_function(arm, p, prepare)
    c = CompiledMPC(mpc_dir)
    rng = np.random.default_rng(3)
    x = rest_state(arm, [0.1, 0.4, -0.6])
    c.init(x)
    params = x[:3]                                       # the posture: the measured angles at mpc_init
    X, U = (np.array(v) for v in hold(x, params))
    for _ in range(5):                                   # the C keeps its state and torque plans between steps
        ref = np.vstack([x[:3, None] + rng.normal(0, 0.05, (3, p.horizon)), rng.normal(0, 0.2, (3, p.horizon))])
        tau_c, _, flag = c.step(x, ref)
        tau_py, X, U = (np.array(v) for v in feedback(x, X, U, *prepare(ref, X, U, params)))
        assert flag == 0 and np.max(np.abs(tau_c - tau_py.ravel())) < 1e-12
        x = x + rng.normal(0, 1e-3, x.shape)
    assert np.all(np.abs(tau_c) <= np.array([jt.limits["tau"] for jt in arm.model.joints]) + 1e-12)


def test_the_split_iteration_is_the_real_time_iteration_where_the_prediction_holds():
    """Prepared before the measurement (the linearisation at the plan, the measured deviation dx_0
    affine), the step equals the monolithic real-time iteration (linearised at the measured
    rollout) when the measurement is the plan's own start, and differs by O(|dx_0|) otherwise
    (the Gauss-Newton Hessian's point moves): the task-space problem, whose residual is nonlinear."""
    from rscasadi.mpc.formulation import controller_arm, feedback_function, prepare_function
    from rscasadi.mpc.problem import mpc_model
    p = load_mpc_problem(ROOT / "problems" / "mpc_arm3_tool.toml")
    arm = controller_arm(mpc_model(p), p.parametric)
    rti, hold = rti_function(arm, p), hold_function(arm, p)
    prepare = prepare_function(arm, p)
    feedback = feedback_function(arm, p, prepare)
    theta = np.array([0.0, 0.3, -0.5])
    x, params = rest_state(arm, theta), np.r_[theta, 0.05]
    X, U = (np.array(v) for v in hold(x, params))
    tool = np.array(arm.frame_placement("tool")(theta)[1]).ravel()
    ref = np.vstack([np.tile(tool[:, None] + 0.02, (1, p.horizon)), np.zeros((3, p.horizon))])
    d = np.random.default_rng(5).normal(size=x.shape)
    gaps = []
    for scale in (0.0, 1e-3, 1e-4):
        split = [np.array(v) for v in feedback(x + scale * d, X, U, *prepare(ref, X, U, params))]
        whole = [np.array(v) for v in rti(x + scale * d, ref, X, U, params)]
        gaps.append(max(np.max(np.abs(a - b)) for a, b in zip(split, whole)))
    assert gaps[0] < 1e-12 and 0 < gaps[2] < gaps[1] / 5


def test_prepare_then_feedback_is_a_step_and_a_feedback_needs_a_prepare(mpc_dir, arm3):
    """The two phases through C give the step's torque bit for bit; a feedback without a prepare
    since the last returns MPC_NOT_PREPARED (9) with the holding torque, one after a refused
    reference returns MPC_BAD_REFERENCE (7); the next prepared sample is acted on as usual."""
    p = load_mpc_problem(PROBLEM)
    x = rest_state(arm3, [0.1, 0.4, -0.6])
    ref = np.vstack([np.tile(x[:3, None] + 0.05, (1, p.horizon)), np.zeros((3, p.horizon))])
    one, two = CompiledMPC(mpc_dir), CompiledMPC(mpc_dir)
    one.init(x)
    two.init(x)
    for _ in range(3):
        tau_step, _, flag = one.step(x, ref)
        assert two.prepare(ref) == 0
        tau_split, seconds, code = two.feedback(x)
        assert flag == code == 0 and np.array_equal(tau_step, tau_split) and seconds > 0
    tau, _, code = two.feedback(x)
    assert code == 9 and np.all(np.isfinite(tau))
    bad = ref.copy()
    bad[0, 3] = np.nan
    assert two.prepare(bad) == 7 and two.feedback(x)[2] == 7
    assert two.prepare(ref) == 0 and two.feedback(x)[2] == 0


def test_the_riccati_qp_is_the_condensed_one_and_its_c_does_not_grow_with_the_horizon(mpc_dir, arm3, tmp_path):
    """qp = "riccati" (HPIPM's interior-point method on the stage structure) solves the same QP
    as the condensed controller: the same torques to 1e-6 of the limit over 20 samples toward a
    reference within reach (prepare then feedback, the phases apart, each plan carried on); a NaN
    measurement is refused as the condensed one refuses it; HPIPM's BLASFEO calls reached the
    vector kernels in the controller's library.  At 40 intervals (auto: Riccati from 70 torques)
    its C is the size it is at 10, where the condensed QP's grows as N^2, and it tracks."""
    import dataclasses
    p = load_mpc_problem(PROBLEM)
    ric = tmp_path / "riccati"
    said = []
    M.generate_mpc(dataclasses.replace(p, qp="riccati"), ric, opt="-O1", log=said.append)
    x = rest_state(arm3, [0.1, 0.4, -0.6])
    ref = np.vstack([np.tile(x[:3, None] + 0.001, (1, p.horizon)), np.zeros((3, p.horizon))])
    mine, theirs = CompiledMPC(ric), CompiledMPC(mpc_dir)
    assert mine.init(x) == theirs.init(x) == 0
    limit = np.array([jt.limits["tau"] for jt in arm3.model.joints])
    saturated = 0
    for _ in range(20):
        assert mine.prepare(ref) == theirs.prepare(ref) == 0
        (a, _, fa), (b, _, fb) = mine.feedback(x), theirs.feedback(x)
        assert fa == fb == 0 and np.max(np.abs(a - b)) < 1e-6 * np.max(limit), (a, b)
        saturated += int(np.any(np.abs(b) > 0.999 * limit))
    assert saturated == 0                                    # the QP's solution, not only its bounds
    child = ("import ctypes, sys, numpy as np\nfrom rscasadi.mpc import CompiledMPC\nc = CompiledMPC(sys.argv[1])\n"
             "x, ref = np.load(sys.argv[2]), np.load(sys.argv[3])\nassert c.init(x) == 0 and c.step(x, ref)[2] == 0\n"
             "print(ctypes.c_int.in_dll(c.lib, 'rsc_tuned_reached').value)")
    np.save(tmp_path / "x.npy", x)
    np.save(tmp_path / "ref.npy", ref)
    run = subprocess.run([sys.executable, "-c", child, str(ric), str(tmp_path / "x.npy"), str(tmp_path / "ref.npy")],
                         capture_output=True, text=True, timeout=120)    # a fresh process: BLASFEO binds once
    assert run.returncode == 0 and run.stdout.split() == ["1"], run.stderr[-2000:]
    x_bad = x.copy()
    x_bad[2] = np.nan
    mine.prepare(ref)
    theirs.prepare(ref)
    (a, _, fa), (b, _, fb) = mine.feedback(x_bad), theirs.feedback(x_bad)
    assert fa == fb == 6 and np.array_equal(a, b)
    long = dataclasses.replace(p, horizon=40)
    M.generate_mpc(long, tmp_path / "long", opt="-O1", log=said.append)
    assert any("(-O1 -std=c99 -I" in line for line in said)                # HPIPM's headers: auto took Riccati
    size = lambda d: sum(f.stat().st_size for f in d.glob("*.c"))
    assert size(tmp_path / "long") < 1.05 * size(ric), (size(tmp_path / "long"), size(ric))
    res = closed_loop(long, tmp_path / "long", duration=0.3, log=lambda m: None)
    assert res["MPC (C)"]["max_error"] < res["feedforward + PD"]["max_error"]


def _steps(directory, x, ref):
    c = CompiledMPC(directory)
    assert c.init(x) == 0
    return np.array([c.step(x, ref)[0] for _ in range(5)])


def test_the_riccati_preparation_on_threads_changes_no_torque(arm3, tmp_path):
    """threads = 3: the Riccati preparation's loops over the intervals run on OpenMP threads, each
    with its own part of the work arrays. The intervals are independent but for the gaps (a
    sequential pass), so the torques must be those of one thread, bitwise, over a closed loop
    (a race on the work arrays shows as other torques); the library must really be threaded, and
    a process forked after a threaded prepare must still step.
    threads > 1 with the condensed QP is refused, naming the field, before anything is written."""
    import dataclasses
    p = dataclasses.replace(load_mpc_problem(PROBLEM), qp="riccati", horizon=7)       # 7: uneven splits
    for t in (1, 3):
        M.generate_mpc(dataclasses.replace(p, threads=t), tmp_path / f"t{t}", opt="-O1", log=lambda m: None)
    assert json.loads((tmp_path / "t3" / "manifest.json").read_text())["threads"] == 3
    assert b"GOMP_parallel" in (tmp_path / "t3" / "librscasadi_mpc.so").read_bytes()
    assert b"GOMP_parallel" not in (tmp_path / "t1" / "librscasadi_mpc.so").read_bytes()
    assert "#define BLOCKS_APART 1" in (tmp_path / "t3" / "rscasadi_mpc.c").read_text()   # the blocks on threads too
    from rscasadi.ocp.fatrop.driver import casadi_dir
    strict = subprocess.run(["cc", "-std=c99", "-fopenmp", "-Wall", "-Wextra", "-Werror", "-pedantic", "-c",
                             str(tmp_path / "t3" / "rscasadi_mpc.c"), f"-I{tmp_path / 't3'}", f"-I{casadi_dir() / 'include'}",
                             "-o", str(tmp_path / "x.o")], capture_output=True, text=True)
    assert strict.returncode == 0, strict.stderr[-2000:]                 # the threaded template, without a warning
    one = closed_loop(dataclasses.replace(p, threads=1), tmp_path / "t1", duration=0.2, log=lambda m: None,
                      traces=(a := {}))
    three = closed_loop(dataclasses.replace(p, threads=3), tmp_path / "t3", duration=0.2, log=lambda m: None,
                        traces=(b := {}))
    assert one["MPC (C)"]["max_error"] == three["MPC (C)"]["max_error"]
    assert np.array_equal(a["MPC (C)"]["x"], b["MPC (C)"]["x"])              # the torques, through the plant
    # GNU OpenMP's threads do not survive fork(): a child of this process (which prepared on 3
    # threads) steps on one, the same torques, instead of waiting forever
    import multiprocessing
    x = rest_state(arm3, [0.1, 0.4, -0.6])
    ref = np.vstack([np.tile(x[:3, None] + 0.01, (1, p.horizon)), np.zeros((3, p.horizon))])
    here = _steps(tmp_path / "t3", x, ref)
    with multiprocessing.get_context("fork").Pool(1) as pool:
        assert np.array_equal(pool.apply_async(_steps, (tmp_path / "t3", x, ref)).get(timeout=60), here)
    with pytest.raises(ModelFileError, match=r"field 'threads': 2 threads need the Riccati QP"):
        M.generate_mpc(dataclasses.replace(p, qp="condensed", threads=2), tmp_path / "no", log=lambda m: None)
    assert not (tmp_path / "no").exists()


def test_the_blocks_share_the_threads_only_with_the_hpipm_they_were_written_for(tmp_path, monkeypatch):
    """rscasadi_mpc.c's `condense` calls HPIPM's per-block routines as CasADi's HPIPM declares
    them; a header that declares them otherwise (a later HPIPM's d_cond_DCtd takes an m2) or
    none leaves the blocks to HPIPM's own loop (BLOCKS_APART 0) instead of a build failure."""
    import shutil
    from rscasadi.mpc import generate as G
    from rscasadi.ocp.fatrop import driver
    real = driver.casadi_dir()
    assert G.hpipm_blocks_apart()
    (tmp_path / "include").mkdir()
    header = (real / "include" / "hpipm_d_cond_aux.h").read_text()
    later = header.replace("struct blasfeo_dvec *d_mask2, int *idxs_rev2", "struct blasfeo_dvec *d_mask2, struct blasfeo_dvec *m2, int *idxs_rev2")
    assert later != header
    (tmp_path / "include" / "hpipm_d_cond_aux.h").write_text(later)
    monkeypatch.setattr(driver, "casadi_dir", lambda: tmp_path)
    assert not G.hpipm_blocks_apart()
    (tmp_path / "include" / "hpipm_d_cond_aux.h").unlink()
    assert not G.hpipm_blocks_apart()
    shutil.rmtree(tmp_path / "include")


def test_the_riccati_controller_links_the_users_blasfeo_or_refuses_it(arm3, tmp_path, monkeypatch):
    """RSCASADI_BLASFEO=/path (a BLASFEO built for the CPU): the Riccati controller's library
    needs it ahead of the wheel's and leaves out the vector kernels; the torques are the default
    controller's to rounding.  A file that is no BLASFEO is refused before anything is written,
    naming the variable and the file.  The stand-in: the wheel's library under another soname (its
    speed is the benchmark's: benchmarks/bench_mpc_horizon.py)."""
    import dataclasses
    from rscasadi.errors import Failed
    from rscasadi.ocp.fatrop import blasfeo
    p = dataclasses.replace(load_mpc_problem(PROBLEM), qp="riccati")
    monkeypatch.delenv(blasfeo.ENV, raising=False)
    M.generate_mpc(p, tmp_path / "default", opt="-O1", log=lambda m: None)
    user = tmp_path / "libblasfeo.so.9"                 # found at run time by its soname in its directory
    user.write_bytes(blasfeo.wheel_library().read_bytes().replace(b"libblasfeo.so.0\x00", b"libblasfeo.so.9\x00"))
    monkeypatch.setenv(blasfeo.ENV, str(user))
    M.generate_mpc(p, tmp_path / "user", opt="-O1", log=lambda m: None)
    manifest = lambda d: json.loads((tmp_path / d / "manifest.json").read_text())
    assert manifest("user")["blasfeo"] == str(user.resolve()) and "kernels" in manifest("default")["blasfeo"]
    assert not any("blasfeo_kernels" in s for s in manifest("user")["sources"])
    needed = subprocess.run(["readelf", "-d", str(tmp_path / "user" / "librscasadi_mpc.so")], capture_output=True,
                            text=True).stdout
    assert "[libblasfeo.so.9]" in needed and f"runpath: [{user.resolve().parent}:" in needed.lower()
    loads = subprocess.run(["ldd", str(tmp_path / "user" / "librscasadi_mpc.so")], capture_output=True, text=True).stdout
    order = [line.split()[0] for line in loads.splitlines() if "blasfeo" in line]
    assert order[0] == "libblasfeo.so.9" and f"=> {user.resolve()}" in loads    # first in the lookup: its symbols bind
    x = rest_state(arm3, [0.1, 0.4, -0.6])
    ref = np.vstack([np.tile(x[:3, None] + 0.01, (1, p.horizon)), np.zeros((3, p.horizon))])
    a, b = CompiledMPC(tmp_path / "default"), CompiledMPC(tmp_path / "user")
    assert a.init(x) == b.init(x) == 0
    for _ in range(5):
        (ta, _, fa), (tb, _, fb) = a.step(x, ref), b.step(x, ref)
        assert fa == fb == 0 and np.allclose(ta, tb, rtol=1e-9, atol=1e-9)
    bad = tmp_path / "libnot.so"
    bad.write_text("not ELF")
    monkeypatch.setenv(blasfeo.ENV, str(bad))
    with pytest.raises(Failed, match=rf"RSCASADI_BLASFEO={re.escape(str(bad))}: cannot be loaded"):
        M.generate_mpc(p, tmp_path / "bad", opt="-O1", log=lambda m: None)
    assert not (tmp_path / "bad").exists()


def test_a_nan_measurement_keeps_the_plan_and_says_so(mpc_dir, arm3):
    """A NaN in the measured state: MPC_BAD_MEASUREMENT (6), the holding torque of the last good
    state (finite, within the limits), and the next good measurement gets the same torque as if
    the NaN had not come (the fuzz of every controller: test_controller_safety.py)."""
    p = load_mpc_problem(PROBLEM)
    x = rest_state(arm3, [0.1, 0.4, -0.6])
    ref = np.vstack([np.tile(x[:3, None] + 0.05, (1, p.horizon)), np.zeros((3, p.horizon))])
    tau_max = M.limit_arrays(arm3)["tau"]
    runs = []
    for inject in (False, True):
        c = CompiledMPC(mpc_dir)
        c.init(x)
        c.step(x, ref)
        if inject:
            bad = x.copy()
            bad[4] = np.nan
            tau, _, flag = c.step(bad, ref)
            assert flag == 6 and np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= tau_max + 1e-12)
        runs.append(c.step(x, ref))
    assert runs[1][2] == 0
    # the NaN step left the plan untouched: the good step after it is the one without it
    assert np.max(np.abs(runs[0][0] - runs[1][0])) < 1e-12


def _symbolic_qp(arm, p):
    """The condensed QP of problem p on arm as a linearisation of symbols: (lin, limits, (x,
    reference, X, U, posture))."""
    n, N = arm.n, p.horizon
    F, _ = M.interval_functions(arm, p.interval, p.substeps)
    limits = M.limit_arrays(arm)
    xm, ref = ca.MX.sym("x", 4 * n), ca.MX.sym("r", 2 * n, N)
    X, U = ca.MX.sym("X", 4 * n, N + 1), ca.MX.sym("U", n, N)
    posture, mass = ca.MX.sym("posture", n), ca.MX.sym("m", 0)
    lin = M._Linearisation(F, M.stage_residual(arm, p, limits), p, xm, ref, X, U, posture, mass)
    return lin, limits, (xm, ref, X, U, posture)


def _qpoases(H, g, lo, hi, A=None, lba=None, uba=None):
    A = np.zeros((0, H.shape[0])) if A is None else A
    qp = ca.conic("reference", "qpoases", {"h": ca.Sparsity.dense(*H.shape), "a": ca.Sparsity.dense(*A.shape)},
                  {"printLevel": "none"})
    rows = {} if lba is None else {"lba": lba, "uba": uba}
    return np.array(qp(h=H, g=g, a=A, lbx=lo, ubx=hi, **rows)["x"]).ravel()


def test_hard_angle_rows_are_exact_where_they_can_hold_and_least_excess_where_not(tmp_path):
    """The QP of the hard link-angle limits (`angle_limits = "hard"`) on the reference arm with a
    +-0.3 rad shoulder yaw, on cold steps towards targets beyond the range: from rest the rows
    can hold, and the interior-point result equals qpOASES' with the rows as hard constraints
    (the exact penalty is exact); from a fast approach they cannot, and its elastic objective
    (the least excess, then the cost) equals qpOASES' optimum on the elastic QP (whose solution
    is not unique: the saturated torques leave some flat)."""
    from test_limits import arm3_with
    from rscasadi.mpc.formulation import HARD_PRICE
    model = arm3_with(tmp_path, "tau = 0.6, dphi = 4.0, psi = 0.15, theta = [-0.3, 0.3]")
    arm = load(model)
    p = M.MPCProblem(model, horizon=10, interval=0.01, substeps=5, angle_limits="hard", weights={"angle_limits": 0.0})
    n, N = arm.n, p.horizon
    lin, limits, (xm, ref, X, U, posture) = _symbolic_qp(arm, p)
    C, cl, cu = lin.angle_rows(X, limits)
    tm = np.tile(limits["tau"], N)
    lo, hi = -tm - ca.vec(U), tm - ca.vec(U)
    d = M.box_qp(lin.H, lin.g, lo, hi, 30, (C, cl, cu), HARD_PRICE)
    qp = ca.Function("qp", [xm, ref, X, U, posture], [lin.H, lin.g, lo, hi, ca.densify(C), cl, cu, d])
    rows = C.shape[0]
    assert C.shape == (n * N, n * N)                          # a row per joint (each has a range) and interval end
    for start, speed, target, holds in ((0.27, 0.0, 0.6, True), (0.29, 0.0, 0.9, True), (-0.28, 0.0, -0.8, True),
                                        (0.28, 8.0, 0.6, False), (-0.25, -10.0, -0.4, False)):
        x = rest_state(arm, [start, 0.0, 0.0])
        x[2 * n] = x[3 * n] = speed
        Xh, Uh = hold_function(arm, p)(x, x[:n])
        R = np.vstack([np.tile(np.array([target, 0.0, 0.0])[:, None], (1, N)), np.zeros((n, N))])
        H, g, lo_v, hi_v, Cv, cl_v, cu_v, dv = (np.array(v) for v in qp(x, R, Xh, Uh, x[:n]))
        dv = dv.ravel()
        if holds:
            d_ref = _qpoases(H, g, lo_v, hi_v, Cv, cl_v, cu_v)
            assert np.max(np.r_[Cv @ d_ref - cu_v.ravel(), cl_v.ravel() - Cv @ d_ref]) > -1e-9, \
                "the case must press against the range"
        else:
            c = np.max(np.abs(g)) + np.max(np.diag(H))            # box_qp's scaling, and the unit-norm rows
            size = np.linalg.norm(Cv, axis=1)
            Cn, m = Cv / size[:, None], len(g)
            He = np.block([[H / c, np.zeros((m, rows))], [np.zeros((rows, m)), np.zeros((rows, rows))]])
            A = np.block([[Cn, -np.eye(rows)], [Cn, np.eye(rows)]])
            e = _qpoases(He, np.r_[g.ravel() / c, HARD_PRICE * np.ones(rows)], np.r_[lo_v.ravel(), np.zeros(rows)],
                         np.r_[hi_v.ravel(), np.full(rows, np.inf)], A, np.r_[np.full(rows, -np.inf), cl_v.ravel() / size],
                         np.r_[cu_v.ravel() / size, np.full(rows, np.inf)])
            assert np.max(e[m:]) > 1e-3, "the case must be one where the range cannot hold"

            def excess(d):
                return np.maximum(0, np.maximum(Cn @ d - cu_v.ravel() / size, cl_v.ravel() / size - Cn @ d))

            def cost(d):                               # the elastic objective: flat along some torques
                return 0.5 * d @ (H / c) @ d + g.ravel() / c @ d + HARD_PRICE * np.sum(excess(d))
            assert cost(dv) <= cost(e[:m]) * (1 + 1e-9)
            assert np.sum(excess(dv)) == pytest.approx(np.sum(e[m:]), rel=1e-6)
            continue
        assert np.max(np.abs(dv - d_ref)) < 1e-6 * max(1.0, np.max(np.abs(d_ref)))


def test_qp_step_equals_an_active_set_solver_on_a_cold_step_to_a_far_pose(arm3):
    """The condensed QP of the first sample of a step from rest to a far pose (many torque bounds
    active; ill-conditioned): the interior-point iterations land on qpOASES' solution."""
    p = load_mpc_problem(PROBLEM)
    n, N = arm3.n, p.horizon
    lin, limits, (xm, ref, X, U, posture) = _symbolic_qp(arm3, p)
    tm = np.tile(limits["tau"], N)
    lo, hi = -tm - ca.vec(U), tm - ca.vec(U)
    qp = ca.Function("qp", [xm, ref, X, U, posture], [lin.H, lin.g, lo, hi, M.box_qp(lin.H, lin.g, lo, hi, p.qp_iterations)])
    x = rest_state(arm3, [0.0, 0.0, 0.0])
    Xh, Uh = hold_function(arm3, p)(x, x[:n])
    rng = np.random.default_rng(7)
    for target in [[0.6, 0.8, -0.9], [-0.3, 0.2, 0.5]] + [rng.uniform(-1.2, 1.2, 3) for _ in range(6)]:
        R = np.vstack([np.tile(np.array(target)[:, None], (1, N)), np.zeros((n, N))])
        H, g, lo_v, hi_v, d = (np.array(v) for v in qp(x, R, Xh, Uh, x[:n]))
        d_ref = _qpoases(H, g, lo_v, hi_v)
        active = np.sum((d_ref <= lo_v.ravel() + 1e-9) | (d_ref >= hi_v.ravel() - 1e-9))
        assert active >= 3, "the case must exercise the bounds"
        assert np.max(np.abs(d.ravel() - d_ref)) < 1e-6


def test_mpc_beats_feedforward_and_pd_under_mismatch(tmp_path):
    """`rscasadi mpc --study 0.4`: the closed loop on a 20 % heavier tip, its json and figure."""
    import json
    out = tmp_path / "mpc"
    assert main(["mpc", str(PROBLEM), "--out", str(out), "--opt=-O1", "--study", "0.4"]) in (0, None)
    res = json.loads((out / "closed_loop.json").read_text())
    assert (out / "closed_loop.png").stat().st_size > 10_000 and not list(out.glob(".closed_loop*"))
    mpc, pd = res["MPC (C)"], res["feedforward + PD"]
    assert 0 < mpc["step_median_s"] <= mpc["step_worst_s"]                # timed in C (mpc_step_seconds)
    assert mpc["max_limit_violation"] == 0.0
    assert mpc["max_error"] < pd["max_error"] / 3            # the full 2 s run: 13x (bench_mpc)
    assert res["feedforward"]["max_error"] > pd["max_error"]  # no feedback: the heavier tip drifts
    assert np.array(mpc["theta"]).shape == (3, len(mpc["t"])) and mpc["t"][-1] == pytest.approx(0.4)
    assert main(["view", str(out / "closed_loop.json"), "--out", str(tmp_path / "mpc.html")]) in (0, None)
    from rscasadi.view import scene_of                       # the MPC's own run, drawn
    scene = scene_of(out / "closed_loop.json")
    assert scene.times[-1] == pytest.approx(0.4, abs=1 / 30) and np.ptp(scene.poses[:, 3, :3, 3], axis=0).max() > 0.01


def test_mpc_of_the_identified_model_on_the_true_arm(identified, synthetic, tmp_path):
    """Controllers built from the identified model file, the plant the (different) arm that
    produced the logs."""
    true_arm, _ = synthetic
    out = tmp_path / "mpc_identified"
    assert main(["mpc", str(PROBLEM), "--out", str(out), "--opt=-O1", "--model", str(identified / "model.toml")]) in (0, None)
    res = closed_loop(PROBLEM, out, duration=0.4, log=lambda m: None, model=identified / "model.toml", plant=true_arm)
    mpc, pd = res["MPC (C)"], res["feedforward + PD"]
    assert mpc["max_limit_violation"] == 0.0
    # the identified model is close: feedforward + PD tracks within ~8 link encoder counts
    # (9.5e-5 rad); the MPC does no worse, and both stay within 20 counts
    count = 2 * np.pi / LINK_COUNTS
    assert mpc["max_error"] <= pd["max_error"] < 20 * count
    assert res["feedforward"]["max_error"] > mpc["max_error"]      # feedback still matters


def test_sqp_mode_reaches_a_far_target_pose_within_the_limits(tmp_path, arm3):
    """Three SQP iterations with the line search per sample, mpc_step_to a pose 0.6-0.9 rad away
    from rest: settled within 1 s, limits kept (the soft ones within 1 %)."""
    problem = tmp_path / "mpc_sqp.toml"
    problem.write_text(PROBLEM.read_text().replace("sqp_iterations = 1", "sqp_iterations = 3")
                       .replace('"arm3.toml"', f'"{(ROOT / "problems" / "arm3.toml").as_posix()}"')
                       .replace('"trajectory_arm3.toml"', f'"{(ROOT / "problems" / "trajectory_arm3.toml").as_posix()}"'))
    out = tmp_path / "mpc_sqp"
    assert main(["mpc", str(problem), "--out", str(out), "--opt=-O1"]) in (0, None)
    res = M.reach_pose(problem, out, [0.6, 0.8, -0.9], seconds=1.0)
    assert res["final_angle_error"] < 1e-4 and res["final_speed"] < 1e-3
    assert res["max_limit_violation"] < 0.01
    assert np.all(np.abs(res["tau"]) <= M.limit_arrays(arm3)["tau"] + 1e-12)


def test_the_real_time_iteration_keeps_the_speed_limits_one_sample_on(mpc_dir, arm3):
    """mpc_step_to the same far pose with one SQP iteration per sample: the slow-side speed rows
    one sample on (formulation.sample_ahead) keep every limit, where rows at the 10 ms intervals'
    ends alone let each re-plan brake later (9.9 % over); the torques within their limits; the
    C controller holds the rows (its CasADi twin is checked against it elsewhere), and they are
    live: at the state reached at full speed they move the first torque."""
    import casadi as ca
    p = load_mpc_problem(PROBLEM)
    res = M.reach_pose(p, mpc_dir, [0.6, 0.8, -0.9], seconds=1.0)
    assert res["final_angle_error"] < 1e-4 and res["max_limit_violation"] == 0.0
    assert np.all(np.abs(res["tau"]) <= M.limit_arrays(arm3)["tau"] + 1e-12)
    ahead = M.formulation.sample_ahead(arm3, p)
    dphi_max = M.limit_arrays(arm3)["dphi"]
    x = rest_state(arm3, [0.1, 0.2, 0.3])
    x[9:] = 0.95 * dphi_max                                  # the slow-side speeds past 90 % of their limits
    r, Jx, Ju = (np.array(v) for v in ahead(x, np.zeros(3), ca.DM(0, 1)))
    assert r.shape[0] == 3 and np.all(r > 0) and np.all(np.abs(np.diag(Ju)) > 0)
    x[9:] = 0.5 * dphi_max
    assert np.all(np.array(ahead(x, np.zeros(3), ca.DM(0, 1))[0]) == 0)


def test_the_documented_problem_file_is_the_shipped_one(tmp_path):
    """docs/user-guide/mpc.md shows the MPC problem file: every field it names is read, and its
    values are those of problems/mpc_arm3.toml."""
    import dataclasses
    doc = (ROOT / "docs" / "user-guide" / "mpc.md").read_text()
    block = doc.split("**MPC problem**", 1)[1].split("```toml\n", 1)[1].split("```", 1)[0]
    path = tmp_path / "documented.toml"
    path.write_text(block.replace('"arm3.toml"', f'"{(ROOT / "problems" / "arm3.toml").as_posix()}"')
                    .replace('"trajectory_arm3.toml"', f'"{(ROOT / "problems" / "trajectory_arm3.toml").as_posix()}"'))
    documented, shipped = load_mpc_problem(path), load_mpc_problem(PROBLEM)
    assert dataclasses.replace(documented, path=shipped.path) == shipped


@pytest.mark.parametrize("text,field", [
    ('model = "arm3.toml"\nhorizon = 0\n', "horizon"),
    ('model = "arm3.toml"\ninterval = -1.0\n', "interval"),
    ('model = "arm3.toml"\n[weights]\nspeed = 1.0\n', "weights.speed"),
    ('model = "arm3.toml"\ncolour = 1\n', "colour"),
    ('model = "arm3.toml"\nsqp_iterations = 0\n', "sqp_iterations"),
    ('model = "arm3.toml"\nqp_iterations = 2.5\n', "qp_iterations"),
])
def test_bad_mpc_problem_names_the_field(tmp_path, text, field):
    path = tmp_path / "bad_mpc.toml"
    path.write_text(text)
    with pytest.raises(ModelFileError, match=rf"bad_mpc\.toml: field '{field}'"):
        load_mpc_problem(path)


@pytest.fixture(scope="module")
def mpc_example(built, mpc_dir, tmp_path_factory):
    from conftest import build_example
    exe = tmp_path_factory.mktemp("mpc_example") / "mpc_example"
    return build_example("mpc", exe, {built[0]: "rscasadi_arm", mpc_dir: "rscasadi_mpc"})


def test_mpc_example_tracks_within_limits(mpc_example):
    import subprocess
    run = subprocess.run([str(mpc_example), "0.01", "1.0"], capture_output=True, text=True, check=True)
    rows = np.array([[float(v) for v in line.split()] for line in run.stdout.splitlines() if not line.startswith("#")])
    assert rows.shape == (100, 7)
    assert np.all(np.abs(rows[:, 4:]) <= np.array([0.6, 0.6, 0.4]) + 1e-12)     # the torque limits
    assert np.ptp(rows[:, 2]) > 0.1, "the shoulder pitch must move"
    summary = run.stdout.splitlines()[-1]
    max_err = float(summary.split("=")[1].split()[0])
    assert max_err < 1e-3
    assert "over 1000 steps" in summary and "deadline misses" in summary     # paced at 1 kHz: 1 s, 1000 steps


def test_mpc_example_is_valgrind_clean_and_refuses_bad_arguments(mpc_example):
    import shutil
    import subprocess
    if shutil.which("valgrind") is not None:
        allocs = []
        for seconds in ("0.52", "0.51"):       # 520 and 510 mpc_steps: the same allocations (no step allocates)
            run = subprocess.run(["valgrind", "--error-exitcode=9", "--leak-check=full", str(mpc_example), "0.01",
                                  seconds], capture_output=True, text=True)
            assert run.returncode == 0, run.stderr
            allocs.append(re.search(r"total heap usage: ([0-9,]+) allocs", run.stderr).group(1))
        assert allocs[0] == allocs[1], allocs
    run = subprocess.run([str(mpc_example), "fast"], capture_output=True, text=True)
    assert run.returncode == 2 and "argument 1" in run.stderr and run.stdout == ""
    run = subprocess.run([str(mpc_example), "0.01", "1", "realtime"], capture_output=True, text=True)
    assert run.returncode == 2 and "usage" in run.stderr and run.stdout == ""


# ----------------------------------------------------------------------------- task space, payload

TOOL = ROOT / "problems" / "mpc_arm3_tool.toml"


def _generated(tmp_path_factory, problem, name: str):
    """The MPC of `problem` generated and compiled (-O1) into a fresh directory."""
    out = tmp_path_factory.mktemp(f"mpc_{name}") / name
    M.generate_mpc(problem, out, opt="-O1", log=lambda m: None)
    return out


@pytest.fixture(scope="module")
def tool_mpc_dir(tmp_path_factory):
    return _generated(tmp_path_factory, TOOL, "arm3_tool")


def test_task_space_c_equals_casadi_with_the_payload_mass_it_is_given(tool_mpc_dir, mpc_dir):
    """The task-space controller in C against its CasADi Function, at the problem's payload mass
    and after mpc_set_payload_mass(0.5): equal to 1e-12, and the mass changes the torques."""
    from rscasadi.mpc.formulation import controller_arm
    from rscasadi.mpc.problem import mpc_model
    from rscasadi.mpc.study import FrameReference
    p = load_mpc_problem(TOOL)
    arm = controller_arm(mpc_model(p))
    rti, hold = split_step(arm, p), hold_function(arm, p)
    x = rest_state(arm, p.theta_start)
    reference = FrameReference(p, arm)
    offsets = p.interval * np.arange(1, p.horizon + 1)
    for mass in (0.05, 0.5):
        c = CompiledMPC(tool_mpc_dir)
        c.init(x)
        if mass != 0.05:
            assert c.set_payload_mass(mass) == 0
        params = np.r_[x[:3], mass]
        X, U = (np.array(v) for v in hold(x, np.r_[x[:3], 0.05]))
        xk = x.copy()
        for k in range(4):
            ref = reference.columns(0.05 * k + offsets)
            tau_c, _, flag = c.step(xk, ref)
            tau_py, X, U = (np.array(v) for v in rti(xk, ref, X, U, params))
            assert flag == 0 and np.max(np.abs(tau_c - tau_py.ravel())) < 1e-12
            xk = xk + 1e-3
        if mass == 0.05:
            light = tau_c
    assert np.max(np.abs(tau_c - light)) > 1e-4
    assert c.set_payload_mass(-1.0) == 5 and c.set_payload_mass(float("nan")) == 5
    assert CompiledMPC(mpc_dir).set_payload_mass(1.0) == 4               # its model holds no payload


def test_two_controllers_live_in_one_process(mpc_dir, arm3):
    """Two controllers of one library, stepped in turn from different states, give the torques
    each gives alone: their state is the caller's."""
    p = load_mpc_problem(PROBLEM)
    starts = [rest_state(arm3, [0.1, 0.4, -0.6]), rest_state(arm3, [-0.3, 0.2, 0.5])]
    ref = lambda x: np.vstack([np.tile(x[:3, None] + 0.1, (1, p.horizon)), np.zeros((3, p.horizon))])
    alone = []
    for x in starts:
        c = CompiledMPC(mpc_dir)
        c.init(x)
        alone.append([c.step(x, ref(x))[0] for _ in range(3)])
    both = [CompiledMPC(mpc_dir) for _ in starts]
    for c, x in zip(both, starts):
        c.init(x)
    together = [[], []]
    for _ in range(3):
        for i, (c, x) in enumerate(zip(both, starts)):
            together[i].append(c.step(x, ref(x))[0])
    assert np.array_equal(np.array(alone), np.array(together))


def test_task_space_mpc_keeps_clear_and_learns_the_payload(tool_mpc_dir, tmp_path):
    """The shipped task-space problem on the arm (quantised encoders, 1 kHz): the links stay out of
    the ball's margin, which the same controller without the obstacle term enters by about 1 cm;
    a payload ten times the modelled one, untold, leaves a static error at the path's end that
    mpc_set_payload_mass removes; no limit is violated."""
    import dataclasses
    res = M.task_study(TOOL, tool_mpc_dir, log=lambda m: None)
    modelled, untold, told = (res[k]["MPC (C)"] for k in ("as_modelled", "untold_payload", "told_payload"))
    assert modelled["min_clearance"] > 0 and modelled["max_path_distance"] < 0.02
    assert all(r["max_limit_violation"] == 0 for r in (modelled, untold, told))
    assert untold["final_error"] > 0.3e-3 and told["final_error"] < 0.05e-3
    assert modelled["label"].startswith("as modelled") and "not told" in untold["label"]
    M.plot_task_study(res, tmp_path / "study.png")
    assert (tmp_path / "study.png").stat().st_size > 20000
    same = M.task_study(TOOL, tool_mpc_dir, plant_mass=load_mpc_problem(TOOL).payload["mass"], log=lambda m: None)
    assert set(same) == {"path", "obstacles", "as_modelled"}          # no case repeats another
    p = load_mpc_problem(TOOL)
    blind = dataclasses.replace(p, weights={**p.weights, "obstacles": 0.0})
    M.generate_mpc(blind, tmp_path / "blind", opt="-O1", log=lambda m: None)
    assert M.task_closed_loop(blind, tmp_path / "blind", log=lambda m: None)["min_clearance"] < -5e-3


@pytest.mark.parametrize("text,field", [
    ('model = "arm3_tool.toml"\norientation = true\n', "orientation"),
    ('model = "arm3_tool.toml"\n[path]\nframe = "tool"\npoints = [[0.6, 0, 0.4], [0.5, 0, 0.4]]\nspeed = 0.2\n', "path"),
    ('model = "arm3_tool.toml"\nframe = "tool"\ntheta_start = [0.0, 0.3, -0.5]\n[path]\nframe = "tool"\n'
     'points = [[0.6, 0, 0.4], [0.5, 0, 0.4]]\n', "path.speed"),
    ('model = "arm3_tool.toml"\nframe = "tool"\n[path]\nframe = "tool"\npoints = [[0.6, 0, 0.4], [0.5, 0, 0.4]]\n'
     'speed = 0.2\n', "theta_start"),
    ('model = "arm3_tool.toml"\nframe = "tool"\n[[obstacles]]\nsphere = { center = [0, 0, 0] }\n', "obstacles[0].sphere"),
    ('model = "arm3_tool.toml"\nframe = "tool"\npayload = { colour = 1 }\n', "payload"),
])
def test_bad_task_space_mpc_problem_names_the_field(tmp_path, text, field):
    path = tmp_path / "bad_mpc.toml"
    path.write_text(text.replace('"arm3_tool.toml"', f'"{(ROOT / "problems" / "arm3_tool.toml").as_posix()}"'))
    with pytest.raises(ModelFileError, match=rf"bad_mpc\.toml: field '{re.escape(field)}'"):
        load_mpc_problem(path)


@pytest.mark.parametrize("text,field", [
    ('frame = "nowhere"\n', "frame"),
    ('frame = "tool"\northogonal = 1\n', "orthogonal"),
])
def test_a_task_space_problem_that_does_not_fit_the_arm_is_refused(tmp_path, text, field):
    path = tmp_path / "bad_mpc.toml"
    path.write_text(f'model = "{(ROOT / "problems" / "arm3_tool.toml").as_posix()}"\n' + text)
    with pytest.raises(ModelFileError, match=rf"bad_mpc\.toml: field '{field}'"):
        M.generate_mpc(path, tmp_path / "out", log=lambda m: None)


def test_the_panda_follows_its_shelf_motion_with_the_part_it_is_told_of(tmp_path):
    """The 7-joint task-space MPC (position and rotation, the ball and the table soft) on the
    committed minimum-time shelf motion with its 2 kg part, told: finite at every step, the hand
    within millimetres of the reference and at it at the end, clear of both obstacles.  At half
    the file's horizon (5 intervals: a third of the compile; the study runs the file's 10)."""
    import dataclasses
    p = dataclasses.replace(load_mpc_problem(ROOT / "problems" / "mpc_panda_shelf.toml"), horizon=5)
    M.generate_mpc(p, tmp_path / "panda", opt="-O1", log=lambda m: None)
    run = M.task_closed_loop(p, tmp_path / "panda", plant_mass=2.0, told=True, settle=0.05, log=lambda m: None)
    assert run["max_error"] < 0.01 and run["final_error"] < 0.5e-3 and run["min_clearance"] > 0


@pytest.fixture(scope="module")
def mpc_tool_example(tool_mpc_dir, tmp_path_factory):
    from conftest import build_example
    d = tmp_path_factory.mktemp("mpc_tool_example")
    arm_dir = d / "arm3_tool"
    assert main(["codegen", str(ROOT / "problems" / "arm3_tool.toml"), "--frames", "tool", "--out", str(arm_dir),
                 "--opt=-O1"]) in (0, None)
    return build_example("mpc_tool", d / "mpc_tool", {arm_dir: "rscasadi_arm", tool_mpc_dir: "rscasadi_mpc"})


def test_the_task_space_c_example_follows_the_path_and_is_valgrind_clean(mpc_tool_example):
    """examples/mpc_tool.c: the tool ends at the path's end at rest, never strays more than the
    ball makes it, and a run under valgrind has no error or leak."""
    import shutil
    import subprocess
    run = subprocess.run([str(mpc_tool_example), "2"], capture_output=True, text=True, check=True)
    rows = np.array([[float(v) for v in line.split()] for line in run.stdout.splitlines() if not line.startswith("#")])
    assert rows.shape == (200, 7)
    assert np.linalg.norm(rows[-1, 1:4] - [0.478388, 0.1, 0.493831]) < 1e-4
    off = float(run.stdout.splitlines()[-1].split("from the path = ")[1].split()[0].rstrip(";"))
    assert off < 0.02
    if shutil.which("valgrind") is not None:
        check = subprocess.run(["valgrind", "--error-exitcode=9", "--leak-check=full", str(mpc_tool_example), "0.4"],
                               capture_output=True, text=True)
        assert check.returncode == 0, check.stderr
    bad = subprocess.run([str(mpc_tool_example), "-1"], capture_output=True, text=True)
    assert bad.returncode == 2 and "argument 1" in bad.stderr and bad.stdout == ""


# ----------------------------------------------------------------------------- seven joints

PANDA = ROOT / "problems" / "mpc_panda.toml"


@pytest.fixture(scope="module")
def panda_mpc_dir(tmp_path_factory):
    return _generated(tmp_path_factory, PANDA, "panda")


def test_the_panda_mpc_tracks_under_a_heavier_last_link(panda_mpc_dir):
    """problems/mpc_panda.toml (7 joints, a 0.1 s horizon) in C on a plant whose last link is 20 %
    heavier, quantised encoders, 0.3 s: within the limits, at least 10x closer than feedforward +
    motor PD, and as close as the 3-joint MPC under the same mismatch (7.8e-4 rad, bench_mpc)."""
    res = closed_loop(PANDA, panda_mpc_dir, duration=0.3, log=lambda m: None)
    mpc, pd = res["MPC (C)"], res["feedforward + PD"]
    assert mpc["max_limit_violation"] == 0.0 and np.isfinite(mpc["max_error"])
    assert mpc["max_error"] < pd["max_error"] / 10 and mpc["max_error"] < 7.8e-4, (mpc["max_error"], pd["max_error"])


def test_the_panda_controller_with_its_step_kernel_equals_the_casadi_function(panda_mpc_dir):
    """Seven joints: the generated controller calls the structured step-Jacobian kernel
    (mpc_step_jacobian, in its own sources) where the CasADi Function uses the implicit-function
    graph; the torques agree to rounding over five steps (the kernel sums in another order)."""
    import json
    p = load_mpc_problem(PANDA)
    arm = load(p.model)
    assert "mpc_step_jacobian.c" in json.loads((panda_mpc_dir / "manifest.json").read_text())["sources"]
    rti, hold = split_step(arm, p), hold_function(arm, p)
    c, rng = CompiledMPC(panda_mpc_dir), np.random.default_rng(5)
    x = rest_state(arm, [0.0, -0.3, 0.0, -2.0, 0.0, 1.7, 0.8])
    c.init(x)
    posture = x[:7].copy()                               # the measured angles at mpc_init
    X, U = (np.array(v) for v in hold(x, posture))
    for _ in range(5):
        ref = np.vstack([x[:7, None] + rng.normal(0, 0.02, (7, p.horizon)), rng.normal(0, 0.1, (7, p.horizon))])
        tau_c, _, flag = c.step(x, ref)
        tau_py, X, U = (np.array(v) for v in rti(x, ref, X, U, posture))
        assert flag == 0 and np.max(np.abs(tau_c - tau_py.ravel())) < 1e-8, np.max(np.abs(tau_c - tau_py.ravel()))
        x = x + rng.normal(0, 1e-4, x.shape)


@pytest.mark.parametrize("parametric,method", [("none", "rk4"), ("payload", "rk4"), ("none", "ros2"),
                                              ("payload", "ros2")])
def test_the_chained_step_kernel_steps_and_chains_as_the_implicit_function_graph(parametric, method):
    """The MPC's kernel is one substep of an interval (codegen.step_kernel, chained): it returns
    the step and carries the interval's A and B through it.  Three substeps of a Panda interval
    against interval_functions without the kernel (RK4: its step Function and the
    implicit-function graph's Jacobian; ROS2: codegen.rosenbrock's graph, a dense solve with W,
    itself checked against AD in test_modes; chained by CasADi's products), at random states and
    torques, with and without the payload's mass as a parameter: the state, A and B, and the
    state alone (Fx, which ROS2 takes from the kernel without its Jacobian), to 1e-9 of their size."""
    import dataclasses
    from rscasadi.mpc.formulation import controller_arm, interval_functions
    from rscasadi.mpc.generate import step_kernel
    from rscasadi.native.build import compiler
    p = dataclasses.replace(load_mpc_problem(PANDA), parametric=parametric)
    arm = controller_arm(M.generate.mpc_model(p), p.parametric)
    _, kernel = step_kernel(arm, ["-O1", "-std=c99"], compiler(), log=lambda m: None, method=method)
    assert kernel.n_out() == 3 and kernel.name_out(2) == "x_next"
    chained = interval_functions(arm, 0.02, 3, kernel, method)
    graph = interval_functions(arm, 0.02, 3, integrator=method)
    rng = np.random.default_rng(3)
    for _ in range(3):
        x = rest_state(arm, rng.uniform(-0.5, 0.5, 7)) + rng.normal(0, 0.05, 28)
        tau, m = rng.normal(0, 0.3, 7), [1.3] * (arm.n_p if arm.free else 0)
        for F, G in zip(chained, graph):
            for a, b in zip(F.call([x, tau, m]), G.call([x, tau, m])):
                a, b = np.array(a), np.array(b)
                assert np.max(np.abs(a - b)) < 1e-9 * max(1.0, np.max(np.abs(b))), np.max(np.abs(a - b))


def test_the_mpc_example_runs_the_panda_valgrind_clean(panda_mpc_dir, panda_built, tmp_path):
    """examples/mpc.c built on the Panda's model and MPC (N = MPC_NU = 7): it tracks, prints 7
    angles and torques within the limits, and under valgrind makes no error, leaks nothing and
    allocates the same for 20 and 30 steps (no step allocates)."""
    import shutil
    import subprocess
    from conftest import build_example
    arm_dir = panda_built
    exe = build_example("mpc", tmp_path / "mpc_panda", {arm_dir: "rscasadi_arm", panda_mpc_dir: "rscasadi_mpc"})
    interval = str(load_mpc_problem(PANDA).interval)
    run = subprocess.run([str(exe), interval, "0.7"], capture_output=True, text=True, check=True)
    rows = np.array([[float(v) for v in line.split()] for line in run.stdout.splitlines() if not line.startswith("#")])
    limits = np.array([jt.limits["tau"] for jt in load(ROOT / "problems" / "panda_sea.toml").model.joints])
    assert rows.shape == (70, 15) and np.all(np.abs(rows[:, 8:]) <= limits + 1e-12)
    assert float(run.stdout.splitlines()[-1].split("=")[1].split()[0]) < 5e-3
    if shutil.which("valgrind") is not None:
        allocs = []
        for seconds in ("0.03", "0.02"):
            check = subprocess.run(["valgrind", "--error-exitcode=9", "--leak-check=full", str(exe), interval, seconds],
                                   capture_output=True, text=True)
            assert check.returncode == 0, check.stderr
            allocs.append(re.search(r"total heap usage: ([0-9,]+) allocs", check.stderr).group(1))
        assert allocs[0] == allocs[1], allocs


def test_native_mpc_equals_the_portable_one(mpc_dir, tmp_path):
    """`rscasadi mpc` compiles for this processor by default (the manifest says so); with
    `--no-native` (mpc_dir) it compiles the same sources for any processor, and steps as the
    native library does, to rounding (fused multiply-adds)."""
    import json
    out = tmp_path / "native"
    assert main(["mpc", str(PROBLEM), "--out", str(out), "--opt=-O1"]) in (0, None)
    assert "-march=native" in json.loads((out / "manifest.json").read_text())["compiler"]
    assert "-march=native" not in json.loads((mpc_dir / "manifest.json").read_text())["compiler"]
    assert (out / "mpc_rti.c").read_text() == (mpc_dir / "mpc_rti.c").read_text()
    arm = load(ROOT / "problems" / "arm3.toml")
    x = rest_state(arm, [0.2, 0.3, -0.4])
    ref = np.vstack([np.tile(np.array([0.3, 0.4, -0.5])[:, None], (1, 10)), np.zeros((3, 10))])
    a, b = CompiledMPC(mpc_dir), CompiledMPC(out)
    a.init(x)
    b.init(x)
    for _ in range(5):
        ta, tb = a.step(x, ref)[0], b.step(x, ref)[0]
        assert np.max(np.abs(ta - tb)) < 1e-9 * max(1.0, np.max(np.abs(ta)))


def test_a_family_controller_takes_an_identified_arm_without_recompiling(mpc_dir, tmp_path_factory, tmp_path):
    """parametric = "family": the same torques as the constant controller on the problem's arm,
    and, after mpc_set_parameters with a heavier arm's parameters (same zeros), the constant
    controller generated for that arm's torques; non-finite parameters are refused."""
    import dataclasses
    import json
    from conftest import heavier_reference
    p = load_mpc_problem(PROBLEM)
    fam_dir = _generated(tmp_path_factory, dataclasses.replace(p, parametric="family"), "family")
    other = heavier_reference(tmp_path)
    other_dir = _generated(tmp_path_factory, dataclasses.replace(p, model=other), "other")
    info = json.loads((fam_dir / "manifest.json").read_text())["parameters"]
    values = dict(zip(*load(other).parameters()))
    p_other = np.array([values[k] for k in info["names"]])
    assert len(info["names"]) > 30 and not np.allclose(p_other, info["nominal"])
    rng = np.random.default_rng(5)
    x = rest_state(load(p.model), [0.1, 0.4, -0.6])
    for constant, set_to in ((mpc_dir, None), (other_dir, p_other)):
        a, b = CompiledMPC(constant), CompiledMPC(fam_dir)
        a.init(x)
        b.init(x, set_to)                              # mpc_init, or mpc_init_parameters
        for _ in range(3):
            ref = np.vstack([x[:3, None] + rng.normal(0, 0.05, (3, p.horizon)), rng.normal(0, 0.2, (3, p.horizon))])
            tau_a, _, fa = a.step(x, ref)
            tau_b, _, fb = b.step(x, ref)
            assert fa == fb == 0 and np.max(np.abs(tau_a - tau_b)) < 1e-9 * (1 + np.max(np.abs(tau_a)))
    assert b.set_parameters(p_other) == 0 and b.set_parameters(np.full(len(p_other), np.nan)) == 5   # BAD_ARGUMENT


def _two_arms(tmp_path):
    """Two reference arms on one base, 0.6 m apart, each with its tool frame: a tree of six SEAs."""
    import tomllib
    from conftest import to_toml
    doc = tomllib.loads((ROOT / "problems" / "arm3.toml").read_text())
    joints = []
    for side, y in (("left", 0.3), ("right", -0.3)):
        for j, jt in enumerate(doc["joints"]):
            jt = dict(jt, name=f"{side}_{jt['name']}", parent="base" if j == 0 else joints[-1]["name"])
            if j == 0:
                jt["origin_xyz"] = [jt["origin_xyz"][0], y, jt["origin_xyz"][2]]
            joints.append(jt)
    two = {"name": "two-arms", "gravity": doc["gravity"], "joints": joints,
           "frames": {f"{s}_tool": {"parent": f"{s}_elbow_pitch", "xyz": [0.3, 0.0, 0.0]} for s in ("left", "right")}}
    path = tmp_path / "two_arms.toml"
    path.write_text(to_toml(two))
    return path


def test_the_mpc_brings_two_frames_to_their_targets_at_once(tmp_path):
    """A task-space MPC of two frames (two arms' tools, frame = [..]; HPIPM's Riccati QP): its
    reference a block per frame, its C's mpc_step_to taking a position per frame; closed loop at
    1 kHz on the tree of six SEAs (RK4 plant, exact encoders), both tools reach their own targets
    (a pose the tree can take, seen only through the frames' positions) within 2 mm in 1.5 s,
    every torque within its limit; the blocks swapped, the tools go elsewhere; a target with a
    bad entry in either frame's block refused (code 7) with torques finite and within limits."""
    import rscasadi
    from rscasadi.dynamics.statics import rest_state
    from rscasadi.mpc.generate import generate_mpc
    from rscasadi.mpc.study import _MPC
    from rscasadi.sim.loop import Encoders, rk4_plant, run_loop
    model = _two_arms(tmp_path)
    (tmp_path / "mpc.toml").write_text(
        f'model = "{model.name}"\nframe = ["left_tool", "right_tool"]\nsample_time = 0.001\nhorizon = 10\n'
        'interval = 0.01\nsubsteps = 5\nqp = "riccati"\n[weights]\nposition = 1e6\nvelocity = 10.0\nposture = 1.0\n'
        'tau = 1e-3\nlimits = 1e5\n')
    manifest = generate_mpc(tmp_path / "mpc.toml", tmp_path / "mpc", opt="-O1", log=lambda m: None)
    assert manifest["sizes"]["reference"] == [12, 10] and manifest["sizes"]["target"] == 6
    assert manifest["task_space"]["frames"] == ["left_tool", "right_tool"]
    arm = rscasadi.load(model)
    pose = np.array([0.3, 0.4, -0.6, -0.2, 0.2, -0.4])
    tools = [np.array(arm.frame_placement(f"{s}_tool")(pose)[1]).ravel() for s in ("left", "right")]
    limits = np.array([jt.limits["tau"] for jt in arm.model.joints])
    x0 = rest_state(arm, np.zeros(6))
    for target, order in ((np.r_[tools[0], tools[1]], (0, 1)), (np.r_[tools[1], tools[0]], (1, 0))):
        run = run_loop(arm, rk4_plant(arm, 0.001), _MPC(CompiledMPC(tmp_path / "mpc"), target=target), x0, 1500,
                       0.001, sensors=Encoders(arm, 0.001, exact=True))
        reached = [np.array(arm.frame_placement(f"{s}_tool")(run.x[:6, -1])[1]).ravel() for s in ("left", "right")]
        errors = [np.linalg.norm(r - tools[i]) for r, i in zip(reached, order)]
        if order == (0, 1):
            assert max(errors) < 2e-3, errors
            assert np.all(np.abs(run.tau) <= limits[:, None] + 1e-12)
        else:                                       # each arm reaches toward the other's target
            assert min(np.linalg.norm(r - t) for r, t in zip(reached, tools)) > 0.1
    mpc, rng = CompiledMPC(tmp_path / "mpc"), np.random.default_rng(0)     # a bad entry in either frame's block
    assert mpc.init(x0) == 0
    for k in range(20):
        target = np.r_[tools[0], tools[1]]
        target[rng.integers(6)] = [np.nan, np.inf, -np.inf, 1e300][k % 4]
        tau, _, code = mpc.step_to(x0, target)
        assert code == 7 and np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= limits + 1e-12), (k, code)
        tau, _, code = mpc.step_to(x0, np.r_[tools[0], tools[1]])
        assert code == 0 and np.all(np.abs(tau) <= limits + 1e-12)


@pytest.mark.parametrize("text,field", [
    ('frame = ["left_tool", "left_tool"]', "frame"),
    ('frame = []', "frame"),
    ('frame = ["left_tool", "right_tool"]\ntheta_start = [0.0, 0.3, -0.5, 0.0, 0.3, -0.5]\n'
     '[path]\nframe = "left_tool"\npoints = [[0.6, 0.3, 0.4], [0.5, 0.3, 0.4]]\nspeed = 0.2', "path"),
])
def test_bad_several_frames_are_named(tmp_path, text, field):
    """A frame named twice, an empty list, a path (one frame's) for two frames, a frame the
    model has not: each refused naming the field."""
    from rscasadi.mpc.problem import mpc_model
    model = _two_arms(tmp_path)
    (tmp_path / "bad.toml").write_text(f'model = "{model.name}"\n{text}\n')
    with pytest.raises(ModelFileError, match=f"field '{field}'"):
        load_mpc_problem(tmp_path / "bad.toml")
    (tmp_path / "none.toml").write_text(f'model = "{model.name}"\nframe = ["left_tool", "nowhere"]\n')
    with pytest.raises(ModelFileError, match="no frame 'nowhere'"):
        mpc_model(load_mpc_problem(tmp_path / "none.toml"))
