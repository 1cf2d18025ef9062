"""fatrop called directly (its C interface, stage by stage) against fatrop through CasADi's
plugin: the same algorithm on the same compiled NLP functions, so the two must iterate alike;
what differs is only the mapping of the NLP to fatrop's stage blocks (CasADi's C++ runtime
against ours), which is what this checks."""
import dataclasses

import casadi as ca
import numpy as np
import pytest

from rscasadi.ocp import load_problem, solve_once, solvers
from rscasadi.ocp.fatrop.driver import _Layout
from rscasadi.model.modelfile import ModelFileError

from conftest import problem, raw_solve

QUIET = {"print_level": 0, "log": lambda m: None}


@pytest.mark.parametrize("case,over", [
    ("min_effort", {}),
    ("min_time", {"objective": "min_time", "max_duration": 5.0}),
    ("lifted", {"transcription": {"condense": False}}),               # collocation rows as path equalities
    ("codesign", {"objective": "min_time", "max_duration": 5.0,     # a design parameter carried as a state
                  "design": {"shoulder_pitch.sea.k1": [300.0, 3000.0]}}),
])
def test_direct_fatrop_iterates_as_casadis_plugin(pitch_arm, monkeypatch, case, over):
    tr = {"intervals": 16, "compiled": True, **over.get("transcription", {})}
    path = problem(pitch_arm, f"direct_{case}.toml", **{**over, "transcription": tr})
    out = {}
    for interface in ("casadi", "direct"):
        p = load_problem(path).replace(solver="fatrop", interface=interface)
        out[interface] = raw_solve(monkeypatch, p)
        assert out[interface][0]["success"], out[interface][0]["status"]
    (a, ra), (b, rb) = out["casadi"], out["direct"]
    assert rb["stats"]["raw_derivatives"]              # the pieces' derivatives, placed by the driver
    assert a["iterations"] == b["iterations"]
    for key in ("x", "lam_g", "lam_x"):                 # multipliers: signs and places of every row
        scale = max(1.0, np.max(np.abs(ra[key])))
        assert np.max(np.abs(ra[key] - rb[key])) <= 1e-9 * scale, key
    assert np.any(ra["lam_g"] != 0) and np.any(ra["lam_x"] != 0) or case == "lifted"


def test_direct_is_the_default_and_reports_fatrops_stats(pitch_arm):
    p = load_problem(problem(pitch_arm, "direct_default.toml", transcription={"intervals": 12, "compiled": True},
                             solver={"name": "fatrop"}))
    assert p.solver.interface == "direct" and solvers.direct(p)
    sol = solve_once(p, **QUIET)
    assert sol["status"] == "Solve_Succeeded" and sol["interface"] == "direct" and sol["iterations"] > 0


def test_bad_interface_is_named(pitch_arm):
    with pytest.raises(ModelFileError, match=r"field 'solver\.interface'.*direct, casadi"):
        load_problem(problem(pitch_arm, "bad_iface.toml", solver={"name": "fatrop", "interface": "acados"}))


def test_direct_interface_needs_the_compiled_nlp(pitch_arm):
    with pytest.raises(ModelFileError, match=r"field 'solver\.interface'.*compiled"):
        load_problem(problem(pitch_arm, "direct_vm.toml", transcription={"condense": False},
                             solver={"name": "fatrop", "interface": "direct"}))
    # by default, an uncompiled problem goes through CasADi's plugin
    p = load_problem(problem(pitch_arm, "vm.toml", transcription={"condense": False}, solver={"name": "fatrop"}))
    assert not solvers.direct(p)


def _triplets(sp: ca.Sparsity):
    return sp.shape, np.array(sp.row()), np.repeat(np.arange(sp.size2()), np.diff(sp.colind()))


def test_layout_refuses_what_is_not_stage_wise():
    # two stages of nx = 1, nu = 1 and a last state: variables x0 u0 x1 u1 x2; rows: gap 0, gap 1
    nx, nu, ng = [1, 1, 1], [1, 1, 0], [0, 0, 0]
    no = np.zeros(2, bool), np.zeros(2, bool), np.zeros(5, bool), np.zeros(5, bool)
    good = ca.sparsify(ca.DM([[1, 1, 1, 0, 0], [0, 0, 1, 1, 1]])).sparsity()
    hess = ca.Sparsity.diag(5)
    _Layout(nx, nu, ng, _triplets(good), _triplets(hess), *no)
    coupled = ca.sparsify(ca.DM([[1, 1, 1, 0, 1], [0, 0, 1, 1, 1]])).sparsity()      # gap 0 depends on x2
    with pytest.raises(ValueError, match="row 0 .*variable 4"):
        _Layout(nx, nu, ng, _triplets(coupled), _triplets(hess), *no)
    hess_coupled = ca.sparsify(ca.DM([[1, 0, 1, 0, 0], [0, 1, 0, 0, 0], [1, 0, 1, 0, 0], [0, 0, 0, 1, 0], [0, 0, 0, 0, 1]])).sparsity()
    with pytest.raises(ValueError, match="couples stages: variables 2 and 0|couples stages: variables 0 and 2"):
        _Layout(nx, nu, ng, _triplets(good), _triplets(hess_coupled), *no)


def test_layout_adds_the_hessian_nonzeros_that_share_a_place():
    # pieces overlap in the Hessian (the start piece and stage 0 at x_0): the driver writes each
    # place's first nonzero and adds the others
    nx, nu, ng = [1, 1, 1], [1, 1, 0], [0, 0, 0]
    no = np.zeros(2, bool), np.zeros(2, bool), np.zeros(5, bool), np.zeros(5, bool)
    jac = ca.sparsify(ca.DM([[1, 1, 1, 0, 0], [0, 0, 1, 1, 1]])).sparsity()
    hess = ((5, 5), np.array([0, 1, 0, 4, 0]), np.array([0, 1, 0, 4, 1]))      # (0, 0) twice
    L = _Layout(nx, nu, ng, _triplets(jac), hess, *no)
    ht = L.arrays["ht"]
    assert list(L.arrays["hadd"]) == [2] and ht[2] == -1 and L.arrays["hadd_to"][0] == ht[0] >= 0
    assert len(set(ht[ht >= 0])) == 4


def test_unknown_fatrop_option_is_named(pitch_arm):
    p = load_problem(problem(pitch_arm, "direct_opt.toml", transcription={"intervals": 12, "compiled": True}))
    with pytest.raises(ValueError, match="no_such_option"):
        solve_once(p, options={"no_such_option": 1.0}, **QUIET)


def test_a_quiet_solve_does_not_silence_the_next_one(pitch_arm, capfd):
    # fatrop keeps the last writer for the whole process
    p = load_problem(problem(pitch_arm, "direct_log.toml", transcription={"intervals": 12, "compiled": True}))
    solve_once(p, **QUIET)
    assert "inf_pr" not in capfd.readouterr().out
    solve_once(p, print_level=5, log=lambda m: None)
    assert "inf_pr" in capfd.readouterr().out


def _tiny_ocp(tmp_path, sign=1.0):
    """min sum u_k^2 + c x_3^2 s.t. x_{k+1} = x_k + u_k, x_0 = 1, |u_k| <= 10, x_k + u_k <= 100:
    u_k = -c / (1 + 3c) for every k.  The NLP's functions under the fatrop plugin's signatures,
    written here by hand (no transcription), gap rows sign * (x_{k+1} - x_k - u_k)."""
    from rscasadi.native.build import compiler
    import subprocess
    x = ca.SX.sym("x", 7)                                   # x0 u0 x1 u1 x2 u2 x3
    c = ca.SX.sym("p")
    xs, us = x[[0, 2, 4, 6]], x[[1, 3, 5]]
    g = []
    for k in range(3):
        g += [sign * (xs[k + 1] - xs[k] - us[k]), xs[k] + us[k]]        # gap row, then a path row
    g = ca.vertcat(*g)
    f = ca.sumsqr(us) + c * xs[3] ** 2
    lam_f, lam_g = ca.SX.sym("lam_f"), ca.SX.sym("lam_g", g.numel())
    lag = lam_f * f + ca.dot(lam_g, g)
    H, grad = ca.hessian(lag, x)
    fns = [ca.Function("nlp_f", [x, c], [f]), ca.Function("nlp_g", [x, c], [g]),
           ca.Function("nlp_grad_f", [x, c], [ca.gradient(f, x)]),
           ca.Function("nlp_jac_g", [x, c], [g, ca.jacobian(g, x)]),
           ca.Function("nlp_hess_l", [x, c, lam_f, lam_g], [grad, H])]
    cg = ca.CodeGenerator("tiny_ocp.c", {"with_header": False})
    for fn in fns:
        cg.add(fn)
    cg.generate(str(tmp_path) + "/")
    lib = tmp_path / "tiny_ocp.so"
    subprocess.run([*compiler(), "-O1", "-fPIC", "-shared", str(tmp_path / "tiny_ocp.c"), "-o", str(lib), "-lm"], check=True)
    return str(lib), {"N": 3, "nx": [1, 1, 1, 1], "nu": [1, 1, 1, 0], "ng": [1, 1, 1, 0]}


def test_direct_fatrop_solves_a_small_ocp_to_its_closed_form(tmp_path):
    from rscasadi.ocp.fatrop.driver import DirectFatrop
    lib, structure = _tiny_ocp(tmp_path)
    inf = np.inf
    lbx = [1.0, -10, -inf, -10, -inf, -10, -inf]
    ubx = [1.0, 10, inf, 10, inf, 10, inf]
    solver = DirectFatrop(lib, structure, {"tol": 1e-10, "print_level": 0})
    res = solver(x0=np.zeros(7), lbx=lbx, ubx=ubx, lbg=[0, -inf] * 3, ubg=[0, 100] * 3, p=10.0)
    assert solver.stats()["success"]
    u = -10.0 / 31.0
    assert np.allclose(res["x"], [1, u, 1 + u, u, 1 + 2 * u, u, 1 + 3 * u], atol=1e-8)
    # KKT: stationarity in u_0 with the gap multipliers (CasADi's sign convention: + lam_g' g)
    assert abs(2 * u - res["lam_g"][0]) < 1e-7


def test_a_gap_row_of_the_wrong_sign_is_refused(tmp_path):
    from rscasadi.ocp.fatrop.driver import DirectFatrop
    lib, structure = _tiny_ocp(tmp_path, sign=-1.0)
    solver = DirectFatrop(lib, structure, {"print_level": 0})
    with pytest.raises(ValueError, match=r"x_\{k\+1\} - F_k"):
        solver(x0=np.zeros(7), lbx=[1.0] + [-np.inf] * 6, ubx=[1.0] + [np.inf] * 6, lbg=[0, -np.inf] * 3,
               ubg=[0, 100] * 3, p=10.0)


def test_direct_fatrop_solves_from_two_threads(tmp_path):
    # the driver's state is per call (and fatrop's process-wide writer behind a lock): solves from
    # threads of one process each find their own closed form
    from concurrent.futures import ThreadPoolExecutor
    from rscasadi.ocp.fatrop.driver import DirectFatrop
    lib, structure = _tiny_ocp(tmp_path)
    inf = np.inf

    def one(c):
        solver = DirectFatrop(lib, structure, {"tol": 1e-10, "print_level": 0})
        res = solver(x0=np.zeros(7), lbx=[1.0] + [-inf] * 6, ubx=[1.0] + [inf] * 6, lbg=[0, -inf] * 3,
                     ubg=[0, 100] * 3, p=c)
        return solver.stats()["success"], res["x"][1]
    with ThreadPoolExecutor(4) as pool:
        out = list(pool.map(one, [1.0, 10.0, 100.0, 1000.0] * 3))
    for (ok, u), c in zip(out, [1.0, 10.0, 100.0, 1000.0] * 3):
        assert ok and abs(u + c / (1 + 3 * c)) < 1e-8


def test_a_reused_solver_iterates_as_a_new_one(pitch_arm, monkeypatch):
    # fatrop's solver is built once per layout and reused: every solve must start afresh (iterates,
    # bounds, barrier parameter, filter), so a solve after others equals a new solver's, bit for bit
    # (lifted: no condensing kernel, whose warm starts would differ in the last bits)
    from rscasadi.ocp.fatrop.driver import DirectFatrop
    p = load_problem(problem(pitch_arm, "reuse.toml", transcription={"intervals": 12, "condense": False, "compiled": True},
                             solver={"name": "fatrop", "interface": "direct", "barrier": "monotone"}))
    _, raw = raw_solve(monkeypatch, p)
    s, kw = raw["solver"], raw["args"]
    first = s(**kw)
    it_first = s.stats()["iter_count"]
    lbx, ubx = np.array(kw["lbx"], float).ravel(), np.array(kw["ubx"], float).ravel()
    finite = np.isfinite(lbx) & np.isfinite(ubx) & (lbx < ubx)
    shrink = 0.01 * np.where(finite, ubx - lbx, 0.0)
    other = {**kw, "x0": np.array(kw["x0"], float).ravel() * 0.5,                 # another start and bounds
             "lbx": lbx + shrink, "ubx": ubx - shrink}
    second = s(**other)
    assert s.stats()["success"] and len(s._sessions) == 1
    fresh = DirectFatrop(s.library, s.structure, dict(s.options), places=s.places, pieces=s.pieces)
    alone = fresh(**other)
    assert fresh.stats()["iter_count"] == s.stats()["iter_count"]
    for key in ("x", "lam_g", "lam_x"):
        assert np.array_equal(second[key], alone[key]), key
    again = s(**kw)
    assert s.stats()["iter_count"] == it_first
    for key in ("x", "lam_g", "lam_x"):
        assert np.array_equal(again[key], first[key]), key
    assert not np.array_equal(second["x"], first["x"])          # the second solve did solve another problem


def test_a_quiet_solver_stays_quiet_beside_a_verbose_one(tmp_path, capfd):
    # one process-wide writer for every (kept) solver: it prints only for a verbose solve
    from rscasadi.ocp.fatrop.driver import DirectFatrop
    lib, structure = _tiny_ocp(tmp_path)
    inf = np.inf
    args = dict(x0=np.zeros(7), lbx=[1.0] + [-inf] * 6, ubx=[1.0] + [inf] * 6, lbg=[0, -inf] * 3, ubg=[0, 100] * 3, p=10.0)
    loud, quiet = DirectFatrop(lib, structure, {"print_level": 5}), DirectFatrop(lib, structure, {"print_level": 0})
    for solver, heard in ((loud, True), (quiet, False), (loud, True), (quiet, False)):
        solver(**args)
        assert ("inf_pr" in capfd.readouterr().out) == heard
