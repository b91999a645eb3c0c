"""Tests of :mod:`controllers.solvers.fast.lanes`: CasADi functions evaluated on many points at
once."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from controllers.solvers.fast.lanes import LaneFunction


def reference(fn: ca.Function, inputs: list[np.ndarray], lanes: int) -> list[np.ndarray]:
    """CasADi's own evaluation, point by point, in the lane layout ``(rows * cols, lanes)``."""
    out = []
    for lane in range(lanes):
        args = [
            np.broadcast_to(a, (a.shape[0], lanes))[:, lane].reshape(
                fn.size1_in(i), fn.size2_in(i), order="F"
            )
            for i, a in enumerate(inputs)
        ]
        res = fn(*args)
        res = res if isinstance(res, (list, tuple)) else [res]
        out.append([np.asarray(ca.densify(r)).ravel(order="F") for r in res])
    return [np.stack([o[i] for o in out], axis=1) for i in range(fn.n_out())]


def every_operation() -> ca.Function:
    """A function using each operation the NumPy form knows, with sparse outputs."""
    x, y = ca.SX.sym("x", 3), ca.SX.sym("y", 2)
    a, b, c = x[0], x[1], x[2]
    terms = [
        a + b, a - b, a * b, a / (2.0 + b * b), ca.power(1.5 + c * c, b), (1.0 + c * c) ** 3,
        ca.atan2(a, b), ca.fmin(a, b), ca.fmax(a, b), a < b, a <= b, a == b, a != b,
        ca.copysign(a, b), ca.fmod(a, 1.0 + c * c), ca.if_else(a > 0, b, 0.0),
        ca.logic_and(a > 0, b > 0), ca.logic_or(a > 0, b > 0), -a, a * a, 2 * a,
        1.0 / (1.0 + c * c), ca.sqrt(1.0 + c * c), ca.exp(a), ca.log(1.0 + c * c), ca.sin(a),
        ca.cos(a), ca.tan(0.3 * a), ca.asin(0.5 * ca.tanh(a)), ca.acos(0.5 * ca.tanh(b)),
        ca.atan(a), ca.sinh(a), ca.cosh(a), ca.tanh(a), ca.asinh(a), ca.acosh(2.0 + c * c),
        ca.atanh(0.5 * ca.tanh(c)), ca.fabs(a), ca.sign(a), ca.floor(a), ca.ceil(a),
        ca.logic_not(a > 0), y[0] * ca.sin(a) + y[1],
    ]  # fmt: skip
    dense = ca.vertcat(*terms)
    sparse = ca.SX(4, 3)
    sparse[0, 1] = a * y[1]
    sparse[3, 2] = ca.cos(b) + 1.0
    return ca.Function("every", [x, y], [dense, sparse, ca.jacobian(dense[-5:], ca.vertcat(x, y))])


def test_numpy_form_equals_casadi_on_every_operation():
    fn = every_operation()
    lane = LaneFunction(fn)
    assert lane.backend == "numpy"
    rng = np.random.default_rng(0)
    inputs = [rng.normal(size=(3, 50)), rng.normal(size=(2, 50))]
    inputs[0][:, :5] = 0.0  # ties and zeros for the comparisons and sign
    got = lane(*inputs)
    for g, r in zip(got, reference(fn, inputs, 50), strict=True):
        np.testing.assert_allclose(g, r, rtol=1e-13, atol=1e-13)


def test_lane_axes_broadcast():
    """An input that is the same for every scenario can have length 1 on that axis."""
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    fn = ca.Function("f", [x, u], [ca.vertcat(x[0] * ca.sin(u), ca.tan(u) + x[1])])
    lane = LaneFunction(fn)
    rng = np.random.default_rng(1)
    X, U = rng.normal(size=(2, 7, 30)), rng.normal(size=(1, 7, 1))
    (out,) = lane(X, U)
    assert out.shape == (2, 7, 30)
    np.testing.assert_allclose(out[0], X[0] * np.sin(U[0]), rtol=1e-15)
    np.testing.assert_allclose(out[1], np.tan(U[0]) + X[1], rtol=1e-15)


def test_repeated_operations_are_computed_once():
    x = ca.SX.sym("x")
    # CasADi keeps both sin(x) nodes; value numbering emits one.
    fn = ca.Function("f", [x], [ca.sin(x) * ca.sin(x) + ca.sin(x)])
    from controllers.solvers.fast.lanes import _source

    assert _source(fn).count("np.sin(") == 1
    (out,) = LaneFunction(fn)(np.array([[0.3, -1.2]]))
    np.testing.assert_allclose(out[0], np.sin([0.3, -1.2]) ** 2 + np.sin([0.3, -1.2]))


def test_unknown_operation_falls_back_to_casadi_map():
    x = ca.SX.sym("x", 2)
    fn = ca.Function("f", [x], [ca.vertcat(ca.erf(x[0]), x[0] * x[1])])
    lane = LaneFunction(fn)
    assert lane.backend == "casadi_map"
    rng = np.random.default_rng(2)
    X = rng.normal(size=(2, 4, 5))
    (out,) = lane(X)
    assert out.shape == (2, 4, 5)
    ref = reference(fn, [X.reshape(2, -1)], 20)[0].reshape(2, 4, 5)
    np.testing.assert_allclose(out, ref, rtol=1e-14)


def test_mx_functions_are_expanded():
    x = ca.MX.sym("x", 2)
    fn = ca.Function("f", [x], [ca.sin(x) * 2.0])
    lane = LaneFunction(fn)
    assert lane.backend == "numpy"
    (out,) = lane(np.array([[0.1, 0.2], [0.3, 0.4]]))
    np.testing.assert_allclose(out, 2.0 * np.sin([[0.1, 0.2], [0.3, 0.4]]))


@pytest.mark.parametrize("lanes", [1, 3])
def test_shapes_of_dense_outputs(lanes: int):
    x = ca.SX.sym("x", 2)
    fn = ca.Function("f", [x], [ca.jacobian(ca.vertcat(x[0] ** 2, x[0] * x[1]), x)])
    (out,) = LaneFunction(fn)(np.ones((2, lanes)) * 2.0)
    # Column-major (2, 2) Jacobian [[2 x0, 0], [x1, x0]] at x = (2, 2).
    np.testing.assert_allclose(out, np.repeat([[4.0], [2.0], [0.0], [2.0]], lanes, axis=1))
