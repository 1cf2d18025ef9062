"""The step Jacobian as a structured C kernel, for arms past the straight-line
SX route (generate.step_functions' implicit-function branch: n >= 5 for the reference arm's joints),
for RK4 (below) and for ROS2, the L-stable step of arms with stiff springs (codegen.rosenbrock;
templates/step_ros2.c: two stage points, each a column block sweep `rsk_stage` as RK4's stages,
and the dense solves with W's nq x nq S); and the forward dynamics' Jacobian itself, one such
sweep (templates/fd_jacobian.c), for trees past straight-line SX.

The mathematics is step_functions' exactly: RK4's four stages, dk_i = [S_i; B_i] with

    S_i = [0 1 0] + c_i h B_{i-1}                           (speed rows)
    B_i = M_i^-1 ([-dr/dx | dQ/dtau] - c_i h dr/dx [S_{i-1}; B_{i-1}])   (acceleration rows)

    dx_next/d(x, tau) = [1 0] + h/6 [6 [0 1 0] + h (B_1 + B_2 + B_3); B_1 + 2 B_2 + 2 B_3 + B_4]

(the speed rows' sum, S_1 + 2 S_2 + 2 S_3 + S_4, folded: c = 0, 1/2, 1/2, 1).  What differs is
how the linear algebra runs: CasADi's generated sparse products and LDL solve walk one column
at a time through index arrays (n = 12: 19 us each per stage), while here every matrix of
2 nq + u columns (5n on an SEA arm) is stored by rows, so each nonzero of dr/dx and of the LDL
factor moves a whole row: a fixed-length inner loop the compiler turns into vector instructions,
accumulated in blocks
of RSK_BK columns that stay in registers.  The sparsity patterns and column blocks are known
here, so the stage is generated unrolled, with constant offsets: no index arrays, no loop
over nonzeros, no matrix to clear (1.4x faster than loops over index arrays at n = 12).
S_i is never stored (dr/dq S_{i-1} = dr/dq [0 1 0] + c_{i-1} h dr/dq B_{i-2}).

Per stage point CasADi generates, as straight-line SX, `fd`: the forward dynamics (for the next
stage point), M's sparse LDL^T factors (CasADi's symbolic ldl with its AMD ordering: D, L^T by
columns and by rows) and the gear ratios.  The residual Jacobian dr/dx (by rows), which only the
linear algebra needs, runs once all four points are known, at the four at once: `jr` emitted by
codegen.lanes, one point per lane of a 4-double vector (n = 12: four evaluations cost 1.7 of one
instead of 4; the kernel 52 -> 42 us).  The kernel has CasADi's calling convention and interface
(sparsity, work sizes, names), so casadi.external, the header and the C harness treat it like any
generated Function; it uses only the caller's work vector (and, for jr's vectors, the stack).
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import casadi as ca
import numpy as np

from rscasadi.model.parameters import gear_ratios
from rscasadi.codegen import lanes
from rscasadi.codegen.lanes import LANES
from rscasadi.errors import InvalidArgument

GAMMA = 1.0 + 1.0 / np.sqrt(2.0)   # ROS2's gamma (codegen.rosenbrock, templates/step_ros2.c)
JR_PIECES_FROM = 20000   # SX instructions of the one-point dr/dx above which it is written in pieces (codegen.lanes,
                         # scalar): a 20-joint tree's (43k) compiles in 29 s instead of 68 s, a call 1.25x as long;
                         # the Panda's (12k) stays CasADi's one function (2026-11-29, 2-core Xeon VM)
BLOCK = 32          # columns accumulated at once (8 AVX2 registers; the last block narrower, to a multiple of 4):
                    # 16 and 20 ran 3 % slower, 64 spilled


class Kernel(NamedTuple):
    """A structured kernel: CasADi Functions, the C that calls them, its header."""

    functions: list          # SX Functions for CasADi to generate into the kernel's file
    body: str                # the kernel's C (after them), with its CasADi-style interface
    header: str              # its declarations and work sizes
    n_instructions: int      # SX instructions of one stage point (both Functions)
    stub: str                # the interface alone (a call fails): a Function for building graphs that call
                             # the kernel, compiled in a moment while the kernel itself compiles with them


def point_functions(arm, name: str, parametric: bool):
    """One stage point's two SX Functions, and M's LDL permutation:
    fd (x, tau[, p]) -> (a, d, L', L, mu): the forward dynamics a = ddq, needed for the next
    stage point, from M's sparse LDL^T factors, M(perm, perm) = L diag(d) L', and the gear
    ratios;  jr (x, a[, p]) -> dr/dx' (2 nq x nq, its columns dr/dx's rows), needed only by the
    linear algebra, so it runs once the four points are known, at all four at once (lanes)."""
    nq = arm.nq
    x, tau, acc = ca.SX.sym("x", 2 * nq), ca.SX.sym("tau", arm.u), ca.SX.sym("a", nq)
    p = [ca.SX.sym("p", arm.n_p)] if parametric else []
    q = arm.split_state(x)
    d, LT, perm = ca.ldl(arm.mass_matrix(parametric=parametric)(q[0], q[1], *p), True)
    mu = gear_ratios(arm.model, arm.free if parametric else None, *p)
    # the forward dynamics from the same factors: the residual r(a) = M a + r(0) (docs/user-guide/model.md
    # section 3) vanishes at a = -M^-1 r(0); 20 % faster than a separate articulated-body sweep
    r0 = arm.residual(parametric=parametric)(*q, ca.DM.zeros(arm.n), ca.DM.zeros(arm.m), tau, *p)
    a = -ca.ldl_solve(r0, d, LT, perm)
    names = ["p"] * len(p)
    fd = ca.Function(name + "_fd", [x, tau] + p, [a, d, LT, LT.T, ca.SX(mu)], ["x", "tau"] + names,
                     ["a", "d", "LT", "L", "mu"], {"cse": True})
    Jr = arm.residual_jacobian(parametric=parametric)(*q, acc[:arm.n], acc[arm.n:], *p)
    jr = ca.Function(name + "_jr", [x, acc] + p, [Jr.T], ["x", "a"] + names, ["JrT"], {"cse": True})
    return fd, jr, [int(i) for i in perm]


def drives(arm) -> dict:
    """Per coordinate driven by an input: (the input's column, its gain as C): dQ/dtau's nonzeros
    (Arm.input_matrix), -mu[j] through a gear, 1 on a direct joint."""
    return {row: (col, f"-mu[{j}]" if geared else "1.0") for col, (row, j, geared) in enumerate(arm.input_places())}


def kernel_source(arm, name: str, parametric: bool, chained: bool = False, method: str = "rk4") -> Kernel:
    """The structured kernel for the public symbol `name`: CasADi generates fd (and a small jr)
    into the file, then the kernel's C follows (a large jr by codegen.lanes, in functions of a few
    hundred statements: JR_PIECES_FROM), by `method`:
    "rk4": the step Jacobian of one RK4 step (jr in vector lanes, the four stages);
    "ros2": that of one ROS2 step (its two stage points and the dense solves with S,
    codegen.rosenbrock and templates/step_ros2.c);
    "fd_jacobian": the forward dynamics' Jacobian M^-1 [-dr/dx | dQ/dtau] itself, one stage
    (templates/fd_jacobian.c), with the interface of the Function it replaces.
    chained (a step method): the kernel of one substep within an interval, (x, tau, h[, p], A0, B0) -> (A A0,
    A B0 + B, x_next): the interval's sensitivities so far carried through this step (A0 = I and
    B0 = 0 at the first substep, where no product is formed) and the step itself, from the
    stage points the Jacobian needs anyway (RK4's x + h/6 (k1 + 2 k2 + 2 k3 + k4))."""
    if method not in STEPS:
        raise InvalidArgument(f"kernel_source: method {method!r}: one of {', '.join(sorted(STEPS))}")
    nq, u, lanes4, jacobian = arm.nq, arm.u, method == "rk4", method == "fd_jacobian"
    fd, jr, perm = point_functions(arm, name, parametric)
    JrT, LT, L = jr.sparsity_out(0), fd.sparsity_out(2), fd.sparsity_out(3)
    speeds = [int(np.searchsorted(JrT.row()[JrT.colind()[r]:JrT.colind()[r + 1]], nq)) + JrT.colind()[r]
              for r in range(nq)]                                    # where a row's speed columns start
    if jacobian:
        n_in, n_out, chained = 5 + parametric, 1, False
    else:
        n_in, n_out = (4 if parametric else 3) + 2 * chained, 2 + chained
    nc = 2 * nq + u
    stride = -(-nc // 4) * 4                                         # (x, tau)'s columns padded to whole vectors
    njr, nlt = max(JrT.nnz(), 1), max(LT.nnz(), 1)
    pieces = not lanes4 and jr.n_instructions() > JR_PIECES_FROM
    point = [fd] if lanes4 or pieces else [fd, jr]                   # what CasADi generates; the work they share
    pt = {k: max(getattr(f, "sz_" + k)() for f in point) for k in ("arg", "res", "iw", "w")}
    if jacobian:         # as fd_jacobian.c lays out w: x, a, D, LT, L, mu, JR, F
        sz_w = pt["w"] + 2 * nq + 2 * nq + 2 * nlt + arm.n + njr + 8 + nq * stride
    elif not lanes4:     # as step_ros2.c lays it out: x2, k1, k2, a1, a2, D, LT, L (two points), mu, JR, S, F1, K1, K2
        sz_w = (pt["w"] + 3 * 2 * nq + 4 * nq + 4 * nlt + arm.n + njr + nq * nq + 8 + 3 * nq * stride
                + chained * 2 * nq * nc)
    else:                # as step_rk4.c lays it out
        sz_w = (pt["w"] + 6 * 2 * nq + 9 * nq + 8 * nlt + arm.n + LANES * njr + 8 + 4 * nq * stride
                + chained * (2 * nq + 2 * nq * nc))
    sizes = {"SZ_ARG": n_in + pt["arg"], "SZ_RES": n_out + pt["res"], "SZ_IW": pt["iw"], "SZ_W": sz_w}
    consts = "".join([
        f"#define RSK_N {arm.n}\n#define RSK_NU {u}\n#define RSK_NV {nq}\n#define RSK_NX {2 * nq}\n",
        f"#define RSK_NC {nc}\n#define RSK_BK {BLOCK}\n#define RSK_NP {stride}\n",
        f"#define RSK_NJR {njr}\n#define RSK_NLT {nlt}\n#define RSK_NIN {n_in}\n",
        f"#define RSK_NOUT {n_out}\n#define RSK_CHAIN {int(chained)}\n#define RSK_STEP {int(not jacobian)}\n",
        f"#define RSK_PT_ARG {pt['arg']}\n#define RSK_PT_RES {pt['res']}\n",
        f"#define RSK_PT_IW {pt['iw']}\n#define RSK_PT_W {pt['w']}\n#define RSK_SZ_W {sz_w}\n",
        f"#define RSK_NPAR {arm.n_p if parametric else 0}\n#define RSK_FD {fd.name()}\n",
        "" if lanes4 else "#define RSK_JR(a, r, i, w, m) ((void)(i), (void)(w), rsk_jr1(a, r), 0)\n" if pieces
        else f"#define RSK_JR {jr.name()}\n",
        "" if lanes4 else f"#define RSK_GAMMA {float(GAMMA)!r}\n"])
    parts, calls = _parts(_unrolled(JrT, speeds, LT, L, perm, stride, drives(arm), LANES if lanes4 else 1))
    jr_c = (lanes.lanes_c(jr, "rsk_jr4", shared=(2,) if parametric else ()) if lanes4   # four points at once
            else lanes.lanes_c(jr, "rsk_jr1", scalar=True) if pieces else "")             # one, in pieces
    function, interface = STEPS[method]
    body = (lanes.PRELUDE + jr_c + _TEMPLATE.replace("@STEP@", function + interface).replace("@NAME@", name)
            .replace("@CONSTS@", consts).replace("@PARTS@", parts).replace("@BLOCKS@", calls))
    header = _HEADER.replace("@NAME@", name) + "".join(f"#define {name}_{k} {v}\n" for k, v in sizes.items())
    stub = (_STUB + consts + interface).replace("@NAME@", name)
    return Kernel(point, body, header, fd.n_instructions() + jr.n_instructions(), stub)


def _unrolled(JrT, speeds, LT, L, perm, stride, drive, jstride):
    """rsk_stage's rows, each a C block (in order), with the sparsity patterns and column blocks as constants: per block,
    forward (row perm[r] of [-dr/dx | dQ/dtau] - s dr/dx [S; B1], then L z = y) and backward
    (L' x = z / d).  speeds[r]: where row r's speed columns start in JrT; drive: dQ/dtau by row;
    jstride: how far apart dr/dx's nonzeros are (LANES where the lanes interleave four points)."""
    n2 = JrT.size2()
    nx = 2 * n2
    jp, jc, lp, lc, rp, rc = JrT.colind(), JrT.row(), LT.colind(), LT.row(), L.colind(), L.row()
    out = []
    for cb in range(0, stride, BLOCK):
        w = min(BLOCK, stride - cb)
        def at(col, value):                    # a scalar entry of this block, if it is in it
            return [f"t[{col - cb}] += {value};"] if cb <= col < cb + w else []
        out.append(f"  /* columns {cb} .. {cb + w - 1} */")
        for r in range(n2):
            y = perm[r]
            lines = [f"  for (c = 0; c < {w}; ++c) t[c] = 0;"]
            lines += [f"  {e}" for k in range(jp[y], jp[y + 1]) for e in at(jc[k], f"-jr[{jstride * k}]")]    # -dr/dx
            if y in drive:
                lines += [f"  {e}" for e in at(nx + drive[y][0], drive[y][1])]                    # dQ/dtau
            b1 = [e for k in range(jp[y], speeds[y]) for e in at(n2 + jc[k], f"ms * jr[{jstride * k}]")]    # dr/dq [0 1 0]
            b1 += [f"RSK_AX(t, ms * jr[{jstride * k}], B1 + {(jc[k] - n2) * stride + cb}, {w})"
                   for k in range(speeds[y], jp[y + 1])]
            b2 = [f"RSK_AX(t, mss * jr[{jstride * k}], B2 + {jc[k] * stride + cb}, {w})" for k in range(jp[y], speeds[y])]
            if b1:
                lines.append("  if (B1) {\n    " + "\n    ".join(b1) + "\n  }")
            if b2:
                lines.append("  if (B2) {\n    " + "\n    ".join(b2) + "\n  }")
            lines += [f"  RSK_AX(t, -lt[{k}], B + {perm[lc[k]] * stride + cb}, {w})" for k in range(lp[r], lp[r + 1])]
            lines.append(f"  RSK_ST(B + {perm[r] * stride + cb}, t, {w})")
            out.append("\n".join(lines))
        for r in reversed(range(n2)):
            lines = [f"  for (c = 0; c < {w}; ++c) t[c] = inv[{r}] * B[{perm[r] * stride + cb} + c];"]
            lines += [f"  RSK_AX(t, -l[{k}], B + {perm[rc[k]] * stride + cb}, {w})" for k in range(rp[r], rp[r + 1])]
            lines.append(f"  RSK_ST(B + {perm[r] * stride + cb}, t, {w})")
            out.append("\n".join(lines))
    return out


PART_LINES = 300    # C lines of the unrolled stage per function: gcc's time grows faster than a function's
                    # length (Baxter's 23 coordinates at -O1: 58 s as one function)

_PART = ("static void rsk_part{k}(const casadi_real *jr, const casadi_real *lt, const casadi_real *l, "
         "const casadi_real *mu,\n    const casadi_real *B1, const casadi_real *B2, casadi_real ms, casadi_real mss, "
         "const casadi_real *inv, casadi_real *B) {{\n  casadi_real t[RSK_BK];\n  int c;\n"
         "  (void)jr; (void)lt; (void)l; (void)mu; (void)B1; (void)B2; (void)ms; (void)mss; (void)inv;\n{body}\n}}\n")


def _parts(rows: list) -> tuple[str, str]:
    """The unrolled stage's rows (in order) as functions of about PART_LINES lines, and the
    calls to them in that order."""
    groups: list = [[]]
    for row in rows:
        if groups[-1] and sum(g.count("\n") + 1 for g in groups[-1]) + row.count("\n") + 1 > PART_LINES:
            groups.append([])
        groups[-1].append(row)
    parts = "".join(_PART.format(k=k, body="\n".join(g)) for k, g in enumerate(groups))
    calls = "\n".join(f"  rsk_part{k}(jr, lt, l, mu, B1, B2, ms, mss, inv, B);" for k in range(len(groups)))
    return parts, calls


TEMPLATES = Path(__file__).with_name("templates")
_HEADER = (TEMPLATES / "step_kernel.h").read_text().split("\n", 1)[1]          # without its comment line
_TEMPLATE = (TEMPLATES / "step_kernel.c").read_text().split("*/", 1)[1]        # without its comment
_STUB = ("#ifndef casadi_real\n#define casadi_real double\n#endif\n#ifndef casadi_int\n#define casadi_int long long int\n"
         "#endif\n/* the kernel's interface alone: a call fails (rscasadi/codegen/step_kernel.py, Kernel.stub) */\n"
         "int @NAME@(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, int mem) {\n"
         "  (void)arg; (void)res; (void)iw; (void)w; (void)mem;\n  return 1;\n}\n")
_COMMON_INTERFACE = (TEMPLATES / "kernel_interface.c").read_text().split("*/", 1)[1]
_STEP_INTERFACE = (TEMPLATES / "step_interface.c").read_text().split("*/", 1)[1] + _COMMON_INTERFACE
_FD_JACOBIAN = (TEMPLATES / "fd_jacobian.c").read_text().split("static const casadi_int rsk_sp_q", 1)
# each method's function (for @STEP@) and its CasADi-style interface (also the stub's)
STEPS = {m: ((TEMPLATES / f"step_{m}.c").read_text(), _STEP_INTERFACE) for m in ("rk4", "ros2")}
STEPS["fd_jacobian"] = (_FD_JACOBIAN[0], "static const casadi_int rsk_sp_q" + _FD_JACOBIAN[1] + _COMMON_INTERFACE)
