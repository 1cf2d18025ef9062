"""An SX Function as C that evaluates it at four points at once, one point per vector lane.

CasADi generates scalar straight-line code.  When the same Function is needed at several
independent points (the step kernel's residual Jacobian at RK4's four stage points), running the
four evaluations in the lanes of one 256-bit vector costs 1.7 scalar evaluations, not 4
(n = 12: 7.9 us for four against 4.7 us for one; the scalar code is bound by latency and
instruction fetch, not arithmetic).  The emitter walks the Function's instruction list (the algorithm CasADi
itself would print) and writes every operation on `rsk_v`, a vector of 4 doubles: GCC and
clang vector extensions where available, else a struct and small functions (portable C99; define
RSK_PORTABLE to force it).  Inputs and outputs are interleaved: nonzero k of lane l at [4 k + l];
a `shared` input is one copy for all lanes (e.g. the parameter vector)."""
from __future__ import annotations

import math

import casadi as ca
from rscasadi.errors import InvalidArgument, WrongType

LANES = 4

_BINARY = {ca.OP_ADD: "RSK_ADD", ca.OP_SUB: "RSK_SUB", ca.OP_MUL: "RSK_MUL", ca.OP_DIV: "RSK_DIV"}
# everything else, lane by lane, as the C expression CasADi's own code generator prints for it
_PER_LANE = {
    ca.OP_NEG: "(-{0})", ca.OP_SQ: "({0}*{0})", ca.OP_TWICE: "(2.*{0})", ca.OP_INV: "(1./{0})",
    ca.OP_SIN: "sin({0})", ca.OP_COS: "cos({0})", ca.OP_TAN: "tan({0})", ca.OP_ASIN: "asin({0})",
    ca.OP_ACOS: "acos({0})", ca.OP_ATAN: "atan({0})", ca.OP_SINH: "sinh({0})", ca.OP_COSH: "cosh({0})",
    ca.OP_TANH: "tanh({0})", ca.OP_EXP: "exp({0})", ca.OP_LOG: "log({0})", ca.OP_SQRT: "sqrt({0})",
    ca.OP_FABS: "fabs({0})", ca.OP_FLOOR: "floor({0})", ca.OP_CEIL: "ceil({0})", ca.OP_ERF: "erf({0})",
    ca.OP_SIGN: "(({0})>0 ? 1. : (({0})<0 ? -1. : ({0})))",
    ca.OP_POW: "pow({0},{1})", ca.OP_CONSTPOW: "pow({0},{1})", ca.OP_ATAN2: "atan2({0},{1})",
    ca.OP_FMIN: "fmin({0},{1})", ca.OP_FMAX: "fmax({0},{1})", ca.OP_HYPOT: "hypot({0},{1})",
    ca.OP_COPYSIGN: "copysign({0},{1})", ca.OP_FMOD: "fmod({0},{1})",
    ca.OP_LT: "(({0})<({1}))", ca.OP_LE: "(({0})<=({1}))", ca.OP_EQ: "(({0})==({1}))",
    ca.OP_NE: "(({0})!=({1}))", ca.OP_NOT: "(!({0}))", ca.OP_AND: "(({0})&&({1}))",
    ca.OP_OR: "(({0})||({1}))", ca.OP_IF_ELSE_ZERO: "(({0}) ? ({1}) : 0.)",
}
_OP_NAMES = {getattr(ca, k): k for k in dir(ca) if k.startswith("OP_")}

PRELUDE = r"""
/* ---- rscasadi: four evaluations in the lanes of rsk_v (rscasadi/codegen/lanes.py) ---- */
#include <math.h>
#include <string.h>
#if (defined(__GNUC__) || defined(__clang__)) && !defined(RSK_PORTABLE)
typedef double rsk_v __attribute__((vector_size(32)));
#define RSK_ADD(a, b) ((a) + (b))
#define RSK_SUB(a, b) ((a) - (b))
#define RSK_MUL(a, b) ((a) * (b))
#define RSK_DIV(a, b) ((a) / (b))
#define RSK_AT(v, i) ((v)[i])
#else
typedef struct { double x[4]; } rsk_v;
static rsk_v rsk_add(rsk_v a, rsk_v b) { int i; for (i = 0; i < 4; ++i) a.x[i] += b.x[i]; return a; }
static rsk_v rsk_sub(rsk_v a, rsk_v b) { int i; for (i = 0; i < 4; ++i) a.x[i] -= b.x[i]; return a; }
static rsk_v rsk_mul(rsk_v a, rsk_v b) { int i; for (i = 0; i < 4; ++i) a.x[i] *= b.x[i]; return a; }
static rsk_v rsk_div(rsk_v a, rsk_v b) { int i; for (i = 0; i < 4; ++i) a.x[i] /= b.x[i]; return a; }
#define RSK_ADD(a, b) rsk_add(a, b)
#define RSK_SUB(a, b) rsk_sub(a, b)
#define RSK_MUL(a, b) rsk_mul(a, b)
#define RSK_DIV(a, b) rsk_div(a, b)
#define RSK_AT(v, i) ((v).x[i])
#endif
/* statements, not functions: a function passing a vector without AVX would change the ABI (gcc -Wpsabi) */
#define RSK_VLD(v, p) memcpy(&(v), (p), sizeof(v))
#define RSK_VST(p, v) memcpy((p), &(v), sizeof(v))
#if defined(__GNUC__) || defined(__clang__)
#define RSK_NOINLINE __attribute__((noinline))
#else
#define RSK_NOINLINE
#endif
#if defined(__STDC_VERSION__) && __STDC_VERSION__ >= 199901L
#define RSK_RESTRICT restrict
#else
#define RSK_RESTRICT
#endif
#define RSK_VBC(v, c) { const double c_ = (c); int i_; for (i_ = 0; i_ < 4; ++i_) RSK_AT(v, i_) = c_; }
"""


CHUNK = 300   # statements per function: gcc's register allocation grows faster than a function's length;
              # the Panda's kernel compiles at -O1 in 8.4 s, not 19 s, and steps as fast (80 us at -O1,
              # 15.6 us at -O3 -march=native: 2026-11-29, 2-core Xeon VM)


def lanes_c(f: ca.Function, name: str, shared=(), scalar: bool = False) -> str:
    """`static void name(const double **arg, double **res)`: f at four points, `arg[i][4 k + l]` the
    nonzero k of input i at point l (one copy, `arg[i][k]`, for i in `shared`), res alike.
    Needs PRELUDE once before it in the same file.  The instructions run in functions of CHUNK
    statements; a work vector live across two of them passes through the array `s` of `name`.
    scalar: f at one point, in doubles (`arg[i][k]`): gcc compiles it much faster than CasADi's
    one function past a few thousand statements, and it runs a little slower (a 20-joint tree's
    forward-dynamics Jacobian kernel at -O3: compiled in 29 s instead of 68 s, a call about 1.25x
    as long; 2026-11-29, 2-core Xeon VM)."""
    if not f.is_a("SXFunction"):
        raise WrongType(f"{f.name()}: lanes_c needs an SX Function")
    code = [_statement(f, k, shared, scalar) for k in range(f.n_instructions())]
    chunks = [code[c:c + CHUNK] for c in range(0, len(code), CHUNK)] or [[]]
    needed: set = set()                      # slots whose value a later chunk reads before writing them
    parts = []
    kind = "double" if scalar else "rsk_v"
    for i, chunk in reversed(list(enumerate(chunks))):
        live_in, written = _live_in(chunk)
        parts.append(_chunk_c(f"{name}_{i}", chunk, live_in, written & needed, kind))
        needed = live_in | (needed - written)
    calls = "".join(f"  {name}_{i}(s, arg, res);\n" for i in range(len(chunks)))
    return ("".join(reversed(parts)) + f"static void {name}(const double **arg, double **res) {{\n"
            + f"  {kind} s[{max(f.sz_w(), 1)}];\n{calls}}}\n")


_SCALAR_BINARY = {ca.OP_ADD: "+", ca.OP_SUB: "-", ca.OP_MUL: "*", ca.OP_DIV: "/"}


def _statement(f: ca.Function, k: int, shared, scalar: bool = False) -> tuple:
    """Instruction k as (C statement, work vectors it reads, the one it writes or None): on rsk_v
    (four points, interleaved), or on doubles with `scalar` (one point)."""
    op, i, o = f.instruction_id(k), f.instruction_input(k), f.instruction_output(k)
    if op == ca.OP_INPUT:
        return (f"w{o[0]} = arg[{i[0]}][{i[1]}];" if scalar else f"RSK_VBC(w{o[0]}, arg[{i[0]}][{i[1]}])"
                if i[0] in shared else f"RSK_VLD(w{o[0]}, arg[{i[0]}] + {LANES * i[1]});"), (), o[0]
    if op == ca.OP_OUTPUT:
        store = f"res[{o[0]}][{o[1]}] = w{i[0]};" if scalar else f"RSK_VST(res[{o[0]}] + {LANES * o[1]}, w{i[0]});"
        return f"if (res[{o[0]}]) {store}", (i[0],), None
    if op == ca.OP_CONST:
        c = f.instruction_constant(k)
        if not math.isfinite(c):
            raise InvalidArgument(f"{f.name()}: constant {c} at instruction {k} has no C literal")
        return (f"w{o[0]} = {c!r};" if scalar else f"RSK_VBC(w{o[0]}, {c!r})"), (), o[0]
    if op in _BINARY:
        expr = f"w{i[0]} {_SCALAR_BINARY[op]} w{i[1]}" if scalar else f"{_BINARY[op]}(w{i[0]}, w{i[1]})"
        return f"w{o[0]} = {expr};", (i[0], i[1]), o[0]
    if op in _PER_LANE:
        args = i[:2] if "{1}" in _PER_LANE[op] else i[:1]
        if scalar:
            return f"w{o[0]} = {_PER_LANE[op].format(*(f'w{j}' for j in args))};", tuple(args), o[0]
        lanes = ", ".join(_PER_LANE[op].format(*(f"RSK_AT(w{j}, {l})" for j in args)) for l in range(LANES))
        return f"{{ const double t_[{LANES}] = {{{lanes}}}; RSK_VLD(w{o[0]}, t_); }}", tuple(args), o[0]
    raise NotImplementedError(f"{f.name()}: operation {_OP_NAMES.get(op, op)} (instruction {k}) "
                              "has no C form in rscasadi.codegen.lanes")


def _live_in(chunk) -> tuple:
    """The work vectors a chunk reads before it writes them, and those it writes."""
    live_in: set = set()
    written: set = set()
    for _, reads, write in chunk:
        live_in |= set(reads) - written
        if write is not None:
            written.add(write)
    return live_in, written


def _chunk_c(name: str, chunk, live_in: set, live_out: set, kind: str = "rsk_v") -> str:
    """One chunk as a function: its work vectors (of `kind`) local, those live across chunks through `s`."""
    local = sorted(live_in | {w for _, _, w in chunk if w is not None})
    lines = [f"{kind} {', '.join(f'w{k}' for k in local)};" if local else "",
             "(void)s; (void)arg; (void)res;"]
    lines += [f"w{k} = s[{k}];" for k in sorted(live_in)] + [c for c, _, _ in chunk]
    lines += [f"s[{k}] = w{k};" for k in sorted(live_out)]
    return (f"static RSK_NOINLINE void {name}({kind} *RSK_RESTRICT s, const double **arg, double **res) {{\n  "
            + "\n  ".join(line for line in lines if line) + "\n}\n")
