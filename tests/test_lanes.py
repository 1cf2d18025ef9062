"""The four-lane emitter (rscasadi.codegen.lanes): its C, in both its forms (vector extensions and
portable C99), equals CasADi's own evaluation of the Function at each of the four points."""
import ctypes
import subprocess

import casadi as ca
import numpy as np
import pytest

from rscasadi.codegen.lanes import LANES, PRELUDE, lanes_c

from conftest import cc


def _every_operation():
    """A Function using every kind of instruction the emitter writes: inputs (one shared),
    constants, the four binary operators, and operations lane by lane."""
    x, y, p = ca.SX.sym("x", 3), ca.SX.sym("y", 2), ca.SX.sym("p", 2)
    a, b, c = x[0], x[1], x[2]
    outs = [a * b + c / y[0] - p[0], -a, a ** 2, 2 * b, 1 / c, ca.sin(a) * ca.cos(b), ca.tanh(c), ca.exp(a),
            ca.log(ca.fabs(b) + 1), ca.sqrt(ca.fabs(c)), ca.atan2(a, y[1]), ca.fmin(a, b), ca.fmax(a, p[1]),
            ca.if_else(a < b, c, y[0]), ca.sign(c), a ** 3, ca.power(ca.fabs(a), y[1]), 3.25 + 0 * a]
    f = ca.Function("f", [x, y, p], [ca.vertcat(*outs[:9]), ca.vertcat(*outs[9:])])
    return f


def _compiled(tmp_path, f, shared, portable):
    src = tmp_path / ("portable.c" if portable else "vector.c")
    src.write_text(PRELUDE + lanes_c(f, "f4", shared) + """
void entry(const double **arg, double **res) { f4(arg, res); }
""")
    lib = src.with_suffix(".so")
    subprocess.run([cc(), "-O1", "-std=c99", "-Wall", "-Werror", "-fPIC", "-shared", str(src), "-o", str(lib), "-lm"]
                   + (["-DRSK_PORTABLE"] if portable else []), check=True)
    return ctypes.CDLL(str(lib))


@pytest.mark.skipif(cc() is None, reason="no C compiler")
@pytest.mark.parametrize("portable", [False, True])
@pytest.mark.parametrize("chunk", [300, 3, 7])
def test_four_lanes_equal_casadi_at_each_point(tmp_path, portable, chunk, monkeypatch):
    """In one function, and in functions of 3 and 7 statements (work vectors live across several
    of them, some written again before they are read)."""
    import rscasadi.codegen.lanes as lanes
    monkeypatch.setattr(lanes, "CHUNK", chunk)
    f = _every_operation()
    lib = _compiled(tmp_path, f, shared=(2,), portable=portable)
    rng = np.random.default_rng(5)
    xs, ys, p = rng.uniform(-2, 2, (LANES, 3)), rng.uniform(0.5, 2, (LANES, 2)), rng.uniform(-1, 1, 2)
    ptr = ctypes.POINTER(ctypes.c_double)
    ins = [np.ascontiguousarray(xs.T.ravel()), np.ascontiguousarray(ys.T.ravel()), p.copy()]
    outs = [np.full(LANES * f.nnz_out(i), np.nan) for i in range(f.n_out())]
    arg = (ptr * 3)(*[a.ctypes.data_as(ptr) for a in ins])
    res = (ptr * 2)(*[o.ctypes.data_as(ptr) for o in outs])
    lib.entry(arg, res)
    for lane in range(LANES):
        want = f(xs[lane], ys[lane], p)
        for i in range(f.n_out()):
            got = outs[i].reshape(-1, LANES)[:, lane]
            assert np.allclose(got, np.array(want[i]).ravel(), rtol=1e-14, atol=1e-15), (lane, i)


def test_unsupported_operation_is_named():
    x = ca.SX.sym("x")
    with pytest.raises(NotImplementedError, match="OP_ERFINV"):
        lanes_c(ca.Function("g", [x], [ca.erfinv(x)]), "g4")


@pytest.mark.skipif(cc() is None, reason="no C compiler")
@pytest.mark.parametrize("chunk", [300, 3, 7])
def test_the_scalar_form_equals_casadi(tmp_path, chunk, monkeypatch):
    """scalar=True (one point in doubles, the ROS2 and forward-dynamics-Jacobian kernels' dr/dx):
    every operation, in one function and in pieces of 3 and 7 statements."""
    import rscasadi.codegen.lanes as lanes
    monkeypatch.setattr(lanes, "CHUNK", chunk)
    f = _every_operation()
    src = tmp_path / "scalar.c"
    src.write_text(PRELUDE + lanes_c(f, "f1", scalar=True) + """
void entry(const double **arg, double **res) { f1(arg, res); }
""")
    lib = src.with_suffix(".so")
    subprocess.run([cc(), "-O1", "-std=c99", "-Wall", "-Werror", "-fPIC", "-shared", str(src), "-o", str(lib), "-lm"],
                   check=True)
    lib = ctypes.CDLL(str(lib))
    rng = np.random.default_rng(6)
    ptr = ctypes.POINTER(ctypes.c_double)
    for _ in range(3):
        ins = [rng.uniform(-2, 2, 3), rng.uniform(0.5, 2, 2), rng.uniform(-1, 1, 2)]
        outs = [np.full(f.nnz_out(i), np.nan) for i in range(f.n_out())]
        lib.entry((ptr * 3)(*[a.ctypes.data_as(ptr) for a in ins]), (ptr * 2)(*[o.ctypes.data_as(ptr) for o in outs]))
        want = f(*ins)
        for i in range(f.n_out()):
            assert np.allclose(outs[i], np.array(want[i]).ravel(), rtol=1e-14, atol=1e-15), i
