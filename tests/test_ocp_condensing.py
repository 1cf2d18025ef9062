"""The condensed NLP (condensing.py): each interval's accelerations solved inside the NLP's
functions by a C kernel.  Checked against a second derivation that shares no code with the
kernel: CasADi's own Newton rootfinder on the *explicit* lifted stage (the kernel solves the
inverse-dynamics form) and CasADi's AD through that rootfinder for the Jacobians and Hessians;
and whole solves against the lifted NLP with the other solver."""
import ctypes
import platform

import casadi as ca
import numpy as np
import pytest

from rscasadi.ocp import load_problem, solve_once
from rscasadi.ocp.solving import guess
from rscasadi.ocp.transcription import Transcription
from rscasadi.dynamics.arm import Arm
from rscasadi.model.collision import with_collision
from rscasadi.model.modelfile import ModelFileError, read

from conftest import REFERENCE, problem

QUIET = {"print_level": 0, "log": lambda m: None}
# the reference arm's hand kept from its first link: a [collision] table whose clearance is one row
PAIRED = {"margin": 0.01, "tip": "tool", "links": {"shoulder_yaw": 0.05, "elbow_pitch": 0.03},
          "pairs": [["elbow_pitch", "shoulder_yaw"]]}


def _pair(name, N=4, **over):
    """The lifted (explicit) and the condensed transcription of one problem, built."""
    base = load_problem(REFERENCE.parent / f"{name}.toml").replace(intervals=N, **over)
    model = read(base.task.model)
    arm = Arm(with_collision(model, base.task.collision, "<test>") if base.task.collision else model)
    lifted = Transcription(base.replace(condense=False, dynamics="explicit"), arm, N=N)
    condensed = Transcription(base.replace(condense=True), arm, N=N)
    return base, arm, lifted, lifted.nlp(), condensed, condensed.nlp(log=lambda m: None)


def _reference(lifted, keep, elim, grows, rk):
    """Condensed stage by CasADi: rootfinder on the lifted stage's dynamics rows, AD through it."""
    fn = lifted.pieces[0].fn
    nz = fn.size1_in(0)
    w, y = ca.MX.sym("w", len(keep)), ca.MX.sym("y", len(elim))
    args = [ca.MX.sym(fn.name_in(i), fn.sparsity_in(i)) for i in range(1, fn.n_in())]
    place = lambda idx, v: ca.mtimes(ca.DM(ca.Sparsity.triplet(nz, len(idx), list(idx), list(range(len(idx)))), 1.0), v)
    rows, _ = fn(place(keep, w) + place(elim, y), *args)
    rf = ca.rootfinder("rf", "newton", ca.Function("G", [y, w, *args], [rows[grows]]), {"abstol": 1e-14})
    y0 = ca.MX.sym("y0", len(elim))
    ys = rf(y0, w, *args)
    rows, f = fn(place(keep, w) + place(elim, ys), *args)
    lam, lam_f = ca.MX.sym("lam", len(rk)), ca.MX.sym("lam_f")
    H, gL = ca.hessian(ca.dot(lam, rows[rk]) + lam_f * f, w)
    return ca.Function("ref", [w, y0, *args, lam, lam_f],
                       [ys, rows[rk], f, ca.jacobian(rows[rk], w), ca.gradient(f, w), gL, H])


def _instance_args(piece, P, P_sym, k):
    """The piece's arguments at instance k for the NLP parameters P."""
    values = ca.Function("a", [P_sym], [ca.MX(a) for a in piece.args])(P)
    values = values if isinstance(values, (list, tuple)) else [values]
    return [v[:, k] if v.size2() == piece.count and piece.count > 1 else v for v in values]


@pytest.mark.parametrize("name,over", [
    ("ocp_min_effort", {}), ("ocp_min_time", {}), ("ocp_tracking", {}), ("ocp_min_time_codesign", {}),
    ("ocp_min_effort", {"parameters": {"elbow_pitch.sea.k1": 700.0, "elbow_pitch.gear_ratio": 90.0}}),
    ("ocp_min_time", {"method": "legendre"}),
    ("ocp_reach_around", {}),               # clearance rows: a recorded call, its Jacobian formed in C
    ("ocp_min_effort", {"model": REFERENCE.parent / "arm3_tool.toml", "collision": PAIRED}),   # one row: a 1 x n Jacobian
])
def test_kernel_equals_casadi_rootfinder_and_its_ad(name, over):
    _kernel_equals_reference(name, over)


def test_a_kernel_left_warm_by_another_problem_still_solves_right():
    """The kernel's per-interval warm starts live in the library, shared by every problem of the
    same shape in a process: after another minimum-time problem (other poses and duration) has
    solved on it, with no reset, a warm start far from the new point must not land on one of
    collocation's spurious roots (accelerations 1e5 times too large)."""
    from rscasadi.ocp import Problem, Task, TranscriptionOptions, Verification
    from rscasadi.ocp.problem import Goal
    other = Problem(Task(REFERENCE.parent / "arm3_tool.toml", "min_time", duration=1.0, theta_start=[0.0, 0.3, -0.5],
                         goal=Goal("tool", [0.351, 0.392, 0.536])),                # the same arm, a goal for its tool
                    TranscriptionOptions(intervals=40), verification=Verification(rounds=0))
    assert solve_once(other, print_level=0, log=lambda m: None)["success"]
    _kernel_equals_reference("ocp_min_time", {})


def _points(name, over):
    """The lifted and condensed transcriptions of a problem, and two instances (the first and the
    last interval) near its first guess: (lifted, condensed, [(k, w, y0, args)])."""
    base, arm, lifted, (nlp_l, *_), cond, (nlp_c, *_) = _pair(name, **over)
    n, nx, nul, na = lifted.n, lifted.nx, lifted.nu_lifted, 2 * lifted.n * lifted.m
    keep = list(np.r_[np.arange(nx + n), nx + nul + np.arange(nx)])
    elim = list(nx + n + np.arange(na))
    N = lifted.N
    t = base.task.duration * np.linspace(0, 1, N + 1)
    w0 = guess(lifted, base, arm, t, None)
    P = lifted.parameters(base.task.theta_start, base.task.theta_end, base.task.duration, base.task.effort_weight, np.full(N, 1 / N),
                          None if not lifted.tracking else np.zeros((n, N)), list(base.task.parameters.values()))
    if lifted.tracking:
        from rscasadi.ocp.solving import _reference as reference_of
        P = lifted.parameters(reference_of(base, t[:1])[:, 0], None, base.task.duration, base.task.effort_weight,
                              np.full(N, 1 / N), reference_of(base, t)[:, 1:], list(base.task.parameters.values()))
    rng = np.random.default_rng(11)
    points = []
    for k in (0, N - 1):
        z = w0[lifted.pieces[0].cols[k]]
        w = z[keep] + 0.01 * rng.standard_normal(len(keep)) * (1 + np.abs(z[keep]))
        points.append((k, w, z[elim], _instance_args(cond.pieces[0], P, nlp_c["p"], k)))
    return lifted, cond, keep, elim, points


def _kernel_equals_reference(name, over):
    lifted, cond, keep, elim, points = _points(name, over)
    nx, na = lifted.nx, 2 * lifted.n * lifted.m
    grows = list(nx + np.arange(na))
    rk = [i for i in range(lifted.pieces[0].rows.shape[1]) if i not in grows]
    ref = _reference(lifted, keep, elim, grows, rk)
    kernel, piece = cond.kernel, cond.pieces[0]
    first, objective, second = piece.derivatives
    rng = np.random.default_rng(11)
    for k, w, y0, args in points:
        lam, lam_f = rng.standard_normal(len(rk)), 0.7
        y_ref, R, f, J, gf, gL, H = ref(w, y0, *args[:-1], lam, lam_f)
        scale = lambda a: max(1.0, float(ca.norm_inf(a)))
        y = kernel.newton(w, *args)
        assert float(ca.norm_inf(y - y_ref)) <= 1e-10 * scale(y_ref)
        R_k, f_k = piece.fn(w, *args)
        assert float(ca.norm_inf(R_k - R)) <= 1e-10 * scale(R) and abs(float(f_k - f)) <= 1e-12 * scale(f)
        assert float(ca.norm_inf(ca.densify(first(w, *args)[1]) - J)) <= 1e-9 * scale(J)
        assert float(ca.norm_inf(objective(w, *args)[1] - gf)) <= 1e-10 * scale(gf)
        gL_k, H_k = second(w, *args, lam, lam_f)
        assert float(ca.norm_inf(gL_k - gL)) <= 1e-9 * scale(gL)
        assert float(ca.norm_inf(ca.densify(H_k) - ca.densify(H))) <= 1e-8 * scale(H)
        assert np.allclose(np.array(ca.densify(H_k)), np.array(ca.densify(H_k)).T, rtol=0, atol=1e-12 * scale(H))


XINUSE = r"""
#include <cpuid.h>
/* 1 if the upper halves of the AVX registers are in use (XGETBV(1), bit 2), -1 if this
   processor cannot tell; compiled without AVX, so that it changes nothing it reads */
int upper_in_use(void) {
  unsigned a, b, c, d;
  if (!__get_cpuid(1, &a, &b, &c, &d) || !(c & (1u << 27)) || __get_cpuid_max(0, 0) < 0xD) return -1;
  __cpuid_count(0xD, 1, a, b, c, d);
  if (!(a & 4)) return -1;
  __asm__ volatile("xgetbv" : "=a"(a), "=d"(d) : "c"(1));
  return (int)((a >> 2) & 1);
}
"""


@pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"), reason="x86's AVX state")
def test_the_kernel_returns_with_the_vector_registers_clean():
    """Every function of a condensing kernel (built for this processor) returns with the upper
    halves of the AVX registers unused.  Its callers (fatrop, IPOPT, CasADi's own code) are SSE
    code, which runs many times slower while they are in use: libm's log 25x on this VM, a
    quarter of the Panda's minimum-time solve went to fatrop's barrier value through it."""
    from rscasadi.native.build import cached_library
    probe = ctypes.CDLL(str(cached_library({"xinuse.c": XINUSE}, ["-O1"], name="xinuse")))
    if probe.upper_in_use() < 0:
        pytest.skip("this processor does not report the AVX state in use")
    lifted, cond, keep, elim, points = _points("ocp_reach_around", {})
    piece = cond.pieces[0]
    first, objective, second = piece.derivatives
    rk = piece.fn.size1_out(0)
    for k, w, y0, args in points:
        calls = {"newton": lambda: cond.kernel.newton(w, *args), "rows": lambda: piece.fn(w, *args),
                 "first": lambda: first(w, *args), "objective": lambda: objective(w, *args),
                 "second": lambda: second(w, *args, np.ones(rk), 0.7)}
        for name, call in calls.items():
            call()
            assert probe.upper_in_use() == 0, f"the kernel's {name} left the AVX registers' upper halves in use"


def test_kernel_reports_a_failed_solve_instead_of_returning_garbage():
    *_, cond, (nlp_c, *_) = _pair("ocp_min_effort")
    piece = cond.pieces[0]
    args = [ca.DM.ones(piece.fn.sparsity_in(i)) * 0.5 for i in range(1, piece.fn.n_in() - 1)] + [ca.DM(0)]
    w = np.full(piece.fn.size1_in(0), np.nan)
    with pytest.raises(RuntimeError):
        piece.fn(w, *args)


@pytest.mark.parametrize("objective", ["min_effort", "min_time", "tracking"])
def test_condensed_solution_equals_the_lifted_one(objective):
    """Same optimum (N = 20): condensed and lifted with IPOPT agree to 1e-9 in the objective;
    fatrop (which stops at a looser point: 1e-7 apart even on one NLP) to 1e-6.  Tracking curves
    x_{k+1} alone: the condensed Hessian must not couple it with x_k (fatrop refuses that)."""
    base = load_problem(REFERENCE.parent / f"ocp_{objective}.toml").replace(intervals=20)
    lifted = solve_once(base.replace(condense=False, solver="ipopt"), **QUIET)
    for solver, tol in (("ipopt", 1e-9), ("fatrop", 1e-6)):
        cond = solve_once(base.replace(condense=True, solver=solver), **QUIET)
        assert cond["success"] and lifted["success"], (cond["status"], lifted["status"])
        assert abs(cond["objective"] - lifted["objective"]) <= tol * abs(lifted["objective"]), solver
        if solver == "ipopt":
            for key, rel in (("theta", 1e-4), ("tau", 1e-3)):
                a, b = np.asarray(cond[key]), np.asarray(lifted[key])
                assert np.max(np.abs(a - b)) <= rel * max(1.0, np.max(np.abs(b))), key


def test_condensed_solves_are_reproducible_in_one_process():
    """The kernel's cache is reset before each solve: the same problem twice gives the same bits."""
    base = load_problem(REFERENCE.parent / "ocp_min_effort.toml").replace(intervals=20)
    a, b = (solve_once(base, **QUIET) for _ in range(2))
    assert a["iterations"] == b["iterations"] and a["tau"] == b["tau"] and a["theta"] == b["theta"]


def test_condense_needs_compiled(pitch_arm):
    path = problem(pitch_arm, "bad.toml", transcription={"compiled": False, "condense": True})
    with pytest.raises(ModelFileError, match="transcription.condense"):
        load_problem(path)
    assert load_problem(problem(pitch_arm, "ok.toml", transcription={"compiled": False})).transcription.condense is False


def test_a_family_nlp_serves_another_arm_of_the_family_without_compiling(tmp_path):
    """`parametric = "family"`: the same minimum-time solution as the constant NLP; an arm with
    the same zeros and heavier links (as identification might give) finds the kernel and the NLP
    in the cache and gets the constant NLP's solution for its own numbers."""
    from conftest import heavier_reference
    other = heavier_reference(tmp_path)
    base = load_problem(REFERENCE.parent / "ocp_min_time.toml").replace(intervals=20)
    for model in (REFERENCE, other):
        plain = solve_once(base.replace(model=model), **QUIET)
        log = []
        fam = solve_once(base.replace(model=model, parametric="family"), print_level=0, log=log.append)
        assert plain["success"] and fam["success"]
        assert abs(fam["objective"] - plain["objective"]) <= 1e-7 * abs(plain["objective"])
        assert np.allclose(fam["tau"], plain["tau"], rtol=0, atol=1e-5 * np.abs(plain["tau"]).max())
    assert not any(m.startswith("compiling the") for m in log), log      # the second arm compiled nothing
    assert abs(plain["objective"] - solve_once(base, **QUIET)["objective"]) > 1e-4     # a different arm


CASADI_QUIET = '#pragma GCC diagnostic push\n#pragma GCC diagnostic ignored "-Wunused-parameter"\n'


def _strict_compile(casadi_part: str, ours: str, where):
    """Our C (a template filled in) under -Wall -Wextra -Werror; CasADi's generated functions before
    it keep their unused parameters."""
    from rscasadi.native.build import compiler
    source = where / "kernel.c"
    source.write_text(CASADI_QUIET + casadi_part + "#pragma GCC diagnostic pop\n" + ours)
    import subprocess
    run = subprocess.run([*compiler(), "-c", "-O1", "-Wall", "-Wextra", "-Werror", str(source), "-o",
                          str(where / "kernel.o")], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-3000:]


@pytest.mark.parametrize("name", ["ocp_min_time", "ocp_tracking"])
def test_the_condensing_kernel_compiles_without_warnings(name, monkeypatch, tmp_path):
    """templates/condensing_kernel.c as filled in for a problem, with every warning an error."""
    import rscasadi.ocp.condensing as condensing
    built = {}

    class Built(Exception):
        pass

    def capture(sources, *args, **kwargs):           # the source, not the library: compiled below
        built.update(sources)
        raise Built
    monkeypatch.setattr(condensing, "cached_library", capture)
    monkeypatch.setattr(condensing, "_KERNELS", {})                   # generated, not found by its key
    monkeypatch.setattr(condensing, "indexed", lambda key, build: (build(), False))
    base = load_problem(REFERENCE.parent / f"{name}.toml").replace(intervals=3)
    with pytest.raises(Built):
        Transcription(base, Arm(read(base.task.model)), N=3).nlp(log=lambda m: None)
    (kernel,) = [text for name, text in built.items() if name.endswith("kernel.c")]    # ours; CasADi's apart
    _strict_compile("", kernel, tmp_path)


@pytest.mark.parametrize("parametric, chained, method", [(False, False, "rk4"), (True, False, "rk4"), (False, True, "rk4"),
                                                     (True, True, "rk4"), (False, True, "ros2"), (True, True, "ros2"),
                                                     (False, False, "ros2"), (False, False, "fd_jacobian"),
                                                     (True, False, "fd_jacobian")])
@pytest.mark.parametrize("pieces", [False, True])
def test_the_step_kernel_compiles_without_warnings(parametric, chained, method, pieces, tmp_path, monkeypatch):
    """templates/step_kernel.c as filled in for an arm (the reference arm: the template's C is
    the same for every arm, the unrolled blocks follow its patterns), every warning an error;
    also as the MPC's chained substep (its products and the step), with either integrator's step,
    and as the forward dynamics' Jacobian; with dr/dx in pieces (codegen.lanes) or CasADi's."""
    import rscasadi.codegen.step_kernel as step_kernel
    monkeypatch.setattr(step_kernel, "JR_PIECES_FROM", 0 if pieces else 10 ** 9)
    from rscasadi.codegen.step_kernel import kernel_source
    from rscasadi.native.build import casadi_c
    kernel = kernel_source(Arm(read(REFERENCE)), "arm_step_jacobian", parametric, chained, method)
    _strict_compile(casadi_c(kernel.functions, "kernel.c"), kernel.body, tmp_path)
