"""Every generated controller against bad data: the one failure policy (rscasadi_guard.h).

A controller fed NaN, infinities or absurd numbers in any input returns the code its header
names and a safe output (the MPC and the impedance controller: the holding torque of the last good
measured state, computed here from the model's inverse dynamics, not from the C; the observer:
its last r), never NaN, never beyond a limit; the next good sample gets exactly what a second
controller that never saw the bad one gets.  The ctypes wrappers refuse arrays of the wrong
length or type before C sees them; a C harness runs the three controllers in one binary under
valgrind."""
import os
import shutil
import subprocess

import numpy as np
import pytest

import rscasadi
from conftest import ROOT, cc
from rscasadi.dynamics.statics import rest_state
from rscasadi.model.limits import limit_arrays
from rscasadi.native.loader import ControllerError

BAD = [np.nan, np.inf, -np.inf, 1e300, -1e300, 1e3]          # 1e3 rad or rad/s: finite but absurd
ARM3_TOOL = ROOT / "problems" / "arm3_tool.toml"
THETA0 = np.array([0.0, 0.3, -0.5])


def holding(arm, x):
    """The motor torques that hold the motors still at x, within the limits (the policy's safe torque)."""
    n, z = arm.n, np.zeros(arm.n)
    tau = np.array(arm.inverse_dynamics()(x[:n], x[n:2 * n], z, z, z, z)[0]).ravel()
    lim = limit_arrays(arm.model)["tau"]
    return np.clip(tau, -lim, lim)


def corrupt(rng, v, bad=BAD):
    """v with one random entry replaced by a random bad value."""
    v = np.array(v, float)
    flat = v.reshape(-1)
    flat[rng.integers(flat.size)] = bad[rng.integers(len(bad))]
    return v


@pytest.fixture(scope="module")
def arm():
    return rscasadi.load(ARM3_TOOL)


PROBLEMS = {name: ROOT / "problems" / f"{name}.toml" for name in ("mpc_arm3", "mpc_arm3_tool")}


@pytest.fixture(scope="module")
def mpc_dirs(tmp_path_factory):
    """The shipped MPC problems' controllers, mpc_arm3's with hard link-angle limits (its C
    symbols prefixed `hard_`: hard_mpc_init, ...) and with the Riccati QP (HPIPM), on one thread
    and on two."""
    from rscasadi.mpc import generate_mpc
    hard = tmp_path_factory.mktemp("hard") / "mpc_arm3_hard.toml"
    text = PROBLEMS["mpc_arm3"].read_text().replace('model = "', f'model = "{ROOT / "problems"}/').replace(
        'trajectory = "', f'trajectory = "{ROOT / "problems"}/')
    hard.write_text(text.replace("[weights]", 'angle_limits = "hard"\n[weights]', 1))
    PROBLEMS["mpc_arm3_hard"] = hard
    riccati = hard.with_name("mpc_arm3_riccati.toml")
    riccati.write_text(text.replace("[weights]", 'qp = "riccati"\n[weights]', 1))
    PROBLEMS["mpc_arm3_riccati"] = riccati
    threaded = hard.with_name("mpc_arm3_riccati_threads.toml")       # its preparation on OpenMP threads
    threaded.write_text(text.replace("[weights]", 'qp = "riccati"\nthreads = 2\n[weights]', 1))
    PROBLEMS["mpc_arm3_riccati_threads"] = threaded
    out = {}
    for name, problem in PROBLEMS.items():
        out[name] = tmp_path_factory.mktemp(name) / "mpc"
        generate_mpc(problem, out[name], opt="-O1", log=lambda m: None, prefix="hard" if "hard" in name else "")
    return out


@pytest.fixture(scope="module")
def interaction_dirs(tmp_path_factory, arm):
    from rscasadi.interaction import generate_impedance, generate_observer
    d = tmp_path_factory.mktemp("interaction")
    generate_impedance(arm, d / "impedance_joint", None, opt="-O1", log=lambda m: None)
    generate_impedance(arm, d / "impedance_cartesian", "tool", opt="-O1", log=lambda m: None, prefix="tool")
    generate_observer(arm, d / "observer", 50.0, threshold=1.0, opt="-O1", log=lambda m: None)
    return d


@pytest.mark.parametrize("name", ["mpc_arm3", "mpc_arm3_tool", "mpc_arm3_hard", "mpc_arm3_riccati",
                                  "mpc_arm3_riccati_threads"])
def test_the_mpc_fuzzed_gives_safe_torques_and_recovers(mpc_dirs, name):
    """200 samples, 40 % of them with a bad entry in the measurement, the reference or the target:
    MPC_BAD_MEASUREMENT (6) or MPC_BAD_REFERENCE (7), the holding torque of the last good state;
    every good sample's torque equals a clean twin's to the last bit.  Also with hard link-angle
    limits (QP rows) and with the Riccati QP, its preparation on one thread and on two."""
    from rscasadi.mpc import CompiledMPC
    from rscasadi.mpc.problem import load_mpc_problem
    p = load_mpc_problem(PROBLEMS[name])
    assert p.angle_limits == ("hard" if name.endswith("hard") else "soft")
    arm = rscasadi.load(p.model)
    c, twin, rng = CompiledMPC(mpc_dirs[name]), CompiledMPC(mpc_dirs[name]), np.random.default_rng(4)
    rows, N = c.sizes["reference"]
    x0 = rest_state(arm, THETA0)
    assert c.init(x0) == 0 and twin.init(x0) == 0
    if p.task_space:
        R, pos = (np.array(v) for v in arm.frame_placement(p.frame)(THETA0))
        column = np.r_[pos.ravel(), np.zeros(3), R.T.ravel()][:rows]
        target = np.r_[pos.ravel(), R.T.ravel()][:c.sizes["target"]]
    else:
        column, target = np.r_[THETA0 + 0.05, np.zeros(3)], THETA0 + 0.05
    limit = limit_arrays(arm.model)["tau"]
    good, codes = x0, []
    for k in range(200):
        x = x0 + rng.normal(0, [1e-3] * 6 + [1e-2] * 6)
        ref = np.tile(column[:, None], (1, N))
        kind = rng.choice(["good", "x", "reference", "target"], p=[0.6, 0.15, 0.15, 0.1])
        if kind == "good":
            tau, _, code = c.step(x, ref)
            tau_twin, _, code_twin = twin.step(x, ref)
            assert code == 0 and code_twin == 0 and np.array_equal(tau, tau_twin), k
            good = x
        else:
            if kind == "x":
                tau, _, code = c.step(corrupt(rng, x), ref)
            elif kind == "reference":
                tau, _, code = c.step(x, corrupt(rng, ref))
            else:
                tau, _, code = c.step_to(x, corrupt(rng, target))
            expect = 6 if kind == "x" else 7
            good = good if kind == "x" else x
            assert code == expect, (k, kind, code)
            assert np.max(np.abs(tau - holding(arm, good))) < 1e-9, (k, kind)
        assert np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= limit + 1e-12), k
        codes.append(code)
    assert {0, 6, 7} <= set(codes)


def test_the_mpc_refuses_before_init_and_after_a_refused_init(mpc_dirs):
    from rscasadi.mpc import CompiledMPC
    c = CompiledMPC(mpc_dirs["mpc_arm3"])
    arm = rscasadi.load(ROOT / "problems" / "arm3.toml")
    x = rest_state(arm, THETA0)
    ref = np.zeros(c.sizes["reference"])
    tau, _, code = c.step(x, ref)
    assert code == 8 and not np.any(tau)                             # MPC_NOT_INITIALISED, zeros
    for bad in ([np.nan] + [0.0] * 11, [1e3] + [0.0] * 11, [0.0] * 6 + [1e6] * 6):
        with pytest.raises(ControllerError, match="MPC_BAD_MEASUREMENT") as err:
            c.init(bad)
        assert err.value.code == 6
        tau, _, code = c.step(x, ref)
        assert code == 8 and not np.any(tau)
    assert c.init(x) == 0 and c.step(x, ref)[2] == 0


def test_the_wrappers_check_every_array_against_the_manifest(mpc_dirs, interaction_dirs):
    """A short or long array, a wrong shape or a non-number is a ControllerError naming the
    argument and the size, before C sees it."""
    from rscasadi.interaction import CompiledImpedance, CompiledObserver
    from rscasadi.mpc import CompiledMPC
    c = CompiledMPC(mpc_dirs["mpc_arm3"])
    x = np.zeros(12)
    for bad in (np.zeros(11), np.zeros(13), np.zeros(0)):
        with pytest.raises(ControllerError, match="x must have 12 values"):
            c.init(bad)
    c.init(x)
    rows, N = c.sizes["reference"]
    for bad in (np.zeros((rows, N - 1)), np.zeros((rows - 1, N)), np.zeros(rows * N)):
        with pytest.raises(ControllerError, match=f"reference must be {rows} x {N}"):
            c.step(x, bad)
    with pytest.raises(ControllerError, match="target must have 3 values"):
        c.step_to(x, [0.1, 0.2])
    for bad in (np.array(["a"] * 12), np.zeros(12, complex), np.array([None] * 12)):
        with pytest.raises(ControllerError, match="real numbers"):
            c.step(bad, np.zeros((rows, N)))
    with pytest.raises(ControllerError, match="theta must have 3 values"):
        c.set_posture([0.0])
    with pytest.raises(ControllerError, match="mass must be a number"):
        c.set_payload_mass("heavy")
    imp = CompiledImpedance(interaction_dirs / "impedance_joint")
    imp.init(x)
    with pytest.raises(ControllerError, match="stiffness must have 3 values"):
        imp.step(x, np.zeros(3), np.ones(2), np.ones(3))
    obs = CompiledObserver(interaction_dirs / "observer")
    obs.init(x)
    with pytest.raises(ControllerError, match="tau must have 3 values"):
        obs.step(x, np.zeros(4))
    with pytest.raises(ControllerError, match="not a generated controller"):
        CompiledMPC(interaction_dirs)


@pytest.mark.parametrize("space", ["joint", "cartesian"])
def test_the_impedance_controller_and_its_python_twin_fuzzed(interaction_dirs, arm, space):
    """C and Python twin on the same fuzzed samples: the same code, the same torques (the
    holding torque of the last good state on a refused one), finite and within the limits; a
    clean twin gets the same torques on every good sample."""
    from rscasadi.interaction import CompiledImpedance, ImpedanceController
    from rscasadi.interaction.study import pose_of
    d = interaction_dirs / f"impedance_{space}"
    c, clean = CompiledImpedance(d), CompiledImpedance(d)
    py = ImpedanceController(arm, "tool" if space == "cartesian" else None)
    rng = np.random.default_rng(8)
    x0 = rest_state(arm, THETA0)
    assert c.init(x0) == 0 and clean.init(x0) == 0 and py.init(x0) == 0
    ref = pose_of(arm, "tool", THETA0) if space == "cartesian" else THETA0 + 0.02
    nk = 6 if space == "cartesian" else 3
    K, zeta = np.full(nk, 200.0), np.full(nk, 0.7)
    limit = limit_arrays(arm.model)["tau"]
    good, codes = x0, []
    for k in range(150):
        x = x0 + rng.normal(0, [1e-3] * 6 + [1e-2] * 6)
        args = [x, ref, K, zeta]
        kind = int(rng.integers(-3, 4))                        # < 0: a good sample; else the input to corrupt
        if kind >= 0:                                          # a stiffness of 1e3 is no fault: -1 is
            args[kind] = corrupt(rng, args[kind], BAD[:-1] + [-1.0] if kind == 2 else BAD)
        tau, code = c.step(*args)
        tau_py = py.step(*args)
        assert code == py.code and np.max(np.abs(tau - tau_py)) < 1e-12, (k, kind)
        if kind < 0:
            assert code == 0 and np.array_equal(tau, clean.step(*args)[0])
            good = x
        else:
            good = good if kind == 0 else x
            assert code == (6 if kind == 0 else 7), (k, kind, code)
            assert np.max(np.abs(tau - holding(arm, good))) < 1e-9
        assert np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= limit + 1e-12)
        codes.append(code)
    assert {0, 6, 7} <= set(codes)


def test_the_observer_and_its_python_twin_fuzzed(interaction_dirs, arm):
    """A refused sample keeps the state and returns the last r (C and Python alike); every good
    sample after it equals a clean observer's."""
    from rscasadi.interaction import CompiledObserver, MomentumObserver
    c, clean = CompiledObserver(interaction_dirs / "observer"), CompiledObserver(interaction_dirs / "observer")
    py = MomentumObserver(arm, 50.0, 1e-3, 1.0)
    rng = np.random.default_rng(3)
    x0 = rest_state(arm, THETA0)
    assert c.init(x0) == 0 and clean.init(x0) == 0 and py.init(x0) == 0
    r_last, codes = np.zeros(6), []
    for k in range(150):
        x, tau = x0 + rng.normal(0, 1e-3, 12), rng.normal(0, 0.05, 3)
        kind = rng.choice(["good", "x", "tau"], p=[0.6, 0.2, 0.2])
        xs, taus = (corrupt(rng, x) if kind == "x" else x), (corrupt(rng, tau) if kind == "tau" else tau)
        r, code = c.step(xs, taus)
        r_py = py.step(xs, taus)
        assert code == py.code and np.max(np.abs(r - r_py)) < 1e-9, (k, kind)
        assert np.all(np.isfinite(r))
        if kind == "good":
            assert code in (0, 1) and np.array_equal(r, clean.step(x, tau)[0])
            r_last = r
        else:
            assert code == (6 if kind == "x" else 7) and np.array_equal(r, r_last)
        codes.append(code)
    assert {6, 7} <= set(codes) and set(codes) & {0, 1}


def test_the_python_twins_refuse_an_init_and_act_only_after_one(arm):
    from rscasadi.interaction import ImpedanceController, MomentumObserver
    x = rest_state(arm, THETA0)
    imp, obs = ImpedanceController(arm, None), MomentumObserver(arm, 50.0, 1e-3)
    assert not np.any(imp.step(x, THETA0, [100.0] * 3, [0.7] * 3)) and imp.code == 8
    assert not np.any(obs.step(x, np.zeros(3))) and obs.code == 8
    bad = x.copy()
    bad[7] = np.nan
    assert imp.init(bad) == 6 and obs.init(bad) == 6
    assert imp.step(x, THETA0, [100.0] * 3, [0.7] * 3).shape == (3,) and imp.code == 8
    assert imp.init(x) == 0 and obs.init(x) == 0


def test_four_controllers_in_one_binary_under_valgrind(mpc_dirs, interaction_dirs, built, tmp_path):
    """tests/c/controllers_guard.c links the joint-space MPC, impedance controller, observer and
    the arm library's guarded feedforward of the 3-joint arm into one program (no symbol
    clashes) and feeds them NULL arrays, garbage state memory and every bad value in every entry:
    all checks pass, and under valgrind (installed in CI) no invalid read or write."""
    dirs = {mpc_dirs["mpc_arm3"]: "rscasadi_mpc", interaction_dirs / "impedance_joint": "rscasadi_impedance",
            interaction_dirs / "observer": "rscasadi_observer", built[0]: "rscasadi_arm"}
    exe = tmp_path / "guard"
    subprocess.run([cc(), "-std=c99", "-Wall", "-Wextra", "-Werror", "-O1", *[f"-I{d}" for d in dirs],
                    str(ROOT / "tests" / "c" / "controllers_guard.c"), *[f"-L{d}" for d in dirs],
                    *[f"-l{lib}" for lib in dirs.values()], *[f"-Wl,-rpath,{d}" for d in dirs], "-lm", "-o", str(exe)],
                   check=True)
    run = subprocess.run([str(exe)], capture_output=True, text=True)
    assert run.returncode == 0 and run.stdout.strip().endswith("0 failed"), run.stderr[-3000:]
    if shutil.which("valgrind") is None and os.environ.get("CI") and os.geteuid() == 0 and shutil.which("apt-get"):
        env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")          # CI on Debian installs it
        subprocess.run(["apt-get", "update", "-qq"], env=env, capture_output=True, timeout=600)
        subprocess.run(["apt-get", "install", "-y", "-qq", "valgrind"], env=env, capture_output=True, timeout=900)
    if shutil.which("valgrind") is None:
        pytest.skip("valgrind is not installed: the checks passed without it")
    check = subprocess.run(["valgrind", "--error-exitcode=9", str(exe)], capture_output=True, text=True)
    assert check.returncode == 0, check.stderr[-3000:]


PREFIXED = r"""
#include <stdio.h>
#include "rscasadi_mpc.h"
#include "hard_mpc.h"
#include "tool_impedance.h"
static mpc_t soft;
static hard_mpc_t hard;
static tool_impedance_t imp;
int main(void) {
  double x[MPC_NX] = {0}, ref[MPC_NREF], tau[MPC_NU], tau_hard[HARD_MPC_NU], tau_imp[TOOL_IMPEDANCE_NU];
  const double x_tool[TOOL_IMPEDANCE_NX] = {X_TOOL}, pose[TOOL_IMPEDANCE_NREF] = {POSE};
  const double k[TOOL_IMPEDANCE_NK] = {300, 300, 300, 50, 50, 50}, z[TOOL_IMPEDANCE_NK] = {0.7, 0.7, 0.7, 0.7, 0.7, 0.7};
  for (int k = 0; k < MPC_HORIZON; ++k)
    for (int i = 0; i < 2 * MPC_NU; ++i) ref[2 * MPC_NU * k + i] = i < MPC_NU ? 0.1 : 0.0;
  if (mpc_init(&soft, x) || hard_mpc_init(&hard, x) || tool_impedance_init(&imp, x_tool)) return 2;
  if (mpc_step(&soft, x, ref, tau) || hard_mpc_step(&hard, x, ref, tau_hard)) return 3;
  if (tool_impedance_step(&imp, x_tool, pose, k, z, tau_imp)) return 4;
  for (int i = 0; i < MPC_NU; ++i) printf("%.17g %.17g %.17g\n", tau[i], tau_hard[i], tau_imp[i]);
  return 0;
}
"""


def test_controllers_with_prefixes_link_into_one_program(mpc_dirs, interaction_dirs, arm, tmp_path):
    """The same problem's MPC with soft and with hard angle limits, the second generated with
    prefix "hard" (hard_mpc_t, hard_mpc_step, HARD_MPC_NU, hard_mpc.h, libhard_mpc.so), and a
    Cartesian impedance controller with prefix "tool": one C program links the three (-Wall
    -Wextra -Werror) and each returns, to the last bit, what its library returns through Python."""
    from rscasadi.interaction.generate import CompiledImpedance
    from rscasadi.interaction.study import pose_of
    from rscasadi.mpc import CompiledMPC
    dirs = {mpc_dirs["mpc_arm3"]: "rscasadi_mpc", mpc_dirs["mpc_arm3_hard"]: "hard_mpc",
            interaction_dirs / "impedance_cartesian": "tool_impedance"}
    assert CompiledMPC(mpc_dirs["mpc_arm3_hard"]).manifest["symbol"] == "hard_mpc"
    x_tool, pose = rest_state(arm, THETA0), pose_of(arm, "tool", THETA0 + [0.0, 0.05, 0.0])
    numbers = lambda v: ", ".join(repr(float(a)) for a in v)
    (tmp_path / "linked.c").write_text(PREFIXED.replace("X_TOOL", numbers(x_tool)).replace("POSE", numbers(pose)))
    exe = tmp_path / "linked"
    subprocess.run([cc(), "-std=c99", "-Wall", "-Wextra", "-Werror", "-O1", *[f"-I{d}" for d in dirs],
                    str(tmp_path / "linked.c"), *[f"-L{d}" for d in dirs], *[f"-l{lib}" for lib in dirs.values()],
                    *[f"-Wl,-rpath,{d}" for d in dirs], "-lm", "-o", str(exe)], check=True)
    run = subprocess.run([str(exe)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    in_c = np.array([[float(v) for v in line.split()] for line in run.stdout.split("\n") if line]).T
    x, ref = np.zeros(12), np.vstack([np.full((3, 10), 0.1), np.zeros((3, 10))])
    for column, directory in zip(in_c[:2], (mpc_dirs["mpc_arm3"], mpc_dirs["mpc_arm3_hard"])):
        mpc = CompiledMPC(directory)
        mpc.init(x)
        tau, _, flag = mpc.step(x, ref)
        assert flag == 0 and np.array_equal(tau, column)
    imp = CompiledImpedance(interaction_dirs / "impedance_cartesian")
    imp.init(x_tool)
    tau, code = imp.step(x_tool, pose, [300.0] * 3 + [50.0] * 3, [0.7] * 6)
    assert code == 0 and np.array_equal(tau, in_c[2]) and np.any(tau != 0)


def test_the_template_c_compiles_without_a_warning(mpc_dirs, interaction_dirs, built, tmp_path):
    """What rscasadi writes from its templates (not CasADi's generated files): every controller's
    source and header (the Riccati one with HPIPM's headers), the arm library's guarded
    feedforward, under -Wall -Wextra -Werror -pedantic."""
    import json
    from rscasadi.ocp.fatrop.driver import casadi_dir
    dirs = [*mpc_dirs.values(), *(d for d in interaction_dirs.iterdir() if d.is_dir())]
    sources = [d / json.loads((d / "manifest.json").read_text())["header"].replace(".h", ".c") for d in dirs]
    sources.append(built[0] / "rscasadi_feedforward.c")
    assert len(sources) == 9 and all(f.exists() for f in sources), sources
    for f in sources:
        run = subprocess.run([cc(), "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-c", str(f), f"-I{f.parent}",
                              f"-I{casadi_dir() / 'include'}", "-o", str(tmp_path / "x.o")], capture_output=True, text=True)
        assert run.returncode == 0, f"{f.name}: {run.stderr[-2000:]}"


def test_the_guarded_feedforward_fuzzed(built):
    """The arm library's ff_init / ff_step (the paper's feedforward with the failure policy) on a
    desired motion with 40 % bad samples: a bad one returns FF_BAD_REFERENCE (7) and the holding
    torque at the last good sample (from the library's own feedforward_step chain and the model's
    inverse dynamics in Python), the next good one equals the unguarded chain that never saw the
    bad sample; before init, FF_NOT_INITIALISED and zeros."""
    from rscasadi.codegen import CompiledFeedforward, load_compiled
    directory, _ = built
    arm = rscasadi.load(ROOT / "problems" / "arm3.toml")
    ff, raw = CompiledFeedforward(directory), load_compiled(directory)
    z = np.zeros(3)
    assert ff.step(THETA0, z, z, 1e-3)[1] == 8 and not np.any(ff.step(THETA0, z, z, 1e-3)[0])
    with pytest.raises(ControllerError, match="FF_BAD_REFERENCE"):
        ff.init([np.nan, 0.0, 0.0], z, z)
    tau0 = ff.init(THETA0, z, z)
    tau_raw, state = raw["feedforward_init"](THETA0, z, z)
    assert np.max(np.abs(tau0 - np.array(tau_raw).ravel())) < 1e-12
    rng, limit = np.random.default_rng(6), limit_arrays(arm.model)["tau"]
    good_theta, h, codes = THETA0, 1e-3, []
    for k in range(200):
        t = (k + 1) * h
        sample = [THETA0 + 0.3 * np.sin(t) * np.ones(3), 0.3 * np.cos(t) * np.ones(3), -0.3 * np.sin(t) * np.ones(3)]
        if rng.random() < 0.4:
            which = int(rng.integers(4))
            if which < 3:
                sample[which] = corrupt(rng, sample[which], BAD[:-1] + [1e5])      # 1e5 rad/s^2: absurd too
                tau, code = ff.step(*sample, h)
            else:
                tau, code = ff.step(*sample, [np.nan, -1.0, 1.0, 10.0][int(rng.integers(4))])
            psi = np.array(state).ravel()[:3]
            assert code == 7 and np.max(np.abs(tau - holding(arm, np.r_[good_theta, good_theta + psi]))) < 1e-9
        else:
            tau, code = ff.step(*sample, h)
            tau_raw, state = raw["feedforward_step"](state, *sample, h)
            assert code == 0 and np.max(np.abs(tau - np.clip(np.array(tau_raw).ravel(), -limit, limit))) < 1e-12, k
            good_theta = sample[0]
        assert np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= limit + 1e-12)
        codes.append(code)
    assert {0, 7} <= set(codes)
