"""Generated C: equal to its symbolic twin, right against independent references, reentrant,
and robust to hostile input."""
import json
import re
import shutil
import subprocess
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import rscasadi
from rscasadi.cli import main
from rscasadi.codegen import CodegenError, functions, generate
from rscasadi.files import OutputError
from rscasadi.reference.numeric import Numeric

from conftest import REFERENCE, cc, random_arm_doc, to_toml, write_arm

HERE = Path(__file__).resolve().parent


def rel(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300)


def test_manifest_describes_the_library(built):
    out, manifest = built
    assert json.loads((out / "manifest.json").read_text()) == manifest
    assert set(manifest) >= {"model", "header", "sources", "library", "functions"}
    assert (out / manifest["header"]).exists() and (out / manifest["library"]).exists()
    assert all((out / s).exists() for s in manifest["sources"])
    fd = manifest["functions"]["forward_dynamics"]
    assert fd["symbol"] == "forward_dynamics"
    assert [i["name"] for i in fd["inputs"]] == ["theta", "phi", "dtheta", "dphi", "tau"]
    assert fd["outputs"] == [{"name": "ddtheta", "rows": 3, "cols": 1}, {"name": "ddphi", "rows": 3, "cols": 1}]
    assert manifest["functions"]["forward_dynamics_jacobian"]["outputs"][0] == {"name": "jacobian", "rows": 6, "cols": 15}
    assert manifest["functions"]["inverse_dynamics_jacobian"]["outputs"][0]["cols"] == 18
    assert [o["name"] for o in manifest["functions"]["step_jacobian"]["outputs"]] == ["A", "B"]
    assert set(manifest["functions"]) == {"forward_dynamics", "inverse_dynamics", "reduced_forward_dynamics",
                                          "reduced_inverse_dynamics", "energy", "forward_dynamics_jacobian",
                                          "inverse_dynamics_jacobian", "step", "step_jacobian",
                                          "feedforward_init", "feedforward_step"}


def test_compiled_equals_symbolic_twin(built, arm3):
    out, manifest = built
    compiled = rscasadi.load_compiled(out)
    twins, _ = functions(arm3)
    rng = np.random.default_rng(21)
    for name in manifest["functions"]:
        f, g = compiled[name], twins[name]
        for _ in range(5):
            args = [rng.normal(size=(g.size1_in(i), g.size2_in(i))) for i in range(g.n_in())]
            for a, b in zip(f(*args) if f.n_out() > 1 else [f(*args)], g(*args) if g.n_out() > 1 else [g(*args)]):
                assert rel(np.array(a), np.array(b)) < 1e-12, name


def test_compiled_against_the_numerical_core(built, arm3):
    """Independent of the symbolic code: the Jacobian by finite differences of the numpy core,
    the RK4 step by a numpy RK4 on the core's forward dynamics."""
    c, num, n = rscasadi.load_compiled(built[0]), Numeric(arm3.model), 3
    rng = np.random.default_rng(22)
    x, tau, h = rng.uniform(-1, 1, 4 * n), rng.uniform(-0.2, 0.2, n), 1e-3
    z = np.concatenate([x, tau])

    def fd(z):
        return np.concatenate(num.forward_dynamics(*np.split(z[:4 * n], 4), z[4 * n:]))
    J = np.array(c["forward_dynamics_jacobian"](*np.split(x, 4), tau))
    eps = 1e-6
    J_fd = np.column_stack([(fd(z + eps * e) - fd(z - eps * e)) / (2 * eps) for e in np.eye(5 * n)])
    assert rel(J, J_fd) < 1e-6

    def f(x):
        return np.concatenate([x[2 * n:], fd(np.concatenate([x, tau]))])
    k1 = f(x); k2 = f(x + h / 2 * k1); k3 = f(x + h / 2 * k2); k4 = f(x + h * k3)
    assert rel(np.array(c["step"](x, tau, h)).ravel(), x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)) < 1e-12
    A, B = (np.array(v) for v in c["step_jacobian"](x, tau, h))
    step = lambda x, tau: np.array(c["step"](x, tau, h)).ravel()
    A_fd = np.column_stack([(step(x + eps * e, tau) - step(x - eps * e, tau)) / (2 * eps) for e in np.eye(4 * n)])
    B_fd = np.column_stack([(step(x, tau + eps * e) - step(x, tau - eps * e)) / (2 * eps) for e in np.eye(n)])
    assert rel(A, A_fd) < 1e-6 and rel(B, B_fd) < 1e-6


def test_rebuild_is_a_cache_hit(built, tmp_path):
    logs = []
    generate(REFERENCE, tmp_path / "again", opt="-O1", log=logs.append)
    assert any(m.startswith("cache hit") for m in logs)
    assert (tmp_path / "again" / "librscasadi_arm.so").read_bytes() == (built[0] / "librscasadi_arm.so").read_bytes()


def test_prefix_and_unbalanced_arm(tmp_path):
    rng = np.random.default_rng(23)
    path = write_arm(tmp_path, random_arm_doc(rng, 2))          # unbalanced rotors: no reduced model
    manifest = generate(path, tmp_path / "p", prefix="my_arm", opt="-O1", log=lambda m: None)
    assert set(manifest["omitted"]) == {"reduced_forward_dynamics", "reduced_inverse_dynamics"}
    assert manifest["functions"]["step"]["symbol"] == "my_arm_step"
    c, arm = rscasadi.load_compiled(tmp_path / "p"), rscasadi.load(path)
    x = [rng.normal(size=2) for _ in range(4)]
    assert rel(np.array(c["energy"](*x)), np.array(arm.energy()(*x))) < 1e-12
    header = "".join((tmp_path / "p" / h).read_text() for h in manifest["headers"])
    assert "int my_arm_forward_dynamics(" in header and manifest["headers"][0] == manifest["header"]


@pytest.mark.parametrize("which", ["reference arm", "kernel"])
def test_no_malloc_and_no_mutable_globals(built, kernel_built, which):
    out, manifest = built if which == "reference arm" else kernel_built[1:]
    for name in manifest["sources"] + manifest["headers"]:
        text = (out / name).read_text()
        assert not re.search(r"\b(malloc|calloc|realloc|free)\s*\(", text), name
        for line in text.splitlines():
            if line.startswith("static") and not re.match(r"static\s+const\b", line):
                assert "(" in line, f"{name}: mutable global: {line}"


@pytest.fixture(scope="module")
def kernel_built(tmp_path_factory, private_cache):
    """A random 5-joint arm (unbalanced rotors), past the straight-line SX step Jacobian: its
    library carries the structured C kernel.  (arm, directory, manifest)"""
    d = tmp_path_factory.mktemp("kernel")
    arm = rscasadi.load(write_arm(d, random_arm_doc(np.random.default_rng(20261123), 5), "arm5.toml"))
    return arm, d / "gen", generate(arm, d / "gen", opt="-O1", log=lambda m: None)


@pytest.mark.skipif(cc() is None, reason="no C compiler")
@pytest.mark.parametrize("which", ["reference arm", "kernel"])
def test_two_threads_at_once(built, kernel_built, tmp_path, which):
    out, n = (built[0], 3) if which == "reference arm" else (kernel_built[1], kernel_built[0].n)
    exe = tmp_path / "threads"
    subprocess.run([cc(), "-std=c99", "-Wall", "-Wextra", "-Werror", "-pthread", f"-DN={n}", f"-I{out}",
                    str(HERE / "c" / "threads.c"), f"-L{out}", "-lrscasadi_arm", f"-Wl,-rpath,{out}", "-lm",
                    "-o", str(exe)], check=True)
    run = subprocess.run([str(exe)], capture_output=True, text=True)
    assert run.returncode == 0 and "identical" in run.stdout, run.stdout + run.stderr


@pytest.mark.skipif(cc() is None or shutil.which("valgrind") is None, reason="no C compiler or valgrind")
def test_step_jacobian_kernel_is_valgrind_clean(kernel_built, tmp_path):
    """The kernel reads only what it wrote (padding columns included) and stays in its work vector."""
    arm, out, _ = kernel_built
    exe = tmp_path / "threads"
    subprocess.run([cc(), "-std=c99", "-O1", "-g", "-pthread", f"-DN={arm.n}", "-DREPEAT=2", f"-I{out}",
                    str(HERE / "c" / "threads.c"), f"-L{out}", "-lrscasadi_arm", f"-Wl,-rpath,{out}", "-lm",
                    "-o", str(exe)], check=True)
    run = subprocess.run(["valgrind", "--error-exitcode=3", "--quiet", str(exe)], capture_output=True, text=True)
    assert run.returncode == 0 and "identical" in run.stdout, run.stdout + run.stderr


def _ad_of_step(step, n, p=()):
    """The step Jacobian by CasADi's AD of the step itself: a route sharing no chain rule."""
    xs, us = ca.MX.sym("x", 4 * n), ca.MX.sym("u", n)
    hs = ca.MX.sym("h")
    return ca.Function("ad", [xs, us, hs], [ca.jacobian(step(xs, us, hs, *p), ca.vertcat(xs, us))])


def test_step_jacobian_kernel_equals_ad_of_the_step(kernel_built):
    arm, out, manifest = kernel_built
    n = arm.n
    assert "step_jacobian" in manifest["kernels"]
    assert "int step_jacobian(" in (out / manifest["header"]).read_text()
    lib = rscasadi.load_compiled(out)
    ad = _ad_of_step(functions(arm)[0]["step"], n)
    rng = np.random.default_rng(7)
    for h in (1e-3, 4e-3):
        x, tau = rng.normal(size=4 * n) * 0.3, rng.normal(size=n) * 0.2
        ref = np.array(ad(x, tau, h))
        got = np.hstack([np.array(v) for v in lib["step_jacobian"](x, tau, h)])
        assert got.shape == ref.shape and rel(got, ref) < 1e-12
        assert rel(lib["step"](x, tau, h), functions(arm)[0]["step"](x, tau, h)) < 1e-12


def test_parametric_step_jacobian_kernel_takes_the_parameters(tmp_path):
    """The parametric kernel at parameters 10 % off the file's equals AD of the symbolic step
    at the same parameters, and differs from it at the file's."""
    arm = rscasadi.load(write_arm(tmp_path, random_arm_doc(np.random.default_rng(11), 4, balanced=True)))
    manifest = generate(arm, tmp_path / "gen", opt="-O1", log=lambda m: None, parametric="all")
    assert "step_jacobian" in manifest["kernels"]
    lib = rscasadi.load_compiled(tmp_path / "gen")
    n, (_, nominal) = arm.n, arm.parameters()
    ps = ca.MX.sym("p", arm.n_p)
    step = functions(arm, parametric=True)[0]["step"]
    xs, us, hs = ca.MX.sym("x", 4 * n), ca.MX.sym("u", n), ca.MX.sym("h")
    ad = ca.Function("ad", [xs, us, hs, ps], [ca.jacobian(step(xs, us, hs, ps), ca.vertcat(xs, us))])
    rng = np.random.default_rng(3)
    x, tau = rng.normal(size=4 * n) * 0.3, rng.normal(size=n) * 0.2
    p = nominal * (1 + 0.1 * rng.uniform(-1, 1, nominal.size))
    got = np.hstack([np.array(v) for v in lib["step_jacobian"](x, tau, 2e-3, p)])
    assert rel(got, np.array(ad(x, tau, 2e-3, p))) < 1e-12
    assert rel(got, np.array(ad(x, tau, 2e-3, nominal))) > 1e-6


def test_hostile_names_never_reach_c(tmp_path):
    doc = random_arm_doc(np.random.default_rng(24), 2, balanced=True)
    evil = 'x"; system("rm -rf ~"); /* $(reboot) `id` */'
    doc["name"] = evil
    doc["joints"][0]["name"] = "j*/ #include <stdio.h> //"
    path = tmp_path / "evil.toml"
    path.write_text(to_toml(doc))
    assert rscasadi.load(path).model.name == evil
    manifest = generate(path, tmp_path / "out", opt="-O1", log=lambda m: None)
    for name in manifest["sources"] + manifest["headers"]:
        text = (tmp_path / "out" / name).read_text()
        assert "rm -rf" not in text and "reboot" not in text and "#include <stdio.h> //" not in text
    with pytest.raises(CodegenError, match="not a C identifier"):
        generate(path, tmp_path / "bad", prefix="a; rm -rf /", log=lambda m: None)
    assert not (tmp_path / "bad").exists()


def test_missing_compiler_and_failed_compile_leave_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("CC", "no-such-compiler-xyz")
    with pytest.raises(CodegenError, match="C compiler 'no-such-compiler-xyz' not found"):
        generate(REFERENCE, tmp_path / "out", log=lambda m: None)
    monkeypatch.setenv("CC", "false")                    # a "compiler" that always fails
    with pytest.raises(CodegenError, match="compiling .* failed"):
        generate(REFERENCE, tmp_path / "out", log=lambda m: None)
    assert list(tmp_path.iterdir()) == []


def test_unwritable_or_foreign_directory(tmp_path):
    """A file in the way, a read-only directory: refused before the work.  A directory of the
    user's: the outputs land beside their files, and a file of theirs that an output would
    replace is refused, untouched."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(OutputError, match="cannot write into"):
        generate(REFERENCE, blocker / "out", log=lambda m: None)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "precious.txt").write_text("keep me")
    manifest = generate(REFERENCE, foreign, opt="-O1", log=lambda m: None)
    assert (foreign / "precious.txt").read_text() == "keep me" and (foreign / manifest["header"]).exists()
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / manifest["header"]).write_text("my own header")
    with pytest.raises(OutputError, match=f"was not written by rscasadi.*{manifest['header']}"):
        generate(REFERENCE, taken, opt="-O1", log=lambda m: None)
    assert [p.name for p in taken.iterdir()] == [manifest["header"]]
    assert (taken / manifest["header"]).read_text() == "my own header"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "foreign", "taken"]


def test_parametric_library_serves_every_arm_with_the_same_joints(tmp_path, arm3):
    """`--parametric`: one library, the same source hash for an arm whose every physical number
    differs (no recompilation), equal to each arm's constant Functions at its own p."""
    from test_parameters import _other_arm
    import tomllib
    with open(REFERENCE, "rb") as fh:
        doc = tomllib.load(fh)
    other = _other_arm(tmp_path, doc, np.random.default_rng(17), balanced=True)
    m_a = generate(REFERENCE, tmp_path / "a", opt="-O1", log=lambda m: None, parametric="all")
    log = []
    m_b = generate(other, tmp_path / "b", opt="-O1", log=log.append, parametric="all")
    assert m_a["source_hash"] == m_b["source_hash"] and any("cache hit" in m for m in log)
    assert m_a["parameters"]["names"] == arm3.parameters()[0]
    assert [i["name"] for i in m_a["functions"]["step"]["inputs"]] == ["x", "tau", "h", "p"]
    lib = rscasadi.load_compiled(tmp_path / "a")
    rng = np.random.default_rng(18)
    for arm in (arm3, other):
        p = arm.parameters()[1]
        twins, _ = functions(arm)
        for name in ("forward_dynamics", "inverse_dynamics", "energy", "forward_dynamics_jacobian", "step",
                     "step_jacobian", "reduced_forward_dynamics"):
            g = twins[name]
            args = [rng.normal(size=(g.size1_in(i), g.size2_in(i))) for i in range(g.n_in())]
            if name.startswith("step"):
                args[2] = np.array([[1e-3]])                     # a 1 kHz step
            got, want = lib[name].call(args + [p]), g.call(args)
            for a, b in zip(got, want):
                assert rel(np.array(a), np.array(b)) < 1e-10, name


def test_family_library_folds_the_zeros_and_serves_every_arm_with_them(tmp_path, arm3):
    """`--parametric family`: p without the model's zero parameters; an arm with the same zeros and
    every other number changed gets the same library (cache hit) and equals its own constant
    Functions at its p; an arm with a number where the family has a zero is refused by name."""
    import copy
    import tomllib
    with open(REFERENCE, "rb") as fh:
        doc = tomllib.load(fh)
    rng = np.random.default_rng(21)
    same = copy.deepcopy(doc)                                 # every nonzero number scaled, zeros kept
    for jt in same["joints"]:
        for key in ("sea", "link", "slow_rotor", "fast_rotor"):
            for field, v in jt[key].items():
                if isinstance(v, list):                       # one factor: a balanced rotor stays one
                    f = rng.uniform(0.7, 1.3)
                    jt[key][field] = [x * f for x in v]
                elif v and field != "eps":
                    jt[key][field] = v * rng.uniform(0.7, 1.3)
    other = rscasadi.load(write_arm(tmp_path, same, "same_zeros.toml"))
    m_a = generate(REFERENCE, tmp_path / "a", opt="-O1", log=lambda m: None, parametric="family")
    log = []
    m_b = generate(other, tmp_path / "b", opt="-O1", log=log.append, parametric="family")
    names, values = arm3.parameters()
    zeros = [k for k, v in zip(names, values) if v == 0]
    assert m_a["parametric"] == "family" and m_a["parameters"]["zero"] == zeros and zeros
    assert m_a["source_hash"] == m_b["source_hash"] and any("cache hit" in m for m in log)
    tied = m_a["parameters"]["tied"]                          # balanced rotors stay balanced: Iyy is Ixx
    assert len(tied) == 6 and all(k.endswith(".Iyy") and v == k[:-3] + "Ixx" for k, v in tied.items())
    # the zeros folded and the balanced rotors in the joint frame: near the constant C's size
    assert m_a["functions"]["forward_dynamics"]["n_instructions"] < 1.2 * arm3.forward_dynamics().n_instructions()
    lib = rscasadi.load_compiled(tmp_path / "a")
    for arm in (arm3, other):
        p = lib.parameters_of(arm)
        assert len(p) == len(names) - len(zeros) - len(tied)
        twins, _ = functions(arm)
        for name in ("forward_dynamics", "forward_dynamics_jacobian", "step", "step_jacobian", "feedforward_step"):
            g = twins[name]
            args = [rng.normal(size=(g.size1_in(i), g.size2_in(i))) for i in range(g.n_in())]
            if name.startswith("step") or name == "feedforward_step":
                args[g.index_in("h")] = np.array([[1e-3]])
            for a, b in zip(lib[name].call(args + [p]), g.call(args)):
                assert rel(np.array(a), np.array(b)) < 1e-10, name
    unbalanced = copy.deepcopy(doc)
    unbalanced["joints"][1]["slow_rotor"]["com"] = [0.001, 0.0, 0.0]
    with pytest.raises(ValueError, match="shoulder_pitch.slow_rotor.mx"):
        lib.parameters_of(rscasadi.load(write_arm(tmp_path, unbalanced, "unbalanced.toml")))
    unbalanced["joints"][1]["slow_rotor"]["com"] = [0.0, 0.0, 0.0]
    unbalanced["joints"][2]["fast_rotor"]["inertia"][1] *= 1.1            # Iyy != Ixx
    with pytest.raises(ValueError, match="elbow_pitch.fast_rotor.Iyy"):
        lib.parameters_of(rscasadi.load(write_arm(tmp_path, unbalanced, "unbalanced.toml")))
    for wrong in ("some", True):                           # one type: none, all or family
        with pytest.raises(CodegenError, match="parametric .* not one of none, all, family"):
            generate(REFERENCE, tmp_path / "c", parametric=wrong)


def test_compiled_feedforward_equals_the_pipeline_over_the_paper_trajectory(built, arm3):
    """feedforward_init/step in C, run sample by sample at 1 kHz, give the torques of the
    paper's pipeline (whose tracking on the complete model is tested in test_simulation)."""
    from rscasadi.sim.simulation import feedforward
    from rscasadi.sim.trajectory import load_trajectory
    out, _ = built
    lib = rscasadi.load_compiled(out)
    traj = load_trajectory(REFERENCE.parent / "trajectory_arm3.toml")
    t = np.linspace(0, 2, 2001)
    want = feedforward(arm3, traj, t)["tau"]
    q = traj(t)
    tau, state = lib["feedforward_init"](q[0][:, 0], q[1][:, 0], q[2][:, 0])
    got = [np.array(tau).ravel()]
    for k in range(1, len(t)):
        tau, state = lib["feedforward_step"](state, q[0][:, k], q[1][:, k], q[2][:, k], 1e-3)
        got.append(np.array(tau).ravel())
    assert np.max(np.abs(np.array(got).T - want)) < 1e-9 * np.max(np.abs(want))


@pytest.mark.parametrize("n", [3, 12])
def test_structured_step_jacobian_equals_ad_of_the_step(n):
    """The step Jacobian by the structured chain rule (straight-line SX at n = 3, dense products
    at n = 12) equals CasADi's AD of the step function itself, a route sharing no chain rule."""
    import sys
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from common import chain_arm
    from rscasadi.codegen.generate import functions
    fns, _ = functions(chain_arm(n))
    step, step_jac = fns["step"], fns["step_jacobian"]
    assert step_jac.is_a("SXFunction") == (n == 3)
    rng = np.random.default_rng(n)
    xs, us = ca.MX.sym("x", 4 * n), ca.MX.sym("u", n)
    for h in (1e-3, 4e-3):
        ad = ca.Function("ad", [xs, us], [ca.jacobian(step(xs, us, h), ca.vertcat(xs, us))])
        x, tau = rng.normal(size=4 * n) * 0.3, rng.normal(size=n) * 0.2
        ref = np.array(ad(x, tau))
        got = np.hstack([np.array(v) for v in step_jac(x, tau, h)])
        assert np.max(np.abs(got - ref)) < 1e-12 * np.max(np.abs(ref))


# ----------------------------------------------------------------------------- task space in C

@pytest.fixture(scope="module")
def frames_built(tmp_path_factory, private_cache):
    """The reference arm with a tool frame, generated with --frames tool,elbow_pitch --external tool."""
    from rscasadi.model.modelfile import document
    d = tmp_path_factory.mktemp("frames")
    doc = document(rscasadi.load(REFERENCE).model)
    doc["frames"] = {"tool": {"parent": "elbow_pitch", "xyz": [0.3, 0.0, 0.02], "rpy": [0.0, 0.4, 0.1]}}
    path = write_arm(d, doc, "arm3_tool.toml")
    assert main(["codegen", str(path), "--out", str(d / "gen"), "--opt=-O1", "--frames", "tool,elbow_pitch",
                 "--external", "tool"]) in (0, None)
    return rscasadi.load(path), d / "gen"


def test_frame_functions_in_c_equal_the_symbolic_ones(frames_built):
    arm, out = frames_built
    lib, rng = rscasadi.load_compiled(out), np.random.default_rng(9)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["frames"] == {"tool": "tool", "elbow_pitch": "elbow_pitch"}
    x, tau, f = [rng.normal(size=3) for _ in range(4)], rng.normal(size=3), rng.normal(size=6)
    pairs = [(lib["frame_placement_tool"](x[0]), arm.frame_placement("tool")(x[0])),
             (lib["frame_jacobian_elbow_pitch_local"](x[0]), arm.frame_jacobian("elbow_pitch", "local")(x[0])),
             (lib["frame_velocity_tool_local_world_aligned"](x[0], x[2]), arm.frame_velocity("tool")(x[0], x[2])),
             (lib["frame_jacobian_dot_times_v_tool"](x[0], x[2]), arm.frame_jacobian_dot_times_v("tool")(x[0], x[2])),
             (lib["center_of_mass"](x[0], x[1]), arm.center_of_mass()(x[0], x[1])),
             (lib["forward_dynamics_external"](*x, tau, f), arm.forward_dynamics(external=["tool"])(*x, tau, f)),
             (lib["inverse_dynamics_external"](*x, tau, tau, f), arm.inverse_dynamics(external=["tool"])(*x, tau, tau, f))]
    for got, want in pairs:
        got, want = (got,) if not isinstance(got, tuple) else got, (want,) if not isinstance(want, tuple) else want
        for g, w in zip(got, want):
            assert rel(np.array(g), np.array(w)) < 1e-12


@pytest.mark.skipif(cc() is None, reason="no C compiler")
def test_frame_functions_in_c_two_threads_werror_and_valgrind(frames_built, tmp_path):
    arm, out = frames_built
    exe = tmp_path / "frames"
    subprocess.run([cc(), "-std=c99", "-O1", "-g", "-Wall", "-Wextra", "-Werror", "-pthread", "-DFRAMES", f"-I{out}",
                    str(HERE / "c" / "threads.c"), f"-L{out}", "-lrscasadi_arm", f"-Wl,-rpath,{out}", "-lm",
                    "-o", str(exe)], check=True)
    run = subprocess.run([str(exe)], capture_output=True, text=True)
    assert run.returncode == 0 and "identical" in run.stdout, run.stdout + run.stderr
    values = np.array(run.stdout.splitlines()[0].split(), float)          # thread 0's inputs, in C
    x = np.array([0.1 * (i + 1) for i in range(12)])
    R, p = (np.array(v) for v in arm.frame_placement("tool")(x[:3]))
    assert np.allclose(values[:9], R.ravel(order="F"), atol=1e-14) and np.allclose(values[9:12], p.ravel(), atol=1e-14)
    if shutil.which("valgrind"):
        subprocess.run([cc(), "-std=c99", "-O1", "-g", "-pthread", "-DREPEAT=2", "-DFRAMES", f"-I{out}",
                        str(HERE / "c" / "threads.c"),
                        f"-L{out}", "-lrscasadi_arm", f"-Wl,-rpath,{out}", "-lm", "-o", str(exe)], check=True)
        run = subprocess.run(["valgrind", "--error-exitcode=3", "--quiet", str(exe)], capture_output=True, text=True)
        assert run.returncode == 0 and "identical" in run.stdout, run.stderr


def test_frame_names_reach_c_only_as_identifiers(tmp_path, capsys):
    from rscasadi.model.modelfile import document
    doc = document(rscasadi.load(REFERENCE).model)
    doc["frames"] = {'tool"; system("id"); /*': {"parent": "elbow_pitch"}, "tool-1": {"parent": "elbow_pitch"},
                     "tool_1": {"parent": "elbow_pitch"}, "9lives": {"parent": "base"}}
    path = write_arm(tmp_path, doc, "hostile.toml")
    manifest = generate(path, tmp_path / "ok", opt="-O1", log=lambda m: None, frames=['tool"; system("id"); /*'])
    header = "".join((tmp_path / "ok" / h).read_text() for h in manifest["headers"])
    assert "frame_placement_tool_system_id(" in header and "system(\"" not in header
    for frames, words in ((["tool-1", "tool_1"], "not distinct"), (["9lives"], "C identifier"), (["nope"], "no frame")):
        with pytest.raises(rscasadi.CodegenError, match=words):
            generate(path, tmp_path / "bad", opt="-O1", log=lambda m: None, frames=frames)
        assert not (tmp_path / "bad").exists()
    assert main(["codegen", str(path), "--out", str(tmp_path / "cli"), "--external", "nope"]) == 2
    assert "--external" in capsys.readouterr().err
