"""fatrop called directly, stage by stage, through its C interface (the header and library ship
in the CasADi wheel), on the same compiled NLP functions CasADi's fatrop plugin would call.

Why: on problem (b) the plugin spent 0.021 s of a 0.114 s solve between fatrop and the NLP's
functions (fatrop's evaluation timers against CasADi's: three sparse projections of the whole
Jacobian per evaluation, the Hessian's, row-by-row packing, the function-call layers).  Here the
Jacobian's and Hessian's nonzeros go straight to fatrop's stage blocks by index maps made once
per NLP layout (fatrop_direct.c for the conventions).  Same algorithm, same options, same
iterates: the tests compare it with the plugin iteration for iteration.

`DirectFatrop(library, structure)` is called like a CasADi nlpsol (x0, lbx, ubx, lbg, ubg, p)
and has `stats()` in the plugin's words.
"""
from __future__ import annotations

import ctypes
import fcntl
import hashlib
import os
import subprocess
import time
from pathlib import Path

import casadi as ca
import numpy as np

from ...codegen import _compiler, cache_dir

_SOURCE = Path(__file__).with_name("fatrop_direct.c")
_NAMES = ("nlp_f", "nlp_g", "nlp_grad_f", "nlp_jac_g", "nlp_hess_l")
_STATS = ("compute_sd_time", "duinf_time", "eval_hess_time", "eval_jac_time", "eval_cv_time", "eval_grad_time",
          "eval_obj_time", "initialization_time", "time_total", "eval_hess_count", "eval_jac_count",
          "eval_cv_count", "eval_grad_count", "eval_obj_count", "iterations_count", "return_flag")
_I = ctypes.POINTER(ctypes.c_int)
_LAYOUTS: dict = {}
_Dp = ctypes.POINTER(ctypes.c_double)


class _Problem(ctypes.Structure):
    _fields_ = ([(k, ctypes.c_int) for k in ("K", "nv", "ng")]
                + [(k, _I) for k in ("nx", "nu", "xoff", "roff", "a_eq", "a_eq_idx", "a_in", "a_in_idx",
                                     "x_eq", "x_eq_idx", "x_in", "x_in_idx")]
                + [(k, ctypes.c_int) for k in ("nnz_j", "nnz_h", "n_jbuf", "n_hbuf")]
                + [("jt", _I), ("ht", _I), ("js", _Dp)]
                + [(k, _I) for k in ("bab_off", "geq_off", "gin_off", "rsq_off")]
                + [(k, ctypes.c_void_p) for k in ("f", "g", "grad_f", "jac_g", "hess_l")]
                + [(k, ctypes.c_int) for k in ("sz_arg", "sz_res", "sz_iw", "sz_w")])


def casadi_dir() -> Path:
    return Path(ca.__file__).parent


def driver_library(log=print) -> str:
    """The compiled driver (once per machine and CasADi version; cached by the hash of its source)."""
    cc, inc, lib_dir = _compiler(), casadi_dir() / "include", casadi_dir()
    for need in (inc / "fatrop" / "ocp" / "OCPCInterface.h", inc / "blasfeo.h"):
        if not need.exists():
            raise RuntimeError(f"fatrop's C interface is missing from this CasADi ({ca.__version__}): {need}")
    flags = ["-O2", "-fPIC", "-shared", f"-I{inc}", f"-L{lib_dir}", "-lfatrop", "-lblasfeo", f"-Wl,-rpath,{lib_dir}", "-lm"]
    source = _SOURCE.read_text()
    key = hashlib.sha256((source + " ".join(cc + flags) + ca.__version__).encode()).hexdigest()[:24]
    directory = cache_dir() / "nlp"
    directory.mkdir(parents=True, exist_ok=True)
    lib = directory / f"fatrop_direct_{key}.so"
    if lib.exists():
        return str(lib)
    with open(directory / "generate.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if lib.exists():
            return str(lib)
        t0 = time.perf_counter()
        part = lib.with_suffix(f".{os.getpid()}.part")
        run = subprocess.run([*cc, str(_SOURCE), "-o", str(part), *flags], capture_output=True, text=True)
        if run.returncode != 0:
            raise RuntimeError(f"compiling the direct fatrop driver failed:\n{run.stderr[-2000:]}")
        part.replace(lib)
        log(f"compiled the direct fatrop driver in {time.perf_counter() - t0:.1f} s: {lib}")
    return str(lib)


def _ints(v) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(v, dtype=np.intc).reshape(-1))


class _Layout:
    """Where every row, variable and nonzero of the NLP goes in fatrop's stage blocks, for one
    classification of rows and variables into equalities, inequalities and free ones."""

    def __init__(self, nx, nu, ng, jac: tuple, hess: tuple, eq_g, in_g, eq_x, in_x):
        K = len(nx)
        nx, nu, ng = (np.asarray(v, int) for v in (nx, nu, ng))
        xoff = np.concatenate([[0], np.cumsum(nx + nu)[:-1]])
        gaps = np.append(nx[1:], 0)
        roff = np.concatenate([[0], np.cumsum(gaps + ng)[:-1]])
        nv, nrow = int(np.sum(nx + nu)), int(np.sum(gaps + ng))
        (jac_shape, r, c), (hess_shape, hr, hc) = jac, hess
        if jac_shape != (nrow, nv) or hess_shape != (nv, nv):
            raise ValueError(f"NLP of {jac_shape[0]} rows and {nv} variables does not match the stage "
                             f"structure ({nrow} rows, {int(np.sum(nx + nu))} variables)")
        v_stage = np.repeat(np.arange(K), nx + nu)
        v_pos = np.arange(nv) - xoff[v_stage]
        v_pos = np.where(v_pos < nx[v_stage], nu[v_stage] + v_pos, v_pos - nx[v_stage])    # u first, then x
        r_stage = np.repeat(np.arange(K), gaps + ng)
        r_gap = np.arange(nrow) - roff[r_stage]                 # < gaps[k]: gap row index
        is_gap = r_gap < gaps[r_stage]
        ld = nx + nu + 1
        lists, masks = {}, {"a_eq": eq_g & ~is_gap, "a_in": in_g & ~is_gap}
        for name, mask, stage in (("a_eq", masks["a_eq"], r_stage), ("a_in", masks["a_in"], r_stage),
                                  ("x_eq", eq_x, v_stage), ("x_in", in_x, v_stage)):
            idx = np.flatnonzero(mask)
            lists[name] = idx
            lists[name + "_idx"] = np.concatenate([[0], np.cumsum(np.bincount(stage[idx], minlength=K))])
        n_eq = np.diff(lists["a_eq_idx"]) + np.diff(lists["x_eq_idx"])
        n_in = np.diff(lists["a_in_idx"]) + np.diff(lists["x_in_idx"])
        sizes = np.stack([ld * gaps, ld * n_eq, ld * n_in], axis=1).reshape(-1)
        offs = np.concatenate([[0], np.cumsum(sizes)[:-1]]).reshape(K, 3)
        # the column of each path row in its stage's Ggt (equalities) or Ggt_ineq block
        col = np.full(nrow, -1)
        for name in ("a_eq", "a_in"):
            idx, start = lists[name], lists[name + "_idx"]
            col[idx] = np.arange(len(idx)) - start[r_stage[idx]]
        k, kc = r_stage[r], v_stage[c]
        jt = np.full(len(r), -1)
        js = np.ones(len(r))
        gap, own = is_gap[r], kc == k
        jt[gap & own] = offs[k, 0][gap & own] + v_pos[c][gap & own] + r_gap[r][gap & own] * ld[k][gap & own]
        js[gap & own] = -1.0
        nxt = gap & (kc == k + 1) & (v_pos[c] >= nu[np.minimum(kc, K - 1)])
        for name, block in (("a_eq", 1), ("a_in", 2)):
            m = own & masks[name][r]
            jt[m] = offs[k, block][m] + v_pos[c][m] + col[r][m] * ld[k][m]
        stray = ~((gap & own) | nxt | (~gap & own))
        if np.any(stray):
            i = int(np.flatnonzero(stray)[0])
            raise ValueError(f"the NLP's Jacobian is not stage-wise: row {r[i]} (stage {k[i]}) depends on variable {c[i]}")
        hk = v_stage[hr]
        if np.any(v_stage[hc] != hk):
            i = int(np.flatnonzero(v_stage[hc] != hk)[0])
            raise ValueError(f"the NLP's Hessian couples stages: variables {hr[i]} and {hc[i]}")
        rsq = np.concatenate([[0], np.cumsum(ld * (nx + nu))[:-1]])
        ht = rsq[hk] + v_pos[hr] + v_pos[hc] * ld[hk]
        self.arrays = {"nx": nx, "nu": nu, "xoff": xoff, "roff": roff, **lists, "jt": jt, "ht": ht,
                       "bab_off": offs[:, 0], "geq_off": offs[:, 1], "gin_off": offs[:, 2], "rsq_off": rsq}
        self.arrays = {key: _ints(v) for key, v in self.arrays.items()}
        self.js = np.ascontiguousarray(js)
        self.K, self.nv, self.ng = K, nv, nrow
        self.n_jbuf, self.n_hbuf = int(np.sum(sizes)), int(np.sum(ld * (nx + nu)))


class DirectFatrop:
    """fatrop on the NLP library `library` (its nlp_* functions with the fatrop plugin's
    signatures) with CasADi's manual stage structure `structure` (N, nx, nu, ng); `options` are
    fatrop's own (tol, max_iter, mu_init, print_level, ...)."""

    def __init__(self, library: str, structure: dict, options: dict | None = None, log=print):
        self.driver = ctypes.CDLL(driver_library(log))
        self.driver.rsf_solve.restype = ctypes.c_int
        self.library, self.nlp = library, ctypes.CDLL(library)
        self.structure = structure
        self.options = dict(options or {})
        ext = {name: ca.external(name, library) for name in _NAMES}
        self.jac_sp, self.hess_sp = ext["nlp_jac_g"].sparsity_out(1), ext["nlp_hess_l"].sparsity_out(1)
        self.n_x, self.n_p = ext["nlp_g"].size1_in(0), ext["nlp_g"].size1_in(1)
        self.n_g = ext["nlp_g"].size1_out(0)
        work = [ext[n].sz_arg() for n in _NAMES], [ext[n].sz_res() for n in _NAMES], \
               [ext[n].sz_iw() for n in _NAMES], [ext[n].sz_w() for n in _NAMES]
        self.work = [max(w) for w in work]
        self.pointers = {}
        for name in _NAMES:
            getattr(self.nlp, name + "_incref", lambda: None)()
            self.pointers[name] = ctypes.cast(getattr(self.nlp, name), ctypes.c_void_p).value
        self._triplets = tuple((sp.shape, np.array(sp.row()), np.repeat(np.arange(sp.size2()), np.diff(sp.colind())))
                               for sp in (self.jac_sp, self.hess_sp))
        self._stats = {}

    def _layout(self, lbx, ubx, lbg, ubg) -> _Layout:
        eq_g, eq_x = lbg == ubg, lbx == ubx
        in_g = ~eq_g & ~(np.isneginf(lbg) & np.isposinf(ubg))
        in_x = ~eq_x & ~(np.isneginf(lbx) & np.isposinf(ubx))
        key = np.packbits(np.concatenate([eq_g, in_g, eq_x, in_x])).tobytes()
        key = (self.library, key)
        if key not in _LAYOUTS:                      # kept for the process: repeated solves, refinements, sweeps
            s = self.structure
            _LAYOUTS[key] = _Layout(s["nx"], s["nu"], s["ng"], *self._triplets, eq_g, in_g, eq_x, in_x)
        return _LAYOUTS[key]

    def _problem(self, L: _Layout) -> _Problem:
        P = _Problem(K=L.K, nv=L.nv, ng=L.ng, nnz_j=self.jac_sp.nnz(), nnz_h=self.hess_sp.nnz(),
                     n_jbuf=L.n_jbuf, n_hbuf=L.n_hbuf, js=L.js.ctypes.data_as(_Dp),
                     sz_arg=self.work[0], sz_res=self.work[1], sz_iw=self.work[2], sz_w=self.work[3])
        for key, v in L.arrays.items():
            setattr(P, key, v.ctypes.data_as(_I))
        for field, name in zip(("f", "g", "grad_f", "jac_g", "hess_l"), _NAMES):
            setattr(P, field, self.pointers[name])
        return P

    def __call__(self, x0, lbx, ubx, lbg, ubg, p) -> dict:
        vec = lambda v, n: np.ascontiguousarray(np.broadcast_to(np.asarray(v, float).reshape(-1), (n,)))  # noqa: E731
        x0, lbx, ubx = (vec(v, self.n_x) for v in (x0, lbx, ubx))
        lbg, ubg, p = vec(lbg, self.n_g), vec(ubg, self.n_g), vec(p, self.n_p)
        L = self._layout(lbx, ubx, lbg, ubg)
        P = self._problem(L)
        names = list(self.options)
        c_names = (ctypes.c_char_p * max(len(names), 1))(*[k.encode() for k in names])
        c_strings = (ctypes.c_char_p * max(len(names), 1))(*[str(self.options[k]).encode() for k in names])
        values = np.array([0.0 if isinstance(self.options[k], str) else float(self.options[k]) for k in names] or [0.0])
        verbose = int(bool(self.options.get("print_level", 0)))
        x, lam_g, lam_x, stats = np.zeros(self.n_x), np.zeros(self.n_g), np.zeros(self.n_x), np.zeros(17)
        ptr = lambda a: a.ctypes.data_as(_Dp)  # noqa: E731
        ret = self.driver.rsf_solve(ctypes.byref(P), ptr(x0), ptr(p), ptr(lbx), ptr(ubx), ptr(lbg), ptr(ubg),
                                    len(names), c_names, ptr(values), c_strings, verbose,
                                    ptr(x), ptr(lam_g), ptr(lam_x), ptr(stats))
        if ret <= -1000:
            raise ValueError(f"fatrop refused option {names[-1000 - ret]!r}={self.options[names[-1000 - ret]]!r}")
        fat = {k: (int(v) if k.endswith(("count", "flag")) else float(v)) for k, v in zip(_STATS, stats)}
        self._stats = {"success": ret == 0, "return_status": fat["return_flag"],
                       "unified_return_status": {0: "SOLVER_RET_SUCCESS", -1: "SOLVER_RET_EXCEPTION"}.get(ret, "SOLVER_RET_UNKNOWN"),
                       "iter_count": fat["iterations_count"], "fatrop": fat, "evaluation_failed": bool(stats[16]),
                       "interface": "direct"}
        return {"x": x, "lam_g": lam_g, "lam_x": lam_x}

    def stats(self) -> dict:
        return dict(self._stats)
