"""The NLP's derivatives assembled stage by stage (assembly.py; the stage's by the chain rule
through its model calls) against CasADi's AD of the whole NLP graph: every objective, explicit and
implicit dynamics, design variables carried as states, fixed model parameters, random points and
multipliers; and the functions a compiled solver loads are those assembled ones."""

import casadi as ca
import numpy as np
import pytest

from rscasadi.ocp import load_problem, solve, solve_once
from rscasadi.ocp.assembly import Piece, assembled, derivative_functions, solver_functions
from rscasadi.ocp.solvers import options
from rscasadi.ocp.transcription import Transcription
from rscasadi.dynamics.arm import Arm
from rscasadi.model.modelfile import read
from rscasadi.model.parameters import with_values

from conftest import REFERENCE, problem


def transcription(name, N=5, **over):
    """The lifted NLP (condense = false): its every function is CasADi's, so AD can check it."""
    p = load_problem(REFERENCE.parent / f"{name}.toml").replace(intervals=N, **{"condense": False, **over})
    tr = Transcription(p, Arm(read(p.task.model)), N=N)
    return tr, *tr.nlp()


def whole_graph_ad(nlp):
    """Reference: CasADi's AD of the NLP as one expression."""
    w, P, f, g = nlp["x"], nlp["p"], nlp["f"], nlp["g"]
    lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", g.numel())
    H, grad_l = ca.hessian(lam_f * f + ca.dot(lam_g, g), w)
    return ca.Function("ref", [w, P, lam_f, lam_g],
                       [ca.gradient(f, w), ca.jacobian(g, w), grad_l, H, ca.triu(H)]), (lam_f, lam_g)


@pytest.mark.parametrize("name,over", [
    ("ocp_min_effort", {}), ("ocp_min_effort", {"dynamics": "implicit"}), ("ocp_min_time", {}),
    ("ocp_tracking", {}), ("ocp_min_time_codesign", {}), ("ocp_min_time_gear_codesign", {}),
    ("ocp_tracking", {"design": {"elbow_pitch.gear_ratio": (40.0, 160.0)}}),
    ("ocp_min_effort", {"parameters": {"elbow_pitch.sea.k1": 700.0, "shoulder_pitch.link.mass": 2.0}}),
    ("ocp_min_effort", {"parameters": {"elbow_pitch.gear_ratio": 90.0}}),
    ("ocp_min_time", {"method": "hermite-simpson"}), ("ocp_min_effort", {"method": "legendre", "dynamics": "implicit"}),
])
def test_assembled_derivatives_equal_ad_of_the_whole_nlp(name, over):
    tr, nlp, lbg, ubg = transcription(name, **over)
    _check_against_ad(tr, nlp)
    assert len(lbg) == len(ubg) == nlp["g"].numel()


def _check_against_ad(tr, nlp, seed=7):
    ref, (lam_f, lam_g) = whole_graph_ad(nlp)
    a = assembled(tr.pieces, nlp["x"], lam_f, lam_g, nlp["g"].numel())
    mine = ca.Function("mine", [nlp["x"], nlp["p"], lam_f, lam_g],
                       [a["grad_f"], a["jac_g"], a["grad_l"], a["hess"], a["triu_hess"]])
    rng = np.random.default_rng(seed)
    for _ in range(2):
        w = 0.3 * rng.standard_normal(nlp["x"].numel())
        P = 0.1 + rng.random(nlp["p"].numel())
        lam = rng.standard_normal(nlp["g"].numel())
        for k, (r, m) in enumerate(zip(ref(w, P, 0.7, lam), mine(w, P, 0.7, lam))):
            assert r.sparsity() == m.sparsity(), f"output {k}: sparsity"
            assert float(ca.norm_inf(r - m)) <= 1e-12 * max(1.0, float(ca.norm_inf(r))), f"output {k}"


def test_another_mesh_reuses_the_stage_derivatives_and_another_stage_does_not():
    """A refinement round's NLP (more intervals, same stage) takes the stage's derivatives built
    for the first round, and they are right there; a stage that differs (in one spring's
    stiffness, a number the stage's code holds) gets its own."""
    tr4, *_ = transcription("ocp_min_effort", N=4, dynamics="implicit")
    tr7, nlp, _, _ = transcription("ocp_min_effort", N=7, dynamics="implicit")
    assert tr7.pieces[0].derivatives is tr4.pieces[0].derivatives
    _check_against_ad(tr7, nlp, seed=11)
    stiffer = Arm(with_values(read(tr4.p.task.model), {f"{tr4.model.joints[-1].name}.sea.k1": 1.01 * tr4.model.joints[-1].k1}))
    other = Transcription(tr4.p, stiffer, N=4)
    other.nlp()
    assert other.pieces[0].derivatives is not tr4.pieces[0].derivatives


@pytest.mark.parametrize("solver", ["fatrop", "ipopt"])
def test_solver_loads_assembled_functions_with_its_own_signatures(solver):
    tr, nlp, lbg, ubg = transcription("ocp_min_time", solver=solver)
    plain = ca.nlpsol("plain", solver, nlp, options(tr.p, tr, 0))
    funcs = {f.name(): f for f in solver_functions(plain, nlp, tr.pieces)}
    assert {"nlp", "nlp_f", "nlp_g", "nlp_grad_f", "nlp_jac_g", "nlp_hess_l"} <= set(funcs)
    rng = np.random.default_rng(3)
    args = {"x": 0.3 * rng.standard_normal(nlp["x"].numel()), "p": 0.1 + rng.random(nlp["p"].numel()),
            "lam_f": 0.5, "lam_g": rng.standard_normal(nlp["g"].numel())}
    for name in ("nlp_grad_f", "nlp_jac_g", "nlp_hess_l"):
        theirs, mine = plain.get_function(name), funcs[name]
        assert theirs.name_in() == mine.name_in() and theirs.name_out() == mine.name_out()
        expect = theirs.call({k: args[k] for k in theirs.name_in()})
        got = mine.call({k: args[k] for k in mine.name_in()})
        for key in theirs.name_out():
            scale = max(1.0, float(ca.norm_inf(expect[key])))
            assert float(ca.norm_inf(ca.densify(expect[key]) - ca.densify(got[key]))) <= 1e-12 * scale, (name, key)


def test_a_compiled_piece_is_its_functions_for_any_mesh():
    """Each piece compiles into a library of its own: its externals give the SX functions'
    values to 1e-12 at random points; the stage of another mesh (a refinement round) is the same
    library and compiles nothing; the lifted NLP solved on two meshes, compiled, ends where
    CasADi's virtual machine ends."""
    from rscasadi.ocp.assembly import derivative_functions
    from rscasadi.ocp.solvers import compiled_piece
    tr, *_ = transcription("ocp_min_time", N=4)
    rng = np.random.default_rng(5)
    for piece in tr.pieces:
        built = compiled_piece(piece, "-O1", log=lambda m: None)
        assert built.library and built.fn.is_a("MXFunction")
        for ours, theirs in zip((built.fn, *built.derivatives), (piece.fn, *derivative_functions(piece))):
            args = [rng.standard_normal(theirs.sparsity_in(i).shape) for i in range(theirs.n_in())]
            for a, b in zip(ours.call(args), theirs.call(args)):
                assert float(ca.norm_inf(a - b)) <= 1e-12 * max(1.0, float(ca.norm_inf(b)))
    lines = []
    tr7, *_ = transcription("ocp_min_time", N=7)
    again = compiled_piece(tr7.pieces[0], "-O1", log=lines.append)
    assert again.library == compiled_piece(tr.pieces[0], "-O1").library and lines == []
    ends = {}
    for compiled in (True, False):
        p = load_problem(REFERENCE.parent / "ocp_min_time.toml").replace(intervals=10, condense=False, compiled=compiled,
                                                                          solver="ipopt", rounds=1)
        ends[compiled] = solve(p, log=lambda m: None, print_level=0)
    assert [r["intervals"] for r in ends[True]["rounds"]] == [r["intervals"] for r in ends[False]["rounds"]]
    assert abs(ends[True]["objective"] - ends[False]["objective"]) < 1e-7 * ends[False]["objective"]


def test_compiled_limited_memory_ipopt_needs_no_hessian(pitch_arm):
    """With a quasi-Newton Hessian there is no nlp_hess_l to assemble: the library is built
    without it and the solve succeeds, at the optimum the exact Hessian finds."""
    sols = {}
    for hessian in ("exact", "limited-memory"):
        path = problem(pitch_arm, f"lm_{hessian}.toml", transcription={"intervals": 20, "compiled": True},
                       solver={"name": "ipopt", "hessian": hessian})
        sols[hessian] = solve_once(load_problem(path), print_level=0, log=lambda m: None)
        assert sols[hessian]["success"], sols[hessian]["status"]
    assert abs(sols["exact"]["objective"] - sols["limited-memory"]["objective"]) < 1e-5 * sols["exact"]["objective"]


@pytest.mark.parametrize("dynamics", ["explicit", "implicit"])
def test_stage_derivatives_go_through_the_model_calls(dynamics):
    """The stage's own Jacobian and Hessian (chain rule through its forward- or inverse-dynamics
    calls) are less than half the code of AD through the inlined stage, which is why they exist."""
    tr, *_ = transcription("ocp_min_time", dynamics=dynamics)
    stage = tr.pieces[0]
    assert stage.derivatives is not None
    by_ad = derivative_functions(Piece(stage.fn, stage.cols, stage.rows, stage.args))
    for own, ad in zip(stage.derivatives, by_ad):
        assert own.sparsity_out(1) == ad.sparsity_out(1)
    for k in (0, 2):                                   # (rows, J) and (grad L, H)
        assert stage.derivatives[k].n_instructions() < 0.5 * by_ad[k].n_instructions()
