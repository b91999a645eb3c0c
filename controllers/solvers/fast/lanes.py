"""CasADi SX functions evaluated on many points at once ("lanes") with NumPy.

The fast solver needs the same small function (a step Jacobian, a Hessian of the
dynamics) at every scenario and every step: ``Ns N`` points. CasADi's virtual machine
evaluates them one after another; here the function's straight-line algorithm (its SX
instructions) is turned once into Python source where every instruction is one NumPy
operation on a vector of all points. A function of a few hundred operations then costs
a few hundred vectorised NumPy calls, whatever the number of points.

Functions with an operation this module does not know fall back to CasADi's ``map``
(correct, slower); :attr:`LaneFunction.backend` says which one is used.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import casadi as ca
import numpy as np

# Opcode -> Python expression template over the operands a, b.
_BINARY = {
    ca.OP_ADD: "{a} + {b}",
    ca.OP_SUB: "{a} - {b}",
    ca.OP_MUL: "{a} * {b}",
    ca.OP_DIV: "{a} / {b}",
    ca.OP_POW: "np.power({a}, {b})",
    ca.OP_CONSTPOW: "np.power({a}, {b})",
    ca.OP_ATAN2: "np.arctan2({a}, {b})",
    ca.OP_FMIN: "np.minimum({a}, {b})",
    ca.OP_FMAX: "np.maximum({a}, {b})",
    ca.OP_LT: "1.0 * ({a} < {b})",
    ca.OP_LE: "1.0 * ({a} <= {b})",
    ca.OP_EQ: "1.0 * ({a} == {b})",
    ca.OP_NE: "1.0 * ({a} != {b})",
    ca.OP_COPYSIGN: "np.copysign({a}, {b})",
    ca.OP_FMOD: "np.fmod({a}, {b})",
    ca.OP_IF_ELSE_ZERO: "np.where({a} != 0, {b}, 0.0)",
    ca.OP_AND: "1.0 * (({a} != 0) & ({b} != 0))",
    ca.OP_OR: "1.0 * (({a} != 0) | ({b} != 0))",
}
_UNARY = {
    ca.OP_ASSIGN: "{a}",
    ca.OP_NEG: "-{a}",
    ca.OP_SQ: "{a} * {a}",
    ca.OP_TWICE: "2.0 * {a}",
    ca.OP_INV: "1.0 / {a}",
    ca.OP_SQRT: "np.sqrt({a})",
    ca.OP_EXP: "np.exp({a})",
    ca.OP_LOG: "np.log({a})",
    ca.OP_SIN: "np.sin({a})",
    ca.OP_COS: "np.cos({a})",
    ca.OP_TAN: "np.tan({a})",
    ca.OP_ASIN: "np.arcsin({a})",
    ca.OP_ACOS: "np.arccos({a})",
    ca.OP_ATAN: "np.arctan({a})",
    ca.OP_SINH: "np.sinh({a})",
    ca.OP_COSH: "np.cosh({a})",
    ca.OP_TANH: "np.tanh({a})",
    ca.OP_ASINH: "np.arcsinh({a})",
    ca.OP_ACOSH: "np.arccosh({a})",
    ca.OP_ATANH: "np.arctanh({a})",
    ca.OP_FABS: "np.abs({a})",
    ca.OP_SIGN: "np.sign({a})",
    ca.OP_FLOOR: "np.floor({a})",
    ca.OP_CEIL: "np.ceil({a})",
    ca.OP_NOT: "1.0 * ({a} == 0)",
}


def _source(fn: ca.Function) -> str:
    """Python source of ``fn``'s algorithm; raises ``NotImplementedError`` on unknown ops.

    CasADi reuses work registers; here every computed value gets its own name (value
    numbering), so an operation repeated on the same values is emitted once.
    """
    lines = ["def lane_eval(inputs, outputs):"]
    for i in range(fn.n_in()):
        lines.append(f"    i{i} = inputs[{i}]")
    for i in range(fn.n_out()):
        lines.append(f"    o{i} = outputs[{i}]")

    def dense(sp: ca.Sparsity) -> list[int]:
        """Dense, column-major position of every nonzero."""
        rows, cols = sp.get_triplet()
        return [c * sp.size1() + r for r, c in zip(rows, cols, strict=True)]

    dense_out = [dense(fn.sparsity_out(i)) for i in range(fn.n_out())]
    dense_in = [dense(fn.sparsity_in(i)) for i in range(fn.n_in())]
    register: dict[int, str] = {}  # work register -> name of the value it holds
    known: dict[tuple, str] = {}  # (operation, operand names) -> name of its value

    def value(key: tuple, expr: str) -> str:
        name = known.get(key)
        if name is None:
            name = known[key] = f"v{len(known)}"
            lines.append(f"    {name} = {expr}")
        return name

    for k in range(fn.n_instructions()):
        op = fn.instruction_id(k)
        ins = fn.instruction_input(k)
        outs = fn.instruction_output(k)
        if op == ca.OP_OUTPUT:
            lines.append(f"    o{outs[0]}[{dense_out[outs[0]][outs[1]]}] = {register[ins[0]]}")
            continue
        register[outs[0]] = _instruction_value(fn, k, op, ins, register, dense_in, value)
    lines.append("    return outputs")
    return "\n".join(lines) + "\n"


def _instruction_value(
    fn: ca.Function,
    k: int,
    op: int,
    ins: list[int],
    register: dict[int, str],
    dense_in: list[list[int]],
    value: Callable[[tuple, str], str],
) -> str:
    """The name of the value instruction ``k`` (operation ``op`` on the work registers
    ``ins``) computes; ``value(key, expr)`` emits a new one once."""
    if op == ca.OP_INPUT:
        pos = dense_in[ins[0]][ins[1]]
        return value(("in", ins[0], pos), f"i{ins[0]}[{pos}]")
    if op == ca.OP_CONST:
        c = float(fn.instruction_constant(k))
        return value(("const", c), repr(c))
    if op == ca.OP_ASSIGN:
        return register[ins[0]]
    if op in _BINARY:
        a, b = register[ins[0]], register[ins[1]]
        return value((op, a, b), _BINARY[op].format(a=a, b=b))
    if op in _UNARY:
        a = register[ins[0]]
        return value((op, a), _UNARY[op].format(a=a))
    raise NotImplementedError(f"CasADi operation {op} has no NumPy lane form")


class LaneFunction:
    """An SX :class:`casadi.Function` evaluated on ``L`` points at once.

    Args:
        fn: a function of SX expressions (any sparsity; outputs are returned dense).
        vm: evaluate with CasADi's virtual machine (``map``) even when NumPy could.

    Call it with one array per input of shape ``(rows * cols, *lanes)`` (the input's dense,
    column-major entries along the first axis; the lane axes broadcast against each other,
    so an input that is the same along some lane axis can have length 1 there, and every
    operation on it alone is done once per distinct value) and get one array per output
    of shape ``(rows * cols, *lanes)``.
    """

    def __init__(self, fn: ca.Function, vm: bool = False) -> None:
        if not fn.is_a("SXFunction"):
            fn = fn.expand()
        self.fn = fn
        self.out_sizes = [fn.size1_out(i) * fn.size2_out(i) for i in range(fn.n_out())]
        self.in_sizes = [fn.size1_in(i) * fn.size2_in(i) for i in range(fn.n_in())]
        try:
            if vm:
                raise NotImplementedError("the CasADi VM was asked for")
            namespace: dict = {"np": np}
            exec(compile(_source(fn), f"<lanes:{fn.name()}>", "exec"), namespace)  # noqa: S102
            self._eval = namespace["lane_eval"]
            self.backend = "numpy"
        except NotImplementedError:
            self._eval = None
            self.backend = "casadi_map"
        self._maps: dict[int, ca.Function] = {}

    def __call__(self, *inputs: np.ndarray) -> list[np.ndarray]:
        shape = np.broadcast_shapes(*(np.shape(a)[1:] for a in inputs))
        if self._eval is not None:
            outputs = [np.zeros((n,) + shape) for n in self.out_sizes]
            with np.errstate(all="ignore"):
                self._eval(inputs, outputs)
            return outputs
        lanes = math.prod(shape)
        inputs = [
            np.broadcast_to(a, (a.shape[0],) + shape).reshape(a.shape[0], lanes) for a in inputs
        ]
        mapped = self._maps.get(lanes)
        if mapped is None:
            mapped = self._maps[lanes] = self.fn.map(lanes)
        args = [
            np.broadcast_to(a, (n, lanes)).reshape(
                self.fn.size1_in(i), self.fn.size2_in(i) * lanes, order="F"
            )
            for i, (a, n) in enumerate(zip(inputs, self.in_sizes, strict=True))
        ]
        res = mapped(*args)
        res = res if isinstance(res, (list, tuple)) else [res]
        return [
            np.asarray(ca.densify(r)).reshape(n, lanes, order="F").reshape((n,) + shape)
            for r, n in zip(res, self.out_sizes, strict=True)
        ]


__all__ = ["LaneFunction"]
