"""fatrop called directly, stage by stage, through its C interface (the header and library ship
in the CasADi wheel), on the same compiled NLP functions CasADi's fatrop plugin would call.

Why: on problem (b) the plugin spent 0.021 s of a 0.114 s solve between fatrop and the NLP's
functions (fatrop's evaluation timers against CasADi's: three sparse projections of the whole
Jacobian per evaluation, the Hessian's, row-by-row packing, the function-call layers).  Here the
Jacobian's and Hessian's nonzeros go straight to fatrop's stage blocks by index maps made once
per NLP layout (driver.c for the conventions).  Same algorithm, same options, same
iterates: the tests compare it with the plugin iteration for iteration.

`DirectFatrop(library, structure)` is called like a CasADi nlpsol (x0, lbx, ubx, lbg, ubg, p)
and has `stats()` in the plugin's words.  Given the NLP's compiled pieces (`NativePieces`)
instead of a library, the driver evaluates them itself, stage by stage: nothing is compiled
for a new mesh or number of intervals.
"""
from __future__ import annotations

import ctypes
import hashlib
import threading
import weakref
from collections import OrderedDict
from pathlib import Path

import casadi as ca
from typing import Any
import numpy as np

from rscasadi.native.build import blasfeo_kernels, cached_library, compiler, native_flags
from rscasadi.native.parallel import openmp_flags, threads_now
from rscasadi.ocp.fatrop import blasfeo
from rscasadi.ocp.assembly import RAW_NAMES
from rscasadi.errors import Failed, InvalidArgument

_SOURCE = Path(__file__).with_name("driver.c")
_NAMES = ("nlp_f", "nlp_g", "nlp_grad_f", "nlp_jac_g", "nlp_hess_l")
_STATS = ("compute_sd_time", "duinf_time", "eval_hess_time", "eval_jac_time", "eval_cv_time", "eval_grad_time",
          "eval_obj_time", "initialization_time", "time_total", "eval_hess_count", "eval_jac_count",
          "eval_cv_count", "eval_grad_count", "eval_obj_count", "iterations_count", "return_flag")
_I = ctypes.POINTER(ctypes.c_int)
_LAYOUTS: dict = {}
# fatrop keeps one output writer per process, replaced by every solver it creates: one solve at a
# time per process (threads could race on it; processes, as the sweeps use, run in parallel)
_ONE_AT_A_TIME = threading.Lock()
_STOPPED: list = []                                     # solvers stopped midway, kept (see `solve`)
_Dp = ctypes.POINTER(ctypes.c_double)
_SESSIONS = 4                   # fatrop solvers kept per DirectFatrop (one per bound layout, the newest)


def _close_sessions(driver, sessions: OrderedDict):
    while sessions:
        driver.rsf_close(ctypes.c_void_p(sessions.popitem()[1][0]))


class _Piece(ctypes.Structure):
    _fields_ = ([(k, ctypes.c_int) for k in ("count", "nz", "nr", "n_args")]  # type: ignore[assignment]
                + [(k, _I) for k in ("cols", "rows", "arg_off", "arg_len", "arg_step")]
                + [(k, ctypes.c_void_p) for k in ("value", "first", "objective", "second")]
                + [(k, _I) for k in ("rows_nz", "grad_f_nz", "grad_l_nz")]
                + [(k, ctypes.c_int) for k in ("n_rows_nz", "n_f_nz", "n_grad_f_nz", "n_grad_l_nz", "nnz_j", "nnz_h")])


class NativePieces:
    """The NLP's pieces (assembly.Piece, each with its C `symbols` and `arg_places`) for the
    driver to evaluate itself, stage by stage on its threads: no library of the whole NLP, so a
    new mesh or number of intervals compiles nothing (the Panda's obstacle task: 7-18 s of
    generated glue a refinement round otherwise).  n_x, n_g, n_p: the NLP's sizes."""

    def __init__(self, pieces: list, n_x: int, n_g: int, n_p: int):
        self.n_x, self.n_g, self.n_p = n_x, n_g, n_p
        self.keep: list = []                          # the arrays and libraries the structs point into
        self.array = (_Piece * len(pieces))()
        work = np.zeros(4, int)
        self.parts: list = [[], []]
        for i, piece in enumerate(pieces):
            if not piece.symbols or piece.arg_places is None:
                raise InvalidArgument(f"piece {piece.fn.name()} has no C functions to call: compile it first")
            lib = ctypes.CDLL(piece.library)
            ext = {role: ca.external(name, piece.library) for role, name in piece.symbols.items()}
            for f in ext.values():
                work = np.maximum(work, [f.sz_arg(), f.sz_res(), f.sz_iw(), f.sz_w()])
            places = np.array(piece.arg_places, dtype=int).reshape(-1, 3)
            for a, (off, length, step) in enumerate(places):
                if ext["value"].nnz_in(1 + a) != length or (step >= 0 and off + length + step * (piece.count - 1) > n_p):
                    raise InvalidArgument(f"piece {piece.fn.name()}: parameter {a} ({ext['value'].name_in(1 + a)}) "
                                          f"is not where its places say")
            vector = lambda f, i: np.array(f.sparsity_out(i).row(), dtype=int)      # a column's nonzeros
            arrays = {"cols": piece.cols, "rows": piece.rows, "arg_off": places[:, 0], "arg_len": places[:, 1],
                      "arg_step": places[:, 2], "rows_nz": vector(ext["value"], 0),
                      "grad_f_nz": vector(ext["objective"], 1), "grad_l_nz": vector(ext["second"], 0)}
            arrays = {k: _ints(v) for k, v in arrays.items()}
            P = self.array[i]
            P.count, P.nz, P.nr, P.n_args = piece.count, piece.cols.shape[1], piece.rows.shape[1], len(places)
            for k, v in arrays.items():
                setattr(P, k, v.ctypes.data_as(_I))
            for role in ("value", "first", "objective", "second"):
                setattr(P, role, ctypes.cast(getattr(lib, piece.symbols[role]), ctypes.c_void_p).value)
            P.n_rows_nz, P.n_f_nz = len(arrays["rows_nz"]), ext["value"].nnz_out(1)
            P.n_grad_f_nz, P.n_grad_l_nz = len(arrays["grad_f_nz"]), len(arrays["grad_l_nz"])
            P.nnz_j, P.nnz_h = ext["first"].nnz_out(1), ext["second"].nnz_out(1)
            self.parts[0].append(piece.count * P.nnz_j)
            self.parts[1].append(piece.count * P.nnz_h)
            self.keep += [lib, ext, arrays]
        self.work = [int(w) + 4 for w in work]           # + the parameters, lam and lam_f


class _Problem(ctypes.Structure):
    _fields_ = ([(k, ctypes.c_int) for k in ("K", "nv", "ng")]  # type: ignore[assignment]  # typeshed: a union
                + [(k, _I) for k in ("nx", "nu", "xoff", "roff", "a_eq", "a_eq_idx", "a_in", "a_in_idx",
                                     "x_eq", "x_eq_idx", "x_in", "x_in_idx")]
                + [(k, ctypes.c_int) for k in ("nnz_j", "nnz_h", "n_jparts", "n_hparts")]
                + [("jt", _I), ("ht", _I), ("js", _Dp), ("jpart", _I), ("hpart", _I)]
                + [(k, _I) for k in ("jorder", "jstart", "horder", "hstart", "hadd", "hadd_to", "hadd_start")]
                + [(k, _I) for k in ("bab_off", "geq_off", "gin_off", "rsq_off")]
                + [(k, ctypes.c_void_p) for k in ("f", "g", "grad_f", "jac_g", "hess_l", "fg")]
                + [(k, ctypes.c_int) for k in ("sz_arg", "sz_res", "sz_iw", "sz_w")]
                + [("n_pieces", ctypes.c_int), ("pieces", ctypes.POINTER(_Piece))])


def casadi_dir() -> Path:
    """The installed casadi package's directory (its headers and fatrop's library)."""
    return Path(ca.__file__).parent


def driver_library(log=print) -> str:
    """The compiled driver (once per machine and CasADi version; cached by the hash of its source)."""
    inc, lib_dir = casadi_dir() / "include", casadi_dir()
    for need in (inc / "fatrop" / "ocp" / "OCPCInterface.h", inc / "blasfeo.h"):
        if not need.exists():
            raise Failed(f"fatrop's C interface is missing from this CasADi ({ca.__version__}): {need}")
    # its per-stage scatter and packing on the NLP's threads (OpenMP, when the compiler has it)
    flags = ["-O2", *openmp_flags(tuple(compiler())), f"-I{inc}"]
    link = [f"-L{lib_dir}", "-lfatrop", "-lblasfeo", f"-Wl,-rpath,{lib_dir}"]
    return str(cached_library({_SOURCE.name: _SOURCE.read_text()}, flags, link, name="fatrop_driver",
                              what="the direct fatrop driver", log=log))


def tuned_kernels_library(log=print) -> str:
    """BLASFEO's hottest kernels for this processor (native.build.blasfeo_kernels; blasfeo.py loads them)."""
    return str(cached_library(blasfeo_kernels(), ["-O3", *native_flags()], name="blasfeo_tuned",
                              what="BLASFEO's product kernels for this processor", log=log))


def _vec(v, n: int) -> np.ndarray:
    return np.ascontiguousarray(np.broadcast_to(np.asarray(v, float).reshape(-1), (n,)))


def _by_stage(stage: np.ndarray, K: int):
    """A stable order of entries by their stage, and where each stage's entries start in it (K + 1)."""
    return np.argsort(stage, kind="stable"), np.concatenate([[0], np.cumsum(np.bincount(stage, minlength=K))])


def _repeats(a: np.ndarray) -> np.ndarray:
    """The positions of the entries of `a` that repeat an earlier entry, in order (a sort: numpy's
    hashing unique took 0.4 s a call on a Hessian's million places)."""
    order = np.argsort(a, kind="stable")
    ordered = a[order]
    again = np.zeros(len(a), bool)
    again[order[1:][ordered[1:] == ordered[:-1]]] = True
    return np.flatnonzero(again)


def _ints(v) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(v, dtype=np.intc).reshape(-1))


class _Layout:
    """Where every row, variable and nonzero of the NLP goes in fatrop's stage blocks, for one
    classification of rows and variables into equalities, inequalities and free ones."""

    def __init__(self, nx, nu, ng, jac: tuple, hess: tuple, eq_g, in_g, eq_x, in_x):
        self.K = K = len(nx)
        nx, nu, ng = (np.asarray(v, int) for v in (nx, nu, ng))
        xoff = np.concatenate([[0], np.cumsum(nx + nu)[:-1]])
        gaps = np.append(nx[1:], 0)                              # stage k's gap rows close x_{k+1}
        roff = np.concatenate([[0], np.cumsum(gaps + ng)[:-1]])
        self.nv, self.ng = int(np.sum(nx + nu)), int(np.sum(gaps + ng))
        if jac[0] != (self.ng, self.nv) or hess[0] != (self.nv, self.nv):
            raise InvalidArgument(f"NLP of {jac[0][0]} rows and {jac[0][1]} variables does not match the stage "
                             f"structure ({self.ng} rows, {self.nv} variables)")
        self.v_stage = np.repeat(np.arange(K), nx + nu)
        pos = np.arange(self.nv) - xoff[self.v_stage]
        self.v_pos = np.where(pos < nx[self.v_stage], nu[self.v_stage] + pos, pos - nx[self.v_stage])  # u, then x
        self.r_stage = np.repeat(np.arange(K), gaps + ng)
        self.r_gap = np.arange(self.ng) - roff[self.r_stage]     # < gaps[k]: the gap row's index
        self.is_gap = self.r_gap < gaps[self.r_stage]
        self.ld = nx + nu + 1                                     # rows of every stage block
        self.masks = {"a_eq": eq_g & ~self.is_gap, "a_in": in_g & ~self.is_gap, "x_eq": eq_x, "x_in": in_x}
        lists = self._lists()
        n_eq = np.diff(lists["a_eq_idx"]) + np.diff(lists["x_eq_idx"])
        n_in = np.diff(lists["a_in_idx"]) + np.diff(lists["x_in_idx"])
        sizes = np.stack([self.ld * gaps, self.ld * n_eq, self.ld * n_in], axis=1).reshape(-1)
        self.offs = np.concatenate([[0], np.cumsum(sizes)[:-1]]).reshape(K, 3)     # BAbt, Ggt, Ggt_ineq
        rsq = np.concatenate([[0], np.cumsum(self.ld * (nx + nu))[:-1]])
        jt, self.js = self._jacobian_places(jac[1], jac[2], lists, nu)
        ht = self._hessian_places(hess[1], hess[2], rsq)
        placed = np.sort(jt[jt >= 0])
        assert not np.any(placed[1:] == placed[:-1]), "two Jacobian nonzeros share a block entry"
        # pieces overlap in the Hessian (e.g. the start piece and stage 0 at x_0): each place's first
        # nonzero is written, the others are added after it
        hadd = _repeats(ht)
        hadd_to = ht[hadd]
        ht[hadd] = -1
        # each stage's nonzeros listed together: the driver places a stage at once, on the
        # thread that evaluated that interval (its values still in that core's cache)
        jorder, jstart = _by_stage(self.r_stage[jac[1]], K)
        kept = np.flatnonzero(ht >= 0)
        horder, hstart = _by_stage(self.v_stage[hess[1][kept]], K)
        hsort, hadd_start = _by_stage(self.v_stage[hess[1][hadd]], K)
        self.arrays = {key: _ints(v) for key, v in {
            "nx": nx, "nu": nu, "xoff": xoff, "roff": roff, **lists, "jt": jt, "ht": ht,
            "jorder": jorder, "jstart": jstart, "horder": kept[horder], "hstart": hstart,
            "hadd": hadd[hsort], "hadd_to": hadd_to[hsort], "hadd_start": hadd_start,
            "bab_off": self.offs[:, 0], "geq_off": self.offs[:, 1], "gin_off": self.offs[:, 2], "rsq_off": rsq}.items()}

    def _lists(self) -> dict:
        """Per stage, its equality and inequality rows and bounded variables (CSR-like)."""
        lists = {}
        for name, mask in self.masks.items():
            idx = np.flatnonzero(mask)
            stage = (self.r_stage if name.startswith("a") else self.v_stage)[idx]
            lists[name], lists[name + "_idx"] = idx, np.concatenate([[0], np.cumsum(np.bincount(stage, minlength=self.K))])
        return lists

    def _jacobian_places(self, r, c, lists, nu):
        """Each Jacobian nonzero's place and sign: a gap row's (x_k, u_k) entries go to BAbt negated
        (fatrop's x_{k+1} = F), its x_{k+1} entry must be 1 (-2: checked in C), path rows to Ggt or
        Ggt_ineq, free rows nowhere (-1).  A place counts stage by stage through the blocks BAbt,
        Ggt, Ggt_ineq, each column-major with ld rows; driver.c turns it into fatrop's memory."""
        col = np.full(self.ng, -1)                                # a path row's column in its block
        for name in ("a_eq", "a_in"):
            idx, start = lists[name], lists[name + "_idx"]
            col[idx] = np.arange(len(idx)) - start[self.r_stage[idx]]
        k, ld, pos = self.r_stage[r], self.ld[self.r_stage[r]], self.v_pos[c]
        own, gap = self.v_stage[c] == k, self.is_gap[r]
        nxt = gap & (self.v_stage[c] == k + 1) & (pos >= nu[np.minimum(self.v_stage[c], self.K - 1)])
        jt, js = np.full(len(r), -1), np.ones(len(r))
        m = gap & own
        jt[m], js[m] = self.offs[k, 0][m] + pos[m] + self.r_gap[r][m] * ld[m], -1.0
        jt[nxt] = -2
        for name, block in (("a_eq", 1), ("a_in", 2)):
            m = own & self.masks[name][r]
            jt[m] = self.offs[k, block][m] + pos[m] + col[r][m] * ld[m]
        stray = ~(own | nxt)
        if np.any(stray):
            i = int(np.flatnonzero(stray)[0])
            raise InvalidArgument(f"the NLP's Jacobian is not stage-wise: row {r[i]} (stage {k[i]}) depends on variable {c[i]}")
        return jt, np.ascontiguousarray(js)

    def _hessian_places(self, hr, hc, rsq):
        """Each Hessian nonzero's place in its stage's RSQ block (u first)."""
        hk = self.v_stage[hr]
        if np.any(self.v_stage[hc] != hk):
            i = int(np.flatnonzero(self.v_stage[hc] != hk)[0])
            raise InvalidArgument(f"the NLP's Hessian couples stages: variables {hr[i]} and {hc[i]}")
        return rsq[hk] + self.v_pos[hr] + self.v_pos[hc] * self.ld[hk]


class DirectFatrop:
    """fatrop on the NLP library `library` (its nlp_* functions with the fatrop plugin's
    signatures) with CasADi's manual stage structure `structure` (N, nx, nu, ng); `options` are
    fatrop's own (tol, max_iter, mu_init, print_level, ...).  With `places` (assembly.places of
    the NLP's pieces) and the library's raw_jac_g and raw_hess_l, the derivatives come unscattered,
    one output per piece, and go to fatrop's blocks from there."""

    def __init__(self, library: str | None, structure: dict, options: dict | None = None, log=print,
                 places: tuple | None = None, pieces: NativePieces | None = None):
        driver = driver_library(log)
        blasfeo.load(str(casadi_dir() / "libfatrop.so"), driver, lambda: tuned_kernels_library(log))
        self.driver = ctypes.CDLL(driver)
        self.driver.rsf_open.restype = ctypes.c_void_p
        self.driver.rsf_close.argtypes = [ctypes.c_void_p]
        self.driver.rsf_run.restype = ctypes.c_int
        self.driver.rsf_request_stop.restype = None
        self.driver.rsf_blasfeo_function.restype = ctypes.c_void_p
        self.blasfeo = blasfeo.in_use(self.driver.rsf_blasfeo_function())
        self.library, self.pieces, self.places = library, pieces, places
        self.structure = structure
        self.options = dict(options or {})
        self.pointers = {}
        if pieces is not None:                       # the driver evaluates the pieces itself
            if places is None:
                raise InvalidArgument("DirectFatrop: pieces need their places (assembly.places)")
            self.raw = True
            self.n_x, self.n_p, self.n_g = pieces.n_x, pieces.n_p, pieces.n_g
            self.work = pieces.work
            self.parts = pieces.parts
        else:
            self.nlp = ctypes.CDLL(library)
            self.raw = places is not None and all(hasattr(self.nlp, name) for name in RAW_NAMES + ("nlp",))
            names = _NAMES[:3] + (RAW_NAMES + ("nlp",) if self.raw else _NAMES[3:])
            ext = {name: ca.external(name, library) for name in names}
            self.n_x, self.n_p = ext["nlp_g"].size1_in(0), ext["nlp_g"].size1_in(1)
            self.n_g = ext["nlp_g"].size1_out(0)
            self.work = [max(getattr(f, "sz_" + k)() for f in ext.values()) for k in ("arg", "res", "iw", "w")]
            for field, name in zip(("f", "g", "grad_f", "jac_g", "hess_l", "fg"), names):
                getattr(self.nlp, name + "_incref", lambda: None)()
                self.pointers[field] = ctypes.cast(getattr(self.nlp, name), ctypes.c_void_p).value
            jac, hess = ext[names[3]], ext[names[4]]
            # the parts after g (scattered Jacobian) or all of them (raw); the Hessian's after grad L
            self.parts = [[f.sparsity_out(i).nnz() for i in range(first, f.n_out())]
                          for f, first in ((jac, 0 if self.raw else 1), (hess, 1))]
        if self.raw:
            for kind, sizes, where in zip(("Jacobian", "Hessian"), self.parts, places):
                if sizes != [len(r) for r, _ in where]:
                    raise InvalidArgument(f"the {kind} parts of {library or 'the pieces'} ({sizes} nonzeros) do not "
                                          "match the pieces' places")
            shapes = ((self.n_g, self.n_x), (self.n_x, self.n_x))
            self._triplets = tuple((shape, np.concatenate([r for r, _ in where]), np.concatenate([c for _, c in where]))
                                   for shape, where in zip(shapes, places))
        else:
            self._triplets = tuple((sp.shape, np.array(sp.row()), np.repeat(np.arange(sp.size2()), np.diff(sp.colind())))
                                   for sp in (jac.sparsity_out(1), hess.sparsity_out(1)))
        # what a layout depends on besides the bounds: the structure and every nonzero's place
        digest = hashlib.sha256(repr(sorted(structure.items())).encode())
        for (shape, r, c) in self._triplets:
            digest.update(repr(shape).encode() + np.ascontiguousarray(r, np.int64).tobytes()
                          + np.ascontiguousarray(c, np.int64).tobytes())
        self._pattern = digest.hexdigest()
        self._offsets = [_ints(np.concatenate([[0], np.cumsum(sizes)])) for sizes in self.parts]
        self._stats: dict[str, Any] = {}
        # one fatrop solver per layout, built on first use (prepare, or the first solve) and reused
        # (closed with self)
        self._sessions: OrderedDict = OrderedDict()
        weakref.finalize(self, _close_sessions, self.driver, self._sessions)

    def _layout(self, lbx, ubx, lbg, ubg) -> _Layout:
        eq_g, eq_x = lbg == ubg, lbx == ubx
        in_g = ~eq_g & ~(np.isneginf(lbg) & np.isposinf(ubg))
        in_x = ~eq_x & ~(np.isneginf(lbx) & np.isposinf(ubx))
        key = (self._pattern, self.raw, np.packbits(np.concatenate([eq_g, in_g, eq_x, in_x])).tobytes())
        if key not in _LAYOUTS:                      # kept for the process: repeated solves, refinements, sweeps
            while len(_LAYOUTS) >= 16:
                _LAYOUTS.pop(next(iter(_LAYOUTS)))
            s = self.structure
            jac, hess = self._triplets
            _LAYOUTS[key] = _Layout(s["nx"], s["nu"], s["ng"], jac, hess, eq_g, in_g, eq_x, in_x)
        return _LAYOUTS[key]

    def _problem(self, L: _Layout) -> _Problem:
        (jo, ho), arrays = self._offsets, L.arrays
        P = _Problem(K=L.K, nv=L.nv, ng=L.ng, nnz_j=int(jo[-1]), nnz_h=int(ho[-1]),
                     n_jparts=len(jo) - 1, n_hparts=len(ho) - 1, js=L.js.ctypes.data_as(_Dp),
                     jpart=jo.ctypes.data_as(_I), hpart=ho.ctypes.data_as(_I),
                     sz_arg=self.work[0], sz_res=self.work[1], sz_iw=self.work[2], sz_w=self.work[3])
        for key, v in arrays.items():
            setattr(P, key, v.ctypes.data_as(_I))
        for field, pointer in self.pointers.items():
            setattr(P, field, pointer)
        if self.pieces is not None:
            P.n_pieces, P.pieces = len(self.pieces.array), self.pieces.array
        return P

    def _session(self, L: _Layout) -> int:
        """The solver of layout L (driver.c's rsf_session), built on first use, with self.options set."""
        if id(L) in self._sessions:
            self._sessions.move_to_end(id(L))
        else:
            P = self._problem(L)
            handle = self.driver.rsf_open(ctypes.byref(P))
            if not handle:
                raise MemoryError("fatrop's solver could not be built")
            self._sessions[id(L)] = (handle, P, L)     # P (and L's arrays) live as long as the solver
            while len(self._sessions) > _SESSIONS:
                self.driver.rsf_close(ctypes.c_void_p(self._sessions.popitem(last=False)[1][0]))
        handle = self._sessions[id(L)][0]
        names = list(self.options)
        c_names = (ctypes.c_char_p * max(len(names), 1))(*[k.encode() for k in names])
        c_strings = (ctypes.c_char_p * max(len(names), 1))(*[str(self.options[k]).encode() for k in names])
        values = np.array([0.0 if isinstance(self.options[k], str) else float(self.options[k]) for k in names] or [0.0])
        ret = self.driver.rsf_options(ctypes.c_void_p(handle), len(names), c_names, values.ctypes.data_as(_Dp), c_strings)
        if ret <= -1000:
            raise InvalidArgument(f"fatrop refused option {names[-1000 - ret]!r}={self.options[names[-1000 - ret]]!r}")
        return handle

    def prepare(self, lbx, ubx, lbg, ubg):
        """Build the solver for these bounds' layout now (a setup step, as an nlpsol's construction;
        else the first solve of each layout builds it: 3 ms on problem (b))."""
        lbx, ubx = (_vec(v, self.n_x) for v in (lbx, ubx))
        lbg, ubg = (_vec(v, self.n_g) for v in (lbg, ubg))
        with _ONE_AT_A_TIME:
            self._session(self._layout(lbx, ubx, lbg, ubg))

    def __call__(self, x0, lbx, ubx, lbg, ubg, p) -> dict:
        x0, lbx, ubx = (_vec(v, self.n_x) for v in (x0, lbx, ubx))
        lbg, ubg, p = _vec(lbg, self.n_g), _vec(ubg, self.n_g), _vec(p, self.n_p)
        L = self._layout(lbx, ubx, lbg, ubg)
        verbose = int(bool(self.options.get("print_level", 0)))
        x, lam_g, lam_x, stats = np.zeros(self.n_x), np.zeros(self.n_g), np.zeros(self.n_x), np.zeros(19)
        threads = threads_now()            # the caller's; the solve runs on a thread of its own
        ptr = lambda a: a.ctypes.data_as(_Dp)  # noqa: E731
        with _ONE_AT_A_TIME:
            session = self._session(L)
            try:
                ret = self._interruptible(lambda: self.driver.rsf_run(
                    ctypes.c_void_p(session), ptr(x0), ptr(p), ptr(lbx), ptr(ubx), ptr(lbg), ptr(ubg), verbose, threads, ptr(x),
                    ptr(lam_g), ptr(lam_x), ptr(stats)))
            except KeyboardInterrupt:                    # a solver stopped midway is not reused, nor destroyed
                _STOPPED.append(self._sessions.pop(id(L)))   # (fatrop's teardown of it crashes): it and the
                raise                                    # arrays it points into stay with the process
            if ret == -1:                                # an exception inside fatrop: a new solver next time
                self.driver.rsf_close(ctypes.c_void_p(self._sessions.pop(id(L))[0]))
        if stats[17]:
            raise InvalidArgument("the NLP's gap-closing rows must read x_{k+1} - F_k(x_k, u_k): a coefficient of "
                             "x_{k+1} is not 1")
        fat = {k: (int(v) if k.endswith(("count", "flag")) else float(v)) for k, v in zip(_STATS, stats)}
        self._stats = {"success": ret == 0, "return_status": fat["return_flag"],
                       "unified_return_status": {0: "SOLVER_RET_SUCCESS", -1: "SOLVER_RET_EXCEPTION"}.get(ret, "SOLVER_RET_UNKNOWN"),
                       "iter_count": fat["iterations_count"], "fatrop": fat, "evaluation_failed": bool(stats[16]),
                       "interface": "direct", "blasfeo": dict(self.blasfeo),
                       "raw_derivatives": self.raw, "threads": int(stats[18]) or 1}
        return {"x": x, "lam_g": lam_g, "lam_x": lam_x}

    def _interruptible(self, solve):
        """solve() (fatrop, in C) on a thread of its own while this one waits, so that Ctrl-C
        (Python runs signal handlers only here, between waits) reaches the caller at once: then
        the solve is asked to stop (driver.c: rsf_request_stop, every later evaluation NaN) and
        waited for, and the KeyboardInterrupt goes on."""
        result = {}
        worker = threading.Thread(target=lambda: result.setdefault("ret", solve()), daemon=True)
        worker.start()
        try:
            while worker.is_alive():
                worker.join(0.05)
        except KeyboardInterrupt:
            while worker.is_alive():                     # asked again: the solve may only now have begun
                self.driver.rsf_request_stop()
                worker.join(0.05)
            raise
        return result["ret"]

    def stats(self) -> dict:
        return dict(self._stats)
