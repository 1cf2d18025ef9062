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
#define RSK_VBC(v, c) { const double c_ = (c); int i_; for (i_ = 0; i_ < 4; ++i_) RSK_AT(v, i_) = c_; }
"""


def lanes_c(f: ca.Function, name: str, shared=()) -> str:
    """`static void name(const double **arg, double **res)`: f at four points, `arg[i][4 k + l]` the
    nonzero k of input i at point l (one copy, `arg[i][k]`, for i in `shared`), res alike.
    Needs PRELUDE once before it in the same file."""
    if not f.is_a("SXFunction"):
        raise WrongType(f"{f.name()}: lanes_c needs an SX Function")
    body = []
    for k in range(f.n_instructions()):
        op, i, o = f.instruction_id(k), f.instruction_input(k), f.instruction_output(k)
        if op == ca.OP_INPUT:
            body.append(f"RSK_VBC(w{o[0]}, arg[{i[0]}][{i[1]}])" if i[0] in shared
                        else f"RSK_VLD(w{o[0]}, arg[{i[0]}] + {LANES * i[1]});")
        elif op == ca.OP_OUTPUT:
            body.append(f"if (res[{o[0]}]) RSK_VST(res[{o[0]}] + {LANES * o[1]}, w{i[0]});")
        elif op == ca.OP_CONST:
            c = f.instruction_constant(k)
            if not math.isfinite(c):
                raise InvalidArgument(f"{f.name()}: constant {c} at instruction {k} has no C literal")
            body.append(f"RSK_VBC(w{o[0]}, {c!r})")
        elif op in _BINARY:
            body.append(f"w{o[0]} = {_BINARY[op]}(w{i[0]}, w{i[1]});")
        elif op in _PER_LANE:
            lanes = ", ".join(_PER_LANE[op].format(*(f"RSK_AT(w{j}, {l})" for j in i)) for l in range(LANES))
            body.append(f"{{ const double t_[{LANES}] = {{{lanes}}}; RSK_VLD(w{o[0]}, t_); }}")
        else:
            raise NotImplementedError(f"{f.name()}: operation {_OP_NAMES.get(op, op)} (instruction {k}) "
                                      "has no vector form in rscasadi.codegen.lanes")
    decl = ", ".join(f"w{k}" for k in range(f.sz_w())) or "w0"
    return (f"static void {name}(const double **arg, double **res) {{\n  rsk_v {decl};\n  "
            + "\n  ".join(body) + "\n}\n")
